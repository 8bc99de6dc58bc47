"""What a least-squares fit's data determine: the parameters' covariance with residuals correlated
within groups, leave-one-group-out residuals, and which parameter combinations stay open.

All of it works on the fit's linearisation at its solution: the residuals ``r`` (n,) and their
Jacobian ``J`` (n, k) with respect to the parameters, and the rows' ``groups`` (n,): the
measurements that share an error (step A's chords of one feature share the feature's shape
irregularity, so its chords are one group). A ``prior`` precision ``P`` (k, k), in the units of
``J^T J``, adds ``P`` to the Gauss-Newton Hessian ``H = J^T J + P`` (a Gaussian prior on the
parameters, centred on the start).

- **Covariance** (:func:`covariance`): the cluster-robust ("sandwich") estimate
  ``C = H^-1 (sum_g J_g^T r_g r_g^T J_g + s^2 P) H^-1`` (Liang & Zeger 1986), which holds however
  the errors are correlated within a group, as long as groups are independent; with every row its
  own group and no prior it is White's estimate. ``P`` is the prior's precision in the units of
  ``J^T J``, ``s^2 / sigma_p^2`` for a prior sd ``sigma_p`` (``s^2`` the residuals' mean square),
  and its term keeps what the data do not fix at the prior's width: along a unit direction ``v``
  with ``J v = 0``, ``v^T C v = s^2 / p = sigma_p^2``, where the sandwich alone would give 0.
  The plain ``s^2 H^-1`` assumes independent rows and is too narrow for correlated ones.
- **Leave one group out** (:func:`leave_group_out`): the residuals a group would have if the fit
  had not seen it, from the one fit, ``e_g = (I - J_g H^-1 J_g^T)^-1 r_g``: exact for a linear
  least-squares problem, a Gauss-Newton step from the solution otherwise (the block PRESS).
- **A fit's posterior** (:func:`posterior_of`): the covariance of a one-axis
  actuator fit's raw parameters under one of three noise models, and a new measurement's
  spread ``s`` about the model (:class:`~jaxafm.model.posterior.Posterior`). ``ar1`` (the
  default): the covariance of the least-squares estimate the fit made when its errors are an
  AR(1) process (the residuals' lag-1 autocorrelation ``rho``), the sandwich
  ``H^-1 J^T Sigma J H^-1`` with ``Sigma`` the AR(1) covariance (:func:`_ar1_covariance`;
  Cochrane & Orcutt 1949 whiten the same way);
  ``blocks``: the cluster-robust covariance above with contiguous blocks of residuals as the
  groups, each as long as the residuals stay correlated (:func:`correlation_length`); both take
  ``s`` from the leave-one-block-out residuals (what the fit does on data it has not seen).
  ``iid``: the textbook ``s^2 H^-1`` with ``s`` the training rms, the naive band. Every method
  has the prior ``P = s^2 / sigma_p^2 I`` with ``sigma_p`` = :data:`PRIOR_SD` (raw parameters
  are order one, so a direction the data do not fix comes out about as wide as the parameter's
  own scale). ``ar1`` is the default by measured coverage: on straight lines with AR(1) noise
  it covers the offset as stated where ``blocks`` runs narrow (too few blocks for strongly
  correlated residuals, tests/test_posterior.py), and on the real records it matches ``blocks``
  (``experiments/uncertainty_coverage.py``, docs/uncertainty.md).
"""

from __future__ import annotations

import numpy as np

from ..model.posterior import METHODS, Posterior

#: the prior sd of every raw (order-one) parameter of :func:`posterior_of`
PRIOR_SD = 1.0


def hessian(J: np.ndarray, prior=None) -> np.ndarray:
    """The Gauss-Newton Hessian ``J^T J + P`` (k, k)."""
    H = J.T @ J
    return H if prior is None else H + np.asarray(prior)


def covariance(J: np.ndarray, r: np.ndarray, groups: np.ndarray, prior=None) -> np.ndarray:
    """The parameters' cluster-robust covariance (k, k), with the ``prior``'s width where the data
    say nothing (module docstring)."""
    Hinv = np.linalg.pinv(hessian(J, prior))
    k = J.shape[1]
    meat = np.zeros((k, k)) if prior is None else np.mean(r**2) * np.asarray(prior)
    _, index = np.unique(groups, return_inverse=True)
    scores = np.zeros((index.max() + 1, k))
    np.add.at(scores, index, J * np.asarray(r)[:, None])  # J_g^T r_g, one row per group
    return Hinv @ (meat + scores.T @ scores) @ Hinv


