"""Model parameters to and from JSON: readable, versioned, round-trips exactly.

``{"format": "jaxafm-model", "version": 1, "model": {"type": "PrandtlIshlinskii",
"fields": {"thresholds": [...], ...}}}``; arrays as nested lists (V, nm, s as in
the code), nested modules as nested objects, absent effects as ``null``.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from . import effects, hysteresis, scanner

FORMAT, VERSION = "jaxafm-model", 1
_TYPES = {
    cls.__name__: cls
    for module in (hysteresis, effects, scanner)
    for cls in vars(module).values()
    if isinstance(cls, type)
    and issubclass(cls, eqx.Module)
    and cls.__module__ == module.__name__
    and not inspect.isabstract(cls)  # a saved model names concrete classes only
}


def _encode(obj):
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, eqx.Module):
        fields = {f.name: _encode(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        return {"type": type(obj).__name__, "fields": fields}
    arr = np.asarray(obj)
    return {"array": arr.tolist(), "dtype": str(arr.dtype)}


def _decode(obj):
    if isinstance(obj, dict) and "type" in obj:
        if obj["type"] not in _TYPES:
            raise ValueError(f"unknown model type {obj['type']!r} in saved model")
        return _TYPES[obj["type"]](**{k: _decode(v) for k, v in obj["fields"].items()})
    if isinstance(obj, dict) and "array" in obj:
        return jnp.asarray(np.asarray(obj["array"], dtype=obj["dtype"]))
    return obj


def save_model(model, path) -> None:
    """Write ``model`` (any jaxafm scanner, axis, operator or effect) as JSON."""
    Path(path).write_text(json.dumps({"format": FORMAT, "version": VERSION, "model": _encode(model)}))


def load_model(path):
    """Read a model written by :func:`save_model`."""
    path = Path(path)
    doc = json.loads(path.read_text())
    if doc.get("format") != FORMAT:
        raise ValueError(f"{path} is not a saved jaxafm model (format {doc.get('format')!r})")
    if doc.get("version") != VERSION:
        raise ValueError(f"{path}: model format version {doc.get('version')} is not supported ({VERSION} is)")
    return _decode(doc["model"])
