"""A push's predicted odds (jaxafm.position.push_odds) and their scores (jaxafm.study.reliability),
against closed forms and pushes drawn from a known miss model with NumPy."""

import numpy as np
import pytest
from scipy import stats

from jaxafm import plots
from jaxafm.position import push_odds
from jaxafm.study.monte_carlo import predicted_push_success
from jaxafm.study.reliability import gate, reliability


@pytest.mark.parametrize("mean, sd, tolerance", [(0.0, 2.0, 3.0), (4.0, 1.5, 5.0), (6.0, 3.0, 2.0)])
def test_success_probability_is_the_rice_distribution_for_a_round_gaussian_miss(mean, sd, tolerance):
    """An isotropic Gaussian miss of mean ``mean`` along the push: its length is Rice distributed,
    P(|m| <= T) = rice.cdf(T / sd, mean / sd) (a Student-t of 1e7 degrees of freedom is Gaussian)."""
    miss = push_odds.Miss(mean, sd, 0.0, sd, 1e7)
    want = stats.rice.cdf(tolerance / sd, mean / sd)
    assert push_odds.success_probability(miss, tolerance) == pytest.approx(want, abs=1e-6)


def test_components_split_a_miss_along_and_across_the_push():
    direction = np.array([[0.6, 0.8]])
    along, across = push_odds.components(np.array([[3.0, 4.0]]) + np.array([[-0.8, 0.6]]), direction)
    np.testing.assert_allclose([along[0], across[0]], [5.0, 1.0], atol=1e-12)


def _pushes(rng, k):
    """``k`` pushes of 100-300 nm whose misses follow the module's model: along 0.5 nm + 3 % of the
    distance, sd 2 nm; across -1 nm + 1 % of the distance, sd 3 nm."""
    L = rng.uniform(100, 300, k)
    along = 0.5 + 0.03 * L + rng.normal(0, 2.0, k)
    across = -1.0 + 0.01 * L + rng.normal(0, 3.0, k)
    return L, along, across


def test_online_misses_are_the_regression_on_the_pushes_before():
    rng = np.random.default_rng(0)
    L, along, across = _pushes(rng, 40)
    observed = rng.uniform(size=40) > 0.2
    miss = push_odds.online_misses(L, along, across, observed)
    k = 30
    prior = np.flatnonzero(observed[:k])
    X = np.column_stack([np.ones(prior.size), L[prior] / 100])
    beta, rss = np.linalg.lstsq(X, along[prior], rcond=None)[:2]
    x = np.array([1, L[k] / 100])
    scale = np.sqrt(rss[0] / (prior.size - 2) * (1 + x @ np.linalg.inv(X.T @ X) @ x))
    assert miss.along[k] == pytest.approx(x @ beta, rel=1e-9)
    assert miss.along_scale[k] == pytest.approx(scale, rel=1e-9)
    assert miss.dof[k] == prior.size - 2
    first = np.flatnonzero(np.cumsum(observed) - observed >= push_odds.MIN_PUSHES)[0]
    assert np.all(np.isnan(miss.along[:first])) and np.isfinite(miss.along[first])


def test_predicted_odds_are_as_often_right_as_they_say():
    """Pushes of particles of radius 2-12 nm (tolerance: one radius) drawn from the known model:
    the mean predicted success equals the observed rate within 3 binomial sd, in the whole and in
    each half of the predictions, and the Brier score beats the overall rate's."""
    rng = np.random.default_rng(1)
    n = 4000
    L, along, across = _pushes(rng, n)
    radius = rng.uniform(2, 12, n)
    ok = np.hypot(along, across) <= radius
    p = push_odds.success_probability(push_odds.online_misses(L, along, across, np.ones(n, bool)), radius)
    scored = np.isfinite(p)
    assert scored.sum() == n - push_odds.MIN_PUSHES
    for part in (scored, scored & (p < np.nanmedian(p)), scored & (p >= np.nanmedian(p))):
        sd = np.sqrt(np.sum(p[part] * (1 - p[part]))) / part.sum()
        assert abs(p[part].mean() - ok[part].mean()) < 3 * sd
    score = reliability(p, ok)
    assert score["brier"] < score["brier_base_rate"]


