"""Levenberg–Marquardt with geodesic acceleration: the solver ``jaxafm.geodesic_levenberg_marquardt``.

Least squares ``min_x C(x) = |r(x)|^2 / 2`` over few parameters and many residuals (step A: 58
parameters, 131,072 pixels at 256²). Each iteration solves for the *velocity*

    v = -(J^T J + mu I)^-1 J^T r

and adds half the *geodesic acceleration* (Transtrum & Sethna 2012, "Improvements to the
Levenberg-Marquardt algorithm for nonlinear least-squares minimization", arXiv:1201.5885)

    a = -(J^T J + mu I)^-1 J^T r_vv,

``r_vv`` the second directional derivative of the residuals along ``v``, while
``2 |a| <= alpha |v|`` (alpha = 0.75; else the step is ``v`` alone): the trial point is
``x + v + a / 2``. The acceleration follows the narrow curved valleys of a sloppy model (here
a lattice's image residuals, whose parameters trade off along such valleys) instead of
zig-zagging across them. ``r_vv`` comes by forward-mode differentiation twice (``curvature="jvp"``,
exact, one more compiled program) or from one more residual evaluation,
``(2 / h) ((r(x + h v) - r(x)) / h - J v)`` with ``h = 1e-3`` (``curvature="difference"``, the
paper's way, for residuals smooth on that scale).

The damping is ``mu I``, not Marquardt's ``mu diag(J^T J)``: weak parameter directions stay near
their start. ``mu`` starts at ``1e-6 max diag(J^T J)`` and follows Nielsen's rule (Madsen, Nielsen
& Tingleff 2004, "Methods for non-linear least squares problems", section 3.2): with the gain ratio
``rho`` of the actual decrease of ``C`` to the decrease the linear model predicts for the
velocity, ``(v^T (mu v - g)) / 2``, a step with ``rho > 0`` is accepted and
``mu *= max(1/3, 1 - (2 rho - 1)^3)``; otherwise ``mu *= nu``, ``nu *= 2``. The Jacobian
(forward mode, materialised) is formed only after an accepted step. The iterations run on the
host; the residuals, the Jacobian and the curvature are jitted functions of ``(x, packed)``,
compiled once per function and argument shapes and reused for other data of the same shapes.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np
import scipy.linalg

#: the largest ratio ``2 |a| / |v|`` at which the acceleration is used
ALPHA = 0.75
#: the first damping, relative to the largest diagonal element of ``J^T J``
TAU = 1e-6
#: the step along the velocity of ``curvature="difference"``
H = 1e-3
CURVATURES = ("jvp", "difference")


@functools.lru_cache(maxsize=64)
def compiled(fn: Callable) -> tuple:
    """``fn(x, packed)`` (flat parameters -> residuals) jitted; ``(r, J)`` at ``x`` jitted (the
    residuals and their forward-mode Jacobian); and ``r_vv`` at ``(x, v)`` jitted (the second
    derivative of the residuals along ``v``, forward mode twice)."""

    def linearised(x, packed):
        def twice(y):  # the residuals, computed once, as the output and as the aux
            r = fn(y, packed)
            return r, r

        J, r = jax.jacfwd(twice, has_aux=True)(x)
        return r, J

    def curvature(x, v, packed):
        along = lambda y: jax.jvp(lambda z: fn(z, packed), (y,), (v,))[1]
        return jax.jvp(along, (x,), (v,))[1]

    return eqx.filter_jit(fn), eqx.filter_jit(linearised), eqx.filter_jit(curvature)


def solve(
    fn: Callable, x0, packed, max_steps: int, rtol: float, atol: float, curvature: str = "jvp"
) -> tuple:
    """Minimise ``|fn(x, packed)|^2 / 2`` from ``x0`` (flat, float64).

    Stops when the velocity is below ``rtol (|x| + rtol)`` or the gradient's largest element
    below ``atol`` (converged), or after ``max_steps`` iterations (each one trial point).
    ``curvature``: how ``r_vv`` is had, one of :data:`CURVATURES`.

    A trial point whose residuals or Jacobian are not finite (a model linearised where its
    derivative is not defined) is not taken: the step is refused as one that raises the cost.

    Returns:
        ``(x, steps, converged)``; ``x`` is ``x0`` and ``steps`` 0 where the residuals or their
        Jacobian at ``x0`` are not finite.
    """
    if curvature not in CURVATURES:
        raise ValueError(f"curvature must be one of {', '.join(CURVATURES)}, got {curvature!r}")
    residuals, linearised, second = compiled(fn)
    x = np.array(x0, dtype=np.float64)

    def at(x):
        r, J = linearised(x, packed)
        r, J = np.asarray(r), np.asarray(J)
        return r, J, J.T @ J, J.T @ r

    def along(x, v, r, J):
        if curvature == "jvp":
            return np.asarray(second(x, v, packed))
        return (2 / H) * ((np.asarray(residuals(x + H * v, packed)) - r) / H - J @ v)

    r, J, A, g = at(x)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(A))):
        return x, 0, False
    cost = 0.5 * float(r @ r)
    mu, nu = TAU * float(np.max(np.diag(A), initial=1.0)), 2.0
    for step in range(max_steps):
        if np.max(np.abs(g), initial=0.0) <= atol:
            return x, step, True
        try:
            factor = scipy.linalg.cho_factor(A + mu * np.eye(len(x)))
        except np.linalg.LinAlgError:
            mu, nu = mu * nu, 2 * nu
            continue
        v = -scipy.linalg.cho_solve(factor, g)
        if np.linalg.norm(v) <= rtol * (np.linalg.norm(x) + rtol):
            return x, step, True
        a = -scipy.linalg.cho_solve(factor, J.T @ along(x, v, r, J))
        accelerate = np.all(np.isfinite(a)) and 2 * np.linalg.norm(a) <= ALPHA * np.linalg.norm(v)
        delta = v + 0.5 * a if accelerate else v
        trial = np.asarray(residuals(x + delta, packed))
        new = 0.5 * float(trial @ trial)
        predicted = 0.5 * float(v @ (mu * v - g))
        rho = (cost - new) / predicted if np.isfinite(new) and predicted > 0 else -1.0
        linear = at(x + delta) if rho > 0 else None
        if linear is not None and np.all(np.isfinite(linear[2])):
            x = x + delta
            r, J, A, g = linear
            cost = 0.5 * float(r @ r)
            mu, nu = mu * max(1 / 3, 1 - (2 * rho - 1) ** 3), 2.0
        else:
            mu, nu = mu * nu, 2 * nu
    return x, max_steps, False
