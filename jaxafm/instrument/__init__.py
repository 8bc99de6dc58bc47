"""The instrument: the simulated AFM and the files a real one writes.

``samples`` (surfaces and the tip), ``afm`` (raster and line scans, moves, presses, the
z-feedback), ``images`` (image files in and out) and ``records`` (actuator time-series files).
Imports the model and the shared leaves; importing it switches JAX to float64
(``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
