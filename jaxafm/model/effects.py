"""The scanner's non-hysteretic effects, one module each (names as in ``docs/conventions.md``).

Each module is a pure function of its parameters, the signal and the sample
times ``t`` (s); lengths are nm. The scanner composes them in the order
hysteresis -> rate_dependence -> creep -> vibration -> coupling -> bow -> drift -> noise;
the AFM records heights through ``FeedbackLag`` or ``FeedbackAsymmetry``.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import checks
from .hysteresis import softplus_inverse, time_parallel

Array = jax.Array

# Every module a fit moves has ``free_parameters(...) -> (raw, rebuild)``, as the hysteresis
# operators do (:meth:`~jaxafm.model.hysteresis.AbstractHysteresis.free_parameters`): its fitted
# parameters divided by a scale, so that a solver sees numbers of order one and Jacobian columns
# of similar size, and ``rebuild(raw)`` the module back. The caller passes the scale where it
# depends on the data (a record's range and duration, an image's pitch) or on how loosely the
# fit should start.


def lowpass(v: Array, t: Array, taus: Array, z0: Array, t0=None, weights=None) -> tuple:
    """First-order lags ``dz_k/dt = (v - z_k) / tau_k``, exact for ``v`` held over each step.

    ``v[n]`` is taken to hold over ``(t[n-1], t[n]]``, so a step applied at
    ``t[0]`` gives ``z_k(t) = v (1 - exp(-(t - t[0]) / tau_k))`` exactly, and
    ``tau -> 0`` gives ``z = v``. Against a continuous drive this leads by half
    a sample, so a fitted ``tau`` absorbs about ``dt/2``. ``z0`` is the state at
    ``t0`` (default ``t[0]``). Returns the lags' weighted sum ``Z @ weights`` (T,)
    (default weights: ones) and the final state (K,); only the sum is stored,
    which keeps forward-mode Jacobians through many lags cheap. On any backend but the CPU
    (:func:`~jaxafm.model.hysteresis.time_parallel`) the lags run as an associative scan over
    time (:func:`associative_lags`).
    """
    dt = jnp.diff(t, prepend=t[:1] if t0 is None else jnp.reshape(t0, (1,)))
    weights = jnp.ones_like(taus) if weights is None else weights

    def step(z, inputs):
        vn, dtn = inputs
        a = jnp.exp(-dtn / taus)
        z = a * z + (1 - a) * vn
        return z, z @ weights

    z0 = jnp.broadcast_to(z0, taus.shape)
    if v.shape[0] == 1:  # one sample (the inverses step sample by sample): no scan
        z, out = step(z0, (v[0], dt[0]))
        return out[None], z
    if time_parallel():
        Z = associative_lags(v, dt, taus, z0)
        return Z @ weights, Z[-1]
    z, out = lax.scan(step, z0, (v, dt))
    return out, z


def associative_lags(v: Array, dt: Array, taus: Array, z0: Array) -> Array:
    """The lags ``Z`` (T, K) of :func:`lowpass` from ``z0`` (K,), as a prefix composition over
    time. Each step is affine, ``z -> a z + b`` with ``a = exp(-dt_n / tau_k)``,
    ``b = (1 - a) v_n``, and affine maps compose into affine maps, ``(a1, b1)`` then ``(a2, b2)``
    being ``(a1 a2, a2 b1 + b2)``: ``Z_n = A_n z0 + B_n`` with ``(A, B)`` the associative scan
    (``jax.lax.associative_scan``, depth O(log T)) of the steps. Equal to the sequential lags to
    round-off (the sums are taken in another order)."""
    a = jnp.exp(-dt[:, None] / taus)
    return affine_prefix(a, (1 - a) * v[:, None], z0)


def affine_prefix(a: Array, b: Array, z0: Array) -> Array:
    """``z_n = a_n z_{n-1} + b_n`` for every ``n`` from ``z0``, as an associative scan over the
    first axis: ``(a1, b1)`` then ``(a2, b2)`` compose into ``(a1 a2, a2 b1 + b2)``."""

    def compose(first, then):
        return first[0] * then[0], then[0] * first[1] + then[1]

    A, B = lax.associative_scan(compose, (a, b))
    return A * z0 + B


HOLDS = ("zero", "linear")


def hold_weights(dt: Array, tau: Array, hold: str) -> tuple:
    """One step of ``dz/dt = (v - z) / tau`` over ``dt`` (s), exact for the input between the
    samples ``v_{n-1}`` and ``v_n`` held at ``v_n`` (``hold="zero"``) or a straight line
    between them (``"linear"``, a first-order hold)::

        z_n = a z_{n-1} + b_prev v_{n-1} + b_now v_n,   a = exp(-x),  x = dt / tau
        zero:    b_prev = 0,        b_now = 1 - a
        linear:  b_prev = g - a,    b_now = 1 - g,      g = (1 - a) / x

    (the linear hold's weights from integrating ``exp(-(dt - s) / tau) v(s) / tau`` over the
    step). Through the linear hold a ramp ``v = c t`` settles to ``z = c (t - tau)``: delayed by
    ``tau`` at any sample time; through the zero hold by ``dt / (exp(dt / tau) - 1)``, which
    falls far below ``tau`` once ``dt > tau``. Returns ``(a, b_prev, b_now)``."""
    x = dt / tau
    a = jnp.exp(-x)
    if hold == "zero":
        return a, jnp.zeros_like(a), 1 - a
    small = x < 1e-6  # g = 1 - x / 2 + O(x^2); the where keeps 0 / 0 out of the gradient
    safe = jnp.where(small, 1.0, x)
    g = jnp.where(small, 1 - x / 2, -jnp.expm1(-safe) / safe)
    return a, g - a, 1 - g


#: the weight (in units of the fit's scale) a creep lag of weight 0 starts a fit from: small
#: enough to be no creep (1e-5 of the move per lag at the fit's usual scale 0.01), large enough
#: for the softplus to pass the fit a gradient (its slope there 1e-3)
CREEP_START_FLOOR = 1e-3
#: the onset (s) a raw value of 0 stands for when a fit frees it (``t0 = ONSET_SCALE_S exp(raw)``:
#: one raw unit is a factor e)
ONSET_SCALE_S = 0.1


class Creep(eqx.Module):
    """Logarithmic creep as a bank of first-order elements (gamma 0.01-0.02 per decade in published
    data: ``docs/index.md``, "What we compare against").

    ``y(t) = v(t) + sum_k g_k z_k(t)``, each ``z_k`` a lag of ``v`` with time
    constant ``tau_k``. After a step of size ``d0``,
    ``y = d0 (1 + sum_k g_k (1 - exp(-t/tau_k)))``, which for log-spaced
    ``tau_k`` with ``g_k = gamma / m`` (``m`` per decade) grows by ``gamma d0``
    per decade of time between ``tau_min`` and ``tau_max``: the slope of
    ``d(t) = d0 (1 + gamma log10(t / 0.1 s))``, with a level about ``gamma d0 / 2`` higher.
    The lags start relaxed at ``v[0]`` (the scanner rested there before ``t[0]``),
    whatever input ``history`` the hysteresis stage was given.

    **With an onset** ``t0`` (:meth:`with_onset`) the bank follows the regularised log law
    ``d(t) = d0 (1 + gamma log10(1 + t / t0))`` (the log law ``log10(t / t0)`` of Jung & Gweon
    2000, kept finite at ``t = 0``): its rate ``d'(t) = gamma d0 / (ln 10 (t + t0))
    = gamma d0 / ln 10 int_0^inf exp(-s (t + t0)) ds`` is a superposition of decays whose
    weight per decade of ``tau = 1 / s`` is ``gamma exp(-t0 / tau)``, so
    ``g_k = (gamma / m) exp(-t0 / tau_k)``: the lags faster than the onset fade, those slower
    creep at ``gamma`` a decade. At 2 lags a decade from 10 ms the bank's step response is
    within 1e-3 gamma of the law for t <= 2 s and any t0 of 30 ms-0.5 s.
    """

    taus: Array  # (K,) s
    weights: Array  # (K,) dimensionless
    onset: Optional[Array] = None  # s: t0 of the log law the weights follow; None: uniform

    def __check_init__(self):
        checks.positive("Creep.taus", self.taus)
        checks.finite("Creep.weights", self.weights)
        if self.onset is not None:
            checks.positive("Creep.onset", self.onset)

    @property
    def per_decade(self) -> Array:
        """``gamma``: the creep (fraction of a step) per decade of time: ``m`` lags a decade times
        their mean weight, or with an onset, once past it, ``m g_K / exp(-t0 / tau_K)`` from the
        slowest lag (whose onset factor is nearest 1)."""
        if self.onset is None:
            return self._lags_per_decade() * jnp.mean(self.weights)
        return self._lags_per_decade() * self.weights[-1] / self._onset_factor()[-1]

    def _lags_per_decade(self) -> Array:
        """``m``: the bank's lags per decade of time (1 for a single lag)."""
        return 1 / jnp.log10(self.taus[1] / self.taus[0]) if self.taus.size > 1 else jnp.asarray(1.0)

    def _onset_factor(self) -> Array:
        """``exp(-t0 / tau_k)`` per lag; ones without an onset."""
        return jnp.ones_like(self.taus) if self.onset is None else jnp.exp(-self.onset / self.taus)

    def with_onset(self, onset: float) -> Creep:
        """The same lags and rate per decade with the onset ``t0`` (s; class docstring)."""
        checks.positive("creep onset", onset)
        t0 = jnp.asarray(onset, dtype=self.taus.dtype)
        return Creep(self.taus, self.per_decade / self._lags_per_decade() * jnp.exp(-t0 / self.taus), t0)

    @classmethod
    def logarithmic(cls, gamma: float, tau_min: float = 0.1, tau_max: float = 1000.0, per_decade: int = 2):
        """Creep of ``gamma`` (fraction per decade) between ``tau_min`` and ``tau_max`` s."""
        checks.nonnegative("creep gamma", gamma)
        checks.positive("creep tau_min", tau_min)
        if not tau_max > tau_min:
            raise ValueError(f"creep tau_max must exceed tau_min, got {tau_min} s and {tau_max} s")
        n = int(round(np.log10(tau_max / tau_min) * per_decade)) + 1
        taus = jnp.logspace(np.log10(tau_min), np.log10(tau_max), n)
        return cls(taus, jnp.full(n, gamma / per_decade))

    def free_parameters(self, scale: float, rate: bool = False) -> tuple:
        """The fitted weights at order one, and the map back (the time constants stay).

        Arguments:
            scale: the weight a raw value of 1 stands for (dimensionless).
            rate: fit one creep rate shared by every lag, so that a logarithmic bank stays
                logarithmic: ``raw`` is the mean over the lags of ``softplus^-1(g_k / scale)``,
                every ``g_k = softplus(raw) scale``; with an :attr:`onset`, ``raw`` is (rate,
                onset), ``g_k = softplus(raw_0) scale exp(-t0 / tau_k)``,
                ``t0 = ONSET_SCALE_S exp(raw_1)``. Otherwise every weight is its own,
                ``raw_k = softplus^-1(max(g_k / scale, CREEP_START_FLOOR))``.

        Every weight stays >= 0: creep continues the move. Weights of either sign would let the
        slow lags cancel one another over a record and part after it (a fit's held-out error on
        the real 5 kHz step record 73,940 nm with them, 120 nm without;
        ``experiments/uncertainty_coverage.py``). A weight of 0 starts at ``CREEP_START_FLOOR`` scale,
        where the fit can still move it.

        Returns:
            ``(raw, rebuild)``: the raw parameters and ``rebuild(raw) -> Creep``.
        """
        if rate and self.onset is not None:  # (rate, log onset): g_k = softplus(p0) scale exp(-t0 / tau_k)
            raw = jnp.stack(
                [
                    softplus_inverse(self.per_decade / self._lags_per_decade() / scale),
                    jnp.log(self.onset / ONSET_SCALE_S),
                ]
            )

            def rebuild(p):
                t0 = ONSET_SCALE_S * jnp.exp(p[1])
                return Creep(self.taus, jax.nn.softplus(p[0]) * scale * jnp.exp(-t0 / self.taus), t0)

            return raw, rebuild
        if rate:
            raw = jnp.mean(softplus_inverse(self.weights / scale))
            return raw, lambda p: Creep(self.taus, jax.nn.softplus(p) * scale * jnp.ones_like(self.weights))
        raw = softplus_inverse(jnp.maximum(self.weights / scale, CREEP_START_FLOOR))
        return raw, lambda p: Creep(self.taus, jax.nn.softplus(p) * scale)

    def initial_state(self, v0) -> tuple:
        """Relaxed at ``v0``: the lags (K,) and the rest level ``v0`` they creep from."""
        v0 = jnp.asarray(v0, dtype=float)
        return jnp.broadcast_to(v0, self.taus.shape), v0

    def run(self, v: Array, t: Array, state: tuple, t0) -> tuple:
        """Output (T,) and the next state, continuing from ``state`` at time ``t0``."""
        z0, rest = state
        out, z = lowpass(v, t, self.taus, z0, t0, self.weights)
        return v + out - rest * jnp.sum(self.weights), (z, rest)

    def __call__(self, v: Array, t: Array) -> Array:
        return self.run(v, t, self.initial_state(v[0]), t[0])[0]


