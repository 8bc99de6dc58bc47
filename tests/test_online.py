"""Predictions learnt from earlier cases (jaxafm.position.online) against a direct least-squares
refit on NumPy draws; the learnt offset field against known fields."""

import numpy as np

from jaxafm.position import online


def _cases(rng, k, m=2):
    """``k`` cases of a known plane in two regressors with correlated Gaussian errors."""
    X = np.column_stack([np.ones(k), rng.uniform(-1, 1, (k, 2))])
    B = np.array([[1.0, -2.0], [3.0, 0.5], [-1.0, 4.0]])[:, :m]
    L = np.array([[2.0, 0.0], [1.5, 0.7]])[:m, :m]
    return X, X @ B + rng.normal(size=(k, m)) @ L.T


def test_each_case_is_predicted_by_the_least_squares_fit_to_the_observed_cases_before_it():
    rng = np.random.default_rng(3)
    X, Y = _cases(rng, 30)
    observed = rng.uniform(size=30) > 0.25
    pred = online.online_regression(X, Y, observed)
    k = 25
    rows = np.flatnonzero(observed[:k])
    B = np.linalg.lstsq(X[rows], Y[rows], rcond=None)[0]
    R = Y[rows] - X[rows] @ B
    h = X[k] @ np.linalg.inv(X[rows].T @ X[rows]) @ X[k]
    np.testing.assert_allclose(pred.mean[k], X[k] @ B, rtol=1e-9)
    np.testing.assert_allclose(pred.cov[k], R.T @ R / (rows.size - 3) * (1 + h), rtol=1e-9)
    assert pred.dof[k] == rows.size - 3
    first = np.flatnonzero(np.cumsum(observed) - observed >= 3 + 3)[0]
    assert np.all(np.isnan(pred.mean[:first])) and np.all(np.isfinite(pred.cov[first]))


def test_a_regressor_the_earlier_cases_never_varied_leaves_only_cases_in_their_span_predicted():
    # the first 20 cases all have the third regressor at 0: a case with it at 0 is predicted as
    # the fit on the first two regressors predicts it, with n - 2 degrees of freedom; a case with
    # it at 0.5 lies outside what they determine and gets NaN; and the first p + 3 cases get NaN
    # whatever their rank
    rng = np.random.default_rng(4)
    X, Y = _cases(rng, 22)
    X[:21, 2] = 0.0
    X[21, 2] = 0.5
    pred = online.online_regression(X, Y, np.ones(22, bool))
    B = np.linalg.lstsq(X[:20, :2], Y[:20], rcond=None)[0]
    R = Y[:20] - X[:20, :2] @ B
    h = X[20, :2] @ np.linalg.inv(X[:20, :2].T @ X[:20, :2]) @ X[20, :2]
    np.testing.assert_allclose(pred.mean[20], X[20, :2] @ B, rtol=1e-9)
    np.testing.assert_allclose(pred.cov[20], R.T @ R / 18 * (1 + h), rtol=1e-9)
    assert pred.dof[20] == 18
    assert np.all(np.isnan(pred.mean[21])) and np.isnan(pred.dof[21])
    assert np.all(np.isnan(pred.dof[:6])) and pred.dof[6] == 4


def test_learnt_field_is_the_prior_mean_without_observations():
    field = online.learn_field(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(2), 1500.0, 100.0, 5.0)
    np.testing.assert_array_equal(field(np.array([[100.0, -300.0], [0.0, 0.0]])), 0.0)


def test_learnt_field_recovers_a_gain_error_and_a_quadratic_bow():
    # the offsets a scanner with a 10 % gain error on x, a 20 nm shift on y and a bow of 15 nm at
    # the workspace's edge on y gives, seen with 1 nm of noise at 60 points of a 3 um workspace
    # centred at (200, -100) nm: the field's coefficients are those, to the noise's error
    # (about 1 nm / sqrt(60) on each; 1 % of the 150 nm gain term is 1.5 nm)
    rng = np.random.default_rng(0)
    centre, half = np.array([200.0, -100.0]), 1500.0
    p = centre + rng.uniform(-half, half, (60, 2))
    u = (p - centre) / half
    truth = np.stack([0.1 * (p[:, 0] - centre[0]), 20.0 + 15.0 * u[:, 0] ** 2], -1)
    field = online.learn_field(p, truth + rng.normal(0, 1.0, truth.shape), centre, half, 100.0, 1.0)
    want = np.zeros((6, 2))
    want[1, 0], want[0, 1], want[3, 1] = 0.1 * half, 20.0, 15.0
    np.testing.assert_allclose(field.coef, want, atol=1.5)
    q = centre + rng.uniform(-half, half, (20, 2))
    assert np.max(np.abs(field(q)[:, 0] - 0.1 * (q[:, 0] - centre[0]))) < 1.5


def _pushes(rng, k):
    """``k`` pushes of 100-300 nm in random directions on a drive whose moves fall short by 4 %
    when x falls and 1 % when it rises, by 2 % on y either way, and whose particle positions are
    seen with 1 nm of noise: the commands (k, 2) nm and the moves seen (k, 2) nm."""
    angle = rng.uniform(0, 2 * np.pi, k)
    c = rng.uniform(100, 300, k)[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    gain_x = np.where(c[:, 0] < 0, 0.96, 0.99)
    moved = np.stack([gain_x * c[:, 0], 0.98 * c[:, 1]], -1)
    return c, moved + rng.normal(0, 1.0, moved.shape)


def test_a_learnt_push_field_recovers_a_direction_dependent_shortfall_and_inverts_it():
    # the shortfall of _pushes in push_regressors' terms (per 100 nm): on x a gain of
    # (0.99 + 0.96) / 2 - 1 on c_x and (0.99 - 0.96) / 2 on |c_x|, on y -0.02 on c_y; learnt from
    # 40 pushes with 1 nm of noise, each coefficient to about 1 nm / sqrt(40) * (100 / 200 nm)
    rng = np.random.default_rng(4)
    c, moved = _pushes(rng, 40)
    field = online.learn_push(c, moved, 100.0, 1.0)
    want = np.zeros((4, 2))
    want[0, 0], want[1, 0], want[2, 1] = -2.5, 1.5, -2.0
    np.testing.assert_allclose(field.coef, want, atol=0.3)
    # a push commanded through it moves its particle by what was wanted, to the noise's error
    wanted, _ = _pushes(rng, 20)
    command = np.stack([np.asarray(field.command(w)) for w in wanted])
    gain_x = np.where(command[:, 0] < 0, 0.96, 0.99)
    truly = np.stack([gain_x * command[:, 0], 0.98 * command[:, 1]], -1)
    assert np.max(np.abs(truly - wanted)) < 1.0  # nm, where the uncommanded push misses by up to 12 nm
    assert np.max(np.abs(np.stack([gain_x * wanted[:, 0], 0.98 * wanted[:, 1]], -1) - wanted)) > 8.0


def test_the_push_field_without_observations_commands_what_is_wanted():
    field = online.learn_push(np.zeros((0, 2)), np.zeros((0, 2)), 100.0, 5.0)
    np.testing.assert_array_equal(field.coef, 0.0)
    np.testing.assert_array_equal(field.command(np.array([120.0, -45.0])), [120.0, -45.0])
