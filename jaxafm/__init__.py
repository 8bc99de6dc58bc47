"""jaxafm: differentiable AFM scanner models and positioning in JAX.

Importing jaxafm switches JAX to float64: identification needs it (design.md, section 2).
"""

import jax

jax.config.update("jax_enable_x64", True)

from .effects import EFFECTS, Bow, Coupling, Creep, Drift, Noise, RateDependence  # noqa: E402
from .hysteresis import (  # noqa: E402
    Anhysteretic, Deadzone, GeneralizedPI, Linear, Preisach, PrandtlIshlinskii, play,
)
from .scanner import Axis, Scanner, default_scanner  # noqa: E402

__version__ = "0.1.0"
