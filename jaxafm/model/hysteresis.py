"""Rate-independent hysteresis operators: play, Prandtl–Ishlinskii, dead-zone, Preisach.

All operators map an input sequence ``u`` (V) of shape ``(T,)`` to an output
``y`` (nm) of shape ``(T,)``. Each is a memoryless ``readout`` of play
(backlash) operators; the plays are the only sequential part, one ``lax.scan``
over time that applies the readout block by block. ``jit``, ``vmap`` and
``grad`` work throughout.

The Preisach model is evaluated through Krejčí's play representation: relay
``(alpha, beta)`` is up exactly when the play of radius ``r = (alpha-beta)/2``
sits above ``s = (alpha+beta)/2``. A plane of ``n`` levels therefore needs ``n``
plays, and one sample costs O(n) instead of O(n^2) relay updates.

Initial state: ``history`` lists the inputs applied before ``t = 0``; every play
starts at ``history[0]`` and then follows the rest. ``history=(u_min, u_max)``
is the paper's initialisation cycle ``{u2, u1}`` (section III-A), after which
the state no longer depends on anything earlier (wiping-out). Without a history
every play starts at ``u[0]`` (a demagnetised, virgin state). To carry on from
where a previous input stopped, ``y, plays = op.run(u, plays)`` takes and returns
the plays' state (``op.initial_state(u0, history)`` makes the first).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import checks

Array = jax.Array


def play_state(radii: Array, history) -> Array:
    """Play outputs after the turning points ``history`` (every play starts at ``history[0]``)."""
    history = jnp.atleast_1d(jnp.asarray(history, dtype=float))
    if history.ndim != 1 or history.shape[0] == 0:
        raise ValueError(f"history must be a non-empty 1-D sequence of inputs (V), got shape {history.shape}")
    checks.finite("history", history)
    p = jnp.broadcast_to(history[0], radii.shape)
    for h in history[1:]:
        p = jnp.clip(p, h - radii, h + radii)
    return p


def _start(radii: Array, u: Array, history) -> Array:
    """The plays' state before ``u[0]``: after ``history``, or every play at ``u[0]``."""
    return play_state(radii, u[:1] if history is None else history)


def _checked_input(u) -> Array:
    u = jnp.asarray(u, dtype=float)
    checks.finite("input u", u)
    if u.ndim != 1:
        raise ValueError(f"input u must be 1-D (T,), got shape {u.shape}; use jax.vmap for batches")
    return u


def _play_step(radii: Array):
    def step(p, ut):
        # clip(p, ut - r, ut + r) as two selects: same values, a cheaper backward pass,
        # and a one-sided derivative at r = 0 (jnp.clip splits that tie's cotangent)
        lo, hi = ut - radii, ut + radii
        p = jnp.where(p < lo, lo, jnp.where(p > hi, hi, p))
        return p, p

    return step


def play(u: Array, radii: Array, history=None) -> Array:
    """Outputs ``P[t, k]`` of the play operators of radius ``radii[k]``, shape ``(T, n)``.

    ``p_k(t) = max(u(t) - r_k, min(u(t) + r_k, p_k(t-1)))`` (the backlash
    operator, Krejčí 1996).
    """
    u = _checked_input(u)
    _, P = lax.scan(_play_step(radii), _start(radii, u, history), u)
    return P