#: the shortest time constant (s) a fitted lag takes (:meth:`FirstOrderLag.free_parameters`): a
#: picosecond, a millionth of the fastest sample time a scanner sees, so no lag at all there
TAU_FLOOR_S = 1e-12


class FirstOrderLag(eqx.Module):
    """``dz/dt = (v - z) / tau``: a first-order lag of time constant ``tau`` (s).

    ``hold`` says what the input does between its samples (:func:`hold_weights`): ``"zero"``
    held at each sample (a drive updated at the sample rate), ``"linear"`` a straight line
    between samples (a continuous drive sampled coarsely, as a raster sampled once a pixel:
    a lag shorter than a pixel's time then still delays the ramp by ``tau``). The linear
    hold's state also carries the last input: ``(z, v_prev)``; the zero hold's is ``(z,)``.
    """

    tau: Array  # s
    hold: str = eqx.field(static=True, default="zero")

    def __check_init__(self):
        checks.positive(f"{type(self).__name__}.tau", self.tau)
        if self.hold not in HOLDS:
            raise ValueError(f"{type(self).__name__}.hold must be one of {HOLDS}, got {self.hold!r}")

    def free_parameters(self, scale: float) -> tuple:
        """The time constant at order one, kept > 0: ``raw = softplus^-1(tau / scale)``, and
        at least :data:`TAU_FLOOR_S`. A fit that wants no lag runs its raw value towards -inf:
        there the softplus reaches 0, and below the floor ``exp(-dt / tau)``'s derivative is
        ``0 * inf`` (NaN); at the floor it is 0, and the lag none at any sample rate.

        Arguments:
            scale: the time constant (s) a raw value of about 1 stands for.

        Returns:
            ``(raw, rebuild)``: the raw parameter and ``rebuild(raw)``, a lag of the same kind.
        """
        rebuild = lambda p: type(self)(jnp.maximum(jax.nn.softplus(p) * scale, TAU_FLOOR_S), self.hold)
        return softplus_inverse(self.tau / scale), rebuild

    def initial_state(self, v0) -> Array:
        """At rest at ``v0``: ``(z,)``, or ``(z, v_prev)`` for the linear hold."""
        v0 = jnp.asarray(v0, dtype=float)
        return jnp.full((1 if self.hold == "zero" else 2,), v0)

    def weights(self, dt: Array) -> tuple:
        """``(a, b_prev, b_now)`` of each step ``dt`` (s): :func:`hold_weights`."""
        return hold_weights(dt, self.tau, self.hold)

    def advance(self, state: Array, v, weights: tuple) -> Array:
        """The state after one sample ``v`` with ``weights`` (:meth:`weights`); its output is
        ``state[0]``."""
        a, b_prev, b_now = weights
        z = a * state[0] + b_now * v + (b_prev * state[1] if self.hold == "linear" else 0.0)
        return jnp.stack([z, v]) if self.hold == "linear" else jnp.reshape(z, (1,))

    def run(self, v: Array, t: Array, z0: Array, t0) -> tuple:
        """Output (T,) and the final state, continuing from ``z0`` at time ``t0``."""
        if self.hold == "zero":
            return lowpass(v, t, jnp.reshape(self.tau, (1,)), z0, t0)
        dt = jnp.diff(t, prepend=jnp.reshape(t0, (1,)))
        a, b_prev, b_now = self.weights(dt)
        b = b_prev * jnp.concatenate([z0[1:], v[:-1]]) + b_now * v
        if time_parallel():
            z = affine_prefix(a, b, z0[0])
        else:
            z = lax.scan(lambda z, ab: (ab[0] * z + ab[1],) * 2, z0[0], (a, b))[1]
        return z, jnp.stack([z[-1], v[-1]])

    def __call__(self, v: Array, t: Array) -> Array:
        return self.run(v, t, self.initial_state(v[0]), t[0])[0]


