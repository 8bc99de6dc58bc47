"""jaxafm: differentiable AFM scanner models and positioning in JAX.

The layers, each a sub-package, data flowing down the list:

- ``config``: the YAML schemas of every command (no JAX);
- ``model``: the scanner (hysteresis, creep, coupling, bow, drift, noise);
- ``instrument``: the simulated AFM, samples, images and data readers;
- ``identify``: features, fits, step A's calibration and the inverses;
- ``position``: steps B and C and the push; ``study``: Monte-Carlo studies;
- ``diagnose``: the sim-to-real gap, beside identify and position;
- ``cli``: the ``jaxafm`` command.

The public names below are loaded on first use (PEP 562), so ``import jaxafm`` and
``import jaxafm.config`` import no JAX. **Precision:** the first use of any JAX part of jaxafm
switches JAX to float64 (``jax_enable_x64``) for the whole process: identification needs it, and
a model built before the switch would hold float32 arrays (see ``jaxafm._precision``). Figures
are drawn on their own ``matplotlib.figure.Figure`` objects: no backend is chosen, no pyplot
state touched. Units (nm, s, V) and effect names: ``docs/conventions.md``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from ._version import __version__  # jaxafm.__version__

#: public name -> the module that defines it: the one list of the public names
_HOMES = {
    "AFM": "instrument.afm",
    "Raster": "instrument.afm",
    "default_afm": "instrument.afm",
    "line_scan": "instrument.afm",
    "move": "instrument.afm",
    "press": "instrument.afm",
    "raster_scan": "instrument.afm",
    "RasterScan": "instrument.afm",
    "AbstractSample": "instrument.samples",
    "AFMImage": "instrument.images",
    "load_image": "instrument.images",
    "read_image": "instrument.images",
    "save_image": "instrument.images",
    "Grating": "instrument.samples",
    "HeightMap": "instrument.samples",
    "Indented": "instrument.samples",
    "Lattice": "instrument.samples",
    "Particles": "instrument.samples",
    "Plane": "instrument.samples",
    "Tip": "instrument.samples",
    "EFFECTS": "config.names",
    "Bow": "model.effects",
    "Coupling": "model.effects",
    "Creep": "model.effects",
    "Drift": "model.effects",
    "FeedbackLag": "model.effects",
    "Noise": "model.effects",
    "RateDependence": "model.effects",
    "AbstractHysteresis": "model.hysteresis",
    "Anhysteretic": "model.hysteresis",
    "Deadzone": "model.hysteresis",
    "GeneralizedPI": "model.hysteresis",
    "Linear": "model.hysteresis",
    "PrandtlIshlinskii": "model.hysteresis",
    "Preisach": "model.hysteresis",
    "play": "model.hysteresis",
    "load_model": "model.io",
    "predict": "model.apply",
    "Band": "model.posterior",
    "band": "model.posterior",
    "Posterior": "model.posterior",
    "read_model_and_posterior": "model.io",
    "read_model_file": "model.io",
    "save_model": "model.io",
    "Axis": "model.scanner",
    "Scanner": "model.scanner",
    "default_scanner": "model.scanner",
}

#: the public names: the keys of ``_HOMES``; the ``TYPE_CHECKING`` imports below name the same
#: names from the same modules for static tools (``tests/test_layout.py`` checks they agree)
__all__ = sorted(_HOMES)


def __getattr__(name: str):
    """Import a public name's module on first use (PEP 562) and keep the name here."""
    if name not in _HOMES:
        raise AttributeError(f"module 'jaxafm' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what static tools (type checkers, editors, the API docs) see
    from .config.names import EFFECTS
    from .instrument.afm import AFM, Raster, RasterScan, default_afm, line_scan, move, press, raster_scan
    from .instrument.images import AFMImage, load_image, read_image, save_image
    from .instrument.samples import (
        AbstractSample,
        Grating,
        HeightMap,
        Indented,
        Lattice,
        Particles,
        Plane,
        Tip,
    )
    from .model.apply import predict
    from .model.effects import Bow, Coupling, Creep, Drift, FeedbackLag, Noise, RateDependence
    from .model.hysteresis import (
        AbstractHysteresis,
        Anhysteretic,
        Deadzone,
        GeneralizedPI,
        Linear,
        PrandtlIshlinskii,
        Preisach,
        play,
    )
    from .model.io import load_model, read_model_and_posterior, read_model_file, save_model
    from .model.posterior import Band, Posterior, band
    from .model.scanner import Axis, Scanner, default_scanner
