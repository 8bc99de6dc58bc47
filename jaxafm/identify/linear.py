"""Fits of operators whose output is linear in their weights: PI and Preisach, thresholds fixed.

With the play radii fixed, ``y = offset + A w`` with ``A`` (T, m) the design rows
(:meth:`~jaxafm.model.hysteresis.PlayOperator.design_rows`: the plays of a PI operator, the
relay states of a Preisach plane) and ``w >= 0``. The least-squares fit is then a non-negative
least-squares problem, solved exactly instead of by a gradient solver crawling through
``softplus``. It runs on the normal equations, streamed over blocks of samples: ``A`` is never
stored, only the plays (T, n) and the Gram matrix (m, m); for a Preisach plane of 50 levels at
20,000 samples that is 13 MB where ``A`` would take 204 MB and a Jacobian-based fit several GB.
The pivoting loop of :func:`nonnegative_solve` keeps to SciPy's BLAS and LAPACK, one library's
threads (docs/development.md, "One BLAS in a loop").
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sl
from scipy.linalg import blas
from scipy.optimize import nnls

from .. import checks
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
    a time (:func:`_rows`, one compiled shape) and reduced into the Gram matrix by BLAS's symmetric
    rank-k update (``dsyrk``: one triangle, half the products of ``A^T A``), so memory is
    O(T n + m^2 + block m), not O(T m). The sums are taken of the rows and the output less their
    values at the first sample kept, which changes no centred sum but keeps them free of
    cancellation: a column that never moves (a play the drive never turns) sums to exactly zero,
    not to round-off of a large offset.

    Raises:
        ValueError: a NaN or inf in ``u`` or ``d``, or ``settle`` leaves no sample (naming it and
            the record's length).
    """
    u, d = jnp.asarray(u, dtype=float), np.asarray(d, dtype=float)
    checks.finite("output d", d)
    if not 0 <= settle < len(u):
        raise ValueError(f"settle={settle} samples must be >= 0 and leave data to fit (record has {len(u)})")
    P = play(u, model.radii(), None if history is None else jnp.asarray(history, dtype=float))
    d0 = d[settle]
    P, d = np.asarray(P)[settle:], d[settle:] - d0
    T = len(d)
    P = np.pad(P, ((0, -T % block), (0, 0)), mode="edge")  # whole blocks; the padded rows are zeroed
    gram = b = s = a0 = None
    for k in range(0, T, block):
        A = np.array(_rows(model, P[k : k + block]))
        if a0 is None:
            a0 = A[0].copy()
            gram, b, s = np.zeros((len(a0), len(a0)), order="F"), np.zeros(len(a0)), np.zeros(len(a0))
        A -= a0
        A[T - k :] = 0.0
        gram = blas.dsyrk(1.0, A.T, beta=1.0, c=gram, lower=1, overwrite_c=1)  # += A^T A, lower
        b += d[k : k + block] @ A[: T - k]
        s += A.sum(0)
    gram = blas.dsyr(-1.0 / T, s, a=gram, lower=1, overwrite_a=1)  # centred: less s s^T / T, lower
    _mirror_lower(gram)
    sd = float(d.sum())
    return NormalEquations(
        gram, b - s * sd / T, a0 + s / T, float(d0 + sd / T), max(float(d @ d) - sd**2 / T, 0.0), T
    )


def _mirror_lower(a: np.ndarray, rows: int = 256) -> None:
    """Copy the lower triangle of the square ``a`` onto its upper one, in place, ``rows`` rows at
    a time (no (m, m) temporary: the Gram matrix's peak is one copy)."""
    m = len(a)
    for i in range(0, m, rows):
        k = np.arange(i, min(i + rows, m))[:, None]
        a[k[:, 0]] = np.where(np.arange(m) > k, a[:, k[:, 0]].T, a[k[:, 0]])


@eqx.filter_jit
def _rows(model, P: Array) -> Array:
    """``model.design_rows(P)``, compiled once per operator and block shape."""
    return model.design_rows(P)


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
        y = blas.dsymv(1.0, G, w, lower=1) - b  # G w by SciPy's BLAS, as the Cholesky (module docstring)
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
