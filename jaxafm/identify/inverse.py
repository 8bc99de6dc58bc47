"""Inverse models: the drive ``u(t)`` (V) that puts the tip at wanted positions (nm).

Step A's compensation. The fitted scanner is inverted stage by stage, in the
reverse order of the forward model:

1. drift: subtract the model's drift velocity times the time since its origin;
2. coupling and bow: a fixed-point solve of ``v + C(v) = q`` (C is a few % of v), every
   sample at once;
3. creep and rate lag: one step of a first-order lag is affine in its input,
   ``v_n = alpha_n h_n + f_n(0)``, so the hysteresis output that gives ``v_n`` is
   ``h_n = (v_n - f_n(0)) / alpha_n``; the decays and ``alpha_n`` depend only on the sample
   times and are computed for all samples at once, only the lags' small state steps;
4. hysteresis, one of
   - ``"analytic"``: the operator's exact inverse (``inverse()``, for a PI or
     generalised-PI model: Kuhnen & Janocha), run after the initialisation cycle
     on the output history;
   - ``"numerical"``: from the plays' state, any state. An operator whose inverse is again
     a play operator (``block_inverse``: PI, generalised PI, linear) is inverted over blocks
     of samples as the forward model runs (one scan for both axes: per sample the lags and
     the inverse plays, per block the drives), from the inverse plays that stand where the
     model's plays stand. Where that does not hold (a drive beyond the limits, a state the
     closed form does not cover) and for other operators, the axis steps sample by sample:
     ``invert_step`` (exact for a PI or generalised-PI model, else a safeguarded Newton root
     find of the monotone map ``u -> H[u; plays]``, Preisach too), the lags following the
     output the drive really gives. Both give the same drive (to rounding) and the model's
     state after it (:func:`inverse_and_state`), so a twin need not run the model again.

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


def axis_targets(model: Scanner, wanted: Array, t: Array, state: ScannerState) -> Array:
    """The axes' outputs (T, 2) nm that put the tip at ``wanted`` (T, 2) nm at times ``t`` (T,) s:
    the scanner's two-axis stages (:meth:`~jaxafm.model.scanner.Scanner.couple`) undone, its
    mean drift since ``state.origin`` taken off, then coupling and bow inverted."""
    q = wanted
    if model.drift is not None:
        q = q - model.drift.velocity * (t - state.origin)[:, None]
    return jax.vmap(lambda p: _undo_coupling(model, p))(q)


def _lag_factors(axis: Axis, t: Array, t0) -> tuple:
    """Per sample, the rate lag's step weights ``(a, b_prev, b_now)`` (each (T,),
    :meth:`~jaxafm.model.effects.FirstOrderLag.weights`), the creep lags' decays
    ``a = exp(-dt / tau)`` (T, K), and the gain ``alpha`` (T,) of the hysteresis output in the
    axis output, ``alpha = b_now (1 + sum_k g_k (1 - a_k))`` (a missing stage is a factor 1)."""
    dt = jnp.diff(t, prepend=jnp.reshape(t0, (1,)))
    rate = creep = None
    gain = jnp.ones_like(dt)
    if axis.rate_dependence is not None:
        rate = axis.rate_dependence.weights(dt)
        gain = gain * rate[2]
    if axis.creep is not None:
        creep = jnp.exp(-dt[:, None] / axis.creep.taus)
        gain = gain * (1 + (1 - creep) @ axis.creep.weights)
    return rate, creep, gain


def _lag_step(axis: Axis, lag: Array, creep: tuple, h, a_rate, a_creep) -> tuple:
    """One sample of the rate lag (:meth:`~jaxafm.model.effects.FirstOrderLag.advance`, weights
    ``a_rate``) and creep (every creep lag ``z <- a z + (1 - a) x``) after the hysteresis output
    ``h`` nm: (output, lag, creep). Sums written out, not as matrix products: inside a scan over
    samples this fuses into one loop."""
    v = h
    if axis.rate_dependence is not None:
        lag = axis.rate_dependence.advance(lag, v, a_rate)
        v = lag[0]
    if axis.creep is not None:
        z, rest = creep
        z = a_creep * z + (1 - a_creep) * v
        v = v + jnp.sum(z * axis.creep.weights, axis=-1) - rest * jnp.sum(axis.creep.weights)
        creep = (z, rest)
    return v, lag, creep


def _lag_target(axis: Axis, v, lag, creep, a_rate, a_creep, gain):
    """The hysteresis output that puts the axis output at ``v`` nm: ``(v - f(0)) / alpha``."""
    return (v - _lag_step(axis, lag, creep, 0.0, a_rate, a_creep)[0]) / gain


def _invertible(axis: Axis) -> None:
    """Raise for a stage the inverses do not undo: a mechanical mode (``vibration``) needs the
    wanted path's second derivative (``v = x + 2 zeta x' / w0 + x'' / w0^2``), which a sampled
    path does not give without filtering it."""
    if axis.vibration is not None:
        raise ValueError(
            "this model has a vibration stage (a mechanical mode), which the inverses do not undo; "
            "compensate with model.without('vibration') and keep the wanted path's rate well below "
            "the mode's frequency"
        )


def _lag_inverse(axis: Axis, v: Array, t: Array, state: AxisState, t0) -> Array:
    """The hysteresis outputs (T,) nm that put ``axis``'s output at ``v`` (T,) nm at times ``t``
    from ``state`` reached at ``t0``, the lags following those outputs: one scan over the lags'
    small state (the hysteresis does not enter it)."""
    _invertible(axis)
    if axis.rate_dependence is None and axis.creep is None:
        return v
    factors = _lag_factors(axis, t, t0)

    def step(carry, inputs):
        vn, a_rate, a_creep, gain = inputs
        h = _lag_target(axis, vn, *carry, a_rate, a_creep, gain)
        return _lag_step(axis, *carry, h, a_rate, a_creep)[1:], h

    return lax.scan(step, (state.lag, state.creep), (v, *factors))[1]


def _per_sample(axis: Axis, v: Array, t: Array, state: AxisState, t0, u0, lo, hi) -> tuple:
    """The drive (T,) V for the axis outputs ``v`` (T,) nm sample by sample: each sample's
    hysteresis output from the lags (:func:`_lag_target`), the drive from the plays
    (``invert_step``, kept in [``lo``, ``hi``]), then the lags follow the output that drive
    really gives. Returns the drive, where it saturated and the axis's state after it."""
    H = axis.hysteresis

    def step(carry, inputs):
        s, u_prev = carry
        vn, a_rate, a_creep, gain = inputs
        h = _lag_target(axis, vn, s.lag, s.creep, a_rate, a_creep, gain)
        u, saturated = H.invert_step(h, s.plays, lo, hi, u_prev)
        y, plays = H.step(u, s.plays)
        _, lag, creep = _lag_step(axis, s.lag, s.creep, y, a_rate, a_creep)
        return (AxisState(plays, lag, creep), u), (u, saturated)

    carry = (state, jnp.asarray(u0, dtype=float))
    (state, _), (u, saturated) = lax.scan(step, carry, (v, *_lag_factors(axis, t, t0)))
    return u, saturated, state


