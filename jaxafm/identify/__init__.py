"""Identification: from images and records to a fitted scanner model, and its inverse.

``features`` and ``line_grating`` (what an image shows), ``fit`` (fitting hysteresis models to
a record), ``calibration`` (step A's end-to-end fit of the scanner to a grating image pair),
``inverse`` (compensation), ``compensate`` (the drive that makes a model follow a trajectory,
after the initialisation cycle) and ``step_a`` (step A on the simulated AFM: calibration scans,
the fitted scanner's twin, compensated scans and their errors). Imports the model, the
instrument and the shared leaves; importing it switches JAX to float64 (``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
from .calibration import CalibrationScan, Identification, identify
from .features import lattice_features
from .fit import FitResult, error_metrics, fit_operator
from .inverse import Compensator, numerical_inverse
from .line_grating import fit_line_grating

__all__ = [
    "CalibrationScan",
    "Compensator",
    "FitResult",
    "Identification",
    "error_metrics",
    "fit_line_grating",
    "fit_operator",
    "identify",
    "lattice_features",
    "numerical_inverse",
]
