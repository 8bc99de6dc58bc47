"""Identification: from images and records to a fitted scanner model, and its inverse.

What an image shows: ``features`` (lattice feature points), ``chords`` (features' edge
crossings) and ``line_grating`` (a 1-D grating's pitch and distortion). Fitting a record:
``fit`` (the solvers and hysteresis fits), ``linear`` (the exact fit of PI and Preisach
weights) and ``projection`` (nuisance parameters projected out
of a linear least-squares problem). Step A, the scanner from calibration-lattice images:
``calibration_scan`` (the data), ``scan_model`` (the model and its parameters), ``image_ops``
(interpolation and blur), ``stages`` (what each stage fits), ``staged_fit`` (:func:`identify`),
``held_out`` (held-out validation), ``plausibility`` (what makes a model unusable),
``polynomial_baseline`` (the paper's) and ``step_a`` (step A on the simulated AFM: calibration
scans, the fitted scanner's twin, compensated scans and their errors). Then ``inverse``
(compensation) and ``compensate`` (the drive that makes a model follow a trajectory, after the
initialisation cycle). Imports the model, the instrument and the shared leaves; importing it
switches JAX to float64 (``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
from .calibration_scan import CalibrationScan
from .features import lattice_features
from .fit import FitResult, error_metrics, fit_operator
from .inverse import Compensator, numerical_inverse
from .line_grating import fit_line_grating
from .scan_model import ScanModel, ScanModelSpec
from .staged_fit import Identification, identify
from .stages import FitPlan

__all__ = [
    "CalibrationScan",
    "Compensator",
    "FitPlan",
    "FitResult",
    "Identification",
    "ScanModel",
    "ScanModelSpec",
    "error_metrics",
    "fit_line_grating",
    "fit_operator",
    "identify",
    "lattice_features",
    "numerical_inverse",
]
