"""jaxafm: differentiable AFM scanner models and positioning in JAX.

Importing jaxafm switches JAX to float64: identification needs it (design.md, section 2).
"""

import jax

jax.config.update("jax_enable_x64", True)

from .afm import AFM, Raster, default_afm, line_scan, move, press, raster_scan  # noqa: E402
from .effects import EFFECTS, Bow, Coupling, Creep, Drift, FeedbackLag, Noise, RateDependence  # noqa: E402
from .hysteresis import (  # noqa: E402
    Anhysteretic, Deadzone, GeneralizedPI, Linear, Preisach, PrandtlIshlinskii, play,
)
from .images import AFMImage, load_image, read_image, save_image  # noqa: E402
from .samples import Grating, HeightMap, Indented, Lattice, Particles, Plane, Tip  # noqa: E402
from .scanner import Axis, Scanner, default_scanner  # noqa: E402

__version__ = "0.1.0"
