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
#: combinations undetermined (``experiments/bench_preisach_fit.py`` reports the Gram matrix's
#: rank), and the ridge settles them on the smallest weights.
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
    multiplied), so memory is O(T n + m^2), not O(T m). The sums are taken of the rows and the
    output less their values at the first sample kept, which changes no centred sum but keeps them
    free of cancellation: a column that never moves (a play the drive never turns) sums to exactly
    zero, not to round-off of a large offset.

    Raises:
        ValueError: ``settle`` leaves no sample (naming it and the record's length).
    """
    u, d = jnp.asarray(u, dtype=float), jnp.asarray(d, dtype=float)
    if not 0 <= settle < len(u):
        raise ValueError(f"settle={settle} samples must be >= 0 and leave data to fit (record has {len(u)})")
    P = play(u, model.radii(), None if history is None else jnp.asarray(history, dtype=float))
    weight = (jnp.arange(len(u)) >= settle).astype(float)
    G, b, s, sd, sdd, n, a0, d0 = _sums(model, P, d, weight, settle, block)
    s, sd, n = np.asarray(s), float(sd), float(n)
    gram = np.array(G)  # a writable copy, centred in place
    gram -= np.outer(s, s / n)
    return NormalEquations(
        gram,
        np.asarray(b) - s * sd / n,
        np.asarray(a0) + s / n,
        float(d0) + sd / n,
        max(float(sdd) - sd**2 / n, 0.0),
        int(n),
    )


@eqx.filter_jit
def _sums(model, P, d, weight, first, block: int, chunks: int = 4):
    """``(A^T W A, A^T W d, sum W A, sum W d, sum W d^2, sum W)`` over blocks of ``block`` rows,
    ``A`` and ``d`` less their values ``a0``, ``d0`` at sample ``first`` (returned after them),
    ``W`` the 0/1 ``weight``.

    ``A^T A`` is symmetric: its columns are cut into ``chunks`` and only the products of chunks on
    and below the diagonal are formed (10 of 16 at 4 chunks)."""
    T = P.shape[0]
    nb = -(-T // block)
    pad = nb * block - T
    Pb = jnp.pad(P, ((0, pad), (0, 0)), mode="edge").reshape(nb, block, -1)
    db = jnp.pad(d, (0, pad)).reshape(nb, block)
    wb = jnp.pad(weight, (0, pad)).reshape(nb, block)  # padded rows weigh nothing
    a0 = model.design_rows(lax.dynamic_slice_in_dim(P, first, 1))[0]
    d0 = d[first]
    m = a0.shape[0]
    edges = np.linspace(0, m, min(chunks, m) + 1).astype(int)
    cut = [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]
    pairs = [(i, j) for i in range(len(cut)) for j in range(i + 1)]

    def body(acc, x):
        G, b, s, sd, sdd, n = acc
        Pk, dk, wk = x
        A = (model.design_rows(Pk) - a0) * wk[:, None]  # rows of weight 0 or 1: W A = W^2 A
        dk = (dk - d0) * wk
        G = tuple(g + A[:, cut[i]].T @ A[:, cut[j]] for g, (i, j) in zip(G, pairs))
        return (G, b + A.T @ dk, s + A.sum(0), sd + dk.sum(), sdd + dk @ dk, n + wk.sum()), None

    zero = jnp.zeros(())
    G0 = tuple(jnp.zeros((cut[i].stop - cut[i].start, cut[j].stop - cut[j].start)) for i, j in pairs)
    (G, b, s, sd, sdd, n), _ = lax.scan(
        body, (G0, jnp.zeros(m), jnp.zeros(m), zero, zero, zero), (Pb, db, wb)
    )
    full = jnp.zeros((m, m))
    for g, (i, j) in zip(G, pairs):
        full = full.at[cut[i], cut[j]].set(g).at[cut[j], cut[i]].set(g.T)
    return full, b, s, sd, sdd, n, a0, d0


def nonnegative_solve(gram: np.ndarray, rhs: np.ndarray, ridge: float = RIDGE, max_steps: int = 100) -> tuple:
    """``argmin_{w >= 0} w^T G w / 2 - b^T w`` (+ ``ridge`` on the unit-scaled weights).

    Block principal pivoting (Kim & Park, "Fast nonnegative matrix factorization: an active-set-like
    method and comparisons", SIAM J. Sci. Comput. 33, 2011, Alg. 2): guess the free set ``F``,
    solve ``G_FF w_F = b_F``, and exchange at once every variable that breaks the KKT conditions
    (``w_F >= 0``, ``y = G w - b >= 0`` off ``F``, each beyond round-off), falling back to one
    exchange at a time when the count of violations stops falling. It ends in a KKT point in tens
    of Cholesky solves, where Lawson-Hanson (scipy's ``nnls``) adds one variable a step
    (``experiments/bench_preisach_fit.py`` times both on the same Gram matrix). Should it not end
    in ``max_steps``, scipy's ``nnls`` solves the same problem. A column with no variance (zero
    diagonal) keeps a zero weight.

    Returns:
        ``(w, steps, how)``: the weights (m,), the pivoting steps, and how it ended: ``"pivoting"``,
        ``"scipy nnls"``, or ``"scipy nnls stopped short"`` (its last iterate returned).
    """
    diag = np.diag(gram)
    scale = np.sqrt(np.where(diag > 0, diag, 1.0))
    G = gram / scale[:, None]  # one (m, m) copy, scaled and ridged in place
    G /= scale[None, :]
    G[np.diag_indices_from(G)] += ridge
    b = rhs / scale
    tol = 1e-12 * max(np.abs(b).max(initial=0.0), 1e-300)
    free = np.zeros(len(b), bool)
    w, y = np.zeros(len(b)), -b
    best, tries = len(b) + 1, 3
    for step in range(max_steps):
        bad = (free & (w < -tol)) | (~free & (y < -tol))
        count = int(bad.sum())
        if count == 0:
            return np.maximum(w, 0.0) / scale, step, "pivoting"
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
            w[free] = sl.cho_solve(_cholesky(G[np.ix_(free, free)], ridge), b[free])
        y = G @ w - b
        y[free] = 0.0
    L = np.tril(_cholesky(G, ridge)[0])  # cho_factor leaves the other triangle as it was
    try:
        w = nnls(L.T, sl.solve_triangular(L, b, lower=True), maxiter=50 * len(b))[0]
    except RuntimeError:  # scipy's iteration limit
        return np.maximum(w, 0.0) / scale, max_steps, "scipy nnls stopped short"
    return w / scale, max_steps, "scipy nnls"


def _cholesky(G: np.ndarray, ridge: float) -> tuple:
    """``scipy.linalg.cho_factor(G, lower=True)``, or a ValueError for a singular ``G`` (a zero
    ``ridge`` on weights the data do not separate)."""
    try:
        return sl.cho_factor(G, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"the normal equations are singular (weights the data cannot tell apart) with ridge={ridge:g}: "
            f"give ridge > 0 (the default is {RIDGE:g})"
        ) from None


@dataclasses.dataclass(frozen=True)
class WeightFit:
    """What :func:`fit_weights` returns.

    Attributes:
        model: the operator with its fitted weights and offset.
        steps: the pivoting steps.
        how: how the solve ended (:func:`nonnegative_solve`).
        mean_square: the mean squared residual (nm^2) over the samples after ``settle``,
            ``(|d_c|^2 - 2 b^T w + w^T G w) / n`` from the normal equations.
    """

    model: object
    steps: int
    how: str
    mean_square: float


def fit_weights(model, u, d, *, history=None, settle: int = 0) -> WeightFit:
    """``model`` (PI or Preisach) with the non-negative weights and the offset that fit ``d`` best
    in least squares (:func:`normal_equations`, :func:`nonnegative_solve`).

    Raises:
        TypeError: for an operator whose output is not linear in all its fitted parameters.
    """
    if not is_linear(model):
        raise TypeError(
            f"the solver 'jaxafm.nnls' fits operators whose output is linear in their weights (pi, "
            f"preisach), not a {type(model).__name__}: use a gradient solver"
        )
    eq = normal_equations(model, u, d, history=history, settle=settle)
    w, steps, how = nonnegative_solve(eq.gram, eq.rhs)
    offset = eq.mean_output - eq.mean_row @ w
    mean_square = max(eq.centred_ss - 2 * eq.rhs @ w + w @ eq.gram @ w, 0.0) / eq.samples
    return WeightFit(model.with_weights(jnp.asarray(w), jnp.asarray(offset)), steps, how, mean_square)
