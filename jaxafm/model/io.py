"""Model parameters to and from JSON: readable, versioned, self-describing, round-trips exactly.

``{"format": "jaxafm-model", "version": 5, "model": {"type": "PrandtlIshlinskii",
"fields": {"thresholds": [...], ...}}, "about": {...}, "uncertainty": {...} or null}``; arrays
as nested lists (V, nm, s as in the code), nested modules as nested objects, absent effects as
``null``. ``about`` (:func:`describe`) says how to use the model: units, axes, effects, the
input history it assumes, the input and output ranges it was fitted on, the data, the jaxafm
version. ``uncertainty`` is the fit's :class:`~jaxafm.model.posterior.Posterior`
(:meth:`~jaxafm.model.posterior.Posterior.to_dict`), checked on load. Version-1 files (no
``about``) and version-2 files (no ``uncertainty``) are still read, as models without one;
version-3 files (lags without ``hold``) read their lags as the zero hold, which they were.
Version-3 and 4 files of a model with creep are read without their uncertainty: it is over
creep weights of either sign, and a fit keeps them >= 0
(:meth:`~jaxafm.model.effects.Creep.free_parameters`).
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
from pathlib import Path
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import effects, hysteresis, scanner
from .posterior import Posterior

FORMAT, VERSION = "jaxafm-model", 5
READABLE = (1, 2, 3, 4, 5)  # format versions this jaxafm reads
SIGNED_CREEP = (3, 4)  # format versions whose uncertainty is over creep weights of either sign
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


def _decode(obj, where: str = "model"):
    """The module or array ``obj`` encodes; ``where``: its place in the file, for errors.

    Raises:
        ValueError: an unknown type, or a number that is not finite (naming its place).
    """
    if isinstance(obj, dict) and "type" in obj:
        if obj["type"] not in _TYPES:
            raise ValueError(f"unknown model type {obj['type']!r} in saved model")
        return _TYPES[obj["type"]](**{k: _decode(v, f"{where}.{k}") for k, v in obj["fields"].items()})
    if isinstance(obj, dict) and "array" in obj:
        a = np.asarray(obj["array"], dtype=obj["dtype"])
        bad = np.flatnonzero(~np.isfinite(a)) if a.dtype.kind == "f" else ()
        if len(bad):
            raise ValueError(
                f"{where}: element {int(bad[0])} is {a.ravel()[bad[0]]}, but a saved model holds finite "
                "numbers only; was the file edited by hand?"
            )
        return jnp.asarray(a)
    return obj


def save_model(model, path, about: Optional[dict] = None, posterior: Optional[Posterior] = None) -> None:
    """Write ``model`` (any jaxafm scanner, axis, operator or effect) as JSON, with ``about``
    (:func:`describe`; default: its units, axes and effects only) and its ``posterior`` (None:
    none), atomically: a reader (or a run killed while writing) sees the old file or the whole
    new one."""
    path = Path(path)
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "model": _encode(model),
        "about": about or describe(model),
        "uncertainty": None if posterior is None else posterior.to_dict(),
    }
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(doc, indent=None))
    tmp.replace(path)


def describe(model, u=None, d=None, *, history=None, source: str = "", **more) -> dict:
    """What a model file says about its model: units, ``axes`` (1 or 2), ``effects``, the
    ``history_v`` it assumes before the first sample (None: at rest at the first input), the
    ``input_range_v`` and ``output_range_nm`` of the data it was fitted on (``u`` (T,) or
    (T, 2) V, ``d`` nm; one [min, max] per axis), ``fitted_to`` (``source``, samples), the
    jaxafm version and anything in ``more``."""
    from .._version import __version__

    ranges = lambda a: (
        None if a is None else np.stack([np.min(a, 0), np.max(a, 0)], -1).reshape(-1, 2).tolist()
    )
    return {
        "units": {"input": "V", "output": "nm", "time": "s"},
        "axes": 2 if isinstance(model, scanner.Scanner) else 1,
        "effects": sorted(getattr(model, "effects", ())),
        "history_v": None if history is None else np.asarray(history, dtype=float).tolist(),
        "input_range_v": ranges(None if u is None else np.asarray(u, dtype=float)),
        "output_range_nm": ranges(None if d is None else np.asarray(d, dtype=float)),
        "fitted_to": {"source": source, "samples": None if u is None else len(u)},
        "jaxafm_version": __version__,
    } | more


def load_model(path):
    """Read a model written by :func:`save_model`, and check that it can be used (see
    :func:`read_model_file`, which also returns what the file says about the model)."""
    return read_model_file(path)[0]


def read_model_file(path) -> tuple:
    """A saved model and its ``about`` (:func:`describe`; ``{}`` in a version-1 file).

    Raises:
        ValueError: naming the file: not a saved model, a format version this jaxafm does not
            read, broken (truncated, edited into something that cannot be built), not
            monotone (:func:`check_monotone`) or with an uncertainty that does not fit it
            (:meth:`~jaxafm.model.posterior.Posterior.from_dict`).
    """
    model, about, _ = read_model_and_posterior(path)
    return model, about


def read_model_and_posterior(path) -> tuple:
    """:func:`read_model_file`'s model and ``about``, and the model's posterior (None where the
    file holds none: written by ``jaxafm calibrate``, by hand, or in format version 1 or 2; and
    for a model with creep in format version 3 or 4, whose uncertainty is over signed creep weights)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file {path} does not exist")
    try:
        doc = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not a saved jaxafm model: not JSON ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise ValueError(f"{path} is not a saved jaxafm model (format {found!r})")
    if doc.get("version") not in READABLE:
        raise ValueError(
            f"{path}: model format version {doc.get('version')!r} is not one this jaxafm reads "
            f"({', '.join(map(str, READABLE))}); it was written by another jaxafm version"
        )
    try:
        model = _decode(doc["model"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: a broken saved model ({type(e).__name__}: {e})") from None
    try:
        check_monotone(model)
    except ValueError as e:
        raise ValueError(f"{path}: {e}; was the file edited by hand?") from None
    about = doc.get("about") or {}
    if not isinstance(about, dict):
        raise ValueError(f"{path}: 'about' must be a mapping, got {type(about).__name__}")
    if doc.get("uncertainty") is None or (doc["version"] in SIGNED_CREEP and _has_creep(model)):
        return model, about, None
    try:
        return model, about, Posterior.from_dict(doc["uncertainty"], model)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from None


def _has_creep(model) -> bool:
    """Whether ``model`` has a creep stage anywhere."""
    leaves = jax.tree_util.tree_leaves(model, is_leaf=lambda m: isinstance(m, effects.Creep))
    return any(isinstance(leaf, effects.Creep) for leaf in leaves)


def check_monotone(model) -> None:
    """Refuse a hysteresis model whose loading curve falls somewhere: it cannot be inverted, and
    it drives a scanner the wrong way. The conditions, for every operator inside ``model``:

    - Prandtl–Ishlinskii: the loading curve's slope between thresholds ``r_i`` and
      ``r_{i+1}`` is ``w_0 + ... + w_i``, which must be > 0 for every ``i`` (Kuhnen 2003);
    - dead zones: ``g_0 + g_1 + ... + g_i`` > 0 on each side (the same for the output map);
    - Preisach: every density >= 0 (a negative one makes some minor loop run backwards);
    - a straight line: gain > 0 nm/V.

    Raises:
        ValueError: naming the parameter, the element and its value.
    """
    ruled = tuple(_RULES)
    for key, leaf in jax.tree_util.tree_leaves_with_path(model, is_leaf=lambda m: isinstance(m, ruled)):
        if isinstance(leaf, ruled):
            for name, values, floor in _RULES[type(leaf)](leaf):
                v = np.ravel(np.asarray(values, dtype=float))
                bad = v < 0 if floor == ">= 0" else v <= 0
                if bad.any():
                    i = int(np.argmax(bad))
                    raise ValueError(
                        f"{type(leaf).__name__} {jax.tree_util.keystr(key) or '(the model)'}: {name} "
                        f"must be {floor} for a monotone model, but element {i} is {v[i]:.4g}"
                    )


#: type -> [(what, values, the bound they must keep)]: the conditions of :func:`check_monotone`.
_RULES = {
    hysteresis.PrandtlIshlinskii: lambda m: [("the partial sums of weights", np.cumsum(m.weights), "> 0")],
    hysteresis.Deadzone: lambda m: [
        ("slope + the partial sums of upper_weights", m.slope + np.cumsum(m.upper_weights), "> 0"),
        ("slope + the partial sums of lower_weights", m.slope + np.cumsum(m.lower_weights), "> 0"),
    ],
    hysteresis.Preisach: lambda m: [("density (lower triangle)", np.tril(m.density), ">= 0")],
    hysteresis.Linear: lambda m: [("gain", m.gain, "> 0")],
}
