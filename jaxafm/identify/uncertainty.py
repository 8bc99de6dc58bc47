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
- **Identifiability** (:func:`open_directions`): the eigenvectors of ``J^T J`` whose curvature
  ``lambda`` is small against the prior's, ``lambda < ratio * prior``: combinations of
  parameters the data leave as the prior had them.
"""

from __future__ import annotations

import numpy as np


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
    for g in np.unique(groups):
        s = J[groups == g].T @ r[groups == g]
        meat += np.outer(s, s)
    return Hinv @ meat @ Hinv


def leave_group_out(J: np.ndarray, r: np.ndarray, groups: np.ndarray, prior=None) -> dict:
    """Each group's residuals (its rows) had the fit not seen it: ``{group: e_g}``."""
    Hinv = np.linalg.pinv(hessian(J, prior))
    out = {}
    for g in np.unique(groups):
        rows = groups == g
        Jg = J[rows]
        out[g] = np.linalg.solve(np.eye(rows.sum()) - Jg @ Hinv @ Jg.T, r[rows])
    return out
