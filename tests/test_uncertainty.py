"""What a fit's data determine: the cluster-robust covariance, leave-group-out residuals and the
model ladder, against closed forms and refits written here in NumPy."""

import numpy as np
import pytest
from scipy.signal import lfilter

from jaxafm.identify import selection, uncertainty
from jaxafm.identify.scan_model import ScanModelSpec


def _regression(seed=0, groups=12, per=8, shared=1.0, own=0.2):
    """y = a + b x with errors shared within a group (sd ``shared``) and a row's own (sd
    ``own``); a group's rows lie near one x (as a feature's chords lie near its site)."""
    rng = np.random.default_rng(seed)
    g = np.repeat(np.arange(groups), per)
    x = rng.uniform(-1, 1, groups)[g] + rng.normal(0, 0.05, g.size)
    y = 0.5 + 2.0 * x + rng.normal(0, shared, groups)[g] + rng.normal(0, own, g.size)
    return np.stack([np.ones_like(x), x], -1), y, g


def test_leave_group_out_equals_the_refit_without_the_group():
    """Exact for linear least squares, with and without a ridge prior: the closed form against
    a refit of the other groups' rows."""
    J, y, g = _regression()
    for prior in (None, 0.3 * np.eye(2)):
        H = J.T @ J + (0 if prior is None else prior)
        theta = np.linalg.solve(H, J.T @ y)
        left = uncertainty.leave_group_out(J, J @ theta - y, g, prior)
        for k in np.unique(g):
            rows = g != k
            Hk = J[rows].T @ J[rows] + (0 if prior is None else prior)
            theta_k = np.linalg.solve(Hk, J[rows].T @ y[rows])
            np.testing.assert_allclose(left[k], J[g == k] @ theta_k - y[g == k], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("rows, per, slab", [(90, 3, 2048), (91, 3, 2048), (91, 3, 12), (90, 21, 2048)])
def test_leave_group_out_of_groups_smaller_than_the_parameters_equals_the_refit(rows, per, slab, monkeypatch):
    """12 parameters, a ridge prior: groups of 3 rows (the direct (b, b) form, not Woodbury's
    (k, k)), the same with a last group of 1 (two sizes, each solved together), the same with
    ``J S^T`` made 12 rows (4 groups) at a time, and groups of 21 rows with a last one of 6 (too
    few small groups for the direct form: Woodbury's for all); the closed form against a refit of
    the other groups' rows."""
    monkeypatch.setattr(uncertainty, "DIRECT_ROWS", slab)
    rng = np.random.default_rng(3)
    J = rng.normal(size=(rows, 12))
    y = J @ rng.normal(size=12) + 0.3 * rng.normal(size=rows)
    g = np.arange(rows) // per
    prior = 0.5 * np.eye(12)
    theta = np.linalg.solve(J.T @ J + prior, J.T @ y)
    left = uncertainty.leave_group_out(J, J @ theta - y, g, prior)
    for k in np.unique(g):
        rows = g != k
        theta_k = np.linalg.solve(J[rows].T @ J[rows] + prior, J[rows].T @ y[rows])
        np.testing.assert_allclose(left[k], J[g == k] @ theta_k - y[g == k], rtol=1e-10, atol=1e-12)


def test_cluster_covariance_covers_shared_errors_where_the_plain_one_does_not():
    """Over many draws, the slope's cluster-robust standard error matches its spread across
    draws (within the Monte-Carlo noise), while s^2 (J^T J)^-1, which takes the rows as
    independent, is far too narrow when most of the error is shared within a group."""
    slopes, robust, plain = [], [], []
    for seed in range(300):
        J, y, g = _regression(seed, groups=40, per=10)
        theta = np.linalg.lstsq(J, y, rcond=None)[0]
        r = J @ theta - y
        slopes.append(theta[1])
        robust.append(np.sqrt(uncertainty.covariance(J, r, g)[1, 1]))
        plain.append(np.sqrt(np.mean(r**2) * np.linalg.inv(J.T @ J)[1, 1]))
    spread = np.std(slopes)
    assert np.median(robust) == pytest.approx(spread, rel=0.2)
    assert np.median(plain) < 0.5 * spread


def test_the_ladder_climbs_while_the_score_falls_by_two_and_stops_where_it_does_not():
    """A scored stand-in for the fits: each play doubling and each effect lowers or raises a
    score by a known amount. The ladder takes the best next rung while it lowers the score by 2
    or more (drift, lowering it by 1, is not kept), and tries rate dependence only with two line
    rates, and without the z signal's edge delay (which it cannot be told from)."""
    gains = {"bow": -5.0, "creep": +2.0, "asymmetry": +1.0, "drift": -1.0, "rate_dependence": -3.0}

    def score(spec):
        plays = {1: 0.0, 2: -4.0, 4: -6.5, 8: -5.0, 16: 0.0}[spec.operators]
        return 100.0 + plays + sum(gains[e] for e in spec.effects if e in gains)

    def fit(spec, start):
        return selection.RungFit(spec, score(spec), "")

    for lag, rates, why in (
        ("feedback_lag", [1.0], "one line rate"),
        ("feedback_lag", [0.5, 2.0], "shift every edge alike"),
        (None, [1.0], "one line rate"),
        (None, [0.5, 2.0], None),
    ):
        effects = ("coupling",) + ((lag,) if lag else ()) + tuple(gains)
        configured = ScanModelSpec(kind="gpi", effects=effects, operators=16, deadzones=3)
        model, chosen, rungs = selection.select(configured, fit, rates, log=lambda *_: None)
        assert chosen.operators == 4 and model is chosen
        base = {"coupling", "bow"} | ({lag} if lag else set())
        assert set(chosen.effects) == base | (set() if why else {"rate_dependence"})
        skipped = [
            r for r in rungs if r.label == "+ rate_dependence" and not r.kept and "not tried" in r.reason
        ]
        assert (skipped[0].reason if skipped else None) == (None if why is None else skipped[0].reason)
        assert why is None or why in skipped[0].reason


def test_aicc_charges_parameters_more_as_they_near_the_data():
    e = np.random.default_rng(0).normal(0, 10.0, (20, 2))
    few, many = selection.aicc(e, 3)[0], selection.aicc(e, 30)[0]
    assert few < many and np.isinf(selection.aicc(e, 39)[0])


def test_a_direction_the_data_do_not_fix_keeps_the_priors_width():
    """Closed form: a parameter no row depends on has the prior's variance (s^2 / p), one the
    rows fix far more tightly has about its sandwich variance."""
    J, y, g = _regression()
    J = np.c_[J, np.zeros(len(J))]  # a third parameter nothing depends on
    theta = np.linalg.lstsq(J[:, :2], y, rcond=None)[0]
    r = J[:, :2] @ theta - y
    sigma_p = 3.0
    prior = np.mean(r**2) / sigma_p**2 * np.eye(3)
    c = uncertainty.covariance(J, r, g, prior)
    assert c[2, 2] == pytest.approx(sigma_p**2, rel=1e-9)
    plain = uncertainty.covariance(J[:, :2], r, g)
    np.testing.assert_allclose(c[:2, :2], plain, rtol=0.02)


@pytest.mark.parametrize("rows, rho", [(1000, 0.96), (130, -0.5), (40, 0.999), (1, 0.9)])
def test_the_blocked_backward_filter_equals_lfilter_run_backwards(rows, rho):
    """``A_t = J_t + rho A_{t+1}`` by (64, 64) blocks against SciPy's ``lfilter`` over the
    reversed rows: records longer than a block and not a multiple of it, shorter than one, and
    a single row."""
    J = np.random.default_rng(rows).normal(size=(rows, 7))
    expected = lfilter([1.0], [1.0, -rho], J[::-1], axis=0)[::-1]
    A = np.concatenate([a for _, a in uncertainty.backward_blocks(J, rho)][::-1])
    np.testing.assert_allclose(A, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("rows", [1000, 2500])
def test_the_ar1_covariance_summed_by_slabs_is_the_dense_sandwich(rows):
    """``H^-1 (s_w^2 A^T A + s^2 P) H^-1`` with ``A`` from SciPy's ``lfilter`` over the reversed
    rows, all of it at once, against the covariance whose ``A^T A`` is summed a slab of rows at a
    time: a record shorter than a slab, and one of two slabs and part of a third."""
    rng = np.random.default_rng(rows)
    J = rng.normal(size=(rows, 5))
    r = lfilter([1.0], [1.0, -0.9], rng.normal(size=rows))  # AR(1) residuals
    prior = np.mean(r**2) * np.eye(5)
    H = J.T @ J + prior
    rho = np.corrcoef(r[:-1], r[1:])[0, 1]
    A = lfilter([1.0], [1.0, -rho], J[::-1], axis=0)[::-1]
    Hinv = np.linalg.inv(H)
    want = Hinv @ (np.mean((r[1:] - rho * r[:-1]) ** 2) * A.T @ A + np.mean(r**2) * prior) @ Hinv
    np.testing.assert_allclose(uncertainty._ar1_covariance(J, r, prior, H), want, rtol=1e-10)
