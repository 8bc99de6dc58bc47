"""jaxafm: differentiable AFM scanner models and positioning in JAX.

Importing jaxafm switches JAX to float64: identification needs it (design.md, section 2).
"""

import jax

jax.config.update("jax_enable_x64", True)

from .instrument.afm import (  # noqa: E402
    AFM,
    Raster,
    default_afm,
    line_scan,
    move,
    press,
    raster_scan,
)
from .instrument.images import AFMImage, load_image, read_image, save_image  # noqa: E402
from .instrument.samples import (  # noqa: E402
    Grating,
    HeightMap,
    Indented,
    Lattice,
    Particles,
    Plane,
    Tip,
)
from .model.effects import (  # noqa: E402
    EFFECTS,
    Bow,
    Coupling,
    Creep,
    Drift,
    FeedbackLag,
    Noise,
    RateDependence,
)
from .model.hysteresis import (  # noqa: E402
    Anhysteretic,
    Deadzone,
    GeneralizedPI,
    Linear,
    PrandtlIshlinskii,
    Preisach,
    play,
)
from .model.scanner import Axis, Scanner, default_scanner  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "AFM",
    "AFMImage",
    "Anhysteretic",
    "Axis",
    "Bow",
    "Coupling",
    "Creep",
    "Deadzone",
    "Drift",
    "EFFECTS",
    "FeedbackLag",
    "GeneralizedPI",
    "Grating",
    "HeightMap",
    "Indented",
    "Lattice",
    "Linear",
    "Noise",
    "Particles",
    "Plane",
    "PrandtlIshlinskii",
    "Preisach",
    "Raster",
    "RateDependence",
    "Scanner",
    "Tip",
    "default_afm",
    "default_scanner",
    "line_scan",
    "load_image",
    "move",
    "play",
    "press",
    "raster_scan",
    "read_image",
    "save_image",
]