class RateDependence(FirstOrderLag):
    """Rate-dependent loops (effect ``rate_dependence``): a lag after hysteresis.

    A Hammerstein structure (rate-independent hysteresis, then linear
    dynamics): the loop widens and tilts as the drive frequency nears ``1/tau``.
    """


class FeedbackLag(FirstOrderLag):
    """z-feedback (effect ``feedback_lag``): the recorded height lags the true one.

    Scanning at ``v`` nm/s shifts an edge by about ``v tau`` along the scan, one
    way in trace and the other in retrace, so the two images differ.
    """


class FeedbackAsymmetry(eqx.Module):
    """z-feedback asymmetry (effect ``feedback_asymmetry``): "parachuting".

    The recorded height ``z`` follows the surface ``h`` through a first-order lag whose time
    constant depends on the direction: ``dz/dt = (h - z) / tau``, ``tau = tau_rise`` while the
    surface is above the recorded height (the tip is pressed: the error signal is large and the
    loop reacts fast), ``tau = tau_fall`` while it is below (the tip loses contact and the error
    saturates at the set point, so the loop retracts slowly and the tip "parachutes" off a
    downward edge). Exact for ``h`` held over each step: ``z`` approaches ``h`` monotonically,
    so the direction does not change within a step. Down-step edges smear by about
    ``v tau_fall`` at scan speed ``v`` while up-step edges stay sharp; ``tau_rise = tau_fall``
    is a :class:`FeedbackLag`.
    """

    tau_rise: Array  # s
    tau_fall: Array  # s

    def __check_init__(self):
        checks.positive("FeedbackAsymmetry.tau_rise", self.tau_rise)
        checks.positive("FeedbackAsymmetry.tau_fall", self.tau_fall)

    def initial_state(self, v0) -> Array:
        return jnp.reshape(jnp.asarray(v0, dtype=float), (1,))

    def run(self, v: Array, t: Array, z0: Array, t0) -> tuple:
        """Recorded heights (T,) and the final state (1,), continuing from ``z0`` at time ``t0``."""
        dt = jnp.diff(t, prepend=jnp.reshape(t0, (1,)))

        def step(z, inputs):
            vn, h = inputs
            tau = jnp.where(vn >= z, self.tau_rise, self.tau_fall)
            z = vn + (z - vn) * jnp.exp(-h / tau)
            return z, z[0]

        z, out = lax.scan(step, jnp.reshape(z0, (1,)), (v, dt))
        return out, z

    def __call__(self, v: Array, t: Array) -> Array:
        return self.run(v, t, self.initial_state(v[0]), t[0])[0]


