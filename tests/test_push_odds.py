"""A push's predicted odds (jaxafm.position.push_odds) and their scores (jaxafm.study.reliability),
against closed forms and pushes drawn from a known miss model with NumPy."""

import numpy as np
import pytest
from scipy import stats

from jaxafm import plots
from jaxafm.position import push_odds
from jaxafm.position.online import Predictive
from jaxafm.study.monte_carlo import predicted_push_success
from jaxafm.study.reliability import gate, reliability


def _miss(mean, cov, dof):
    """One push's predicted miss: ``mean`` (2,) nm, scale matrix ``cov`` (2, 2) nm^2, ``dof``."""
    return Predictive(np.array([mean], float), np.array([cov], float), np.array([dof], float))


@pytest.mark.parametrize(
    "mean, sd, tolerance",
    [(0.0, 2.0, 3.0), (4.0, 1.5, 5.0), (6.0, 3.0, 2.0), (2.0, 0.5, 47.0), (46.0, 0.3, 47.0)],
)
def test_success_probability_is_the_rice_distribution_for_a_round_gaussian_miss(mean, sd, tolerance):
    """An isotropic Gaussian miss of mean ``mean`` along the first axis: its length is Rice
    distributed, P(|m| <= T) = rice.cdf(T / sd, mean / sd) (a Student-t of 1e7 degrees of freedom
    is Gaussian); the last two a miss a hundred times narrower than the tolerance, in the middle
    and at the edge. To 1e-5: a probability far finer than any decision on it needs."""
    miss = _miss([mean, 0.0], np.eye(2) * sd**2, 1e7)
    want = stats.rice.cdf(tolerance / sd, mean / sd)
    assert push_odds.success_probability(miss, tolerance) == pytest.approx(want, abs=1e-5)


@pytest.mark.parametrize("dof", [3.0, 30.0])
def test_success_probability_of_a_correlated_student_t_miss_matches_draws(dof):
    """A bivariate Student-t miss with correlated components, drawn in NumPy as a Gaussian over
    sqrt(chi^2 / nu): the share of 400,000 draws within the tolerance, to 4 binomial sd."""
    mean, cov, tolerance = np.array([1.5, -2.0]), np.array([[9.0, 4.8], [4.8, 4.0]]), 4.0
    rng = np.random.default_rng(5)
    n = 400_000
    draws = mean + rng.multivariate_normal([0, 0], cov, n) / np.sqrt(rng.chisquare(dof, n) / dof)[:, None]
    share = np.mean(np.hypot(*draws.T) <= tolerance)
    got = push_odds.success_probability(_miss(mean, cov, dof), tolerance)[0]
    assert abs(got - share) < 4 * np.sqrt(share * (1 - share) / n)


