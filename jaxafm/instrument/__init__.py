"""The instrument: the simulated AFM and the files a real one writes.

``samples`` (surfaces and the tip), ``afm`` (raster and line scans, moves, presses, the
z-feedback), ``images`` (image files in and out) and ``records`` (actuator time-series files).
Imports the model and the shared leaves; importing it switches JAX to float64
(``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
from .afm import AFM, Raster, RasterScan, default_afm, line_scan, move, press, raster_scan
from .images import AFMImage, from_scan, load_image, read_image, save_image
from .records import Record, read_record
from .samples import AbstractSample, Grating, HeightMap, Indented, Lattice, Particles, Plane, Tip

__all__ = [
    "AFM",
    "AFMImage",
    "AbstractSample",
    "Grating",
    "HeightMap",
    "Indented",
    "Lattice",
    "Particles",
    "Plane",
    "Raster",
    "RasterScan",
    "Record",
    "Tip",
    "default_afm",
    "from_scan",
    "line_scan",
    "load_image",
    "move",
    "press",
    "raster_scan",
    "read_image",
    "read_record",
    "save_image",
]