class Vibration(eqx.Module):
    """The scanner's lowest mechanical mode after the actuator (effect ``vibration``; the paper's
    "structural vibration").

    ``x'' + 2 zeta w0 x' + w0^2 x = w0^2 v`` with ``w0 = 2 pi frequency``: the actuator's
    displacement ``v`` (nm) drives a mass on a spring, under-damped (``0 < zeta < 1``). Exact for
    ``v`` held over each step: the deviation from the rest point ``(v, 0)`` evolves by
    ``exp(A dt)``, ``A = [[0, 1], [-w0^2, -2 sigma]]``, ``sigma = zeta w0``,
    ``wd = w0 sqrt(1 - zeta^2)``:

        exp(A dt) = e^(-sigma dt) [[c + sigma s / wd, s / wd], [-w0^2 s / wd, c - sigma s / wd]],

    ``c = cos(wd dt)``, ``s = sin(wd dt)``. A step rings at ``wd`` and overshoots by
    ``exp(-pi zeta / sqrt(1 - zeta^2))``; slow drives pass with gain 1.
    """

    frequency: Array  # Hz
    damping: Array  # zeta, dimensionless, in (0, 1)

    def __check_init__(self):
        checks.positive("Vibration.frequency (Hz)", self.frequency)
        checks.positive("Vibration.damping", self.damping)
        if checks.is_concrete(self.damping) and not np.all(np.asarray(self.damping) < 1):
            raise ValueError(f"Vibration.damping must be < 1 (an under-damped mode), got {self.damping}")

    def free_parameters(self, max_frequency, max_damping: float) -> tuple:
        """Frequency and damping at order one, kept in ``(0, max_frequency)`` Hz and
        ``(0, max_damping)``: ``frequency = max_frequency sigmoid(a)``,
        ``damping = max_damping sigmoid(b)``, ``raw = (a, b)`` stacked.

        Arguments:
            max_frequency: the highest frequency (Hz) the fit may reach (a record's Nyquist
                frequency: no mode above it shows in the samples).
            max_damping: the highest damping (below 1; a mode rings, has a resonant peak, only
                below 1/sqrt(2)).

        Returns:
            ``(raw, rebuild)``: the raw parameters (2,) and ``rebuild(raw) -> Vibration``.
        """
        logit = lambda p: jnp.log(p) - jnp.log1p(-p)
        raw = jnp.stack([logit(self.frequency / max_frequency), logit(self.damping / max_damping)])

        def rebuild(p):
            q = jax.nn.sigmoid(p)
            return Vibration(max_frequency * q[0], max_damping * q[1])

        return raw, rebuild

    def initial_state(self, v0) -> Array:
        """At rest at ``v0``: position ``v0`` nm, velocity 0 nm/s."""
        return jnp.stack([jnp.asarray(v0, dtype=float), jnp.zeros(())])

    def run(self, v: Array, t: Array, state: Array, t0) -> tuple:
        """Positions (T,) nm and the final (position, velocity) (2,), from ``state`` at ``t0``."""
        dt = jnp.diff(t, prepend=jnp.reshape(t0, (1,)))
        w0 = 2 * jnp.pi * self.frequency
        sigma = self.damping * w0
        wd = w0 * jnp.sqrt(1 - self.damping**2)

        def step(s, inputs):
            vn, h = inputs
            e, c, sn = jnp.exp(-sigma * h), jnp.cos(wd * h), jnp.sin(wd * h)
            x, xd = s[0] - vn, s[1]
            x1 = e * (x * (c + sigma * sn / wd) + xd * sn / wd)
            xd1 = e * (-x * w0**2 * sn / wd + xd * (c - sigma * sn / wd))
            return jnp.stack([x1 + vn, xd1]), x1 + vn

        if v.shape[0] > 1 and time_parallel():
            S = associative_mode(v, dt, w0, sigma, wd, state)
            return S[:, 0], S[-1]
        s, out = lax.scan(step, state, (v, dt))
        return out, s

    def __call__(self, v: Array, t: Array) -> Array:
        return self.run(v, t, self.initial_state(v[0]), t[0])[0]