def play_map(u: Array, radii: Array, readout, plays: Array, block: int = 32):
    """``(readout(P), P[-1])`` for the plays ``P`` started from ``plays``, without storing P.

    The scan runs over blocks of ``block`` samples: an inner scan fills one
    (block, n) slab of plays and ``readout`` reduces it at once;
    ``jax.checkpoint`` makes the gradient recompute a slab instead of storing
    it. On a CPU, writing and re-reading all of P costs more than the plays.
    Returns the outputs (T,) and the plays' final state (n,).
    """
    u = _checked_input(u)
    T = u.shape[0]
    nb = -(-T // block)
    blocks = jnp.pad(u, (0, nb * block - T), mode="edge").reshape(nb, block)  # repeating u[-1] moves no play

    @jax.checkpoint
    def run_block(p, ub):
        p, P = lax.scan(_play_step(radii), p, ub)
        return p, readout(P)

    p, y = lax.scan(run_block, plays, blocks)
    return y.reshape(-1)[:T], p


class PlayOperator(eqx.Module):
    """An operator ``y = f(P)`` of the plays ``P = play(u, radii())``.

    Subclasses give ``radii()`` and ``readout()``, the memoryless map ``f``
    from plays ``(..., n)`` to outputs ``(...)``.
    """

    def radii(self) -> Array:
        raise NotImplementedError

    def readout(self):
        raise NotImplementedError

    def from_plays(self, P: Array) -> Array:
        """The output for known play trajectories ``P`` (T, n)."""
        return self.readout()(P)

    def initial_state(self, u0, history=None) -> Array:
        """The plays (n,) after ``history``, or all at ``u0`` without one."""
        return play_state(self.radii(), jnp.reshape(u0, (1,)) if history is None else history)

    def run(self, u: Array, plays: Array):
        """Outputs (T,) and final plays (n,) for the input ``u`` from the state ``plays``."""
        return play_map(u, self.radii(), self.readout(), plays)

    def step(self, u: Array, plays: Array) -> tuple:
        """``run`` for one sample ``u`` (): the output () and the next plays (n,), without a scan."""
        p, _ = _play_step(self.radii())(plays, u)
        return self.readout()(p), p

    def __call__(self, u: Array, history=None) -> Array:
        u = _checked_input(u)
        return self.run(u, self.initial_state(u[0], history))[0]


class Anhysteretic(eqx.Module):
    """The effect ``hysteresis`` switched off: ``operator`` with every play at the input.

    For a PI operator the straight line of slope ``sum(w)`` through the middle of
    its loops; for a Preisach model the curve of its relays with zero width. It
    meets each loop at mid-input but not at its tips: over a major loop it
    travels further than the hysteretic operator, by about the loop's width.
    """

    operator: PlayOperator

    def initial_state(self, u0, history=None) -> Array:
        return jnp.zeros((0,))  # memoryless

    def run(self, u: Array, plays: Array):
        u = _checked_input(u)
        return self.operator.from_plays(
            jnp.broadcast_to(u[:, None], u.shape + self.operator.radii().shape)
        ), plays

    def step(self, u: Array, plays: Array) -> tuple:
        return self.operator.from_plays(jnp.broadcast_to(u, self.operator.radii().shape)), plays

    def __call__(self, u: Array, history=None) -> Array:
        return self.run(u, self.initial_state(None))[0]


class Linear(eqx.Module):
    """No hysteresis: ``y = gain * u + offset``."""

    gain: Array  # nm/V
    offset: Array  # nm

    def initial_state(self, u0, history=None) -> Array:
        return jnp.zeros((0,))  # memoryless

    def run(self, u: Array, plays: Array):
        checks.finite("input u", u)
        return self.gain * jnp.asarray(u, dtype=float) + self.offset, plays

    def step(self, u: Array, plays: Array) -> tuple:
        return self.gain * u + self.offset, plays

    def __call__(self, u: Array, history=None) -> Array:
        return self.run(u, self.initial_state(None))[0]

    def inverse(self) -> Linear:
        checks.positive("Linear.gain", self.gain)
        return Linear(1.0 / self.gain, -self.offset / self.gain)


class PrandtlIshlinskii(PlayOperator):
    """Classical PI operator ``y = offset + sum_k w_k p_{r_k}[u]`` with ``r_0 = 0``.

    The ``r_0 = 0`` play is the identity, so ``w_0`` is the linear part.
    """

    thresholds: Array  # (n,) V, 0 = r_0 < r_1 < ...
    weights: Array  # (n,) nm/V
    offset: Array  # nm

    def __check_init__(self):
        checks.nonnegative("PrandtlIshlinskii.thresholds", self.thresholds)
        checks.increasing("PrandtlIshlinskii.thresholds", self.thresholds)
        checks.finite("PrandtlIshlinskii.weights", self.weights)
        if np.shape(self.thresholds) != np.shape(self.weights):
            raise ValueError(
                f"PrandtlIshlinskii.thresholds {np.shape(self.thresholds)} and weights "
                f"{np.shape(self.weights)} must have the same shape"
            )

    @classmethod
    def uniform(cls, n: int, span: float, gain: float = 1.0, offset: float = 0.0):
        """``n`` thresholds evenly over ``[0, span)`` V; weights give slope ``gain``."""
        if n < 1:
            raise ValueError(f"number of play operators n must be >= 1, got {n}")
        checks.positive("span", span)
        r = jnp.arange(n) * (span / n)
        w = jnp.zeros(n).at[0].set(gain)
        return cls(r, w, jnp.asarray(offset, dtype=float))

    def radii(self) -> Array:
        return self.thresholds

    def readout(self):
        return lambda P: self.offset + P @ self.weights

    def inverse(self) -> PrandtlIshlinskii:
        """The analytic inverse, again a PI operator (Kuhnen & Janocha 2001).

        ``W_i = sum_{j<=i} w_j``; ``r'_i = sum_{j<=i} w_j (r_i - r_j)``;
        ``w'_0 = 1/w_0``; ``w'_i = -w_i / (W_i W_{i-1})``. It exists iff
        ``r_0 = 0`` and every ``W_i > 0`` (the loading curve rises strictly).
        Give the inverse the *output* history ``pi(history)``.
        """
        r, w = self.thresholds, self.weights
        if checks.is_concrete(r) and float(r[0]) != 0.0:
            raise ValueError(f"PI inverse needs thresholds[0] == 0 (the linear part), got {float(r[0])!r}")
        W = jnp.cumsum(w)
        if checks.is_concrete(W) and (np.asarray(W) <= 0).any():
            i = int(np.argmax(np.asarray(W) <= 0))
            raise ValueError(
                "PI inverse does not exist: the partial weight sum w[0]+...+w[i] must be > 0 "
                f"for every i, but at i={i} it is {float(W[i])!r} nm/V (the loading curve "
                "stops rising). Constrain the weights to keep it positive."
            )
        r_inv = W * r - jnp.cumsum(w * r)
        W_prev = jnp.concatenate([jnp.ones(1), W[:-1]])
        w_inv = jnp.where(jnp.arange(r.size) == 0, 1.0 / w[0], -w / (W * W_prev))
        # plays are shift-equivariant and sum(w') = 1/W_last, so the offset folds in
        return PrandtlIshlinskii(r_inv, w_inv, -self.offset / W[-1])


def _deadzone_side_inverse(slope, d, g):
    """Inverse dead-zone thresholds and weights for one side (Kuhnen 2003, eq. 14)."""
    G = slope + jnp.cumsum(g)
    G_prev = jnp.concatenate([jnp.reshape(slope, (1,)), G[:-1]])
    return G * d - jnp.cumsum(g * d), -g / (G * G_prev)


class Deadzone(eqx.Module):
    """Dead-zone superposition about ``c``: ``S(z) = c + g_0 (z-c) + sum_i g_i s_{d_i}(z-c)`` (nm -> nm).

    ``s_d(x) = max(x - d, 0)`` for the upper thresholds ``d > 0`` and
    ``min(x - d, 0)`` for the lower ones ``d < 0``. A monotone piecewise-linear
    map with ``S(c) = c``: following a symmetric PI operator it bends the loop
    unevenly, which is how the generalised (modified) PI model reproduces
    asymmetric hysteresis (Kuhnen 2003).
    """

    slope: Array  # g_0 > 0
    upper: Array  # (m,) nm above the centre, 0 < d_1 < d_2 < ...
    upper_weights: Array  # (m,)
    lower: Array  # (k,) nm below the centre, 0 > d_-1 > d_-2 > ...
    lower_weights: Array  # (k,)
    centre: Array = eqx.field(default=0.0, converter=jnp.asarray)  # nm

    def __check_init__(self):
        checks.positive("Deadzone.slope", self.slope)
        checks.positive("Deadzone.upper", self.upper)
        checks.increasing("Deadzone.upper", self.upper)
        checks.positive("Deadzone.lower (negated)", -jnp.asarray(self.lower))
        checks.increasing("Deadzone.lower (negated)", -jnp.asarray(self.lower))
        checks.finite("Deadzone.upper_weights", self.upper_weights)
        checks.finite("Deadzone.lower_weights", self.lower_weights)
        checks.finite("Deadzone.centre", self.centre)

    @classmethod
    def identity(cls, lower: Array, upper: Array, centre: float = 0.0):
        """Zero-weight dead zones at the given thresholds: ``S(z) = z``."""
        lower, upper = jnp.asarray(lower, dtype=float), jnp.asarray(upper, dtype=float)
        return cls(
            jnp.ones(()),
            upper,
            jnp.zeros_like(upper),
            lower,
            jnp.zeros_like(lower),
            jnp.asarray(centre, dtype=float),
        )

    def __call__(self, z: Array) -> Array:
        x = (jnp.asarray(z, dtype=float) - self.centre)[..., None]
        up = jax.nn.relu(x - self.upper) @ self.upper_weights
        down = jax.nn.relu(self.lower - x) @ self.lower_weights
        return self.centre + self.slope * x[..., 0] + up - down

    def inverse(self) -> Deadzone:
        """The analytic inverse, again a dead-zone superposition about the same centre.

        Exists iff every partial slope ``g_0 + g_1 + ... + g_i`` is positive on
        both sides (the map rises strictly).
        """
        for side, g in (("upper", self.upper_weights), ("lower", self.lower_weights)):
            G = self.slope + jnp.cumsum(g)
            if checks.is_concrete(G) and (np.asarray(G) <= 0).any():
                i = int(np.argmax(np.asarray(G) <= 0))
                raise ValueError(
                    f"Deadzone inverse does not exist: slope + {side}_weights[:{i + 1}].sum() "
                    f"= {float(G[i])!r} must be > 0 (the map must rise strictly)"
                )
        up, up_w = _deadzone_side_inverse(self.slope, self.upper, self.upper_weights)
        lo, lo_w = _deadzone_side_inverse(self.slope, self.lower, self.lower_weights)
        return Deadzone(1.0 / self.slope, up, up_w, lo, lo_w, self.centre)


class GeneralizedPI(PlayOperator):
    """Generalised (modified) PI operator ``y = S[PI[u]]`` for asymmetric loops.

    Kuhnen's modified PI model: a classical PI operator followed by a dead-zone
    superposition. Its inverse is analytic too: ``PI^-1[S^-1[y]]``.
    """

    pi: PrandtlIshlinskii
    deadzone: Deadzone

    def radii(self) -> Array:
        return self.pi.radii()

    def readout(self):
        pi = self.pi.readout()
        return lambda P: self.deadzone(pi(P))

    def inverse(self) -> _InverseGeneralizedPI:
        return _InverseGeneralizedPI(self.deadzone.inverse(), self.pi.inverse())


class _InverseGeneralizedPI(eqx.Module):
    """``u = PI^-1[S^-1[y]]``; ``history`` is the output history of the forward model."""

    deadzone_inverse: Deadzone
    pi_inverse: PrandtlIshlinskii

    def __call__(self, y: Array, history=None) -> Array:
        h = None if history is None else self.deadzone_inverse(jnp.asarray(history, dtype=float))
        return self.pi_inverse(self.deadzone_inverse(y), h)


class Preisach(PlayOperator):
    """Discretised Preisach model on a plane of ``n`` levels over ``[u_min, u_max]``.

    ``y = offset + sum_{i>=j} density[i, j] * R_{alpha_i, beta_j}[u]`` with relays
    ``R = +-1`` at ``alpha_i = u_min + (i + 1/2) D``, ``beta_j = u_min + (j + 1/2) D``,
    ``D = (u_max - u_min) / n``. Only the lower triangle (alpha >= beta) is used.
    With ``smooth=True`` each relay's weight is spread evenly over ``+-D/2``
    along its play line, which makes the output continuous in ``u`` (a Preisach
    operator all the same); ``smooth=False`` gives the bare relay grid.

    Relays switch up at ``u >= alpha`` and down at ``u <= beta``, except for an
    input that lands exactly on ``beta`` (or ``alpha``) of the bare relay grid:
    a play cannot tell which side it came from, so such ties are settled by
    rounding. Quantised drives can hit them; the smooth model is continuous there.
    """

    density: Array  # (n, n) nm, >= 0, lower triangle
    u_min: Array  # V
    u_max: Array  # V
    offset: Array  # nm
    smooth: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        d = self.density
        if np.ndim(d) != 2 or np.shape(d)[0] != np.shape(d)[1]:
            raise ValueError(f"Preisach.density must be square (n, n), got shape {np.shape(d)}")
        checks.nonnegative("Preisach.density", d)
        if checks.is_concrete(d) and np.any(np.triu(np.asarray(d), 1) != 0):
            i, j = np.argwhere(np.triu(np.asarray(d), 1) != 0)[0]
            raise ValueError(
                f"Preisach.density[{i}, {j}] lies above the diagonal (alpha < beta) and must be 0"
            )
        checks.finite("Preisach.u_min", self.u_min)
        checks.finite("Preisach.u_max", self.u_max)
        if checks.is_concrete(self.u_max) and checks.is_concrete(self.u_min):
            if float(self.u_max) <= float(self.u_min):
                raise ValueError(
                    f"Preisach plane needs u_max > u_min, got u_min={float(self.u_min)!r} V, "
                    f"u_max={float(self.u_max)!r} V"
                )

    @classmethod
    def uniform(
        cls, n: int, u_min: float, u_max: float, total: float = 1.0, offset: float = 0.0, smooth: bool = True
    ):
        """Even density over the ``n(n+1)/2`` hysterons, summing to ``total`` nm."""
        if n < 1:
            raise ValueError(f"number of Preisach levels n must be >= 1, got {n}")
        tri = np.tril(np.ones((n, n)))
        return cls(
            jnp.asarray(tri * total / tri.sum()),
            jnp.asarray(float(u_min)),
            jnp.asarray(float(u_max)),
            jnp.asarray(float(offset)),
            smooth,
        )

    @property
    def levels(self) -> int:
        return self.density.shape[0]

    def _step(self):
        return (self.u_max - self.u_min) / self.levels

    def radii(self) -> Array:
        """Play radii ``r_k = k D / 2`` (one play per diagonal ``i - j = k``)."""
        return jnp.arange(self.levels) * self._step() / 2

    def masses(self) -> Array:
        """Relay weights on play lines: ``M[k, j] = density[j + k, j]`` (zero past the edge)."""
        n = self.levels
        k, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        i = j + k
        return jnp.where(i < n, jnp.tril(self.density)[np.minimum(i, n - 1), j], 0.0)

    def readout(self):
        """``P (..., n) -> y = offset + sum_k 2 F_k(p_k) - F_k(inf)``, its tables built once.

        ``F_k`` is the cumulative relay weight along play line ``k`` up to
        ``p_k``; relay ``(k, j)`` sits at ``s_kj = u_min + (2j + k + 1) D / 2``.
        Smooth: with ``q = (p_k - s_k0) / D + 1/2`` and ``i = floor(q)``,
        ``F_k = C[k, i] + (q - i) M[k, i] = A[k, i] + q M[k, i]`` (``A = C - i M``),
        both read from flattened tables at ``k n + i``.
        """
        n, D = self.levels, self._step()
        M = self.masses()
        C = jnp.concatenate([jnp.zeros((n, 1)), jnp.cumsum(M, axis=1)], axis=1)  # (n, n+1)
        s0 = self.u_min + (jnp.arange(n) + 1) * D / 2  # first relay of each play line
        base = self.offset - jnp.sum(C[:, -1])
        if self.smooth:
            A, Mf = (C[:, :-1] - jnp.arange(n) * M).ravel(), M.ravel()

            def readout(P):
                q = jnp.clip((P - s0) / D + 0.5, 0.0, n)
                i = jnp.arange(n) * n + jnp.minimum(jnp.floor(q), n - 1).astype(int)
                return base + 2 * jnp.sum(A[i] + q * Mf[i], axis=-1)
        else:
            Cf = C.ravel()

            def readout(P):
                i = jnp.arange(n) * (n + 1) + jnp.clip(jnp.floor((P - s0) / D).astype(int) + 1, 0, n)
                return base + 2 * jnp.sum(Cf[i], axis=-1)

        return readout

    def relay_states(self, P: Array) -> Array:
        """States (T, n, n) in [-1, 1] of every relay, so ``y = offset + sum(states * density)``.

        O(n^2) per sample, without gathers: the design matrix of a fit, where the
        output is linear in the density once the plays are known.
        """
        n, D = self.levels, self._step()
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        k = np.where(i >= j, i - j, 0)
        s = self.u_min + (i + j + 1) * D / 2  # relay centres (alpha + beta) / 2
        x = (P[:, k] - s) / D
        states = jnp.clip(2 * x, -1.0, 1.0) if self.smooth else jnp.where(x >= 0, 1.0, -1.0)
        return jnp.where(i >= j, states, 0.0)
