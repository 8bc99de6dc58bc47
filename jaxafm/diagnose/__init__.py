"""The sim-to-real gap: which unmodelled effect explains what the nominal model misses, in a
record, an image or a set of scans (what ``jaxafm diagnose`` runs: ``jaxafm.jobs.diagnose``).

Sits beside identification and positioning: imports the model, the instrument, identification
and the shared leaves; importing it switches JAX to float64 (``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
from .core import Candidate, DataKind, Diagnosis, Rules, diagnose
from .image import diagnose_image
from .record import diagnose_record
from .scans import ScanPair, diagnose_scans

__all__ = [
    "Candidate",
    "DataKind",
    "Diagnosis",
    "Rules",
    "ScanPair",
    "diagnose",
    "diagnose_image",
    "diagnose_record",
    "diagnose_scans",
]
