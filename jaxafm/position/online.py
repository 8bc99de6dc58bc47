"""Predictions learnt while positioning: each new case predicted from the cases observed before
it on the same scanner, by a linear regression and its predictive distribution
(:func:`online_regression`); a smooth offset field over the workspace and the drift since the
model was made, tracked by a Kalman filter from every position observed (:class:`Tracker`,
:func:`learn_field`); and how far a push moves its particle for what it commands, learnt from
the pushes checked before (:func:`learn_push`).

For observations ``Y`` (n, m) on regressors ``X`` (n, p), least squares gives ``B`` (p, m) and the
residuals' covariance ``S = R^T R / (n - p)``. A new case ``x`` (p,) is predicted at ``x B``
with covariance ``S (1 + x (X^T X)^-1 x^T)`` and ``n - p`` degrees of freedom (with regressors of
rank ``r < p``, the pseudo-inverse and ``n - r``, for a case within their span): per output, the
Student-t predictive of a linear regression under a flat prior (its diagonal's square root the
t's scale).

The sums over the cases before each one run cumulatively: a whole sequence costs O(n p^2).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

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
    ``p + min_extra`` observed rows before it or with a part outside their regressors' span,
    which they do not determine (a direction none of them took). Within the span the fit is the
    minimum-norm one (the pseudo-inverse of ``X^T X``), whose prediction there is unique, with
    ``n - r`` degrees of freedom (``r`` the rank of the earlier rows' regressors)."""
    X = np.asarray(X, float)
    k, p = X.shape
    w = np.asarray(observed, bool).astype(float)
    Y = np.where(w[:, None] > 0, np.asarray(Y, float).reshape(k, -1), 0.0)
    before = lambda v: np.cumsum(v, axis=0) - v  # sums over the rows before each one
    n = before(w)
    XtX = before(w[:, None, None] * X[:, :, None] * X[:, None, :])
    XtY = before(w[:, None, None] * X[:, :, None] * Y[:, None, :])
    YtY = before(w[:, None, None] * Y[:, :, None] * Y[:, None, :])
    inv = np.linalg.pinv(XtX, hermitian=True)
    projector = inv @ XtX  # onto the span of the earlier rows' regressors
    rank = np.rint(np.trace(projector, axis1=1, axis2=2))
    outside = np.einsum("ki,kij->kj", X, np.eye(p) - projector)
    spanned = np.linalg.norm(outside, axis=-1) <= 1e-9 * np.maximum(np.linalg.norm(X, axis=-1), 1e-300)
    ok = (n >= p + min_extra) & spanned
    B = inv @ XtY
    rss = YtY - np.swapaxes(B, 1, 2) @ XtY
    nu = np.maximum(n - rank, 1)
    leverage = np.einsum("ki,kij,kj->k", X, inv, X)
    cov = rss / nu[:, None, None] * (1 + leverage)[:, None, None]
    nan = np.where(ok, 1.0, np.nan)
    return Predictive(
        np.einsum("ki,kim->km", X, B) * nan[:, None], cov * nan[:, None, None], (n - rank) * nan
    )


class OffsetField(NamedTuple):
    """A smooth offset field over the workspace (:class:`Tracker`): what to add to a wanted
    position so that the tip truly reaches it. ``coef`` (6, 2) nm: each axis's coefficients on
    :func:`quadratic` (the constant is the offset, the linear terms the gains' and the coupling's
    errors across the workspace, the quadratic ones the bow's); ``centre`` (2,) and ``half`` nm:
    the workspace's centre and half-size, which scale positions; ``cov`` (6, 6) nm^2: the
    coefficients' posterior covariance, the same for both axes (``None``: not known)."""

    coef: np.ndarray
    centre: np.ndarray
    half: float
    cov: Optional[np.ndarray] = None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """The field (k, 2) nm at ``points`` (k, 2) nm."""
        return quadratic(points, self.centre, self.half) @ self.coef

    def sd(self, points: np.ndarray) -> np.ndarray:
        """The field's posterior standard deviation (k,) nm at ``points`` (k, 2) nm, along
        either axis: ``sqrt(q P q^T)`` for the regressors ``q`` and the covariance ``P``."""
        q = quadratic(points, self.centre, self.half)
        return np.sqrt(np.einsum("ki,ij,kj->k", q, self.cov, q))


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


