"""Positioning on the simulated AFM: the paper's steps B and C and the push.

``landmarks`` (step B's indent grid and map, eq. 3-5), ``positioning`` (moves, presses, step C's
local scan, the push), ``survey`` (the stages of the ablation, their survey of the workspace and
what it finds) and ``trials`` (the vmapped trials from a survey, with typed results). Imports the
model, the instrument, identification and the shared leaves; importing it switches JAX to
float64 (``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
from .landmarks import LandmarkGrid, LandmarkMap, find_features
from .positioning import LocalScan, Positioner, Push, goto, local_scan, push

__all__ = [
    "LandmarkGrid",
    "LandmarkMap",
    "LocalScan",
    "Positioner",
    "Push",
    "find_features",
    "goto",
    "local_scan",
    "push",
]
