"""Nuisance parameters projected out of a linear least-squares problem (Frisch-Waugh-Lovell).

In ``b = A theta + Z gamma + e``, where only ``theta`` is wanted, the least-squares ``theta``
(its covariance and the residuals too) is that of ``M b = M A theta + e`` with
``M = I - Z (Z^T W Z)^+ Z^T W`` the weighted projection onto the orthogonal complement of the
nuisance columns ``Z``: each vector is replaced by its residual after a fit of ``Z``. Nuisances
that belong to groups of samples -- a width per scan row, a wall slope per row, a background per
image -- are block-diagonal in ``Z``: each group's own columns, fitted to that group's samples.
:func:`project_out` does this for all the groups at once.
"""

from __future__ import annotations

from typing import Optional

import numpy as np


def project_out(v, nuisance, groups: Optional[np.ndarray] = None, weights=None) -> np.ndarray:
    """``v`` less its weighted least-squares fit by the ``nuisance`` columns, group by group.

    ``M v = v - Z_g (Z_g^T W Z_g)^+ Z_g^T W v`` per group ``g``, ``W = diag(weights)``: the
    residual of ``v`` after the nuisance parameters are fitted to it (Frisch-Waugh-Lovell). A
    sample of weight 0 (held out, masked) does not steer the fit but is projected like the
    others, with the coefficients of its group's weighted samples. A group whose nuisance
    columns are all 0 on its weighted samples keeps its samples as they are.

    Arguments:
        v: (n,) or (n, m): the data or design columns to project.
        nuisance: (n,) or (n, k): the nuisance columns ``Z`` (one column: (n,)).
        groups: (n,) whole numbers >= 0: each sample's group (its own nuisance parameters);
            ``None``: one group.
        weights: (n,) >= 0: each sample's weight; ``None``: all 1.

    Returns:
        ``M v``, shaped as ``v``.
    """
    v = np.asarray(v, dtype=float)
    z = np.asarray(nuisance, dtype=float)
    z = z[:, None] if z.ndim == 1 else z
    n, k = z.shape
    g = np.zeros(n, dtype=int) if groups is None else np.unique(groups, return_inverse=True)[1].ravel()
    wz = z if weights is None else z * np.asarray(weights, dtype=float)[:, None]
    flat = v.reshape(n, -1)
    count = g.max() + 1 if n else 0
    zz = np.zeros((count, k, k))
    np.add.at(zz, g, wz[:, :, None] * z[:, None, :])
    zv = np.zeros((count, k, flat.shape[1]))
    np.add.at(zv, g, wz[:, :, None] * flat[:, None, :])
    if k == 1:  # one column: the pseudo-inverse of a number
        coef = np.divide(zv, zz, out=np.zeros_like(zv), where=zz != 0)
    else:
        coef = np.linalg.pinv(zz) @ zv  # (groups, k, m)
    return (flat - np.einsum("ij,ijk->ik", z, coef[g])).reshape(v.shape)