def test_components_split_a_miss_along_and_across_the_push():
    direction = np.array([[0.6, 0.8]])
    miss = np.array([[3.0, 4.0]]) + np.array([[-0.8, 0.6]])
    along, across = push_odds.components(miss, direction)
    np.testing.assert_allclose([along[0], across[0]], [5.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(push_odds.from_components(along, across, direction), miss, atol=1e-12)


#: the frame's error over a push (module docstring): offset b (nm) and map M (per nm of push);
#: x's drive 3 % long, y's 2 % short, their axes turned by 10 mrad over the push
OFFSET, MAP = np.array([0.5, -1.0]), np.array([[0.03, -0.01], [0.01, -0.02]])
#: the scatter's covariance (nm^2): 2 nm and 3 nm sd, correlation 0.3
SCATTER = np.array([[4.0, 1.8], [1.8, 9.0]])


def _pushes(rng, k):
    """``k`` pushes of 100-300 nm in any direction, their misses drawn from the module's model."""
    angle = rng.uniform(0, 2 * np.pi, k)
    push = rng.uniform(100, 300, k)[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    return push, OFFSET + push @ MAP.T + rng.multivariate_normal([0, 0], SCATTER, k)


def test_online_misses_are_the_regression_on_the_pushes_before():
    rng = np.random.default_rng(0)
    push, miss = _pushes(rng, 40)
    observed = rng.uniform(size=40) > 0.2
    predicted = push_odds.online_misses(push, miss, observed)
    k = 30
    prior = np.flatnonzero(observed[:k])
    X = np.column_stack([np.ones(prior.size), push[prior] / 100])
    B = np.linalg.lstsq(X, miss[prior], rcond=None)[0]
    R = miss[prior] - X @ B
    x = np.append(1.0, push[k] / 100)
    cov = R.T @ R / (prior.size - 3) * (1 + x @ np.linalg.inv(X.T @ X) @ x)
    np.testing.assert_allclose(predicted.mean[k], x @ B, rtol=1e-9)
    np.testing.assert_allclose(predicted.cov[k], cov, rtol=1e-9)
    assert predicted.dof[k] == prior.size - 3
    first = np.flatnonzero(np.cumsum(observed) - observed >= push_odds.MIN_PUSHES)[0]
    assert np.all(np.isnan(predicted.mean[:first])) and np.isfinite(predicted.mean[first]).all()


def test_predicted_odds_are_as_often_right_as_they_say_in_every_direction():
    """Pushes of particles of radius 2-12 nm (tolerance: one radius) drawn from the known model:
    the mean predicted success equals the observed rate within 3 binomial sd, in the whole, in
    each half of the predictions and for the pushes mostly along x and mostly along y (whose
    misses differ: the axes' scale errors differ), and the Brier score beats the overall rate's."""
    rng = np.random.default_rng(1)
    n = 4000
    push, miss = _pushes(rng, n)
    radius = rng.uniform(2, 12, n)
    ok = np.hypot(*miss.T) <= radius
    p = push_odds.success_probability(push_odds.online_misses(push, miss, np.ones(n, bool)), radius)
    scored = np.isfinite(p)
    assert scored.sum() == n - push_odds.MIN_PUSHES
    along_x = np.abs(push[:, 0]) > np.abs(push[:, 1])
    halves = (p < np.nanmedian(p), p >= np.nanmedian(p), along_x, ~along_x)
    for part in (scored, *(scored & h for h in halves)):
        sd = np.sqrt(np.sum(p[part] * (1 - p[part]))) / part.sum()
        assert abs(p[part].mean() - ok[part].mean()) < 3 * sd
    score = reliability(p, ok)
    assert score["brier"] < score["brier_base_rate"]


def test_odds_of_pushes_commanded_through_a_learnt_field_follow_the_command():
    """Pushes commanded through a field relearnt every round of 8 (each round's estimate of the
    frame's map off by 0.03 per axis pair, drawn in NumPy), their misses from the module's model
    of what was commanded, ``m = (c - d) + b + M c + eps``: the odds from the commands are as
    often right as they say (3 binomial sd) in the whole, in each half and along each axis, and
    their Brier score is lower than that of the same odds taken from the wanted pushes alone,
    which see each round's ``c - d`` as scatter."""
    rng = np.random.default_rng(3)
    n, per_round = 4000, 8
    angle = rng.uniform(0, 2 * np.pi, n)
    push = rng.uniform(100, 300, n)[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    learnt = np.repeat(MAP + rng.normal(0, 0.03, (n // per_round, 2, 2)), per_round, axis=0)
    command = np.linalg.solve(np.eye(2) + learnt, (push - OFFSET)[..., None])[..., 0]
    miss = command - push + OFFSET + command @ MAP.T + rng.multivariate_normal([0, 0], SCATTER, n)
    radius = rng.uniform(2, 12, n)
    ok = np.hypot(*miss.T) <= radius
    odds = {
        name: push_odds.success_probability(push_odds.online_misses(push, miss, np.ones(n, bool), c), radius)
        for name, c in {"command": command, "wanted": None}.items()
    }
    p = odds["command"]
    scored = np.isfinite(p)
    along_x = np.abs(push[:, 0]) > np.abs(push[:, 1])
    halves = (p < np.nanmedian(p), p >= np.nanmedian(p), along_x, ~along_x)
    for part in (scored, *(scored & h for h in halves)):
        sd = np.sqrt(np.sum(p[part] * (1 - p[part]))) / part.sum()
        assert abs(p[part].mean() - ok[part].mean()) < 3 * sd
    assert reliability(p, ok)["brier"] < reliability(odds["wanted"], ok)["brier"]


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
        "push_dx": np.ones(2 * n),
        "push_dy": np.zeros(2 * n),
        "push_command_x_nm": distance,  # commanded as wanted
        "push_command_y_nm": np.zeros(2 * n),
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
