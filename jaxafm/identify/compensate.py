"""The drive that makes a model (one axis, or a two-axis scanner) follow a wanted trajectory
(the paper's step A, "exerting the input sequence on the piezo-actuator").

The drive starts with the initialisation cycle ``{u2, u1}``: from the lower end ``u2`` of the
input range the model was fitted on, a ramp to its upper end ``u1``, which wipes out the
actuator's memory (the wiping-out property), so that the model knows its state. From there the
wanted trajectory is inverted through the analytic inverse (a PI or generalised-PI operator, or a
scanner whose axes have one: Kuhnen & Janocha) or the numerical one (any model: per sample from
the plays' state, through creep, rate dependence and a scanner's coupling, bow and mean drift).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..model.hysteresis import AbstractHysteresis
from ..model.scanner import Axis, Scanner, mean_scanner
from .inverse import Compensator, invert_axis


def choose_method(model, method: str) -> str:
    """``analytic`` for an operator that has an exact inverse (PI, generalised PI, a line) or a
    scanner whose axes have one, else ``numerical``; an explicit ``analytic`` for another model
    is an error."""
    if isinstance(model, Scanner):
        exact = all(a.hysteresis.has_inverse for a in (model.x, model.y))
    else:
        exact = isinstance(model, AbstractHysteresis) and model.has_inverse
    if method == "analytic" and not exact:
        raise ValueError(
            f"method: analytic needs PI, generalised-PI or linear hysteresis (on a scanner, on both "
            f"axes; on one axis, without creep or rate dependence), but the model is a "
            f"{type(model).__name__} with {', '.join(sorted(model.effects)) or 'no effects'}: use numerical"
        )
    return method if method != "auto" else ("analytic" if exact else "numerical")


def drive(model, t: np.ndarray, x: np.ndarray, u_range: np.ndarray, cycle_s: float, method: str) -> tuple:
    """The whole drive: the initialisation cycle, then the inverse of the trajectory.

    Arguments:
        model: a one-axis model or a scanner.
        t: times (T,) s; x: wanted positions (T, A) nm.
        u_range: the fitted input range (A, 2) V; the cycle runs from its lower to its upper end.
        cycle_s: the cycle's duration, s.
        method: ``analytic`` or ``numerical``.

    Returns:
        Times (C + T,) s, drives (C + T, A) V and C, the number of cycle samples.

    Raises:
        ValueError: the trajectory needs a drive outside ``u_range``.
    """
    dt = float(np.median(np.diff(t)))
    n = max(2, int(round(cycle_s / dt)))
    u_cycle = np.linspace(u_range[:, 0], u_range[:, 1], n)  # (n, A)
    t_cycle = dt * np.arange(n)
    times = t_cycle[-1] + dt + t
    if isinstance(model, Scanner):
        u = _scanner_inverse(mean_scanner(model), x, times, u_cycle, t_cycle, u_range, method)
    else:
        u = _axis_inverse(model, x[:, 0], times, u_cycle[:, 0], t_cycle, u_range[0], method)[:, None]
    return np.concatenate([t_cycle, times]), np.concatenate([u_cycle, u]), n


def _axis_inverse(model, x, times, u_cycle, t_cycle, u_range, method) -> np.ndarray:
    """One axis's drive (T,) V after the cycle: exact inverse or per-sample numerical inverse."""
    if method == "analytic":
        u = np.asarray(model.inverse()(jnp.asarray(x), history=model(jnp.asarray(u_range))))
        saturated = (u < u_range[0]) | (u > u_range[1])
    else:
        axis = model if isinstance(model, Axis) else Axis(model)
        state = axis.initial_state(u_cycle[0])
        _, state = axis.run(jnp.asarray(u_cycle), jnp.asarray(t_cycle), state, jnp.asarray(t_cycle[0]))
        u, saturated = invert_axis(
            axis, jnp.asarray(x), jnp.asarray(times), state, t_cycle[-1], u_cycle[-1], *u_range
        )
        u, saturated = np.asarray(u), np.asarray(saturated)
    margin = 1e-6 * (u_range[1] - u_range[0])
    bad = saturated & ((u <= u_range[0] + margin) | (u >= u_range[1] - margin))
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(
            f"trajectory: the wanted {x[k]:.1f} nm at {times[k] - times[0]:.3g} s needs a drive beyond the "
            f"fitted input range [{u_range[0]:.3g}, {u_range[1]:.3g}] V ({100 * bad.mean():.1f} % of the samples)"
        )
    return u


def _scanner_inverse(model: Scanner, x, times, u_cycle, t_cycle, u_range, method) -> np.ndarray:
    """A scanner's drive (T, 2) V after the cycle, through step A's :class:`Compensator`."""
    state = model.initial_state(u_cycle[0], t_cycle[0])
    _, state = model.run(jnp.asarray(u_cycle), jnp.asarray(t_cycle), state, jax.random.key(0))
    volts = Compensator(
        model,
        state,
        jnp.asarray(u_cycle[-1]),
        u_range,
        method,
        history=jnp.asarray(u_range.T),  # {u2, u1} per axis: what the cycle leaves in the plays
        u_max=float(np.abs(u_range).max()),
    )
    try:
        return np.asarray(volts(jnp.asarray(x), jnp.asarray(times)))
    except ValueError as e:
        raise ValueError(f"trajectory: {e}") from None
