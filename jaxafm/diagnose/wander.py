"""Drift as a random process: a rate and a wander, by a Kalman smoother, beside a short-memory
misfit.

What a model without drift leaves of a drifting record is taken, per output, as a straight
drift of rate ``v`` plus a random-walk wander (a local linear trend with a fixed slope: Durbin &
Koopman, *Time Series Analysis by State Space Methods*, 2012, §3.2), plus a coloured term ``a``
(a first-order autoregression, the sampled Ornstein-Uhlenbeck process: D&K §3.4), the rest white:

    r_n = w_n + a_n + e_n,                                e_n ~ N(0, s^2),
    w_{n+1} = w_n + v (t_{n+1} - t_n) + eta_n,            eta_n ~ N(0, lambda s^2 (t_{n+1} - t_n)),
    a_{n+1} = phi_n a_n + xi_n,  phi_n = exp(-(t_{n+1} - t_n) / tau),  xi_n ~ N(0, kappa s^2 (1 - phi_n^2)),

``lambda`` (1/s) the wander's diffusion over the white noise's variance, ``kappa`` the coloured
term's stationary variance over it, ``tau`` (s) its time constant. The coloured term is what a
plant's misfit leaves over a few milliseconds (a loop's kink between play radii, a missed
resonance): without it the walk alone must follow that misfit, its diffusion grows tens of
times and its bridges across a held-out block follow the misfit's last excursion. ``tau`` is
held to :data:`COLOURED_TIMES_S` (30 ms at most): with a time constant of a second the coloured
term takes the wander itself. ``kappa = 0`` is the walk alone. Only ``w`` is the drift: ``a``
stays in the residual.

The start ``w_0`` and the rate ``v`` are unknown (diffuse), so the filter estimates them as it
goes: ``v`` is the generalised-least-squares rate given the wander, not a line through its
excursions; ``a_0`` starts at its stationary variance. An Ornstein-Uhlenbeck wander with a time
constant longer than the record is a random walk over it. Samples that are not observed (held
out, settling) are skipped by the filter, so the smoother (Rauch-Tung-Striebel) interpolates the
drift across a held-out block from the training data on both sides and extrapolates it (rate, no
wander) across a held-out end: the drift's prediction of what it was not trained on.

``(lambda, tau, kappa)`` maximise the likelihood with ``s^2`` concentrated out (D&K §2.10): per
output, over the ``n`` observed samples but the first two (which set the diffuse start and
rate), with one-step prediction errors ``e_n`` of variance ``s^2 f_n``,

    -2 ln L = n ln(2 pi s^2) + sum ln f_n + sum e_n^2 / (s^2 f_n),   s^2 = sum (e_n^2 / f_n) / n,

found on a grid (every output at once), ``lambda`` refined by a parabola through the best grid
point and its neighbours.

The same model without the drift (no wander, ``lambda = 0``, and a rate known to be 0: the
coloured term beside white noise, :func:`fit_wander` with ``drift=False``) is the noise model a
record's fits without a drift are scored under when their evidence is weighed against a drift's
(:attr:`~jaxafm.diagnose.record.RecordFit.evidence`): the drift's likelihood models the
residual's colour, a least-squares BIC does not, and colour is not drift. Its likelihood runs
over the same samples (all observed but the first two), so the two are on one scale. Units: nm, s.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

#: The grid of lambda (1/s) the likelihood is maximised over: from a wander whose spread over
#: 1e4 s matches the white noise (1e-6) to one that matches it within 0.1 ms (1e4).
LAMBDA_GRID = np.geomspace(1e-6, 1e4, 41)
#: The coloured term's time constants (s) tried: a plant's misfit decorrelates within a few
#: milliseconds; with 0.1-1 s on the grid the coloured term takes the wander.
COLOURED_TIMES_S = np.array([1e-3, 3e-3, 1e-2, 3e-2])
#: Its stationary variances tried, over the white noise's: none (the walk alone), then 0.1-1000.
COLOURED_RATIOS = np.r_[0.0, np.geomspace(0.1, 1e3, 9)]
#: The start's and the rate's variance (units of s^2; the rate per sampling step) before any
#: sample: diffuse; the likelihood and the smoother differ from the exact limit by O(1 / _DIFFUSE).
_DIFFUSE = 1e8
_OBSERVED = jnp.array([1.0, 0.0, 1.0])  # r = w + a (+ e): the state (w, v h, a) seen
#: Free parameters per output beyond the start and the rate: ``lambda``, ``tau``, ``kappa``, ``s^2``.
PARAMETERS_PER_OUTPUT = 4
#: The same without the drift (``drift=False``): ``tau``, ``kappa``, ``s^2``.
NOISE_PARAMETERS_PER_OUTPUT = 3


@dataclasses.dataclass(frozen=True)
class Wander:
    """A fitted drift, per output: its rate and its wander, and the coloured term beside them.

    Attributes:
        level: the smoothed drift ``w`` (T, k) nm at every sample, observed or not.
        velocity: the rate ``v`` (k,) nm/s.
        ratio: ``lambda`` (k,) 1/s, the wander's diffusion over the white noise's variance.
        noise_var: ``s^2`` (k,) nm^2, the white noise's variance.
        coloured: the smoothed coloured term ``a`` (T, k) nm.
        coloured_ratio: ``kappa`` (k,), its stationary variance over the white noise's (0: none).
        coloured_time_s: ``tau`` (k,) s, its time constant.
        innovations: one-step prediction errors ``e_n`` (T, k) nm, 0 off :attr:`used`.
        minus_two_log_l: ``-2 ln L`` (k,) of the observed samples, ``2 pi`` terms included.
        used: (T, k) True on the samples in the likelihood (observed, after the first two).
    """

    level: np.ndarray
    velocity: np.ndarray
    ratio: np.ndarray
    noise_var: np.ndarray
    coloured: np.ndarray
    coloured_ratio: np.ndarray
    coloured_time_s: np.ndarray
    innovations: np.ndarray
    minus_two_log_l: np.ndarray
    used: np.ndarray

    @property
    def diffusion(self) -> np.ndarray:
        """The wander's diffusion ``q = lambda s^2`` (k,) nm^2/s: its spread after ``t`` s is
        ``sqrt(q t)`` nm."""
        return self.ratio * self.noise_var

    @property
    def coloured_sd(self) -> np.ndarray:
        """The coloured term's standard deviation ``sqrt(kappa s^2)`` (k,) nm."""
        return np.sqrt(self.coloured_ratio * self.noise_var)

    def bic(self, parameters: int) -> float:
        """The BIC of a model with ``parameters`` free parameters whose residual this drift
        explains, on the scale of a least-squares fit's ``n ln(RSS / n) + k ln n``
        (:func:`jaxafm.identify.fit.bic`): for white residuals ``-2 ln L = n ln(2 pi RSS / n) + n``,
        so ``-2 ln L - n (ln 2 pi + 1) + k ln n``, ``n`` the likelihood's samples. The diffuse
        likelihood already pays for the start and the rate (the log-determinant of their
        information, about ``ln n + 3 ln n`` where the BIC charges ``2 ln n``): ``parameters``
        counts neither."""
        n = int(self.used.sum())
        return float(np.sum(self.minus_two_log_l) - n * (np.log(2 * np.pi) + 1) + parameters * np.log(n))


