"""One call to apply any saved model to an input: :func:`predict`.

A model file (:mod:`jaxafm.model.io`) may hold a hysteresis operator (PI, generalised PI,
Preisach, a straight line), an :class:`~jaxafm.model.scanner.Axis` (hysteresis with creep and
rate dependence) or a two-axis :class:`~jaxafm.model.scanner.Scanner`; each is applied the same
way, ``predict(model, u, t, history)``. A one-axis model's :func:`evaluator` is the same output
as a function of the model, its plays run once: what a fit evaluates and a linearisation
differentiates.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Optional

import jax.numpy as jnp
import numpy as np

from .hysteresis import AbstractHysteresis
from .scanner import Axis, Scanner


def predict(model, u, t=None, history=None) -> np.ndarray:
    """The model's output for the input ``u``, starting from rest after ``history``.

    Arguments:
        model: an operator, an ``Axis`` or a ``Scanner`` (e.g. from ``load_model``).
        u: the input, (T,) V for one axis, (T, 2) V for a scanner.
        t: the sample times (T,) s; needed by a model with creep, rate dependence or drift
            (an operator ignores them).
        history: the inputs applied before ``u[0]``, (H,) V or (H, 2) V (e.g. the
            initialisation cycle); None: at rest at ``u[0]``.

    Returns:
        The output, (T,) nm or (T, 2) nm. A scanner's position noise and drift wander (random)
        are left out; its mean drift is kept.

    Raises:
        ValueError: an input of the wrong shape, or a model that needs times without them.
    """
    u = jnp.asarray(u, dtype=float)
    axes = 2 if isinstance(model, Scanner) else 1
    if u.ndim != axes or (axes == 2 and u.shape[1] != 2):
        raise ValueError(
            f"a {type(model).__name__} takes an input u of shape {('(T,)', '(T, 2)')[axes - 1]} V, got {u.shape}"
        )
    if not isinstance(model, (AbstractHysteresis, Axis, Scanner)):
        raise ValueError(f"cannot apply a {type(model).__name__}: not a hysteresis operator, axis or scanner")
    if t is None and not isinstance(model, AbstractHysteresis):
        raise ValueError(
            f"a {type(model).__name__} (with {', '.join(sorted(model.effects))}) needs the sample times t (s)"
        )
    return np.asarray(model.predict(u, None if t is None else jnp.asarray(t, dtype=float), history))


def evaluator(model, u, t=None, history=None) -> Callable:
    """``f(m) = m.predict(u, t, history)`` for one-axis models shaped like ``model``, with the
    plays run once.

    A fit keeps every threshold grid fixed, so the play trajectories -- the only sequential part
    of the hysteresis -- do not depend on the fitted parameters
    (:meth:`~jaxafm.model.hysteresis.AbstractHysteresis.evaluator`): a fit and a linearisation
    (:func:`~jaxafm.model.posterior.linearise`) evaluate and differentiate the rest alone.

    Arguments:
        model: a hysteresis operator or an :class:`~jaxafm.model.scanner.Axis`.
        u: the input (T,) V.
        t: the sample times (T,) s; an Axis needs them.
        history: the inputs (H,) V before ``u[0]``, or ``None``.

    Returns:
        ``f(m) -> (T,) nm`` for models ``m`` of the same structure.
    """
    h = model.hysteresis if isinstance(model, Axis) else model
    hysteresis = h.evaluator(u, history)
    if isinstance(model, Axis):
        if t is None:
            raise ValueError("an Axis (creep or rate dependence) needs the sample times t (s)")
        t = jnp.asarray(t, dtype=float)
        return lambda m: m.dynamics(hysteresis(m.hysteresis), t)
    return hysteresis


def axes_of(model) -> int:
    """How many axes a model drives: 2 for a scanner, else 1."""
    return 2 if isinstance(model, Scanner) else 1


def input_history(about: dict, override: Optional[list] = None):
    """The history a prediction starts from: ``override`` if given, else the one the model file
    says it was fitted with (None: at rest at the first input)."""
    chosen = override if override is not None else about.get("history_v")
    return None if chosen is None else jnp.asarray(chosen, dtype=float)