def test_reliability_bins_and_brier_by_hand():
    p = np.array([0.05, 0.15, 0.12, 0.95, 1.0, np.nan])
    y = np.array([False, True, False, True, True, True])
    s = reliability(p, y)
    assert s["trials"] == 5
    assert s["brier"] == pytest.approx(np.mean((p[:5] - y[:5]) ** 2))
    assert s["brier_base_rate"] == pytest.approx(0.6 * 0.4)
    assert [(b["lo"], b["trials"]) for b in s["bins"]] == [(0.0, 1), (0.1, 2), (0.9, 2)]
    assert s["bins"][1]["predicted_pct"] == pytest.approx(13.5)
    assert s["bins"][1]["observed_pct"] == pytest.approx(50.0)
    assert reliability(np.array([np.nan]), np.array([True]))["trials"] == 0


def test_contact_odds_are_laplaces_rule_of_succession():
    contact = np.array([True, False, True, True, False])
    pushed = np.array([True, True, False, True, True])
    np.testing.assert_allclose(push_odds.contact_odds(contact, pushed), [1 / 2, 2 / 3, 2 / 4, 2 / 4, 3 / 5])


def test_a_study_learns_each_scanners_odds_from_its_own_earlier_pushes(tmp_path):
    """Two scanners of 600 trials, one pushing within 1 nm (sd), the other within 6 nm, particles
    of 5 nm, and a tip that misses its particle on 5 % of the pushes (the particle stays: a miss
    of the whole distance): each scanner's odds come from its own pushes alone (NaN for its first
    MIN_PUSHES and for a trial that did not push), and match its observed success within 3
    binomial sd; the reliability figure is drawn."""
    rng = np.random.default_rng(2)
    n = 600
    sd = np.repeat([1.0, 6.0], n)
    distance = rng.uniform(100, 300, 2 * n)
    misses = rng.normal(0, 1, (2 * n, 2)) * sd[:, None]
    contact = rng.uniform(size=2 * n) > 0.05
    misses[~contact] = [-1.0, 0.0] * distance[~contact, None]
    along, across = push_odds.components(misses, np.tile([1.0, 0.0], (2 * n, 1)))
    error = np.hypot(along, across)
    error[7] = np.nan  # a trial that did not push
    r = {
        "trial": np.arange(2 * n),
        "scanner": np.repeat([0, 1], n),
        "radius_nm": np.full(2 * n, 5.0),
        "push_distance_nm": distance,
        "push_contact": contact,
        "push_first_along_nm": np.where(np.isfinite(error), along, np.nan),
        "push_first_across_nm": np.where(np.isfinite(error), across, np.nan),
        "push_first_error_nm": error,
    }
    p = predicted_push_success(r, 1.0)
    first = np.flatnonzero(np.isfinite(p))
    assert np.all(np.isnan(p[: first[0]])) and first[0] >= push_odds.MIN_PUSHES and np.isnan(p[7])
    assert np.all(np.isnan(p[n : n + push_odds.MIN_PUSHES]))
    ok = contact & (error <= 5.0)
    for s in (0, 1):
        part = (r["scanner"] == s) & np.isfinite(p)
        bound = 3 * np.sqrt(np.sum(p[part] * (1 - p[part]))) / part.sum()
        assert abs(p[part].mean() - ok[part].mean()) < bound
    # truth: 0.95 (1 - exp(-25 / 72)) = 0.28 and 0.95
    assert np.nanmean(p[n:]) < 0.5 < np.nanmean(p[:n])
    plots.push_reliability(reliability(p, ok), p, tmp_path / "odds.png")
    assert (tmp_path / "odds.png").stat().st_size > 10_000


def test_the_gate_counts_the_pushes_made_and_their_success_by_hand():
    # six tried pushes (one not tried), odds 0.2-1 and one without odds (made at every threshold)
    p = np.array([0.2, 0.6, 0.95, 0.995, np.nan, 0.999, 0.1])
    ok = np.array([False, True, False, True, True, True, True])
    tried = np.array([True, True, True, True, True, True, False])
    rows = gate(p, ok, tried)
    assert [g["min_odds"] for g in rows] == [0.5, 0.9, 0.99]
    # >= 0.5: pushes 1, 2, 3, 4, 5 (4 of 5 succeeded); >= 0.9: 2, 3, 4, 5; >= 0.99: 3, 4, 5
    np.testing.assert_allclose([g["made_pct"] for g in rows], [500 / 6, 400 / 6, 300 / 6])
    np.testing.assert_allclose([g["success_of_made_pct"] for g in rows], [80.0, 75.0, 100.0])