def _transition(steps, phi):
    """The state ``(w, v h, a)``'s transition over ``steps = dt / h``: ``w += (v h) steps``, the
    rate unchanged (carried per sampling step ``h``, so that a diffuse start is diffuse alike for
    both: in nm/s its variance would have to dwarf ``1 / h^2``), ``a *= phi``."""
    return jnp.array([[1.0, steps, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, phi]])


def _noise(dt, phi, ratio, kappa):
    """The state noise's covariance over ``dt`` s, units of ``s^2``."""
    return jnp.diag(jnp.array([ratio * dt, 0.0, kappa * (1.0 - phi**2)]))


def _filter(r, dt, observed, ratio, tau, kappa, h, rate_var=_DIFFUSE):
    """The Kalman filter of ``r`` (T,) for the state ``(w, v h, a)`` at ``(lambda, tau, kappa) =
    (ratio, tau, kappa)``, covariances in units of ``s^2``: per sample the filtered and predicted
    means (3,) and covariances (3, 3), the one-step error ``e_n``, its variance ``f_n`` and
    ``used``: the samples in the likelihood (observed, after the first two observed, which set
    the diffuse level and rate). ``rate_var``: the rate's variance before any sample (0: known
    to be 0)."""

    def step(carry, x):
        m, p, seen = carry
        rn, dtn, obs = x
        phi = jnp.exp(-dtn / tau)
        f_ = _transition(dtn / h, phi)
        m, p = f_ @ m, f_ @ p @ f_.T + _noise(dtn, phi, ratio, kappa)
        f = _OBSERVED @ p @ _OBSERVED + 1.0
        e = rn - _OBSERVED @ m
        gain = jnp.where(obs, p @ _OBSERVED / f, 0.0)
        m_f, p_f = m + gain * e, p - jnp.outer(gain, gain) * f
        used = obs & (seen >= 2)
        return (m_f, p_f, seen + obs), (m_f, p_f, m, p, jnp.where(used, e, 0.0), f, used)

    x = (r, jnp.concatenate([jnp.zeros(1), dt]), observed)
    start = (jnp.zeros(3), jnp.diag(jnp.array([_DIFFUSE, rate_var, kappa])), jnp.zeros((), int))
    return lax.scan(step, start, x)[1]