#: the pseudo observations (axes) of the :class:`Tracker`'s prior on its variance factor, at 1
FACTOR_PRIOR_DOF = 4

#: the tracker's state per axis: the field's six coefficients, the drift's offset and its velocity
FIELD, DRIFT, VELOCITY = slice(0, 6), 6, 7


class Tracker(NamedTuple):
    """A Kalman filter over where the tip truly goes, refined by every position observed.

    An observation at time ``t`` is the offset ``y`` (2,) nm that a wanted position ``p`` (2,) nm
    needed (the command that truly reached a place, minus the place): per axis

        y = q(p) b + d(t) + e,        e ~ N(0, noise_nm^2),

    ``q`` the :func:`quadratic` regressors and ``b`` (6,) the field's coefficients (offset,
    gains and coupling, bow: constant in time), ``d`` the offset that the drift since the
    model was made calls for (Mokaberi & Requicha's drift state, 2006): ``d(t0) = 0``, moving
    at a velocity ``v`` (constant, a priori ``N(0, velocity_prior^2)``) plus a random walk of
    ``walk`` nm^2 per second, ``d(t + dt) = d(t) + v dt + w``, ``w ~ N(0, walk dt)``. The state
    ``(b, d, v)`` (8,) per axis has a Gaussian posterior; as both axes share the regressors,
    the noise and the prior, they share its covariance ``cov`` (8, 8) nm^2 (velocity in nm/s)
    and differ in the means ``mean`` (8, 2). Without drift (``velocity_prior`` and ``walk`` 0)
    the field's posterior mean is the ridge regression of every observation (:func:`ridge`),
    however they are split into updates.

    A true scanner is never a quadratic field plus a drift (the hysteresis leaves a miss that
    depends on the path, and a wrong model class more of it), so the filter also learns how far
    its assumptions hold: the *variance factor* ``f^2``, the mean square of the innovations
    ``nu`` (each observation less its prediction) in units of their predicted variance ``S``
    (``nu^T S^-1 nu``, 1 per axis where the model holds), with :data:`FACTOR_PRIOR_DOF` pseudo
    observations of 1 (a scaled inverse-chi^2 prior on the factor, updated by the chi^2 sums):
    ``f^2 = (chi2 + nu_0) / (dof + nu_0)``. :meth:`predict` scales its sd by ``f``.

    Fields: ``mean``, ``cov`` (given ``noise_nm``), the ``time`` (s) they hold at, the
    workspace's ``centre`` (2,) and ``half`` nm, ``noise_nm``, ``walk`` (nm^2/s), and the
    innovations' ``chi2`` over ``dof`` axes observed."""

    mean: np.ndarray
    cov: np.ndarray
    time: float
    centre: np.ndarray
    half: float
    noise_nm: float
    walk: float
    chi2: float = 0.0
    dof: int = 0

    @classmethod
    def start(
        cls,
        centre,
        half: float,
        prior_nm: float,
        noise_nm: float,
        velocity_prior: float = 0.0,
        walk: float = 0.0,
        time: float = 0.0,
    ) -> Tracker:
        """Nothing observed yet, the model made at ``time`` s: each field coefficient
        ``N(0, prior_nm^2)``, the drift 0 and its velocity ``N(0, velocity_prior^2)`` nm/s."""
        cov = np.diag([prior_nm**2] * 6 + [0.0, velocity_prior**2])
        return cls(np.zeros((8, 2)), cov, float(time), np.asarray(centre, float), half, noise_nm, walk)

    def at(self, time: float) -> Tracker:
        """The state predicted forward to ``time`` s (no earlier than :attr:`time`):
        ``d += v dt``, its variance grown by the walk."""
        dt = float(time) - self.time
        if dt < 0:
            raise ValueError(f"Tracker.at: time {time} s is before the state's {self.time} s")
        F = np.eye(8)
        F[DRIFT, VELOCITY] = dt
        cov = F @ self.cov @ F.T
        cov[DRIFT, DRIFT] += self.walk * dt
        return self._replace(mean=F @ self.mean, cov=cov, time=float(time))

    def observe(self, points, offsets, times=None) -> Tracker:
        """The state after the observations ``offsets`` (n, 2) nm at ``points`` (n, 2) nm made at
        ``times`` (n,) s (``None``: all now), in time order: the Kalman update of those made
        at one time at once, in Joseph's form (which keeps the covariance symmetric and
        positive)."""
        points, offsets = np.reshape(points, (-1, 2)), np.reshape(offsets, (-1, 2))
        times = np.full(len(points), self.time) if times is None else np.asarray(times, float)
        state = self
        for t in np.unique(times):
            now = times == t
            state = state.at(t)._update(points[now], offsets[now])
        return state

    def _update(self, points: np.ndarray, offsets: np.ndarray) -> Tracker:
        H = self._regressors(points)
        S = H @ self.cov @ H.T + self.noise_nm**2 * np.eye(len(H))
        K = np.linalg.solve(S, H @ self.cov).T
        A = np.eye(8) - K @ H
        cov = A @ self.cov @ A.T + self.noise_nm**2 * K @ K.T
        nu = offsets - H @ self.mean
        return self._replace(
            mean=self.mean + K @ nu,
            cov=(cov + cov.T) / 2,
            chi2=self.chi2 + float(np.sum(nu * np.linalg.solve(S, nu))),
            dof=self.dof + nu.size,
        )

    @property
    def factor(self) -> float:
        """The variance factor's square root ``f`` (class docstring): 1 where the observations
        scatter as the filter predicts them."""
        return float(np.sqrt((self.chi2 + FACTOR_PRIOR_DOF) / (self.dof + FACTOR_PRIOR_DOF)))

    def _regressors(self, points: np.ndarray) -> np.ndarray:
        """The observation rows (k, 8) at ``points``: ``q(p)``, 1 for the drift, 0 for its velocity."""
        q = quadratic(points, self.centre, self.half)
        return np.concatenate([q, np.ones((len(q), 1)), np.zeros((len(q), 1))], -1)

    def predict(self, points, time=None) -> tuple:
        """The offset (k, 2) nm that ``points`` (k, 2) nm call for at ``time`` s (``None``: now)
        and its standard deviation (k,) nm along either axis: that of the state's estimate
        times the :attr:`factor` (a new observation adds ``noise_nm`` in quadrature)."""
        state = self if time is None else self.at(time)
        H = state._regressors(np.reshape(points, (-1, 2)))
        return H @ state.mean, self.factor * np.sqrt(np.einsum("ki,ij,kj->k", H, state.cov, H))

    def field(self, time=None) -> OffsetField:
        """The offset field at ``time`` s (``None``: now): the coefficients with the drift's
        offset added to the constant, and their covariance."""
        state = self if time is None else self.at(time)
        A = np.zeros((6, 8))
        A[:, FIELD] = np.eye(6)
        A[0, DRIFT] = 1.0
        return OffsetField(A @ state.mean, self.centre, self.half, A @ state.cov @ A.T)

    @property
    def drift(self) -> tuple:
        """The drift's offset (2,) nm now and its standard deviation along either axis, nm."""
        return self.mean[DRIFT], float(np.sqrt(self.cov[DRIFT, DRIFT]))


def learn_field(
    points: np.ndarray, offsets: np.ndarray, centre: np.ndarray, half: float, prior_nm: float, noise_nm: float
) -> OffsetField:
    """The offset field that ``offsets`` (n, 2) nm observed at ``points`` (n, 2) nm support
    without drift: a :class:`Tracker` with coefficients ``N(0, prior_nm^2)`` (a field of some
    ``prior_nm`` across the workspace, a priori) updated by them; its mean is :func:`ridge`'s."""
    return Tracker.start(centre, half, prior_nm, noise_nm).observe(points, offsets).field()


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
