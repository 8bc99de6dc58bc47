"""Inverse models: the drive ``u(t)`` (V) that puts the tip at wanted positions (nm).

Step A's compensation. The fitted scanner is inverted stage by stage, in the
reverse order of the forward model, one sample at a time so that every
stateful stage carries its state:

1. drift: subtract the model's drift velocity times the time since its origin;
2. coupling and bow: a fixed-point solve of ``v + C(v) = q`` (C is a few % of v);
3. creep and rate lag: one step of a first-order lag is affine in its input, so
   the hysteresis output that gives ``v`` is ``(v - f(0)) / (f(1) - f(0))``;
4. hysteresis, one of
   - ``"analytic"``: the operator's exact inverse (``inverse()``, for a PI or
     generalised-PI model: Kuhnen & Janocha), run after the initialisation cycle
     on the output history;
   - ``"numerical"``: per sample from the plays' state (``invert_step``), exact
     for a PI or generalised-PI model, else a safeguarded Newton root find of the
     monotone map ``u -> H[u; plays]`` (Preisach too).

The paper's baseline, a neural network trained on (position, voltage) pairs per
branch, is :class:`NeuralInverse`.
"""

from __future__ import annotations

import time
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import checks
from ..model.scanner import Axis, AxisState, Scanner, ScannerState

Array = jax.Array
METHODS = ("analytic", "numerical")


def _undo_coupling(model: Scanner, q: Array, iterations: int = 8) -> Array:
    """Axis outputs ``v`` (2,) nm with ``bow(coupling(v)) = q``, by fixed-point iteration."""

    def forward_extra(v):
        p = v
        if model.coupling is not None:
            p = model.coupling(p)
        if model.bow is not None:
            p = model.bow(p)
        return p - v

    return lax.fori_loop(0, iterations, lambda _, v: q - forward_extra(v), q)


def _dynamics(axis: Axis, h: Array, t: Array, s: AxisState, t0: Array) -> tuple:
    """One sample of the axis's lag and creep after the hysteresis output ``h``: (output, lag, creep)."""
    v, lag, creep = jnp.reshape(h, (1,)), s.lag, s.creep
    tt = jnp.reshape(t, (1,))
    if axis.rate_dependence is not None:
        v, lag = axis.rate_dependence.run(v, tt, lag, t0)
    if axis.creep is not None:
        v, creep = axis.creep.run(v, tt, creep, t0)
    return v[0], lag, creep


def _hysteresis_target(axis: Axis, v: Array, t: Array, s: AxisState, t0: Array) -> Array:
    """The hysteresis output that makes the axis output ``v`` at time ``t`` (affine solve)."""
    f0 = _dynamics(axis, jnp.zeros(()), t, s, t0)[0]
    f1 = _dynamics(axis, jnp.ones(()), t, s, t0)[0]
    return (v - f0) / (f1 - f0)


def _step_axis(axis: Axis, v: Array, t: Array, s: AxisState, t0: Array, u_prev: Array, lo, hi):
    """One sample of the numerical inverse on one axis: the drive (V) that puts its output at
    ``v`` nm at time ``t``, the state after it, and whether it saturated at ``lo`` or ``hi`` V."""
    h = _hysteresis_target(axis, v, t, s, t0)
    u, saturated = axis.hysteresis.invert_step(h, s.plays, lo, hi, u_prev)
    y, plays = axis.hysteresis.step(u, s.plays)
    _, lag, creep = _dynamics(axis, y, t, s, t0)
    return u, AxisState(plays, lag, creep), saturated


def _targets(model: Scanner, wanted: Array, t: Array, state: ScannerState) -> Array:
    """Axis outputs (T, 2) nm wanted before coupling, bow and drift."""
    q = wanted
    if model.drift is not None:
        q = q - model.drift.velocity * (t - state.origin)[:, None]
    return jax.vmap(lambda p: _undo_coupling(model, p))(q)


