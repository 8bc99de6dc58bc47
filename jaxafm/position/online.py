"""Predictions learnt while positioning: each new case predicted from the cases observed before
it on the same scanner, by a linear regression and its predictive distribution
(:func:`online_regression`); a smooth offset field over the workspace, learnt from the
points where it was observed (:func:`learn_field`); and how far a push moves its particle for
what it commands, learnt from the pushes checked before (:func:`learn_push`).

For observations ``Y`` (n, m) on regressors ``X`` (n, p), least squares gives ``B`` (p, m) and the
residuals' covariance ``S = R^T R / (n - p)``. A new case ``x`` (p,) is predicted at ``x B``
with covariance ``S (1 + x (X^T X)^-1 x^T)`` and ``n - p`` degrees of freedom: per output, the
Student-t predictive of a linear regression under a flat prior (its diagonal's square root the
t's scale).

The sums over the cases before each one run cumulatively: a whole sequence costs O(n p^2).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax


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


class OffsetField(NamedTuple):
    """A smooth offset field over the workspace learnt from points where it was observed: the
    posterior mean of a Bayesian linear regression on a quadratic in the position
    (:func:`learn_field`). ``coef`` (6, 2) nm: each axis's coefficients on :func:`quadratic`;
    ``centre`` (2,) and ``half`` nm: the workspace's centre and half-size, which scale positions."""

    coef: np.ndarray
    centre: np.ndarray
    half: float

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """The field (k, 2) nm at ``points`` (k, 2) nm."""
        return quadratic(points, self.centre, self.half) @ self.coef


def quadratic(points: np.ndarray, centre: np.ndarray, half: float) -> np.ndarray:
    """The regressors (k, 6) of a quadratic field at ``points`` (k, 2) nm, in units of ``half``
    from ``centre``: ``1, x, y, x^2, x y, y^2``."""
    x, y = ((np.reshape(points, (-1, 2)) - centre) / half).T
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1)


def ridge(F: np.ndarray, Y: np.ndarray, prior: float, noise_nm: float) -> np.ndarray:
    """The posterior mean ``b`` (p, 2) of ``Y = F b + e`` for observations ``Y`` (n, 2) nm on
    regressors ``F`` (n, p), each axis independently, under ``b ~ N(0, prior^2 I)`` and
    ``e ~ N(0, noise_nm^2)``: ``b = (F^T F + (noise_nm / prior)^2 I)^-1 F^T Y`` (ridge regression),
    zero (the prior's mean) with no observation."""
    A = F.T @ F + (noise_nm / prior) ** 2 * np.eye(F.shape[1])
    return np.linalg.solve(A, F.T @ np.reshape(Y, (-1, 2)))


def learn_field(
    points: np.ndarray, offsets: np.ndarray, centre: np.ndarray, half: float, prior_nm: float, noise_nm: float
) -> OffsetField:
    """The offset field that ``offsets`` (n, 2) nm observed at ``points`` (n, 2) nm support,
    positions scaled as :func:`quadratic` scales them: observations
    ``offset = quadratic(point) b + e`` and coefficients ``b ~ N(0, prior_nm^2 I)`` (a field of
    some ``prior_nm`` across the workspace, a priori), by :func:`ridge`."""
    centre = np.asarray(centre, float)
    return OffsetField(ridge(quadratic(points, centre, half), offsets, prior_nm, noise_nm), centre, half)


#: the unit (nm) of a push in :func:`push_regressors`: coefficients of order the push's relative error
PUSH_UNIT = 100.0


def push_regressors(command):
    """The regressors (..., 4) of a push's shortfall at its commanded vector ``command`` (..., 2)
    nm, in units of :data:`PUSH_UNIT`: ``c_x, |c_x|, c_y, |c_y|``. A gain of the move along each
    axis is ``c``; one that differs with the direction of the move (the branch of the hysteresis
    loop a push runs on after the tip backed away from the particle) adds ``|c|``. No constant: a
    push of nothing moves nothing."""
    c = command / PUSH_UNIT
    return jnp.concatenate([c[..., :1], jnp.abs(c[..., :1]), c[..., 1:], jnp.abs(c[..., 1:])], -1)


class PushField(eqx.Module):
    """How a push moves a particle on a scanner, learnt from the pushes checked before
    (:func:`learn_push`): a push commanded by ``c`` (2,) nm (the tip's travel in the wanted
    frame) moves its particle by ``c + s(c)``, the shortfall ``s(c) = push_regressors(c) coef``
    (``coef`` (4, 2) nm). Runs under ``jit``; the zero field commands what is wanted."""

    coef: jax.Array

    def shortfall(self, command: jax.Array) -> jax.Array:
        """``s(c)`` (..., 2) nm at commands ``c`` (..., 2) nm."""
        return push_regressors(command) @ self.coef

    def command(self, wanted: jax.Array, iterations: int = 8) -> jax.Array:
        """The command ``c`` (2,) nm whose push moves the particle by ``wanted`` (2,) nm,
        ``c + s(c) = wanted``, by the fixed point ``c <- wanted - s(c)`` (a contraction while the
        learnt gains are below one; ``iterations`` steps from ``c = wanted``)."""
        return lax.fori_loop(0, iterations, lambda _, c: wanted - self.shortfall(c), wanted)


#: no push checked yet: pushes command what is wanted
NO_PUSH_FIELD = PushField(jnp.zeros((4, 2)))


def learn_push(commands: np.ndarray, moved: np.ndarray, prior: float, noise_nm: float) -> PushField:
    """The :class:`PushField` that pushes commanded by ``commands`` (n, 2) nm, which moved their
    particles by ``moved`` (n, 2) nm as their checks saw them, support: shortfalls
    ``moved - commands = push_regressors(c) b + e`` with ``b ~ N(0, prior^2 I)`` (nm per
    :data:`PUSH_UNIT`) and ``e ~ N(0, noise_nm^2)``, by :func:`ridge`."""
    commands = np.reshape(commands, (-1, 2))
    F = np.asarray(push_regressors(jnp.asarray(commands)))
    return PushField(jnp.asarray(ridge(F, np.reshape(moved, (-1, 2)) - commands, prior, noise_nm)))
