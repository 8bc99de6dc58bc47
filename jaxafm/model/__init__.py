"""The scanner model: drive voltages u(t) (V) to tip positions x(t), y(t) (nm).

``hysteresis`` (the operators: play, Prandtl–Ishlinskii, generalised PI, Preisach),
``effects`` (rate dependence, creep, coupling, bow, drift, noise, feedback lag), ``scanner``
(an axis and the two-axis scanner that compose them) and ``io`` (model files).
Imports only the shared leaves (``config``, ``checks``); importing it switches JAX to float64
(``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
from .effects import Bow, Coupling, Creep, Drift, FeedbackLag, Noise, RateDependence
from .hysteresis import (
    AbstractHysteresis,
    Anhysteretic,
    Deadzone,
    GeneralizedPI,
    Linear,
    PlayOperator,
    PrandtlIshlinskii,
    Preisach,
    play,
)
from .io import load_model, save_model
from .scanner import Axis, Scanner, default_scanner

__all__ = [
    "AbstractHysteresis",
    "Anhysteretic",
    "Axis",
    "Bow",
    "Coupling",
    "Creep",
    "Deadzone",
    "Drift",
    "FeedbackLag",
    "GeneralizedPI",
    "Linear",
    "Noise",
    "PlayOperator",
    "PrandtlIshlinskii",
    "Preisach",
    "RateDependence",
    "Scanner",
    "default_scanner",
    "load_model",
    "play",
    "save_model",
]
