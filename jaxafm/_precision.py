"""float64 for every part of jaxafm that uses JAX.

Each JAX sub-package (``model``, ``instrument``, ``identify``, ``position``, ``diagnose``,
``study``) imports this module first, so importing any of them, or a name from ``jaxafm`` that
lives in one, switches JAX to float64 (``jax_enable_x64``) before any of jaxafm's arrays exist.
It is set on import, not left to the caller, because:

- identification needs float64: a fit's loss is a sum over thousands of samples and its
  Gauss-Newton steps solve with the Jacobian's squares, which float32's 7 digits do not carry
  (the tests check inverses to 1e-9 of the range and the fit-loss gradient to 1e-6 against
  finite differences);
- a model built before the switch would hold float32 arrays and mix them with float64 ones
  later, so the switch must come before the first model, not at the first fit.

Importing ``jaxafm`` alone or ``jaxafm.config`` (checking a YAML file), or running
``jaxafm --help``, imports no JAX and changes no setting.
"""

import jax

jax.config.update("jax_enable_x64", True)
