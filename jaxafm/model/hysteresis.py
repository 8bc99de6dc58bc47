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

Every operator is an :class:`AbstractHysteresis`. Besides running from a state
(``initial_state``, ``run``, ``step``) it names the effects it holds
(``effects``, ``without``), hands its fitted parameters out and back
(``free_parameters``, ``evaluator``, ``design_matrix``, ``with_weights``) and
inverts itself where it can (``inverse``, ``has_inverse``, ``invert_step``, and over a whole
input at once ``block_inverse``, ``invert_run``, ``has_block_inverse``).
The scanner, the fits and the inverses ask the operator instead of testing its
type, so a new operator is one class in this file.
"""

# no `from __future__ import annotations` here: equinox reads the AbstractVar annotation
# of AbstractHysteresis when the class is made, and cannot read it from a string
import abc
import warnings
from collections.abc import Callable
from typing import NamedTuple, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from equinox import AbstractVar
from jax import lax

from .. import checks

Array = jax.Array

#: how many times the span its plays cover (:meth:`AbstractHysteresis.drive_span`) a drive may
#: span before :func:`warn_beyond_span` warns
SPAN_TOLERANCE = 1.5


def warn_beyond_span(operators: dict, u) -> None:
    """Warn (``UserWarning``) where the input ``u`` (T,) or (T, A) V spans, on an axis, more than
    :data:`SPAN_TOLERANCE` times the span its operator covers (``operators``: axis name ->
    operator, in the columns' order; :meth:`AbstractHysteresis.drive_span`). Beyond that span every
    play saturates and the model extrapolates a straight line from data it was never built or
    fitted for. Inside ``jit`` (a traced input) nothing is checked."""
    if not checks.is_concrete(u) or np.size(u) == 0:
        return
    u = np.asarray(u, dtype=float).reshape(np.shape(u)[0], -1)
    beyond = []
    for (name, op), column in zip(operators.items(), u.T):
        span = op.drive_span()
        lo, hi = float(column.min()), float(column.max())
        if span is not None and hi - lo > SPAN_TOLERANCE * span:
            beyond.append(
                f"{name} from {lo:g} to {hi:g} V ({(hi - lo) / span:.1f} times the {span:g} V its hysteresis covers)"
            )
    if beyond:
        warnings.warn(
            f"a drive far beyond the model's range: {'; '.join(beyond)}. Its play thresholds span the "
            "drive it was built or fitted for; beyond that every play saturates and the model "
            "extrapolates a straight line: expect large errors",
            UserWarning,
            stacklevel=3,
        )


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
    checks.some_samples("input u", u)
    return u


def _play_step(radii: Array):
    def step(p, ut):
        # clip(p, ut - r, ut + r) as two selects: same values, a cheaper backward pass,
        # and a one-sided derivative at r = 0 (jnp.clip splits that tie's cotangent)
        lo, hi = ut - radii, ut + radii
        p = jnp.where(p < lo, lo, jnp.where(p > hi, hi, p))
        return p, p

    return step


@eqx.filter_jit
def _compiled_run(operator, u: Array, state: Array, parallel: bool) -> tuple:
    """``operator.run(u, state)`` compiled once per operator structure and shapes: called outside
    ``jit``, a run's scans and readouts (closures made afresh each call) were traced and compiled
    again on every call (0.13 s a call for a 20-play PI at 20,000 samples). The caller checks the
    input first: traced, ``u`` cannot be. ``parallel``: :func:`time_parallel`'s answer, a static
    argument so that a run traced on one path is never reused for the other."""
    return operator.run(u, state)


def _carried_play_step(carry: tuple, ut: Array) -> tuple:
    """:func:`_play_step` with the radii in the carry: one module-level function, so that
    :func:`play` called outside ``jit`` finds its scan traced and compiled already (a closure is a
    new function each call, traced and compiled again: 0.07 s against 0.004 s for 50 plays and
    20,000 samples, and one more executable kept each time)."""
    p, radii = carry
    p, _ = _play_step(radii)(p, ut)
    return (p, radii), p


def play(u: Array, radii: Array, history=None) -> Array:
    """Outputs ``P[t, k]`` of the play operators of radius ``radii[k]``, shape ``(T, n)``.

    ``p_k(t) = max(u(t) - r_k, min(u(t) + r_k, p_k(t-1)))`` (the backlash
    operator, Krejčí 1996). Sample by sample on a CPU, by :func:`associative_plays`
    elsewhere (:func:`time_parallel`).
    """
    u = _checked_input(u)
    start = _start(radii, u, history)
    if time_parallel():
        return associative_plays(u, radii, start)
    _, P = lax.scan(_carried_play_step, (start, radii), u)
    return P


def time_parallel() -> bool:
    """Whether the plays, the first-order lags and the vibration mode run as associative scans
    over time (:func:`associative_plays`, :func:`~jaxafm.model.effects.associative_lags`,
    :func:`~jaxafm.model.effects.associative_mode`) rather than sample by sample: on any backend
    but the CPU. Measured side by side
    (``experiments/bench_play_scan.py``, 50 plays; ``experiments/bench_lag_scan.py``): on 2 CPU
    cores the associative plays are 4-10 times slower and compile for up to a minute, the lags
    mixed (0.2-2.9 times); on an H200 the sample-by-sample scans run under 1e5 samples/s and the
    associative ones up to 3e8 (plays) and 1e9 (one lag)."""
    return jax.default_backend() != "cpu"


def associative_plays(u: Array, radii: Array, start: Array) -> Array:
    """The plays ``P`` (T, n) of :func:`play` from the state ``start`` (n,), as a prefix
    composition over time. Each update is a clamp, ``p_t = clip(p_{t-1}, u_t - r, u_t + r)``,
    and clamps compose into clamps, ``clip(clip(y, a, b), c, d) = clip(y, clip(a, c, d),
    clip(b, c, d))`` for ``a <= b``, ``c <= d``: ``P_t = clip(start, A_t, B_t)`` with ``(A, B)``
    the associative scan (``jax.lax.associative_scan``, depth O(log T)) of the pairs
    ``(u_t - r, u_t + r)``. A clamp only selects, so ``P`` equals the sequential plays exactly."""

    def clamp(y, lo, hi):  # two selects, as _play_step: the same values and derivatives
        return jnp.where(y < lo, lo, jnp.where(y > hi, hi, y))

    def compose(first, then):
        return clamp(first[0], *then), clamp(first[1], *then)

    A, B = lax.associative_scan(compose, (u[:, None] - radii, u[:, None] + radii), axis=0)
    return clamp(start, A, B)


def play_map(u: Array, radii: Array, readout, plays: Array, block: int = 32):
    """``(readout(P), P[-1])`` for the plays ``P`` started from ``plays``, without storing P.

    The scan runs over blocks of ``block`` samples: an inner scan fills one
    (block, n) slab of plays and ``readout`` reduces it at once;
    ``jax.checkpoint`` makes the gradient recompute a slab instead of storing
    it. On a CPU, writing and re-reading all of P costs more than the plays.
    Elsewhere (:func:`time_parallel`) all of P is made at once by
    :func:`associative_plays` and read out in one call.
    Returns the outputs (T,) and the plays' final state (n,).
    """
    u = _checked_input(u)
    if time_parallel():
        P = associative_plays(u, radii, plays)
        return readout(P), P[-1]
    T = u.shape[0]
    nb = -(-T // block)
    blocks = jnp.pad(u, (0, nb * block - T), mode="edge").reshape(nb, block)  # repeating u[-1] moves no play

    @jax.checkpoint
    def run_block(p, ub):
        p, P = lax.scan(_play_step(radii), p, ub)
        return p, readout(P)

    p, y = lax.scan(run_block, plays, blocks)
    return y.reshape(-1)[:T], p


def softplus_inverse(x: Array) -> Array:
    """The raw value ``log(exp(x) - 1)`` whose softplus is ``x`` (``x`` floored at 1e-9).

    Fits keep weights non-negative by fitting this raw value instead of the weight.
    """
    x = jnp.maximum(x, 1e-9)
    return x + jnp.log(-jnp.expm1(-x))


def _weight_maps(positive: bool) -> tuple:
    """``(to_raw, from_raw)`` for fitted weights: through softplus (kept >= 0) or as they are."""
    if positive:
        return softplus_inverse, jax.nn.softplus
    return (lambda w: w), (lambda p: p)


def _called(u: Array, history, m: "AbstractHysteresis") -> Array:
    """``m(u, history)``: an operator's output (:meth:`AbstractHysteresis.evaluator`)."""
    return m(u, history)


def _from_plays(P: Array, m: "PlayOperator") -> Array:
    """``m``'s output from its plays ``P`` (T, n) run once (:meth:`PlayOperator.evaluator`)."""
    return m.from_plays(P)


def _from_relays(states: Array, m: "Preisach") -> Array:
    """A Preisach plane's output from its relay states (T, n, n) computed once
    (:meth:`Preisach.evaluator`): ``offset + sum_ij states_ij density_ij``."""
    return m.offset + jnp.einsum("tij,ij->t", states, m.density)


class BlockInverse(NamedTuple):
    """An operator's inverse as plays (:meth:`AbstractHysteresis.block_inverse`).

    ``pre``: the memoryless map from the operator's output (nm) to the plays' input;
    ``radii`` (m,) and ``plays`` (m,): the inverse plays and where they stand;
    ``readout``: plays (..., m) -> the operator's input (...) V; ``state``: the inverse
    plays (m,) -> the operator's state standing there; ``exact``: whether this describes the
    inverse from that state (a bool array).
    """

    pre: Callable
    radii: Array
    plays: Array
    readout: Callable
    state: Callable
    exact: Array


class AbstractHysteresis(eqx.Module):
    """A hysteresis operator: input ``u`` (T,) V -> output ``y`` (T,) nm, with a state.

    Concrete operators fill in ``offset`` and the state methods ``initial_state``,
    ``run`` and ``step``. The other methods have defaults that an operator
    overrides where it can: the effects it holds, its fitted parameters, a design
    matrix when its output is linear in its weights, and its inverse.
    """

    offset: AbstractVar[Array]  # nm, added to the output (for a generalised PI: its PI's)

    @abc.abstractmethod
    def initial_state(self, u0, history=None) -> Array:
        """The operator's state before the first sample.

        Arguments:
            u0: the first input (V); without a history the operator starts at rest there.
            history: the inputs (H,) V applied before it (see the module docstring), or ``None``.

        Returns:
            The state, an array ((n,) plays in V; (0,) for a memoryless operator).
        """

    @abc.abstractmethod
    def run(self, u: Array, state: Array) -> tuple:
        """Drive the operator on from ``state``.

        Arguments:
            u: the input (T,) V.
            state: where the operator stands (from ``initial_state`` or an earlier ``run``).

        Returns:
            The output (T,) nm and the state after the last sample.
        """

    @abc.abstractmethod
    def step(self, u: Array, state: Array) -> tuple:
        """``run`` for one sample ``u`` () V, without a scan: the output () nm and the next state."""

    def __call__(self, u: Array, history=None) -> Array:
        """The output (T,) nm for the input ``u`` (T,) V, from the state ``initial_state(u[0], history)``;
        an input far beyond :meth:`drive_span` warns (:func:`warn_beyond_span`)."""
        u = _checked_input(u)
        warn_beyond_span({"u": self}, u)
        return _compiled_run(self, u, self.initial_state(u[0], history), time_parallel())[0]

    def drive_span(self) -> Optional[float]:
        """The span of inputs (V) the operator covers, the drive it was built or fitted for (a
        wider one saturates every play); None for an operator without plays."""
        return None

    def predict(self, u: Array, t: Array, history=None) -> Array:
        """The output (T,) nm for a record's inputs ``u`` (T,) V at times ``t`` (T,) s.

        Rate-independent: ``t`` is not used. An :class:`~jaxafm.model.scanner.Axis` (hysteresis
        plus rate-dependent stages) is called the same way, so either can be applied to a record.
        """
        return self(u, history)

    @property
    def effects(self) -> frozenset:
        """The effect names this operator holds (``hysteresis``, ``asymmetry``; see docs/conventions.md)."""
        return frozenset()

    def without(self, name: str) -> "AbstractHysteresis":
        """The operator with the effect ``name`` switched off; itself when it does not hold it."""
        return self

    def free_parameters(self, u_span, d_range, positive: bool = True) -> tuple:
        """The fitted parameters at order one, and the map back to an operator.

        Threshold grids stay fixed. Weights are scaled by ``d_range / u_span``, offsets
        by ``d_range``, so that every Jacobian column of a fit is of similar size.

        Arguments:
            u_span: the span of the fitted input (V).
            d_range: the range of the fitted output (nm).
            positive: keep weights and densities non-negative (through softplus), as
                an analytic inverse needs; ``False`` leaves them free (the output stays
                linear in them).

        Returns:
            ``(raw, rebuild)``: a pytree of raw parameters and ``rebuild(raw) -> operator``.
        """
        raise TypeError(f"cannot fit a {type(self).__name__}")

    def evaluator(self, u: Array, history=None) -> Callable:
        """``f(m) = m(u, history)`` for operators ``m`` shaped like this one.

        Operators whose sequential part does not depend on the fitted parameters
        run it once here, so that a fit evaluates only the rest. The evaluator is a pytree
        (``jax.tree_util.Partial``) holding what it computed: it passes through ``jit`` as data.
        """
        return jax.tree_util.Partial(_called, u, history)

    def design_matrix(self, u: Array, history=None) -> Array:
        """Columns ``A`` (T, m) with output ``offset + A @ weights`` (dead zones, if any, at identity).

        Arguments:
            u: the input (T,) V.
            history: the inputs (H,) V applied before it, or ``None``.

        Returns:
            The design matrix (T, m); ``with_weights`` puts solved weights back.
        """
        raise TypeError(f"the output of a {type(self).__name__} is not linear in weights: no design matrix")

    def with_weights(self, weights: Array, offset: Array) -> "AbstractHysteresis":
        """The operator with the weights (m,) of ``design_matrix``'s columns and ``offset`` nm."""
        raise TypeError(f"the output of a {type(self).__name__} is not linear in weights: no design matrix")

    def inverse(self):
        """The analytic inverse operator (output nm -> input V), where one exists."""
        raise ValueError(
            f"{type(self).__name__} has no analytic inverse: invert it numerically "
            "(invert_step, or Compensator(..., method='numerical'))"
        )

    @property
    def has_inverse(self) -> bool:
        """Whether ``inverse()`` exists for this kind of operator."""
        return type(self).inverse is not AbstractHysteresis.inverse

    def block_inverse(self, state: Array) -> "BlockInverse":
        """The inverse as plays standing where the operator stands, for a whole input at once.

        For operators whose inverse is again a play operator (PI, generalised PI, linear):
        ``u = readout(play(pre(y); radii, plays))``, run over blocks of samples as the
        forward model runs (:func:`play_map`) instead of ``invert_step`` sample by sample.

        Arguments:
            state: where the operator stands.

        Returns:
            A :class:`BlockInverse`; its ``exact`` is false where this state or these
            parameters lie outside what the closed form covers (then invert sample by sample).
        """
        raise TypeError(
            f"{type(self).__name__} has no inverse over a block of samples: invert it sample by sample "
            "(invert_step)"
        )

    @property
    def has_block_inverse(self) -> bool:
        """Whether ``block_inverse`` exists for this kind of operator."""
        return type(self).block_inverse is not AbstractHysteresis.block_inverse

    def invert_run(self, y: Array, state: Array) -> tuple:
        """The inputs ``u`` (T,) V whose ``run`` from ``state`` outputs ``y`` (T,) nm, all at once
        (:meth:`block_inverse` run by :func:`play_map`).

        Returns:
            ``(u, exact)``: the inputs (T,) V, not bounded, and whether they are exact.
        """
        b = self.block_inverse(state)
        u, _ = play_map(b.pre(y), b.radii, b.readout, b.plays)
        return u, b.exact & jnp.all(jnp.isfinite(u))

    def invert_step(self, y: Array, state: Array, lo, hi, u_guess: Array, tol: float = 1e-7) -> tuple:
        """The input ``u`` in ``[lo, hi]`` V whose ``step`` from ``state`` outputs ``y`` nm.

        A safeguarded Newton root find of the monotone map ``u -> step(u, state)``:
        Newton steps, bisection when a step leaves the bracket, to ``|error| <= tol`` nm.

        Arguments:
            y: the wanted output () nm.
            state: where the operator stands.
            lo: the lowest input (V).
            hi: the highest input (V).
            u_guess: where the search starts (V), e.g. the previous sample's input.
            tol: the output tolerance (nm).

        Returns:
            ``(u, saturated)``: the input () V, and whether ``y`` lies beyond the outputs
            at ``lo`` or ``hi`` (then ``u`` is that end).
        """
        H = lambda u: self.step(u, state)[0] - y
        below, above = H(lo) > 0, H(hi) < 0

        def body(c):
            u, a, b, _, i = c
            f, df = jax.jvp(H, (u,), (jnp.ones(()),))
            a, b = jnp.where(f < 0, u, a), jnp.where(f > 0, u, b)
            step = u - f / jnp.where(df > 0, df, 1.0)
            step = jnp.where((step > a) & (step < b) & (df > 0), step, 0.5 * (a + b))
            return jnp.where(jnp.abs(f) <= tol, u, step), a, b, jnp.abs(f), i + 1

        start = jnp.clip(u_guess, lo, hi)
        u, *_ = lax.while_loop(
            lambda c: (c[3] > tol) & (c[4] < 60),
            body,
            (start, jnp.asarray(lo, float), jnp.asarray(hi, float), jnp.asarray(jnp.inf), 0),
        )
        u = jnp.where(below, lo, jnp.where(above, hi, u))
        return u, below | above


class PlayOperator(AbstractHysteresis):
    """An operator ``y = f(P)`` of the plays ``P = play(u, radii())``: the effect ``hysteresis``.

    Subclasses give ``radii()`` and ``readout()``, the memoryless map ``f``
    from plays ``(..., n)`` to outputs ``(...)``.
    """

    @abc.abstractmethod
    def radii(self) -> Array:
        """The play radii (n,) V."""

    @abc.abstractmethod
    def readout(self) -> Callable:
        """The map from plays (..., n) V to outputs (...) nm."""

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

    @property
    def effects(self) -> frozenset:
        return frozenset({"hysteresis"})

    def without(self, name: str) -> "AbstractHysteresis":
        return Anhysteretic(self) if name == "hysteresis" else self

    def evaluator(self, u: Array, history=None) -> Callable:
        """``f(m) = m(u, history)`` with the plays run once: fits keep the radii fixed."""
        return jax.tree_util.Partial(_from_plays, play(u, self.radii(), history))

    def drive_span(self) -> Optional[float]:
        """``2 (r_n + (r_n - r_{n-1}))`` V for the sorted radii ``r`` (n >= 2): the radii are spaced
        over half the input span a model is built or fitted for (``PrandtlIshlinskii.uniform``,
        ``with_loop_width``, a Preisach plane's ``u_max - u_min``), so this is that span. None
        with fewer than two plays, or traced radii."""
        r = self.radii()
        if not checks.is_concrete(r) or np.size(r) < 2:
            return None
        r = np.sort(np.asarray(r, dtype=float))
        span = 2 * (r[-1] + (r[-1] - r[-2]))
        return float(span) if span > 0 else None


class Anhysteretic(AbstractHysteresis):
    """The effect ``hysteresis`` switched off: ``operator`` with every play at the input.

    For a PI operator the straight line of slope ``sum(w)`` through the middle of
    its loops; for a Preisach model the curve of its relays with zero width. It
    meets each loop at mid-input but not at its tips: over a major loop it
    travels further than the hysteretic operator, by about the loop's width.
    """

    operator: PlayOperator

    @property
    def offset(self) -> Array:
        return self.operator.offset

    def initial_state(self, u0, history=None) -> Array:
        return jnp.zeros((0,))  # memoryless

    def run(self, u: Array, plays: Array):
        u = _checked_input(u)
        return self.operator.from_plays(
            jnp.broadcast_to(u[:, None], u.shape + self.operator.radii().shape)
        ), plays

    def step(self, u: Array, plays: Array) -> tuple:
        return self.operator.from_plays(jnp.broadcast_to(u, self.operator.radii().shape)), plays

    @property
    def effects(self) -> frozenset:
        return self.operator.effects - {"hysteresis"}

    def without(self, name: str) -> "AbstractHysteresis":
        if name in self.effects:
            return Anhysteretic(self.operator.without(name))
        return self


class Linear(AbstractHysteresis):
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

    def free_parameters(self, u_span, d_range, positive: bool = True) -> tuple:
        """``(gain / (d_range / u_span), offset / d_range)``; the gain keeps its sign."""
        ws = d_range / u_span  # weight scale, nm/V
        raw = (self.gain / ws, self.offset / d_range)
        return raw, lambda p: Linear(p[0] * ws, p[1] * d_range)

    def design_matrix(self, u: Array, history=None) -> Array:
        return jnp.asarray(u, dtype=float)[:, None]

    def with_weights(self, weights: Array, offset: Array) -> "Linear":
        return Linear(weights[0], offset)

    def inverse(self) -> "Linear":
        checks.positive("Linear.gain", self.gain)
        return Linear(1.0 / self.gain, -self.offset / self.gain)

    def block_inverse(self, state: Array) -> BlockInverse:
        """``u = (y - offset) / gain`` through one play of radius 0 (the identity), exact for a
        rising line; the state stays empty."""
        readout = lambda Q: (Q[..., 0] - self.offset) / self.gain
        return BlockInverse(lambda y: y, jnp.zeros(1), jnp.zeros(1), readout, lambda q: state, self.gain > 0)


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
    def uniform(cls, n: int, span: float, gain: float = 1.0, offset: float = 0.0, others: float = 0.0):
        """``n`` thresholds evenly over ``[0, span)`` V, the linear weight ``w_0 = gain`` nm/V.

        Arguments:
            n: the number of plays.
            span: the thresholds' range (V).
            gain: the linear weight (nm/V).
            offset: the output offset (nm).
            others: every other weight as a fraction of ``gain`` (a fit starts from a small
                positive value, so that softplus has a gradient there).

        Returns:
            The operator; with ``others=0`` a straight line of slope ``gain``.
        """
        if n < 1:
            raise ValueError(f"number of play operators n must be >= 1, got {n}")
        checks.positive("span", span)
        r = jnp.arange(n) * (span / n)
        w = jnp.zeros(n).at[0].set(gain)
        if others:
            w = w.at[1:].set(others * gain)
        return cls(r, w, jnp.asarray(offset, dtype=float))

    @classmethod
    def with_loop_width(cls, n: int, span: float, travel: float, loop_width: float) -> "PrandtlIshlinskii":
        """A PI operator whose major loop over ``span`` V moves ``travel`` nm, ``loop_width`` wide.

        Thresholds ``r_k = k span / (2n)``. On the major loop, play ``k`` moves
        ``span - 2 r_k`` and opens a gap of ``min(2 r_k, span - 2 r_k)`` at
        mid-input, where every play's gap peaks. Equal weights ``b`` above ``w_0 = a``
        then give ``b = W T / sum_k min(...)`` and ``a = (T - b sum_k (span - 2 r_k)) / span``
        for width fraction ``W`` and travel ``T``.

        Arguments:
            n: the number of plays (>= 2).
            span: the major loop's input span (V).
            travel: the major loop's output travel (nm).
            loop_width: the loop's width at mid-input, a fraction of ``travel`` (0 to 1).

        Returns:
            The operator, zero offset.
        """
        if n < 2 or not 0 <= loop_width < 1:
            raise ValueError(
                f"need n >= 2 operators and 0 <= loop_width < 1, got n={n}, loop_width={loop_width}"
            )
        r = np.arange(1, n) * span / (2 * n)
        b = loop_width * travel / np.minimum(2 * r, span - 2 * r).sum()
        a = (travel - b * (span - 2 * r).sum()) / span
        if a <= 0:
            raise ValueError(f"loop_width={loop_width} is too wide for a PI operator with {n} plays")
        return cls(jnp.arange(n) * span / (2 * n), jnp.full(n, b).at[0].set(a), jnp.zeros(()))

    def radii(self) -> Array:
        return self.thresholds

    def readout(self):
        return lambda P: self.offset + P @ self.weights

    def free_parameters(self, u_span, d_range, positive: bool = True) -> tuple:
        """Weights in units of ``d_range / u_span`` (softplus-raw when ``positive``), offset in
        units of ``d_range``; the thresholds stay."""
        ws = d_range / u_span  # weight scale, nm/V
        to_raw, from_raw = _weight_maps(positive)
        raw = (to_raw(self.weights / ws), self.offset / d_range)
        return raw, lambda p: PrandtlIshlinskii(self.thresholds, from_raw(p[0]) * ws, p[1] * d_range)

    def design_matrix(self, u: Array, history=None) -> Array:
        """The plays (T, n): the output is ``offset + plays @ weights``."""
        return self.design_rows(play(u, self.radii(), history))

    def design_rows(self, P: Array) -> Array:
        """The rows of :meth:`design_matrix` for the plays ``P`` (T, n): the plays themselves."""
        return P

    def with_weights(self, weights: Array, offset: Array) -> "PrandtlIshlinskii":
        return PrandtlIshlinskii(self.thresholds, weights, offset)

    def inverse(self) -> "PrandtlIshlinskii":
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
        return PrandtlIshlinskii(*self._inverse_parameters())

    def _inverse_parameters(self) -> tuple:
        """The inverse operator's thresholds, weights and offset (:meth:`inverse`), unchecked."""
        r, w = self.thresholds, self.weights
        W = jnp.cumsum(w)
        r_inv = W * r - jnp.cumsum(w * r)
        W_prev = jnp.concatenate([jnp.ones(1), W[:-1]])
        w_inv = jnp.where(jnp.arange(r.size) == 0, 1.0 / w[0], -w / (W * W_prev))
        # plays are shift-equivariant and sum(w') = 1/W_last, so the offset folds in
        return r_inv, w_inv, -self.offset / W[-1]

    def inverse_state(self, plays: Array) -> Array:
        """The plays (n,) nm of :meth:`inverse` that stand where the forward ``plays`` (n,) V stand.

        ``q_i = offset + W_i p_i + sum_{j>i} w_j p_j`` (``W_i = sum_{j<=i} w_j``): the output
        with every play narrower than ``r_i`` moved onto ``p_i``. Driven by the forward
        operator's output, they move exactly as the plays of radius ``r'_i`` (:meth:`inverse`)
        while the forward plays come from one input history (:func:`_one_history`).
        """
        wp = self.weights * plays
        wider = jnp.concatenate([jnp.cumsum(wp[::-1])[::-1][1:], jnp.zeros(1)])  # sum_{j>i} w_j p_j
        return self.offset + jnp.cumsum(self.weights) * plays + wider

    def forward_state(self, q: Array) -> Array:
        """The forward plays (n,) V where the inverse plays ``q`` (n,) nm stand, inverting
        :meth:`inverse_state`: ``q_i - q_{i+1} = W_i (p_i - p_{i+1})`` and
        ``p_{n-1} = (q_{n-1} - offset) / W_{n-1}``."""
        W = jnp.cumsum(self.weights)
        step = (q[:-1] - q[1:]) / W[:-1]
        return (q[-1] - self.offset) / W[-1] + jnp.concatenate([jnp.cumsum(step[::-1])[::-1], jnp.zeros(1)])

    def block_inverse(self, plays: Array) -> BlockInverse:
        """The inverse operator (:meth:`inverse`) from :meth:`inverse_state`. Exact while
        ``r_0 = 0``, every ``W_i > 0`` and the plays come from one input history (every state
        the model reaches does)."""
        r_inv, w_inv, offset = self._inverse_parameters()
        r, W = self.thresholds, jnp.cumsum(self.weights)
        exact = (r[0] == 0) & jnp.all(W > 0) & _one_history(r, plays, jnp.max(W) / jnp.min(W))
        readout = lambda Q: Q @ w_inv + offset
        return BlockInverse(lambda y: y, r_inv, self.inverse_state(plays), readout, self.forward_state, exact)

    def invert_step(self, y: Array, state: Array, lo, hi, u_guess: Array = None, tol: float = 1e-7) -> tuple:
        """The input ``u`` in ``[lo, hi]`` V with ``step(u, state)`` outputting ``y``, exactly.

        From the plays' state, the output is piecewise linear in ``u``: rising, play
        ``k`` moves once ``u`` passes ``b_k = p_k + r_k`` (falling: ``p_k - r_k``),
        so at ``b_j`` it is ``Y_j = y0 + s sum_k w_k max(0, s (b_j - b_k))`` (``s``
        the direction) with slope ``W_j = sum_{k: s b_k <= s b_j} w_k`` beyond it.
        The last breakpoint not past ``y`` gives ``u = b_j + (y - Y_j) / W_j``.
        ``u_guess`` and ``tol`` are not needed.

        Returns:
            ``(u, saturated)``: the input () V clipped to ``[lo, hi]``, and whether it was.
        """
        r, w = self.thresholds, self.weights
        y0 = self.offset + state @ w
        sign = jnp.where(y >= y0, 1.0, -1.0)
        b = state + sign * r
        ahead = sign * (b[:, None] - b[None, :])  # (j, k): how far b_j lies beyond b_k
        Y = y0 + sign * (jnp.maximum(ahead, 0.0) @ w)
        W = (ahead >= 0) @ w
        passed = sign * (y - Y) >= 0
        j = jnp.argmax(jnp.where(passed, sign * b, -jnp.inf))
        u = b[j] + (y - Y[j]) / W[j]
        return jnp.clip(u, lo, hi), (u < lo) | (u > hi)


def _one_history(radii: Array, plays: Array, condition=1.0) -> Array:
    """Whether ``plays`` (n,) could come from one input history: a play state is then 1-Lipschitz
    in the radius, ``|p_{k+1} - p_k| <= r_{k+1} - r_k``, to float64 rounding of plays that were
    computed through a map of ``condition`` number (:meth:`PrandtlIshlinskii.forward_state`)."""
    scale = jnp.max(jnp.abs(plays)) + jnp.max(jnp.abs(radii))
    slack = 16 * jnp.finfo(float).eps * scale * condition
    return jnp.all(jnp.abs(jnp.diff(plays)) <= jnp.diff(radii) + slack)


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
    asymmetric hysteresis (Kuhnen 2003). A memoryless map of the output, not an
    operator on the input: it is a part of :class:`GeneralizedPI`.
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

    def inverse(self) -> "Deadzone":
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
    superposition (the effect ``asymmetry``). Its inverse is analytic too:
    ``PI^-1[S^-1[y]]``.
    """

    pi: PrandtlIshlinskii
    deadzone: Deadzone

    @property
    def offset(self) -> Array:
        """The PI operator's offset (nm), before the dead zones."""
        return self.pi.offset

    def radii(self) -> Array:
        return self.pi.radii()

    def readout(self):
        pi = self.pi.readout()
        return lambda P: self.deadzone(pi(P))

    @property
    def effects(self) -> frozenset:
        return frozenset({"hysteresis", "asymmetry"})

    def without(self, name: str) -> "AbstractHysteresis":
        return self.pi if name == "asymmetry" else PlayOperator.without(self, name)

    def free_parameters(self, u_span, d_range, positive: bool = True) -> tuple:
        """The PI operator's parameters, then each side's dead-zone weights.

        With ``positive`` each side's partial slopes ``g_0 + g_1 + ... + g_i`` are fitted
        through softplus, in units of ``g_0``: the dead zones stay monotone and invertible
        however far the fit moves them. Otherwise the weights are fitted as they are.
        """
        pi_raw, pi_rebuild = self.pi.free_parameters(u_span, d_range, positive)
        dz = self.deadzone
        if positive:
            partial = lambda g: softplus_inverse((dz.slope + jnp.cumsum(g)) / dz.slope)
            weights = lambda p: jnp.diff(jax.nn.softplus(p) * dz.slope, prepend=dz.slope)
        else:
            partial = weights = lambda g: g
        raw = (pi_raw, partial(dz.upper_weights), partial(dz.lower_weights))
        return raw, lambda p: GeneralizedPI(
            pi_rebuild(p[0]), Deadzone(dz.slope, dz.upper, weights(p[1]), dz.lower, weights(p[2]), dz.centre)
        )

    def design_matrix(self, u: Array, history=None) -> Array:
        """The PI operator's plays (T, n): exact while the dead zones are the identity."""
        return self.pi.design_matrix(u, history)

    def with_weights(self, weights: Array, offset: Array) -> "GeneralizedPI":
        """The PI operator's weights and offset replaced, the dead zones kept."""
        return GeneralizedPI(self.pi.with_weights(weights, offset), self.deadzone)

    def inverse(self) -> "_InverseGeneralizedPI":
        return _InverseGeneralizedPI(self.deadzone.inverse(), self.pi.inverse())

    def invert_step(self, y: Array, state: Array, lo, hi, u_guess: Array = None, tol: float = 1e-7) -> tuple:
        """Exactly, as the PI operator's :meth:`PrandtlIshlinskii.invert_step` of ``S^-1[y]``."""
        return self.pi.invert_step(self.deadzone.inverse()(y), state, lo, hi, u_guess, tol)

    def block_inverse(self, plays: Array) -> BlockInverse:
        """``PI^-1[S^-1[y]]``: the PI operator's (:meth:`PrandtlIshlinskii.block_inverse`) after
        the dead zones' inverse; exact where that is and every partial slope of the dead zones
        is positive."""
        dz = self.deadzone
        b = self.pi.block_inverse(plays)
        rising = [jnp.all(dz.slope + jnp.cumsum(g) > 0) for g in (dz.upper_weights, dz.lower_weights)]
        return b._replace(
            pre=_elementwise(dz.inverse()), exact=b.exact & (dz.slope > 0) & rising[0] & rising[1]
        )


def _elementwise(dz: Deadzone) -> Callable:
    """``dz`` as a function of one sample, its sums over thresholds written out instead of as
    matrix products: inside a scan over samples this fuses into one loop (the same map)."""

    def S(z):
        x = (z - dz.centre)[..., None]
        up = jnp.sum(jax.nn.relu(x - dz.upper) * dz.upper_weights, axis=-1)
        down = jnp.sum(jax.nn.relu(dz.lower - x) * dz.lower_weights, axis=-1)
        return dz.centre + dz.slope * x[..., 0] + up - down

    return S


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

    @classmethod
    def with_loop_width(
        cls,
        n: int,
        u_range: float,
        travel: float,
        loop_width: float,
        centre: float = 0.0,
        centre_sd: float = 1.0,
        half_width_scale: float = 1.0,
    ) -> "Preisach":
        """A smooth plane of ``n`` levels over ``+-u_range`` V whose major loop moves ``travel``
        nm and is ``loop_width`` (a fraction of the travel) wide at ``u = 0``.

        The density is the usual one factorised in the relays' centres ``c = (alpha + beta) / 2``
        and half-widths ``h = (alpha - beta) / 2`` (Mayergoyz, *Mathematical Models of
        Hysteresis*, ch. 1), ``c`` and ``h`` in units of ``u_range``: off the diagonal
        ``mu ~ g(c) exp(-h / half_width_scale)``, ``g(c) = exp(-(c - centre)^2 / 2 centre_sd^2)``,
        and on it (relays of no width: the reversible, anhysteretic part) ``mu ~ g(c)``, summing
        to ``travel / 2`` (relays of +-1, so the output spans the travel). Coming down to
        ``u = 0`` from the top and up from the bottom differ by the relays with
        ``beta < 0 < alpha``, twice their mass, so the reversible share is what leaves them
        ``loop_width`` of the total. An off-centre ``centre`` makes the loop asymmetric (steeper
        on its side). With the default scale (and ``default_scanner``'s centre and spread), a
        loop of a fifth of the major loop's amplitude is 0.36 times as wide for its span as the
        major loop; the real stack of ``piezo_ramped_sine_1hz.dat`` gives 0.44, and a plane
        without the reversible part would give 2 (``python experiments/minor_loop_widths.py``).

        Raises:
            ValueError: naming the argument, for ``n`` odd or < 2 (an even ``n`` puts ``u = 0``
                between two levels, where the width is exact), a range, travel, spread or scale
                that is not > 0, or a width beyond what the hysteretic part alone reaches.
        """
        if n < 2 or n % 2 or min(u_range, travel, centre_sd, half_width_scale) <= 0:
            raise ValueError(
                f"Preisach.with_loop_width needs an even n >= 2 (u = 0 between two levels) and u_range, "
                f"travel, centre_sd, half_width_scale > 0, got n={n}, u_range={u_range}, travel={travel}, "
                f"centre_sd={centre_sd}, half_width_scale={half_width_scale}"
            )
        edges = np.linspace(-u_range, u_range, n + 1)
        mid = (edges[:-1] + edges[1:]) / 2
        alpha, beta = np.meshgrid(mid, mid, indexing="ij")
        off = alpha > beta
        c, h = (alpha + beta) / 2 / u_range, np.where(off, alpha - beta, 0) / 2 / u_range
        g = np.exp(-((c - centre) ** 2) / (2 * centre_sd**2))
        hysteretic = g * off * np.exp(-h / half_width_scale)
        reversible = g * np.eye(n)
        widest = hysteretic[(beta < 0) & (alpha > 0)].sum() / hysteretic.sum()
        if not 0 <= loop_width <= widest:
            raise ValueError(
                f"Preisach.with_loop_width: loop_width={loop_width} is outside what {n} levels reach "
                f"with half_width_scale={half_width_scale}: 0 to {widest:.3f}"
            )
        share = loop_width / widest  # of the hysteretic part; the rest is reversible
        density = share * hysteretic / hysteretic.sum() + (1 - share) * reversible / reversible.sum()
        return cls(
            jnp.asarray(density * travel / 2),
            jnp.asarray(-float(u_range)),
            jnp.asarray(float(u_range)),
            jnp.zeros(()),
            True,
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
        n = self.levels
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        return jnp.where(i >= j, self._states(P, np.maximum(i, j), j), 0.0)

    def _states(self, P: Array, i: np.ndarray, j: np.ndarray) -> Array:
        """States in [-1, 1] of the relays ``(i, j)`` (``i >= j``, index arrays of one shape) for
        the plays ``P`` (T, n): relay ``(i, j)`` reads play ``i - j`` against its centre
        ``(alpha + beta) / 2 = u_min + (i + j + 1) D / 2``."""
        D = self._step()
        x = (P[:, i - j] - (self.u_min + (i + j + 1) * D / 2)) / D
        return jnp.clip(2 * x, -1.0, 1.0) if self.smooth else jnp.where(x >= 0, 1.0, -1.0)

    def _triangle(self) -> tuple:
        """Indices of the lower triangle (alpha >= beta), where the density may be non-zero."""
        return np.tril_indices(self.levels)

    def roughness(self, total) -> Array:
        """The density's second differences, in units of ``total`` nm spread evenly over the
        ``n (n + 1) / 2`` relays: below the diagonal along ``alpha`` (``density[i+1, j] -
        2 density[i, j] + density[i-1, j]``) and along ``beta`` (likewise in ``j``), on cells
        with ``i > j`` only, and along the diagonal (``density[k+1, k+1] - 2 density[k, k] +
        density[k-1, k-1]``). The diagonal's relays have no width: they are the reversible part
        of the output, a ridge the hysteretic density beside it need not continue, so no
        difference spans both. Zero for a density linear in ``alpha`` and ``beta`` below the
        diagonal and linear along it. As a prior (step A's,
        :func:`~jaxafm.identify.stages.prior_chord_residuals`) this is second-difference
        Tikhonov regularisation: it carries the density smoothly into the cells the data leave
        free instead of letting each take any weight."""
        n = self.levels
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        d = self.density / (total / (n * (n + 1) / 2))
        a = np.nonzero((i - 1 > j) & (i + 1 < n))
        b = np.nonzero((j >= 1) & (j + 1 < i))
        k = np.arange(1, n - 1)
        return jnp.concatenate(
            [
                d[a[0] + 1, a[1]] - 2 * d[a] + d[a[0] - 1, a[1]],
                d[b[0], b[1] + 1] - 2 * d[b] + d[b[0], b[1] - 1],
                d[k + 1, k + 1] - 2 * d[k, k] + d[k - 1, k - 1],
            ]
        )

    def free_parameters(self, u_span, d_range, positive: bool = True) -> tuple:
        """The lower triangle's densities in units of ``d_range`` over their number (softplus-raw
        when ``positive``) and the offset in units of ``d_range``; the plane stays."""
        tri = self._triangle()
        scale = d_range / len(tri[0])
        to_raw, from_raw = _weight_maps(positive)
        raw = (to_raw(self.density[tri] / scale), self.offset / d_range)

        def rebuild(p):
            density = jnp.zeros_like(self.density).at[tri].set(from_raw(p[0]) * scale)
            return Preisach(density, self.u_min, self.u_max, p[1] * d_range, self.smooth)

        return raw, rebuild

    def evaluator(self, u: Array, history=None) -> Callable:
        """``f(m) = m(u, history)`` through the relay states, computed once: the output is
        linear in the density, so a fit evaluates one design matrix."""
        return jax.tree_util.Partial(_from_relays, self.relay_states(play(u, self.radii(), history)))

    def design_matrix(self, u: Array, history=None) -> Array:
        """The relay states (T, n(n+1)/2) of the lower triangle, row by row."""
        return self.design_rows(play(u, self.radii(), history))

    def design_rows(self, P: Array) -> Array:
        """The rows of :meth:`design_matrix` for the plays ``P`` (T, n): the lower triangle's relay
        states, made from n plays a sample, so that a fit can stream them in blocks of samples
        (:func:`~jaxafm.identify.linear.normal_equations`) instead of storing all T rows."""
        return self._states(P, *self._triangle())

    def with_weights(self, weights: Array, offset: Array) -> "Preisach":
        """The lower triangle's densities (n(n+1)/2,) nm, in ``design_matrix``'s order."""
        density = jnp.zeros_like(self.density).at[self._triangle()].set(weights)
        return Preisach(density, self.u_min, self.u_max, offset, self.smooth)


class FactorizedPreisach(Preisach):
    """A Preisach plane whose density is a PI density times a profile over the relays' centres.

    ``density[i, j] = w[i - j] g(c_ij)``, ``c_ij = (i + j) / (2 n - 2)`` the relay's centre
    ``(alpha + beta) / 2`` on [0, 1] across the plane, ``g`` piecewise linear through ``nodes``
    evenly spaced values ``profile`` (> 0). ``g = 1`` is a Prandtl-Ishlinskii operator on the
    plane (one weight per play line ``i - j``); a profile that falls off both ways from the middle
    gives the narrower outer loops of a Preisach density concentrated near the input's centre (the
    factorised densities of Mayergoyz's "Mathematical Models of Hysteresis", ch. 1), and a skewed
    one an asymmetric loop. The diagnosis's Preisach rung: ``n + nodes`` free parameters (the
    middle node is kept, :meth:`free_parameters`) instead of ``n (n + 1) / 2 + 1``, so the cells a
    training drive never reaches are not free. ``density`` is kept equal to
    ``factors(lines, profile)``.
    """

    lines: Array = None  # (n,) nm, the play lines' weights
    profile: Array = None  # (K,) dimensionless, > 0

    def profile_matrix(self, profile: Array) -> Array:
        """``g(c_ij)`` (n, n) for node values ``profile`` (K,)."""
        n = self.levels
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        c = (i + j) / max(2 * n - 2, 1)
        return jnp.interp(jnp.asarray(c), jnp.linspace(0.0, 1.0, profile.shape[0]), profile)

    def factors(self, weights: Array, profile: Array) -> Array:
        """The density (n, n) of play-line ``weights`` (n,) and centre ``profile`` (K,)."""
        n = self.levels
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        return jnp.where(i >= j, weights[np.clip(i - j, 0, n - 1)] * self.profile_matrix(profile), 0.0)

    @classmethod
    def from_plane(cls, plane: Preisach, nodes: int = 5) -> "FactorizedPreisach":
        """The plane of ``plane`` with a flat profile (``g = 1``) and its density's play lines
        (``density[k, 0]``) as the weights."""
        lines = jnp.stack([plane.density[k, 0] for k in range(plane.levels)])
        start = cls(
            plane.density, plane.u_min, plane.u_max, plane.offset, plane.smooth, lines, jnp.ones(nodes)
        )
        return start.with_weights(lines, plane.offset)

    def design_rows(self, P: Array) -> Array:
        """Columns (T, n): the relay states along each play line weighted by the profile, so the
        output is ``offset + A @ lines``."""
        n = self.levels
        states = self.relay_states(P) * self.profile_matrix(self.profile)
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        onehot = ((i - j)[..., None] == np.arange(n)) & (i >= j)[..., None]
        return jnp.einsum("tij,ijk->tk", states, jnp.asarray(onehot, dtype=float))

    def with_weights(self, weights: Array, offset: Array) -> "FactorizedPreisach":
        """The play lines' ``weights`` (n,) nm, the profile kept."""
        weights = jnp.asarray(weights)
        density = self.factors(weights, self.profile)
        return FactorizedPreisach(
            density, self.u_min, self.u_max, jnp.asarray(offset), self.smooth, weights, self.profile
        )

    def free_parameters(self, u_span, d_range, positive: bool = True) -> tuple:
        """Play-line weights in units of ``d_range / n`` (softplus-raw when ``positive``), the
        profile's values but its middle one (softplus-raw) and the offset in units of ``d_range``.

        The middle node stays where it is: ``w[i - j] g(c)`` is unchanged when ``w`` is scaled by
        ``a`` and ``g`` by ``1 / a``, so with every node free the model would have a parameter that
        changes nothing: counted in the BIC, and a direction a solver drifts along (measured on a
        record: a play-line weight 12.1 -> 17.1 and a node 1.67 -> 1.18 between 30 and 300
        Levenberg-Marquardt steps, the output the same to 0.001 nm)."""
        scale = d_range / self.levels
        to_raw, from_raw = _weight_maps(positive)
        middle = self.profile.shape[0] // 2
        pinned = self.profile[middle]
        free = softplus_inverse(jnp.delete(self.profile, middle, assume_unique_indices=True))
        raw = (to_raw(self.lines / scale), free, self.offset / d_range)

        def rebuild(p):
            lines = from_raw(p[0]) * scale
            profile = jnp.insert(jax.nn.softplus(p[1]), middle, pinned)
            density = self.factors(lines, profile)
            return FactorizedPreisach(
                density, self.u_min, self.u_max, p[2] * d_range, self.smooth, lines, profile
            )

        return raw, rebuild
