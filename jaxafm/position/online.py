"""Predictions learnt while positioning: each new case predicted from the cases observed before
it on the same scanner, by a linear regression and its predictive distribution.

For observations ``Y`` (n, m) on regressors ``X`` (n, p), least squares gives ``B`` (p, m) and the
residuals' covariance ``S = R^T R / (n - p)``. A new case ``x`` (p,) is predicted at ``x B``
with covariance ``S (1 + x (X^T X)^-1 x^T)`` and ``n - p`` degrees of freedom: per output, the
Student-t predictive of a linear regression under a flat prior (its diagonal's square root the
t's scale).

The sums over the cases before each one run cumulatively: a whole sequence costs O(n p^2).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Predictive(NamedTuple):
    """Each case's prediction from the cases before it: ``mean`` (k, m), ``cov`` (k, m, m) and
    ``dof`` (k,); NaN where too few cases were observed before it."""

    mean: np.ndarray
    cov: np.ndarray
    dof: np.ndarray


def online_regression(X: np.ndarray, Y: np.ndarray, observed: np.ndarray, min_extra: int = 3) -> Predictive:
    """Each row of ``X`` (k, p) predicted from the rows before it whose ``Y`` (k, m) was
    ``observed`` (k,) bool, by the module's regression; NaN for a row with fewer than
    ``p + min_extra`` observed rows before it."""
    X = np.asarray(X, float)
    k, p = X.shape
    w = np.asarray(observed, bool).astype(float)
    Y = np.where(w[:, None] > 0, np.asarray(Y, float).reshape(k, -1), 0.0)
    before = lambda v: np.cumsum(v, axis=0) - v  # sums over the rows before each one
    n = before(w)
    ok = n >= p + min_extra
    XtX = np.where(ok[:, None, None], before(w[:, None, None] * X[:, :, None] * X[:, None, :]), np.eye(p))
    XtY = before(w[:, None, None] * X[:, :, None] * Y[:, None, :])
    YtY = before(w[:, None, None] * Y[:, :, None] * Y[:, None, :])
    inv = np.linalg.inv(XtX)
    B = inv @ XtY
    rss = YtY - np.swapaxes(B, 1, 2) @ XtY
    nu = np.maximum(n - p, 1)
    leverage = np.einsum("ki,kij,kj->k", X, inv, X)
    cov = rss / nu[:, None, None] * (1 + leverage)[:, None, None]
    nan = np.where(ok, 1.0, np.nan)
    return Predictive(np.einsum("ki,kim->km", X, B) * nan[:, None], cov * nan[:, None, None], (n - p) * nan)