@eqx.filter_jit
def numerical_inverse(model: Scanner, wanted: Array, t: Array, state: ScannerState, u0: Array, u_max: float):
    """The drive (T, 2) V that puts ``model``, from ``state`` with the drive at ``u0``, at ``wanted``
    (T, 2) nm at times ``t``, sample by sample, and where each sample saturated at ``+-u_max``."""
    v = _targets(model, wanted, t, state)

    def step(carry, inputs):
        sx, sy, t_prev, u_prev = carry
        vn, tn = inputs
        ux, sx, bad_x = _step_axis(model.x, vn[0], tn, sx, t_prev, u_prev[0], -u_max, u_max)
        uy, sy, bad_y = _step_axis(model.y, vn[1], tn, sy, t_prev, u_prev[1], -u_max, u_max)
        u = jnp.stack([ux, uy])
        return (sx, sy, tn, u), (u, jnp.stack([bad_x, bad_y]))

    _, (u, saturated) = lax.scan(step, (state.x, state.y, state.t, u0), (v, t))
    return u, saturated


@eqx.filter_jit
def invert_axis(axis: Axis, wanted: Array, t: Array, state: AxisState, t0, u0, lo, hi) -> tuple:
    """The drive (T,) V that puts one ``axis``, from ``state`` reached at ``t0`` s with the drive
    at ``u0`` V, at ``wanted`` (T,) nm at times ``t`` (T,) s, sample by sample (the numerical
    inverse of :func:`numerical_inverse` on one axis), with every drive kept in [``lo``, ``hi``]
    V; and where each sample saturated there."""

    def step(carry, inputs):
        s, t_prev, u_prev = carry
        v, tn = inputs
        u, s, saturated = _step_axis(axis, v, tn, s, t_prev, u_prev, lo, hi)
        return (s, tn, u), (u, saturated)

    _, (u, saturated) = lax.scan(
        step, (state, jnp.asarray(t0, dtype=float), jnp.asarray(u0, dtype=float)), (wanted, t)
    )
    return u, saturated


@eqx.filter_jit
def _analytic(model: Scanner, wanted: Array, t: Array, state: ScannerState, history: Array):
    v = _targets(model, wanted, t, state)

    def step(carry, inputs):
        sx, sy, t_prev = carry
        vn, tn = inputs
        hs, new = [], []
        for axis, s, vk in ((model.x, sx, vn[0]), (model.y, sy, vn[1])):
            h = _hysteresis_target(axis, vk, tn, s, t_prev)
            _, lag, creep = _dynamics(axis, h, tn, s, t_prev)
            hs.append(h)
            new.append(AxisState(s.plays, lag, creep))
        return (new[0], new[1], tn), jnp.stack(hs)

    _, h = lax.scan(step, (state.x, state.y, state.t), (v, t))
    u = []
    for k, axis in enumerate((model.x, model.y)):
        H = axis.hysteresis
        u.append(H.inverse()(h[:, k], history=H(history[:, k])))
    return jnp.stack(u, axis=-1)


