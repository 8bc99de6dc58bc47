"""The scanner model: drive voltages u(t) (V) to tip positions x(t), y(t) (nm).

``hysteresis`` (the operators: play, Prandtl–Ishlinskii, generalised PI, Preisach),
``effects`` (rate dependence, creep, coupling, bow, drift, noise, feedback lag), ``scanner``
(an axis and the two-axis scanner that compose them) and ``io`` (model files).
Imports only the shared leaves (``config``, ``checks``); importing it switches JAX to float64
(``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