def _blocks(tree, T: int, block: int):
    """Every (T, ...) array of ``tree`` padded to whole blocks (its last sample repeated) and cut
    into (blocks, block, ...)."""
    nb = -(-T // block)

    def cut(a):
        a = jnp.concatenate([a, jnp.repeat(a[-1:], nb * block - T, axis=0)])
        return a.reshape((nb, block) + a.shape[1:])

    return jax.tree_util.tree_map(cut, tree)


def _blocked(axes: list, v: list, t: Array, states: list, t0, block: int = 16) -> list:
    """The drives for axis outputs ``v`` (one (T,) nm per axis) of axes whose hysteresis has a
    :meth:`~jaxafm.model.hysteresis.AbstractHysteresis.block_inverse`, all axes in one scan
    over blocks of ``block`` samples: per sample the lags' target ``h`` (:func:`_lag_target`),
    the lags following it and the inverse plays ``q <- clip(q, pre(h) - r', pre(h) + r')``;
    per block the drives ``readout(Q)``. Returns per axis (drive (T,) V, whether it is exact,
    the axis's state after it)."""
    T = t.shape[0]
    inverses = [a.hysteresis.block_inverse(s.plays) for a, s in zip(axes, states)]
    inputs = [(vk, *_lag_factors(a, t, t0)) for a, vk in zip(axes, v)]
    live = _blocks(jnp.ones(T, bool), T, block).at[-1, (T - 1) % block + 1 :].set(False)

    def sample(carry, x):
        xs, keep = x
        new = []
        for a, b, (lag, creep, q), (vn, a_rate, a_creep, gain) in zip(axes, inverses, carry, xs):
            h = _lag_target(a, vn, lag, creep, a_rate, a_creep, gain)
            _, lag, creep = _lag_step(a, lag, creep, h, a_rate, a_creep)
            z = b.pre(h)
            new.append((lag, creep, jnp.clip(q, z - b.radii, z + b.radii)))
        new = jax.tree_util.tree_map(lambda n, o: jnp.where(keep, n, o), new, carry)  # padding: no move
        return new, [c[2] for c in new]

    def run_block(carry, x):
        carry, Q = lax.scan(sample, carry, x)
        return carry, [b.readout(Qk) for b, Qk in zip(inverses, Q)]

    start = [(s.lag, s.creep, b.plays) for s, b in zip(states, inverses)]
    end, u = lax.scan(run_block, start, (_blocks(inputs, T, block), live))
    out = []
    for b, uk, (lag, creep, q) in zip(inverses, u, end):
        uk = uk.reshape(-1)[:T]
        out.append((uk, b.exact & jnp.all(jnp.isfinite(uk)), AxisState(b.state(q), lag, creep)))
    return out


def _or_per_sample(axis: Axis, v: Array, t: Array, state: AxisState, t0, u0, lo, hi, blocked) -> tuple:
    """The blocked result ``(u, exact, next state)`` of one axis where it holds (exact, every drive
    in [``lo``, ``hi``]), else the axis inverted again sample by sample: a ``while_loop`` that
    runs no iteration when it is not needed, also under ``vmap``. Returns (drive, saturated,
    next state)."""
    u, exact, after = blocked
    saturated = (u < lo) | (u > hi)

    def again(c):
        # v read through the carry (the flag is true here): else XLA hoists the loop-invariant
        # sample-by-sample scan out of the loop and runs it whether it is needed or not
        w = jnp.where(c[3], v, c[0])
        return (*_per_sample(axis, w, t, state, t0, u0, lo, hi), jnp.zeros((), bool))

    redo = ~exact | jnp.any(saturated)
    return lax.while_loop(lambda c: c[3], again, (u, saturated, after, redo))[:3]


def _invert(axes: list, v: Array, t: Array, states: list, t0, u0: Array, lo, hi) -> list:
    """Per axis (drive (T,) V in [``lo``, ``hi``], where it saturated, state after it) for the
    axis outputs ``v`` (T, A) nm: the axes with a block inverse together (:func:`_blocked`),
    each checked (:func:`_or_per_sample`); the others sample by sample (:func:`_per_sample`)."""
    for a in axes:
        _invertible(a)
    fast = [k for k, a in enumerate(axes) if a.hysteresis.has_block_inverse]
    out = {
        k: _per_sample(a, v[:, k], t, states[k], t0, u0[k], lo, hi)
        for k, a in enumerate(axes)
        if k not in fast
    }
    if fast:
        blocked = _blocked([axes[k] for k in fast], [v[:, k] for k in fast], t, [states[k] for k in fast], t0)
        for k, b in zip(fast, blocked):
            out[k] = _or_per_sample(axes[k], v[:, k], t, states[k], t0, u0[k], lo, hi, b)
    return [out[k] for k in range(len(axes))]


def _scanner_inverse(model: Scanner, wanted: Array, t: Array, state: ScannerState, u0: Array, u_max) -> tuple:
    """:func:`numerical_inverse`'s drive and saturation, and the axes' states after the drive."""
    v = axis_targets(model, wanted, t, state)
    u0 = jnp.asarray(u0, dtype=float)
    out = _invert([model.x, model.y], v, t, [state.x, state.y], state.t, u0, -u_max, u_max)
    return jnp.stack([o[0] for o in out], axis=-1), jnp.stack([o[1] for o in out], axis=-1), out


@eqx.filter_jit
def numerical_inverse(model: Scanner, wanted: Array, t: Array, state: ScannerState, u0: Array, u_max: float):
    """The drive (T, 2) V that puts ``model``, from ``state`` with the drive at ``u0``, at ``wanted``
    (T, 2) nm at times ``t``, and where each sample saturated at ``+-u_max`` (there the drive
    stops at the limit and the model follows what it gives). The drive of stepping sample by
    sample, computed over blocks of samples where that is exact (:func:`_invert`)."""
    return _scanner_inverse(model, wanted, t, state, u0, u_max)[:2]


@eqx.filter_jit
def inverse_and_state(model: Scanner, wanted: Array, t: Array, state: ScannerState, u0: Array, u_max: float):
    """:func:`numerical_inverse` ``(u, saturated)`` and the model's state after the drive ``u``:
    ``model.run(u, t, state)[1]`` (to rounding) without running the model again. For a model
    without drift and noise, as a twin of the instrument is (their state needs a key)."""
    if model.drift is not None or model.noise is not None:
        raise ValueError("the state after a drive of a model with drift or noise needs model.run with a key")
    u, saturated, out = _scanner_inverse(model, wanted, t, state, u0, u_max)
    return u, saturated, ScannerState(out[0][2], out[1][2], state.wander, t[-1], state.origin)


@eqx.filter_jit
def invert_axis(axis: Axis, wanted: Array, t: Array, state: AxisState, t0, u0, lo, hi) -> tuple:
    """The drive (T,) V that puts one ``axis``, from ``state`` reached at ``t0`` s with the drive
    at ``u0`` V, at ``wanted`` (T,) nm at times ``t`` (T,) s (the numerical inverse of
    :func:`numerical_inverse` on one axis), with every drive kept in [``lo``, ``hi``] V; and where
    each sample saturated there."""
    u0 = jnp.reshape(jnp.asarray(u0, dtype=float), (1,))
    t0 = jnp.asarray(t0, dtype=float)
    ((u, saturated, _),) = _invert([axis], wanted[:, None], t, [state], t0, u0, lo, hi)
    return u, saturated


@eqx.filter_jit
def _analytic(model: Scanner, wanted: Array, t: Array, state: ScannerState, history: Array):
    v = axis_targets(model, wanted, t, state)
    u = []
    for k, (axis, s) in enumerate(((model.x, state.x), (model.y, state.y))):
        H = axis.hysteresis
        h = _lag_inverse(axis, v[:, k], t, s, state.t)
        u.append(H.inverse()(h, history=H(history[:, k])))
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