class Compensator(eqx.Module):
    """The drive for wanted positions through a fitted scanner model, from the model's
    ``state`` (where the twin of the instrument stands) with the drive at ``u_now`` (2,) V.

    ``method``: ``"numerical"`` (any hysteresis model, any state) or ``"analytic"``
    (a model whose operator ``has_inverse``: PI, generalised-PI or linear, right after the
    initialisation cycle: ``history`` (H, 2) V,
    the cycle and any monotone moves since). ``u_range`` (2, 2) V: the drive range the
    model was fitted over, per axis [min, max]; a wanted position that needs a drive
    outside it raises an error. Call as ``volts(wanted, t)``: wanted (T, 2) nm, t (T,) s.
    """

    model: Scanner
    state: ScannerState
    u_now: Array
    u_range: np.ndarray
    method: str = eqx.field(static=True, default="numerical")
    history: Optional[Array] = None
    u_max: float = eqx.field(static=True, default=10.0)

    def __check_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown inverse method {self.method!r}; one of {', '.join(METHODS)}")
        if self.method == "analytic":
            for a in ("x", "y"):
                h = getattr(self.model, a).hysteresis
                if not h.has_inverse:
                    raise ValueError(
                        f"the analytic inverse needs a hysteresis model with one (PI or generalised-PI), "
                        f"but axis {a} has a {type(h).__name__}: use method='numerical'"
                    )
            if self.history is None:
                raise ValueError(
                    "the analytic inverse needs the drive history since the initialisation cycle"
                )

    def __call__(self, wanted: Array, t: Array) -> Array:
        wanted, t = jnp.asarray(wanted, dtype=float), jnp.asarray(t, dtype=float)
        if wanted.ndim != 2 or wanted.shape[1] != 2 or t.shape != wanted.shape[:1]:
            raise ValueError(
                f"wanted positions must be (T, 2) nm with times (T,) s, got {wanted.shape}, {t.shape}"
            )
        checks.increasing("times t", t)
        if self.method == "analytic":
            u = _analytic(self.model, wanted, t, self.state, jnp.asarray(self.history, dtype=float))
            saturated = np.zeros(u.shape, dtype=bool)
        else:
            u, saturated = numerical_inverse(
                self.model, wanted, t, self.state, jnp.asarray(self.u_now, dtype=float), self.u_max
            )
        self._check(np.asarray(u), np.asarray(saturated), np.asarray(wanted))
        return u

    def _check(self, u: np.ndarray, saturated: np.ndarray, wanted: np.ndarray) -> None:
        lo, hi = np.asarray(self.u_range)[:, 0], np.asarray(self.u_range)[:, 1]
        margin = 0.02 * (hi - lo)
        bad = saturated | (u < lo - margin) | (u > hi + margin) | ~np.isfinite(u)
        if bad.any():
            n, k = np.argwhere(bad)[0]
            raise ValueError(
                f"wanted position ({wanted[n, 0]:.0f}, {wanted[n, 1]:.0f}) nm needs a drive of {u[n, k]:.3g} V on "
                f"{'xy'[k]}, outside the range the model was fitted over, [{lo[k]:.3g}, {hi[k]:.3g}] V: "
                "keep targets inside the calibrated area or calibrate over a larger scan"
            )


# ---------------------------------------------------------------------------------------------
# The paper's baseline: a small neural network per branch, position -> voltage


class NeuralInverse(eqx.Module):
    """A 1 -> width -> width -> 1 tanh network mapping position (nm) to drive (V) on one branch,
    with inputs and outputs scaled to about [-1, 1] (the paper's inverse model, section III-A)."""

    layers: tuple
    x_scale: tuple = eqx.field(static=True)
    u_scale: tuple = eqx.field(static=True)

    def __call__(self, x: Array) -> Array:
        h = (jnp.asarray(x, dtype=float)[..., None] - self.x_scale[0]) / self.x_scale[1]
        for w, b in self.layers[:-1]:
            h = jnp.tanh(h @ w + b)
        w, b = self.layers[-1]
        return (h @ w + b)[..., 0] * self.u_scale[1] + self.u_scale[0]


def train_neural_inverse(
    x: np.ndarray, u: np.ndarray, width: int = 16, seed: int = 0, max_steps: int = 3000
) -> tuple:
    """Fit a :class:`NeuralInverse` to pairs ``x`` (nm) -> ``u`` (V) by BFGS (optimistix) on the
    mean squared error; returns ``(network, seconds)``."""
    import optimistix as optx

    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    xs = (float(x.mean()), float(np.ptp(x) / 2) or 1.0)
    us = (float(u.mean()), float(np.ptp(u) / 2) or 1.0)
    keys = jax.random.split(jax.random.key(seed), 3)
    sizes = [(1, width), (width, width), (width, 1)]
    layers = tuple((jax.random.normal(k, s) / np.sqrt(s[0]), jnp.zeros(s[1])) for k, s in zip(keys, sizes))
    net = NeuralInverse(layers, xs, us)
    params, static = eqx.partition(net, eqx.is_inexact_array)

    def loss(p, _):
        return jnp.mean(((eqx.combine(p, static)(x) - u) / us[1]) ** 2)

    start = time.perf_counter()
    sol = optx.minimise(loss, optx.BFGS(rtol=1e-10, atol=1e-12), params, max_steps=max_steps, throw=False)
    return eqx.combine(sol.value, static), time.perf_counter() - start
