"""A drift as a random process, a rate and a wander beside a coloured term, by the Kalman
smoother of jaxafm.diagnose.wander: against dense Gaussian algebra and against random walks and
first-order autoregressions drawn with NumPy."""

import numpy as np
import pytest

from jaxafm.diagnose import wander as W
from jaxafm.diagnose.wander import Whitener, fit_wander


def _series(seed: int, n: int = 60, q: float = 25.0, s: float = 2.0):
    """A random walk of diffusion ``q`` nm^2/s plus white noise of ``s`` nm, at uneven times."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n))
    w = np.r_[0.0, np.cumsum(np.sqrt(q * np.diff(t)) * rng.standard_normal(n - 1))]
    return t, w, w + s * rng.standard_normal(n)


def _ar1(rng, t, sd: float, tau: float) -> np.ndarray:
    """A stationary first-order autoregression of standard deviation ``sd`` decaying by
    ``exp(-dt / tau)`` between samples at ``t``: the Ornstein-Uhlenbeck process, sampled exactly."""
    a = np.empty(t.size)
    a[0] = sd * rng.standard_normal()
    for n in range(1, t.size):
        phi = np.exp(-(t[n] - t[n - 1]) / tau)
        a[n] = phi * a[n - 1] + sd * np.sqrt(1 - phi**2) * rng.standard_normal()
    return a


def _coloured_cov(wander: W.Wander, t: np.ndarray) -> np.ndarray:
    """The fitted coloured term's covariance (units of the white noise's variance)."""
    return wander.coloured_ratio[0] * np.exp(-np.abs(np.subtract.outer(t, t)) / wander.coloured_time_s[0])


@pytest.mark.parametrize("kappas", [[0.0], W.COLOURED_RATIOS], ids=["walk alone", "with a coloured term"])
def test_the_smoothed_drift_is_the_gaussian_posterior_mean_across_a_held_out_block(monkeypatch, kappas):
    """The drift's and the coloured term's posterior means given the observed samples, by dense
    conditioning: prior ``w(t) = w_0 + v tau + walk``, ``w_0 ~ N(0, D)``, ``v ~ N(0, D / h^2)``
    (``tau = t - t_0``, ``h`` = 1 ms the sampling step; units of the noise's variance), the
    walk's covariance ``lambda min(tau_i, tau_j)``, the coloured term's ``kappa exp(-|t_i - t_j|
    / tau_c)``; observed ``r = w + a + e``. D = 1e5 stands for the diffuse start (the smoother's
    1e8): they differ by O(1 / D). Once with the coloured term held off, once fitted (a
    6 nm, 5 ms autoregression drawn in the record: it must be found)."""
    monkeypatch.setattr(W, "COLOURED_RATIOS", np.asarray(kappas))
    t, _, r = _series(0, n=120)
    r = r + 40.0 * (t - t[0]) + _ar1(np.random.default_rng(10), t, 6.0, 5e-3)  # a rate of 40 nm/s
    observed = np.ones(t.size, bool)
    observed[40:70] = False  # a held-out block: the smoother must interpolate across it
    observed[100:] = False  # and a held-out end: extrapolate
    wander = fit_wander(r, t, observed)
    assert (wander.coloured_ratio[0] > 0) == (len(kappas) > 1)
    lam = wander.ratio[0]
    tau = t - t[0]
    prior = 1e5 * (1 + np.outer(tau, tau) / 1e-3**2) + lam * np.minimum.outer(tau, tau)
    coloured = _coloured_cov(wander, t)
    o = observed
    weights = np.linalg.solve(prior[np.ix_(o, o)] + coloured[np.ix_(o, o)] + np.eye(o.sum()), r[o])
    np.testing.assert_allclose(wander.level[:, 0], prior[:, o] @ weights, atol=1e-4 * np.ptp(r))
    np.testing.assert_allclose(wander.coloured[:, 0], coloured[:, o] @ weights, atol=1e-4 * np.ptp(r))


def test_the_likelihood_is_that_of_the_samples_less_the_line_through_the_first_two():
    """With a diffuse start and rate the likelihood is that of ``c_n = r_n - r_1 - (tau_n /
    tau_2) (r_2 - r_1)`` (``tau`` from the first observed sample; start and rate cancel), a
    Gaussian of covariance ``A S A^T``, ``S = s^2 (lambda min(tau_i, tau_j) + C + I)``, ``C`` the
    coloured term's: at the fitted ``lambda``, ``kappa``, ``tau_c`` and ``s^2`` the filter's
    ``-2 ln L`` must be it."""
    t, _, r = _series(1)
    r = r + _ar1(np.random.default_rng(11), t, 5.0, 3e-3)
    observed = np.ones(t.size, bool)
    observed[:5] = False  # settling samples: the likelihood starts at the first observed ones
    observed[40:50] = False
    wander = fit_wander(r, t, observed)
    lam, s2 = wander.ratio[0], wander.noise_var[0]
    to, ro = t[observed], r[observed]
    tau = to - to[0]
    a = np.eye(tau.size)[2:]
    a[:, 0] -= 1 - tau[2:] / tau[1]
    a[:, 1] -= tau[2:] / tau[1]
    assert wander.coloured_ratio[0] > 0
    coloured = _coloured_cov(wander, to)
    cov = a @ (s2 * (lam * np.minimum.outer(tau, tau) + coloured + np.eye(tau.size))) @ a.T
    c = a @ ro
    sign, logdet = np.linalg.slogdet(2 * np.pi * cov)
    assert sign > 0
    dense = logdet + c @ np.linalg.solve(cov, c)
    assert wander.minus_two_log_l[0] == pytest.approx(dense, rel=1e-6)
    assert wander.used[:, 0].sum() == observed.sum() - 2


def test_a_random_walk_in_white_noise_is_recovered():
    """6 s at 1 kHz of a walk of 25 nm^2/s in 2 nm noise (per output, two outputs, the second
    walk half as fast): the maximum-likelihood diffusion scatters by 12 % (sd over 20 seeds of
    this NumPy draw) and the noise variance by 1.6 %; bounds of about 3.3 sd. The noise variance
    is the white term's plus the coloured term's where the fit gives that a share of it (here
    one output: a tenth of it at 1 ms, a time constant of one sample)."""
    rng = np.random.default_rng(7)
    t = np.arange(6000) / 1000.0
    walk = lambda q: np.r_[0.0, np.cumsum(np.sqrt(q * np.diff(t)) * rng.standard_normal(t.size - 1))]
    r = np.stack([walk(25.0), walk(6.25)], 1) + 2.0 * rng.standard_normal((t.size, 2))
    wander = fit_wander(r, t, np.ones(t.size, bool))
    np.testing.assert_allclose(wander.diffusion, [25.0, 6.25], rtol=0.4)
    np.testing.assert_allclose(wander.noise_var * (1 + wander.coloured_ratio), 4.0, rtol=0.05)


def test_a_random_walk_beside_a_coloured_term_is_recovered():
    """6 s at 1 kHz of a walk of 25 nm^2/s, a 6 nm autoregression of 10 ms and 2 nm of white
    noise: the time constant is the grid's 10 ms, the coloured term's standard deviation falls
    on the grid point next to 6 nm (the grid of ``kappa`` steps the standard deviation by a
    factor 1.78), and the diffusion scatters by 0.28 in its logarithm (sd over 12 seeds of this
    NumPy draw): bounds of 3 sd, a factor 2.3."""
    rng = np.random.default_rng(5)
    t = np.arange(6000) / 1000.0
    walk = np.r_[0.0, np.cumsum(np.sqrt(25.0 * np.diff(t)) * rng.standard_normal(t.size - 1))]
    r = walk + _ar1(rng, t, 6.0, 0.01) + 2.0 * rng.standard_normal(t.size)
    wander = fit_wander(r, t, np.ones(t.size, bool))
    assert wander.coloured_time_s[0] == 0.01
    assert 6.0 / 1.34 < wander.coloured_sd[0] < 6.0 * 1.34
    assert 25.0 / 2.3 < wander.diffusion[0] < 25.0 * 2.3


def test_white_noise_has_no_wander_and_the_bic_of_a_straight_line():
    """A rate in white noise, no walk: the rate is the least-squares line's, the fitted
    diffusion negligible (its spread over the 3 s record well under the noise), and the BIC
    that of the least-squares line (2 parameters) plus less than ``2 ln n``: the diffuse
    likelihood pays for the start and the rate through the log-determinant of their information
    (``ln n`` and ``3 ln n`` to leading order) where the BIC pays ``ln n`` for each."""
    from jaxafm.identify.fit import bic

    rng = np.random.default_rng(3)
    t = np.arange(3000) / 1000.0
    r = (5.0 * t + 2.0 * rng.standard_normal(t.size))[:, None]
    wander = fit_wander(r, t, np.ones(t.size, bool))
    line = np.polyfit(t, r[:, 0], 1)
    assert wander.velocity[0] == pytest.approx(line[0], abs=0.05)  # 5 nm/s +- 0.07 (1 sd)
    assert np.sqrt(wander.diffusion[0] * 3.0) < 0.5
    rss = np.sum((r[:, 0] - np.polyval(line, t)) ** 2)
    assert 0 < wander.bic(0) - bic(rss, t.size, 2) < 2 * np.log(t.size)


def test_too_few_observed_samples_are_refused():
    t = np.arange(100) / 100.0
    observed = np.zeros(100, bool)
    observed[:5] = True
    with pytest.raises(ValueError, match="at least 10 observed samples, got 5"):
        fit_wander(np.zeros(100), t, observed)


def test_fitting_under_the_whitener_is_generalised_least_squares_with_the_wander_covariance():
    """The whitened one-step errors ``L r`` make least squares under ``|L r|^2`` the generalised
    least squares of the wander's covariance, its diffuse start and rate profiled out. Truth from
    dense linear algebra (no filter): a random walk of diffusion ``lambda`` (units of the white
    noise's variance) from an unknown level at an unknown rate is the covariance
    ``I + lambda min(t_i - t_0, t_j - t_0)`` with ``1`` and ``t - t_0`` as extra regressors of flat
    prior, a coloured term ``kappa exp(-|t_i - t_j| / tau_c)`` beside it; the coefficient of a
    regressor ``x`` from the dense GLS on the observed samples equals the one from least squares
    on ``L x`` and ``L d``, held-out gaps in the record and all."""
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.005, 0.015, 300))
    observed = (np.arange(t.size) // 30) % 2 == 0  # alternating blocks
    lam, kappa, tau_c = 40.0, 3.0, 0.03
    x = np.sin(2 * np.pi * 1.3 * t) + 0.3 * t
    walk = np.cumsum(rng.normal(0, np.sqrt(lam * np.diff(t, prepend=t[0]))))
    d = 2.5 * x + 4.0 + 1.5 * t + walk + _ar1(rng, t, np.sqrt(kappa), tau_c) + rng.normal(0, 1, t.size)

    o = observed
    s = t[o] - t[0]
    cov = (
        np.eye(o.sum())
        + lam * np.minimum.outer(s, s)
        + kappa * np.exp(-np.abs(np.subtract.outer(s, s)) / tau_c)
    )
    regressors = np.stack([x[o], np.ones(o.sum()), s], 1)
    w = np.linalg.solve(cov, regressors)
    dense = np.linalg.solve(regressors.T @ w, w.T @ d[o])[0]

    whiten = Whitener.of(t, observed, np.array([lam]), np.array([kappa]), np.array([tau_c]))
    lx, ld = (np.asarray(whiten(v[:, None]))[:, 0] for v in (x, d))
    assert lx @ ld / (lx @ lx) == pytest.approx(dense, rel=1e-6)
    # the first two observed samples set the diffuse start and rate: no error of theirs counts
    assert np.count_nonzero(lx) == observed.sum() - 2


def test_without_the_drift_the_likelihood_is_that_of_the_samples_less_the_first():
    """``drift=False``: no wander and a rate known to be 0, the level still diffuse, so the
    likelihood (over the same samples as the drift's, all observed but the first two) is that
    of the differences ``c_n = r_n - r_1`` (the level cancels), covariance ``A S A^T``, ``S =
    s^2 (C + I)``, given the first of them: ``-2 ln L = -2 ln N(c; A S A^T) + 2 ln N(c_2;
    (A S A^T)_22)``, at the fitted ``kappa``, ``tau_c`` and ``s^2``."""
    t, _, _ = _series(2)
    rng = np.random.default_rng(12)
    r = 30.0 + _ar1(rng, t, 5.0, 3e-3) + 2.0 * rng.standard_normal(t.size)
    observed = np.ones(t.size, bool)
    observed[20:30] = False
    noise = fit_wander(r, t, observed, drift=False)
    assert noise.ratio[0] == 0 and noise.velocity[0] == 0 and noise.coloured_ratio[0] > 0
    to, ro = t[observed], r[observed]
    a = np.eye(to.size)[1:]
    a[:, 0] = -1.0
    cov = a @ (noise.noise_var[0] * (_coloured_cov(noise, to) + np.eye(to.size))) @ a.T
    c = a @ ro
    m2ll = lambda x, s: np.linalg.slogdet(2 * np.pi * s)[1] + x @ np.linalg.solve(s, x)
    dense = m2ll(c, cov) - m2ll(c[:1], cov[:1, :1])
    assert noise.minus_two_log_l[0] == pytest.approx(dense, rel=1e-6)
    assert noise.used[:, 0].sum() == observed.sum() - 2
    # the smoother's level is the GLS mean of the observed samples under that covariance
    s = _coloured_cov(noise, t) + np.eye(t.size)
    weights = np.linalg.solve(s[np.ix_(observed, observed)], np.ones(observed.sum()))
    gls = weights @ ro / weights.sum()
    np.testing.assert_allclose(noise.level[:, 0], gls, atol=1e-3 * np.ptp(r))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_colour_is_not_drift_but_a_walk_is(seed):
    """6 s at 1 kHz of a 6 nm autoregression of 10 ms in 2 nm of white noise, no drift: scored
    under the same noise model, the drift's BIC (walk, rate, 4 parameters) is above the
    coloured term's alone (3 parameters): the data do not pay for the rate (about ``3 ln n``
    through the diffuse likelihood) and the walk. A least-squares BIC, which takes the colour
    for white, is far above both: weighed against it a drift would be named for the colour.
    The same record with a walk of 25 nm^2/s added (its spread over 6 s, 12 nm, twice the
    coloured term's): the drift's BIC is below the coloured term's by more than the diagnosis's
    10 (:class:`~jaxafm.diagnose.core.Rules`: "very strong" evidence)."""
    from jaxafm.diagnose.core import Rules
    from jaxafm.identify.fit import bic

    rng = np.random.default_rng(seed)
    t = np.arange(6000) / 1000.0
    observed = np.ones(t.size, bool)
    coloured = _ar1(rng, t, 6.0, 0.01) + 2.0 * rng.standard_normal(t.size)
    drift, noise = fit_wander(coloured, t, observed), fit_wander(coloured, t, observed, drift=False)
    assert drift.bic(W.PARAMETERS_PER_OUTPUT) > noise.bic(W.NOISE_PARAMETERS_PER_OUTPUT)
    white = bic(np.sum((coloured - coloured.mean()) ** 2), t.size, 1)
    assert white - drift.bic(W.PARAMETERS_PER_OUTPUT) > 1000
    walk = np.r_[0.0, np.cumsum(np.sqrt(25.0 * np.diff(t)) * rng.standard_normal(t.size - 1))]
    wandering = coloured + walk
    drift, noise = fit_wander(wandering, t, observed), fit_wander(wandering, t, observed, drift=False)
    gain = noise.bic(W.NOISE_PARAMETERS_PER_OUTPUT) - drift.bic(W.PARAMETERS_PER_OUTPUT)
    assert gain > Rules().min_delta_bic
