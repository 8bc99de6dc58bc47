"""Input validation with messages that name the argument and what is allowed.

Checks run only on concrete values: inside ``jit``/``vmap``/``grad`` the
arguments are tracers and are trusted (they were checked when built).
"""

from __future__ import annotations

import jax
import numpy as np


def is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _values(x):
    return np.asarray(x, dtype=float) if is_concrete(x) else None


def finite(name: str, x) -> None:
    """Raise if ``x`` holds NaN or inf."""
    v = _values(x)
    if v is None:
        return
    bad = ~np.isfinite(v)
    if bad.any():
        idx = np.argwhere(bad)[0]
        raise ValueError(
            f"{name} must be finite, but element {tuple(int(i) for i in idx)} is "
            f"{v[tuple(idx)]!r} ({int(bad.sum())} non-finite of {v.size}); "
            "remove or interpolate the bad samples first"
        )


def some_samples(name: str, x) -> None:
    """Raise if ``x`` holds no samples (its first axis is empty)."""
    shape = np.shape(x)
    if shape and shape[0] == 0:
        raise ValueError(f"{name} holds no samples (shape {shape}): give one or more")


def nonnegative(name: str, x) -> None:
    """Raise if ``x`` holds NaN, inf or a negative value."""
    finite(name, x)
    v = _values(x)
    if v is not None and (v < 0).any():
        idx = tuple(int(i) for i in np.argwhere(v < 0)[0])
        raise ValueError(f"{name} must be >= 0, but element {idx} is {v[idx]!r}")


def positive(name: str, x) -> None:
    """Raise if ``x`` holds NaN, inf or a value <= 0."""
    finite(name, x)
    v = _values(x)
    if v is not None and (v <= 0).any():
        idx = tuple(int(i) for i in np.argwhere(v <= 0)[0])
        raise ValueError(f"{name} must be > 0, but element {idx} is {v[idx]!r}")


def increasing(name: str, x) -> None:
    """Raise if the 1-D array ``x`` is not strictly increasing."""
    finite(name, x)
    v = _values(x)
    if v is None:
        return
    d = np.diff(v)
    bad = d <= 0
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"{name} must be strictly increasing, but {name}[{i}]={v[i]!r} and {name}[{i + 1}]={v[i + 1]!r}"
        )