def associative_mode(v: Array, dt: Array, w0, sigma, wd, state: Array) -> Array:
    """The states ``S`` (T, 2) (position nm, velocity nm/s) of :class:`Vibration` from ``state``,
    as a prefix composition over time. Each step is affine, ``s -> M_n s + (I - M_n) (v_n, 0)``
    with ``M_n = exp(A dt_n)`` (the class docstring's closed form), and affine maps compose into
    affine maps, ``(M1, b1)`` then ``(M2, b2)`` being ``(M2 M1, M2 b1 + b2)``: ``S_n = P_n state +
    Q_n`` with ``(P, Q)`` the associative scan (``jax.lax.associative_scan``, depth O(log T)) of
    the steps. Equal to the sequential steps to round-off (the sums are taken in another order)."""
    e, c, sn = jnp.exp(-sigma * dt), jnp.cos(wd * dt), jnp.sin(wd * dt)
    M = e[:, None, None] * jnp.stack(
        [
            jnp.stack([c + sigma * sn / wd, sn / wd], -1),
            jnp.stack([-(w0**2) * sn / wd, c - sigma * sn / wd], -1),
        ],
        -2,
    )
    b = jnp.stack([v, jnp.zeros_like(v)], -1) - M[:, :, 0] * v[:, None]

    def compose(first, then):
        return then[0] @ first[0], jnp.einsum("...ij,...j->...i", then[0], first[1]) + then[1]

    P, Q = lax.associative_scan(compose, (M, b))
    return jnp.einsum("tij,j->ti", P, state) + Q