class Whitener(eqx.Module):
    """The filter of :func:`_filter` at fixed ``(lambda, tau, kappa)`` as a linear map of the
    residuals: its gains and one-step error variances do not depend on the data, so the
    normalised one-step errors ``e_n / sqrt(f_n)`` of residuals ``r`` (T, k) are ``L r``, ``L``
    lower triangular. A model fitted to minimise ``|L r|^2`` is fitted under the drift's
    covariance (generalised least squares: Durbin & Koopman §6.2, regression effects in state
    space), the wander's start and rate profiled out, instead of by turns with the smoothed
    drift. The diagnosis fits by turns; ``experiments/drift_rounds.py`` measures both
    (``docs/diagnosis.md`` says why).

    Attributes (per sample, per output): ``steps`` (T,) the transition's ``dt / h``; ``phi``
    (T, k) the coloured term's decay; ``gain`` (T, k, 3), 0 off the observed samples; ``f``
    (T, k); ``used`` (T, k) the samples in the likelihood."""

    steps: jax.Array
    phi: jax.Array
    gain: jax.Array
    f: jax.Array
    used: jax.Array

    @classmethod
    def of(cls, t, observed, ratio, coloured_ratio=0.0, coloured_time_s=1e-3) -> Whitener:
        """At ``lambda = ratio``, ``kappa = coloured_ratio`` and ``tau = coloured_time_s`` (k,)
        for samples at ``t`` (T,) s, ``observed`` (T,): for a fitted :class:`Wander` ``w``,
        ``Whitener.of(t, observed, w.ratio, w.coloured_ratio, w.coloured_time_s)``."""
        dt, obs = jnp.diff(jnp.asarray(t, float)), jnp.asarray(observed, bool)
        h = float(np.median(np.diff(t)))
        ratio = np.atleast_1d(ratio)
        kappa, tau = (np.broadcast_to(x, ratio.shape) for x in (coloured_ratio, coloured_time_s))
        cols = [_filter(jnp.zeros(obs.shape), dt, obs, *map(float, q), h) for q in zip(ratio, tau, kappa)]
        gain = jnp.stack([jnp.where(obs[:, None], c[3] @ _OBSERVED / c[5][:, None], 0.0) for c in cols], 1)
        dt0 = jnp.concatenate([jnp.zeros(1), dt])
        phi = jnp.exp(-dt0[:, None] / jnp.asarray(tau, float)[None, :])
        return cls(dt0 / h, phi, gain, jnp.stack([c[5] for c in cols], 1), jnp.stack([c[6] for c in cols], 1))

    def __call__(self, r) -> jax.Array:
        """``L r``: the normalised one-step errors (T, k) of residuals ``r`` (T, k) nm, 0 off
        :attr:`used`."""

        def step(m, x):
            rn, s, phi, k = x
            m = jax.vmap(lambda mk, pk: _transition(s, pk) @ mk)(m, phi)
            e = rn - m @ _OBSERVED
            return m + k * e[:, None], e

        _, e = lax.scan(step, jnp.zeros((r.shape[1], 3)), (r, self.steps, self.phi, self.gain))
        return jnp.where(self.used, e / jnp.sqrt(self.f), 0.0)


def _minus_two_log_l(r, dt, observed, ratio, tau, kappa, h, rate_var):
    """``(-2 ln L with s^2 concentrated out, s^2)`` of one output at ``(lambda, tau, kappa)``."""
    return _concentrated(*_filter(r, dt, observed, ratio, tau, kappa, h, rate_var)[-3:])


def _concentrated(e, f, used):
    """``(-2 ln L, s^2)`` from the one-step errors ``e``, their variances ``f`` (units of
    ``s^2``) and the samples ``used``: ``s^2`` concentrated out (module docstring)."""
    n = jnp.sum(used)
    s2 = jnp.sum(jnp.where(used, e**2 / f, 0.0)) / n
    return n * jnp.log(2 * jnp.pi * s2) + jnp.sum(jnp.where(used, jnp.log(f), 0.0)) + n, s2


