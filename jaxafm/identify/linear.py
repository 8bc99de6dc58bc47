"""Fits of operators whose output is linear in their weights: PI and Preisach, thresholds fixed.

With the play radii fixed, ``y = offset + A w`` with ``A`` (T, m) the design rows
(:meth:`~jaxafm.model.hysteresis.PlayOperator.design_rows`: the plays of a PI operator, the
relay states of a Preisach plane) and ``w >= 0``. The least-squares fit is then a non-negative
least-squares problem, solved exactly instead of by a gradient solver crawling through
``softplus``. It runs on the normal equations, streamed over blocks of samples: ``A`` is never
stored, only the plays (T, n) and the Gram matrix (m, m); for a Preisach plane of 50 levels at
20,000 samples that is 13 MB where ``A`` would take 204 MB and a Jacobian-based fit several GB.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sl
from jax import lax
from scipy.optimize import nnls

from ..model.hysteresis import PrandtlIshlinskii, Preisach, play

Array = jax.Array

#: Tikhonov weight on the weights scaled to unit column norms: a drive leaves some weight
#: combinations undetermined (a 50-level plane on a 20,000-sample record: rank 856 of 1,275), and
#: the ridge settles them on the smallest weights. At 1e-6 it raised the training rms of that fit
#: by 1e-4 of itself (2.058579 -> 2.058779 nm, noise ~2 nm), where 1e-8 and 1e-10 let the pivoting
#: cycle for 126 steps or more.
RIDGE = 1e-6


def is_linear(model) -> bool:
    """Whether ``model``'s fitted parameters are all weights its output is linear in: a PI operator
    or a Preisach plane (a factorised Preisach's profile and a generalised PI's dead zones are not)."""
    return type(model) in (PrandtlIshlinskii, Preisach)


@dataclasses.dataclass(frozen=True)
class NormalEquations:
    """``min_w |A w - d|^2`` over the weighted samples, the offset eliminated (centred sums).

    Attributes:
        gram: ``A_c^T A_c`` (m, m), ``A_c`` the rows less their weighted mean.
        rhs: ``A_c^T d`` (m,).
        mean_row: the rows' weighted mean (m,).
        mean_output: the output's weighted mean (nm).
        centred_ss: ``sum (d - mean_output)^2`` (nm^2): the residual sum of squares of ``w = 0``.
        samples: the number of samples weighted in.
    """

    gram: np.ndarray
    rhs: np.ndarray
    mean_row: np.ndarray
    mean_output: float
    centred_ss: float
    samples: int


def normal_equations(model, u, d, *, history=None, settle: int = 0, block: int = 256) -> NormalEquations:
    """The normal equations of ``model``'s weights for the record ``(u, d)``, the first ``settle``
    samples left out. The plays (T, n) are run once; the design rows are made ``block`` samples at
    a time and reduced into the Gram matrix (only the blocks on and below its diagonal are
    multiplied), so memory is O(T n + m^2), not O(T m)."""
    u, d = jnp.asarray(u, dtype=float), jnp.asarray(d, dtype=float)
    weight = jnp.arange(len(u)) >= settle
    P = play(u, model.radii(), None if history is None else jnp.asarray(history, dtype=float))
    G, b, s, sd, sdd, n = _sums(model, P, d, weight.astype(float), block)
    s, sd, n = np.asarray(s), float(sd), float(n)
    return NormalEquations(
        np.asarray(G) - np.outer(s, s) / n,
        np.asarray(b) - s * sd / n,
        s / n,
        sd / n,
        float(sdd) - sd**2 / n,
        int(n),
    )


@eqx.filter_jit
def _sums(model, P, d, weight, block: int, chunks: int = 4):
    """``(A^T W A, A^T W d, sum W A, sum W d, sum W d^2, sum W)`` over blocks of ``block`` rows.

    ``A^T A`` is symmetric: its columns are cut into ``chunks`` and only the products of chunks on
    and below the diagonal are formed (10 of 16 at 4 chunks; measured at 20,000 samples and 1,275
    columns: 0.54 s against 0.72 s for the whole product)."""
    T = P.shape[0]
    nb = -(-T // block)
    pad = nb * block - T
    Pb = jnp.pad(P, ((0, pad), (0, 0)), mode="edge").reshape(nb, block, -1)
    db = jnp.pad(d, (0, pad)).reshape(nb, block)
    wb = jnp.pad(weight, (0, pad)).reshape(nb, block)  # padded rows weigh nothing
    m = model.design_rows(P[:1]).shape[1]
    edges = np.linspace(0, m, min(chunks, m) + 1).astype(int)
    cut = [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]
    pairs = [(i, j) for i in range(len(cut)) for j in range(i + 1)]

    def body(acc, x):
        G, b, s, sd, sdd, n = acc
        Pk, dk, wk = x
        A = model.design_rows(Pk) * wk[:, None]  # rows of weight 0 or 1: W A = W^2 A
        G = tuple(g + A[:, cut[i]].T @ A[:, cut[j]] for g, (i, j) in zip(G, pairs))
        return (G, b + A.T @ dk, s + A.sum(0), sd + wk @ dk, sdd + wk @ dk**2, n + wk.sum()), None

    zero = jnp.zeros(())
    G0 = tuple(jnp.zeros((cut[i].stop - cut[i].start, cut[j].stop - cut[j].start)) for i, j in pairs)
    (G, b, s, sd, sdd, n), _ = lax.scan(
        body, (G0, jnp.zeros(m), jnp.zeros(m), zero, zero, zero), (Pb, db, wb)
    )
    full = jnp.zeros((m, m))
    for g, (i, j) in zip(G, pairs):
        full = full.at[cut[i], cut[j]].set(g).at[cut[j], cut[i]].set(g.T)
    return full, b, s, sd, sdd, n


def nonnegative_solve(gram: np.ndarray, rhs: np.ndarray, ridge: float = RIDGE, max_steps: int = 100) -> tuple:
    """``argmin_{w >= 0} w^T G w / 2 - b^T w`` (+ ``ridge`` on the unit-scaled weights).

    Block principal pivoting (Kim & Park, "Fast nonnegative matrix factorization: an active-set-like
    method and comparisons", SIAM J. Sci. Comput. 33, 2011, Alg. 2): guess the free set ``F``,
    solve ``G_FF w_F = b_F``, and exchange at once every variable that breaks the KKT conditions
    (``w_F >= 0``, ``y = G w - b >= 0`` off ``F``), falling back to one exchange at a time when
    the count of violations stops falling. It ends in a KKT point in tens of Cholesky solves,
    where Lawson-Hanson (scipy's ``nnls``) adds one variable a step (measured on a 50-level plane,
    1,275 weights: 0.15 s against 0.75-0.9 s). Should it not end in ``max_steps``, scipy's
    ``nnls`` solves the same problem.

    Returns:
        ``(w, steps)``: the weights (m,) and the pivoting steps (``max_steps + 1``: scipy's).
    """
    diag = np.diag(gram)
    scale = np.sqrt(np.where(diag > 0, diag, 1.0))
    G = gram / np.outer(scale, scale) + ridge * np.eye(len(rhs))
    b = rhs / scale
    free = np.zeros(len(b), bool)
    w, y = np.zeros(len(b)), -b
    best, tries = len(b) + 1, 3
    for step in range(max_steps):
        bad = (free & (w < 0)) | (~free & (y < 0))
        count = int(bad.sum())
        if count == 0:
            return w / scale, step
        if count < best:
            best, tries = count, 3
            free ^= bad
        elif tries > 0:
            tries -= 1
            free ^= bad
        else:  # the backup rule: exchange only the last violator
            free[np.flatnonzero(bad)[-1]] ^= True
        w = np.zeros(len(b))
        if free.any():
            w[free] = sl.cho_solve(sl.cho_factor(G[np.ix_(free, free)], check_finite=False), b[free])
        y = G @ w - b
        y[free] = 0.0
    L = np.linalg.cholesky(G)
    return nnls(L.T, sl.solve_triangular(L, b, lower=True), maxiter=50 * len(b))[0] / scale, max_steps + 1


def fit_weights(model, u, d, *, history=None, settle: int = 0) -> tuple:
    """``model`` (PI or Preisach) with the non-negative weights and the offset that fit ``d`` best
    in least squares (:func:`normal_equations`, :func:`nonnegative_solve`).

    Returns:
        ``(fitted, steps, mean_square)``: the operator, the pivoting steps and the mean squared
        residual (nm^2) over the samples after ``settle``, ``(|d_c|^2 - 2 b^T w + w^T G w) / n``
        from the normal equations.

    Raises:
        TypeError: for an operator whose output is not linear in all its fitted parameters.
    """
    if not is_linear(model):
        raise TypeError(
            f"the solver 'jaxafm.nnls' fits operators whose output is linear in their weights (pi, "
            f"preisach), not a {type(model).__name__}: use a gradient solver"
        )
    eq = normal_equations(model, u, d, history=history, settle=settle)
    w, steps = nonnegative_solve(eq.gram, eq.rhs)
    offset = eq.mean_output - eq.mean_row @ w
    mean_square = max(eq.centred_ss - 2 * eq.rhs @ w + w @ eq.gram @ w, 0.0) / eq.samples
    return model.with_weights(jnp.asarray(w), jnp.asarray(offset)), steps, mean_square