class Coupling(eqx.Module):
    """Linear x<->y cross-coupling: ``x += xy * y``, ``y += yx * x`` (dimensionless)."""

    xy: Array
    yx: Array

    def free_parameters(self, scale: float, hold_yx: bool = False) -> tuple:
        """``(xy / scale, yx / scale)``, or ``(xy / scale,)`` with ``yx`` held (a gauge fixed
        elsewhere), and the map back.

        Arguments:
            scale: the coupling a raw value of 1 stands for (dimensionless).
            hold_yx: keep ``yx`` as it is.

        Returns:
            ``(raw, rebuild)``: the raw parameters and ``rebuild(raw) -> Coupling``.
        """
        if hold_yx:
            return (self.xy / scale,), lambda p: Coupling(p[0] * scale, self.yx)
        return (self.xy / scale, self.yx / scale), lambda p: Coupling(p[0] * scale, p[1] * scale)

    def __call__(self, p: Array) -> Array:
        x, y = p[..., 0], p[..., 1]
        return jnp.stack([x + self.xy * y, y + self.yx * x], axis=-1)


class Bow(eqx.Module):
    """Quadratic cross-coupling of a tube scanner: ``x += bx * y^2``, ``y += by * x^2`` (1/nm)."""

    bx: Array
    by: Array

    def free_parameters(self, scale) -> tuple:
        """``(bx / scale, by / scale)`` and the map back.

        Arguments:
            scale: the bow (1/nm) a raw value of 1 stands for: about the relative bend over the
                travel divided by the travel.

        Returns:
            ``(raw, rebuild)``: the raw parameters and ``rebuild(raw) -> Bow``.
        """
        return (self.bx / scale, self.by / scale), lambda p: Bow(p[0] * scale, p[1] * scale)

    def __call__(self, p: Array) -> Array:
        x, y = p[..., 0], p[..., 1]
        return jnp.stack([x + self.bx * y**2, y + self.by * x**2], axis=-1)