@jax.jit
def _grid(r, dt, observed, ratios, taus, kappas, h, rate_var):
    """``-2 ln L`` (len(ratios), len(taus), len(kappas), k) over the grid, every output of ``r``
    (T, k) at once."""
    per_output = jax.vmap(_minus_two_log_l, in_axes=(1, None, None, None, None, None, None, None))
    at = lambda q, tau, kappa: per_output(r, dt, observed, q, tau, kappa, h, rate_var)[0]
    return jax.vmap(lambda q: jax.vmap(lambda tau: jax.vmap(lambda kappa: at(q, tau, kappa))(kappas))(taus))(
        ratios
    )


@jax.jit
def _smooth(r, dt, observed, ratio, tau, kappa, h, rate_var):
    """The Rauch-Tung-Striebel smoother of one output: ``(states (T, 3), e, -2 ln L, s^2, used)``.
    Without a coloured term (``kappa = 0``) or a rate (``rate_var = 0``) their rows and columns
    of the covariances are zero: a unit there keeps the smoother's solve regular and leaves them 0."""
    m_f, p_f, m_p, p_p, e, f, used = _filter(r, dt, observed, ratio, tau, kappa, h, rate_var)
    none = jnp.diag(jnp.array([0.0, rate_var == 0, kappa == 0], float))

    def back(m_next, x):
        m, p, m_pred, p_pred, dtn = x
        f_ = _transition(dtn / h, jnp.exp(-dtn / tau))
        m_s = m + p @ f_.T @ jnp.linalg.solve(p_pred + none, m_next - m_pred)
        return m_s, m_s

    dts = jnp.concatenate([dt, jnp.zeros(1)])
    xs = (m_f[:-1], p_f[:-1], m_p[1:], p_p[1:], dts[:-1])
    _, states = lax.scan(back, m_f[-1], xs, reverse=True)
    m2ll, s2 = _concentrated(e, f, used)
    return jnp.concatenate([states, m_f[-1:]]), e, m2ll, s2, used


def _refined(grid: np.ndarray, m2ll: np.ndarray) -> float:
    """The minimum of ``m2ll`` over ``log(grid)``: the best grid point, moved to the vertex of
    the parabola through it and its neighbours where that lies between them."""
    i = int(np.nanargmin(m2ll))
    if 0 < i < len(grid) - 1:
        x = np.log(grid)
        y0, y1, y2 = m2ll[i - 1 : i + 2]
        curv = y0 - 2 * y1 + y2
        if curv > 0:
            return float(np.exp(x[i] + 0.5 * (y0 - y2) / curv * (x[i + 1] - x[i])))
    return float(grid[i])


def fit_wander(r, t, observed, drift: bool = True) -> Wander:
    """The drift, a rate and a wander, beside a coloured term, in the residuals ``r`` (T,) or
    (T, k) nm at times ``t`` (T,) s, trained on the ``observed`` (T,) samples (module docstring);
    ``drift=False``: the coloured term alone (no wander, the rate 0).

    Raises:
        ValueError: when fewer than 10 samples are observed.
    """
    r = np.asarray(r, float).reshape(len(t), -1)
    observed = np.asarray(observed, bool)
    if observed.sum() < 10:
        raise ValueError(f"a drift's wander needs at least 10 observed samples, got {int(observed.sum())}")
    rj, dt, obs = jnp.asarray(r), jnp.diff(jnp.asarray(t, float)), jnp.asarray(observed)
    h = float(np.median(np.diff(t)))
    ratios, rate_var = (LAMBDA_GRID, _DIFFUSE) if drift else (np.zeros(1), 0.0)
    grids = (ratios, COLOURED_TIMES_S, COLOURED_RATIOS)
    m2ll = np.asarray(_grid(rj, dt, obs, *map(jnp.asarray, grids), h, rate_var))
    hyper = []
    for k in range(r.shape[1]):
        _, j, i = np.unravel_index(np.nanargmin(m2ll[..., k]), m2ll.shape[:3])
        hyper.append((_refined(ratios, m2ll[:, j, i, k]), COLOURED_TIMES_S[j], COLOURED_RATIOS[i]))
    cols = [_smooth(rj[:, k], dt, obs, *q, h, rate_var) for k, q in enumerate(hyper)]
    states, e, m2, s2, used = (np.stack([np.asarray(c[i]) for c in cols], -1) for i in range(5))
    ratio, tau, kappa = np.array(hyper).T
    return Wander(states[:, 0], states[0, 1] / h, ratio, s2, states[:, 2], kappa, tau, e, m2, used)
