"""Monte-Carlo positioning studies (``monte_carlo``: the ``jaxafm study`` job).

Imports positioning and everything below it; importing it switches JAX to float64
(``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
