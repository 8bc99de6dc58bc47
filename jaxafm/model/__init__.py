"""The scanner model: drive voltages u(t) (V) to tip positions x(t), y(t) (nm).

``hysteresis`` (the operators: play, Prandtl–Ishlinskii, generalised PI, Preisach),
``effects`` (rate dependence, creep, coupling, bow, drift, noise, feedback lag), ``scanner``
(an axis and the two-axis scanner that compose them), ``io`` (self-describing model files) and
``apply`` (one call, :func:`predict`, that applies any of them to an input).
Imports only the shared leaves (``config``, ``checks``); importing it switches JAX to float64
(``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
from .apply import predict
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
from .io import describe, load_model, read_model_file, save_model
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
    "describe",
    "load_model",
    "play",
    "predict",
    "read_model_file",
    "save_model",
]
