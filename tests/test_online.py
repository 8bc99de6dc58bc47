"""Predictions learnt from earlier cases (jaxafm.position.online) against a direct least-squares
refit on NumPy draws."""

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