def leave_group_out(J: np.ndarray, r: np.ndarray, groups: np.ndarray, prior=None, H=None) -> dict:
    """Each group's residuals (its rows) had the fit not seen it: ``{group: e_g}``,
    ``e_g = (I - J_g H^-1 J_g^T)^-1 r_g``, by one of two equal forms: the Woodbury identity
    ``(I - J_g H^-1 J_g^T)^-1 = I + J_g (H - J_g^T J_g)^-1 J_g^T``, a (k, k) solve for each group
    (``k`` parameters); or, for the groups of ``b < k`` rows when they are many enough that
    forming ``W = S J^T`` (``S^T S = H^-1``, :func:`_half_inverse`: ``n k^2`` products for
    ``n`` rows) costs less than their (k, k) solves (``k^3 / 3`` each), ``J_g H^-1 J_g^T =
    W_g^T W_g`` and a (b, b) solve each, the groups of one size solved together, ``W`` made
    :data:`DIRECT_ROWS` rows at a time. (A
    1,276-parameter Preisach plane on 4,000 samples in groups of a few rows: 478 s by Woodbury
    alone.) With a positive definite ``prior`` every matrix solved is positive definite
    (``H - J_g^T J_g`` is at least the prior) and solved directly (LU); without, by least
    squares (either may then be singular). ``H``: the Gauss-Newton Hessian ``J^T J + prior``
    (:func:`hessian`), if the caller has it already. Every product and solve here is NumPy's, one
    library's threads (docs/development.md, "One BLAS in a loop")."""
    n, k = J.shape
    H = hessian(J, prior) if H is None else H
    solve = np.linalg.solve if prior is not None else lambda a, b: np.linalg.lstsq(a, b, rcond=None)[0]
    order = np.argsort(groups, kind="stable")
    names, first = np.unique(np.asarray(groups)[order], return_index=True)
    rows_of = dict(zip(names, np.split(order, first[1:])))
    small = {g: rows for g, rows in rows_of.items() if len(rows) < k}
    out = {}
    if len(small) * k > 3 * n:  # the direct form for the small groups
        S = _half_inverse(H, prior is not None)  # J H^-1 J^T = (J S^T)(J S^T)^T
        for size in {len(rows) for rows in small.values()}:
            same = [g for g, rows in small.items() if len(rows) == size]
            idx = np.stack([small[g] for g in same])  # (groups, b)
            step = max(1, DIRECT_ROWS // size)
            for part in range(0, len(same), step):  # J S^T a slab of rows at a time, never (n, k)
                rows = idx[part : part + step]
                V = (J[rows.ravel()] @ S.T).reshape(*rows.shape, -1)  # (groups, b, k)
                a = np.eye(size) - V @ V.transpose(0, 2, 1)
                rg = r[rows]
                e = np.linalg.solve(a, rg[..., None])[..., 0] if prior is not None else _lstsq_each(a, rg)
                out |= dict(zip(same[part : part + step], e))
        rows_of = {g: rows for g, rows in rows_of.items() if g not in out}
    for g, rows in rows_of.items():
        Jg, rg = J[rows], r[rows]
        out[g] = rg + Jg @ solve(H - Jg.T @ Jg, Jg.T @ rg)
    return {g: out[g] for g in names}


#: rows of ``J S^T`` that :func:`leave_group_out`'s direct form holds at a time
DIRECT_ROWS = 2048


def _half_inverse(H: np.ndarray, definite: bool) -> np.ndarray:
    """``S`` (k, k) with ``S^T S = H^-1``: ``L^-1`` for ``H = L L^T`` when ``H`` is positive
    definite, else ``diag(lambda^-1/2) V^T`` over the eigenvalues ``lambda`` above round-off (the
    pseudo-inverse's)."""
    if definite:
        return np.linalg.inv(np.linalg.cholesky(H))
    lam, V = np.linalg.eigh(H)
    keep = lam > len(H) * np.finfo(float).eps * lam.max()
    return V[:, keep].T / np.sqrt(lam[keep])[:, None]


def _lstsq_each(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``lstsq(a_g, b_g)`` for each of the stacked matrices ``a`` (g, b, b) and vectors ``b`` (g, b)."""
    return np.stack([np.linalg.lstsq(ag, bg, rcond=None)[0] for ag, bg in zip(a, b)])


def correlation_length(r: np.ndarray) -> int:
    """Samples over which the residuals ``r`` stay correlated: twice the first lag at which
    their autocorrelation falls below zero, at least 1 and at most a tenth of the record."""
    x = np.asarray(r, dtype=float) - np.mean(r)
    n = len(x)
    spectrum = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(spectrum * np.conj(spectrum))[:n]
    below = np.flatnonzero(acf < 0)
    first = int(below[0]) if len(below) else n
    return int(max(1, min(2 * first, n // 10)))


def posterior_of(
    J: np.ndarray, r: np.ndarray, input_span_v: float, output_range_nm: float, method: str
) -> Posterior:
    """The :class:`~jaxafm.model.posterior.Posterior` of a fit whose residuals are ``r`` (n,) nm
    with Jacobian ``J`` (n, k) in the raw parameters of ``free_parameters(input_span_v,
    output_range_nm)``, under the noise model ``method`` (module docstring)."""
    if method not in METHODS:
        raise ValueError(f"unknown noise model {method!r}; one of {', '.join(METHODS)}")
    C, sd, block = _noise_model(method, J, r)
    return Posterior(C, sd, input_span_v, output_range_nm, method, block)


def _noise_model(method: str, J: np.ndarray, r: np.ndarray) -> tuple:
    """``(C, s, block)`` of :func:`posterior_of` for the residuals ``r`` (n,) nm and their Jacobian
    ``J`` (n, k)."""
    eye = np.eye(J.shape[1]) / PRIOR_SD**2
    s2 = float(np.mean(r**2))
    if method == "iid":
        return s2 * np.linalg.inv(J.T @ J + s2 * eye), np.sqrt(s2), 1
    block = correlation_length(r)
    groups = np.arange(len(r)) // block
    H = hessian(J, s2 * eye)
    held = np.concatenate(list(leave_group_out(J, r, groups, prior=s2 * eye, H=H).values()))
    spread = float(np.sqrt(np.mean(held**2)))
    if method == "blocks":
        C = covariance(J, r, groups, prior=s2 * eye)
        return 0.5 * (C + C.T), spread, block
    return _ar1_covariance(J, r, s2 * eye, H), spread, block


def _ar1_covariance(J: np.ndarray, r: np.ndarray, prior: np.ndarray, H: np.ndarray) -> np.ndarray:
    """The covariance of the least-squares estimate when its errors are AR(1) (module
    docstring): ``H^-1 (J^T Sigma J + s^2 P) H^-1``, ``H = J^T J + P``, with ``Sigma`` the AR(1)
    covariance of the residuals' lag-1 autocorrelation ``rho`` and innovation variance
    ``s_w^2``. ``Sigma = s_w^2 L^-1 L^-T`` for the whitening ``(L x)_t = x_t - rho x_{t-1}``,
    so ``J^T Sigma J = s_w^2 A^T A`` with ``A = L^-T J``, the backward filter
    ``A_t = J_t + rho A_{t+1}`` (:func:`backward_blocks`), summed :data:`GRAM_ROWS` rows at a
    time: ``A`` (n, k) is never stored."""
    rho = float(np.corrcoef(r[:-1], r[1:])[0, 1])
    sw2 = float(np.mean((r[1:] - rho * r[:-1]) ** 2))
    gram, slab = np.zeros((J.shape[1], J.shape[1])), []
    for start, a in backward_blocks(J, rho):
        slab.append(a)
        if start % GRAM_ROWS == 0:  # every GRAM_ROWS rows, and the first block
            A = np.concatenate(slab[::-1])
            gram += A.T @ A
            slab = []
    Hinv = np.linalg.inv(H)
    C = Hinv @ (sw2 * gram + np.mean(r**2) * prior) @ Hinv
    return 0.5 * (C + C.T)


#: rows of the backward filter's output that :func:`_ar1_covariance` holds at a time
GRAM_ROWS = 1024


def backward_blocks(J: np.ndarray, rho: float, block: int = 64):
    """``A`` (n, k) with ``A_t = J_t + rho A_{t+1}`` (``A_n = 0`` beyond the last row), ``block``
    rows at a time from the end, each yielded as ``(start, A[start : start + block])``: within a
    block ``A_t = sum_{s >= t} rho^(s - t) J_s`` over its rows plus ``rho^(b - t) A_b`` from the
    block after (``b`` its first row), one (block, block) triangular Toeplitz product per block:
    the same numbers as ``scipy.signal.lfilter`` run backwards over the rows, by matrix products
    instead of its sample-by-sample recursion. ``block`` divides :data:`GRAM_ROWS`."""
    n = len(J)
    i = np.arange(block)
    powers = rho ** np.maximum(i[None, :] - i[:, None], 0)
    M = np.where(i[None, :] >= i[:, None], powers, 0.0)  # M[t, s] = rho^(s - t), s >= t
    carry = rho ** (block - i)  # rho^(b - t): what the next block's first row adds
    after = np.zeros(J.shape[1])
    for start in range(((n - 1) // block) * block, -1, -block):
        rows = slice(start, min(start + block, n))
        m = rows.stop - start
        a = M[:m, :m] @ J[rows] + np.outer(carry[:m], after)  # after = 0 for the short last block
        after = a[0]
        yield start, a