class Drift(eqx.Module):
    """Thermal drift: constant velocity plus an Ornstein–Uhlenbeck wander, per axis.

    ``d(t) = v t + w(t)``, ``dw = -theta w dt + sigma dW``, sampled exactly
    at the given times (``theta = 0`` gives a random walk). Velocity in nm/s,
    ``sigma`` in nm/sqrt(s), ``theta`` in 1/s. Called plainly, ``t`` starts at
    0 and ``w(t[0]) = 0``; ``run`` continues a wander ``w0`` from time ``t0``.
    """

    velocity: Array  # (2,) nm/s
    sigma: Array  # (2,) nm/sqrt(s)
    theta: Array  # 1/s

    def __check_init__(self):
        checks.finite("Drift.velocity", self.velocity)
        checks.nonnegative("Drift.sigma", self.sigma)
        checks.nonnegative("Drift.theta", self.theta)

    def free_parameters(self, scale) -> tuple:
        """The velocity (2,) in units of ``scale`` nm/s, and the map back; the wander
        (``sigma``, ``theta``) stays as it is (no fit to one realisation can tell it).

        Returns:
            ``(raw, rebuild)``: the raw velocity and ``rebuild(raw) -> Drift``.
        """
        return self.velocity / scale, lambda p: Drift(p * scale, self.sigma, self.theta)

    def __call__(self, t: Array, key: Array) -> Array:
        return self.run(t, key, jnp.zeros(2), t[0], t[0])[0]

    def run(self, t: Array, key: Array, w0: Array, t0, origin) -> tuple:
        """Drift (T, 2) nm since time ``origin`` and the final wander (2,)."""
        dt = jnp.diff(t, prepend=jnp.reshape(t0, (1,)))[:, None]
        theta = jnp.maximum(self.theta, 1e-12)
        decay = jnp.exp(-theta * dt)
        std = self.sigma * jnp.sqrt(-jnp.expm1(-2 * theta * dt) / (2 * theta))
        kicks = std * jax.random.normal(key, (t.shape[0], 2))

        def step(w, inputs):
            a, kick = inputs
            w = a * w + kick
            return w, w

        w, W = lax.scan(step, w0, (decay, kicks))
        return self.velocity * (t - origin)[:, None] + W, w


class Noise(eqx.Module):
    """White position noise of standard deviation ``std`` (2,) nm per axis."""

    std: Array

    def __check_init__(self):
        checks.nonnegative("Noise.std", self.std)

    def __call__(self, shape, key: Array) -> Array:
        return self.std * jax.random.normal(key, shape)
