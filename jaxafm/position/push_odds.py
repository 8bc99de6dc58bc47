"""A push's odds of success, predicted before it is made from the pushes already checked on the
same scanner (the pushing task of paper section IV).

Every push's miss ``m`` (2,) nm, the particle's final centre minus its goal, is measured against
a reference outside the instrument's frame (in a study: the truth). A check in the instrument's
own frame cannot see that frame's scale error over the push: on the study's test scanner it
measured misses of 0.3-3.8 nm where the true ones were 4.9-13.6 nm. Over a push of vector
``d = L e`` (nm, ``e`` its unit direction) the frame errs by an affine map, the drive's scale
error along each axis and the rotation and coupling of the axes over the push (``M d``, ``M``
2 x 2), plus an offset ``b`` that the centring and the contact add, plus scatter:

    m = b + M d + eps,        eps ~ N(0, Sigma).

The miss along a push therefore depends on its direction wherever the two axes' scale errors
differ, which no model in the push's distance alone can follow. After ``n`` checked pushes the
multivariate least-squares fit on ``x = (1, d / 100 nm)`` gives the next push's miss the
bivariate Student-t predictive of a linear regression under a flat prior
(:func:`~jaxafm.position.online.online_regression`): mean ``x B``, scale matrix
``S (1 + x (X^T X)^-1 x^T)``, ``nu = n - 3`` degrees of freedom. The push succeeds when its miss
lies within the tolerance ``T``:

    P = int_{-T}^{T} p_1(m_1) [F_2|1(h) - F_2|1(-h)] dm_1,        h = sqrt(T^2 - m_1^2),

``p_1`` the first component's marginal, a Student-t of ``nu`` degrees of freedom, and ``F_2|1``
the second's distribution given the first, a Student-t of ``nu + 1`` degrees of freedom with
mean ``mu_2 + S_12 / S_11 (m_1 - mu_1)`` and squared scale
``(nu + q) / (nu + 1) (S_22 - S_12^2 / S_11)``, ``q = (m_1 - mu_1)^2 / S_11`` (Ding, "On the
conditional distribution of the multivariate t distribution", The American Statistician 70,
2016). The integral runs by Gauss-Legendre quadrature in ``u = F_1(m_1)``, which puts its nodes
where the miss's density is however narrow it is against ``T`` (:func:`success_probability`).

Where pushes are commanded through what the earlier ones taught (a learnt push field,
:class:`~jaxafm.position.online.PushField`), a push wanted as ``d`` is commanded as another
vector ``c``, and the frame errs by the affine map of what was commanded, while the miss is
still taken against the goal ``d`` asked for:

    m = (c - d) + b + M c + eps.

The regression then runs on ``x = (1, c / 100 nm)`` with ``m - (c - d)`` and adds ``c - d`` back
to its prediction; with ``c = d`` it is the model above. (Fitted on ``d`` instead, the
``c - d`` that each round's learnt field changes lands in the scatter and the misses of the
pushes before no longer describe the next one.)

A push whose tip misses the particle leaves it where it was, a miss of the whole distance that
no scatter of the pushes that touched it describes: the regression learns from the pushes that
made contact, and the odds are those of contact, by Laplace's rule of succession over the
earlier pushes (``(k + 1) / (n + 2)`` after ``k`` contacts in ``n``, :func:`contact_odds`), times
those of landing within the tolerance.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from .online import Predictive, online_regression

#: pushes checked on a scanner before its next push is given odds (the predictive's three
#: coefficients per component and ``nu = n - 3 >= 3``, the least for which its covariance is finite
#: and its tails no heavier than a few pushes warrant)
MIN_PUSHES = 6
#: Gauss-Legendre nodes over the first component of :func:`success_probability`
NODES = 128
#: pushes' vectors are taken per this many nm in the regression: ``X^T X`` of order one
PUSH_UNIT_NM = 100.0


def success_probability(miss: Predictive, tolerance) -> np.ndarray:
    """The probability that a push whose predicted miss is ``miss`` (``mean`` (k, 2) nm, ``cov``
    (k, 2, 2) nm^2: the bivariate Student-t's scale matrix, ``dof`` (k,)) ends within
    ``tolerance`` (k,) nm of its goal (module docstring); one value per push."""
    x, w = np.polynomial.legendre.leggauss(NODES)
    T = np.asarray(tolerance, float)[..., None]
    mean, S = np.asarray(miss.mean, float), np.asarray(miss.cov, float)
    nu = np.asarray(miss.dof, float)[..., None]
    mu1, mu2 = mean[..., 0:1], mean[..., 1:2]
    s11, s12, s22 = S[..., 0, 0, None], S[..., 0, 1, None], S[..., 1, 1, None]
    s1 = np.sqrt(s11)
    lo, hi = stats.t.cdf((-T - mu1) / s1, nu), stats.t.cdf((T - mu1) / s1, nu)
    m1 = np.clip(mu1 + s1 * stats.t.ppf(lo + (hi - lo) * (x + 1) / 2, nu), -T, T)
    q = (m1 - mu1) ** 2 / s11
    centre = mu2 + s12 / s11 * (m1 - mu1)
    scale = np.sqrt((nu + q) / (nu + 1) * (s22 - s12**2 / s11))
    h = np.sqrt(np.maximum(T**2 - m1**2, 0.0))
    inside = stats.t.cdf((h - centre) / scale, nu + 1) - stats.t.cdf((-h - centre) / scale, nu + 1)
    return np.clip(np.sum(w * (hi - lo) / 2 * inside, axis=-1), 0.0, 1.0)


def components(miss_nm: np.ndarray, direction: np.ndarray) -> tuple:
    """A push's miss (k, 2) nm along and across its unit ``direction`` (k, 2): ``(a, c)``, each (k,)."""
    along = np.sum(miss_nm * direction, axis=-1)
    across = miss_nm[..., 1] * direction[..., 0] - miss_nm[..., 0] * direction[..., 1]
    return along, across


def from_components(along: np.ndarray, across: np.ndarray, push: np.ndarray) -> np.ndarray:
    """A push's miss (k, 2) nm from its components ``along`` and ``across`` (k,) nm the push,
    whose direction ``push`` (k, 2) gives (its vector or its unit direction): the inverse of
    :func:`components`."""
    e = np.asarray(push, float)
    e = e / np.linalg.norm(e, axis=-1, keepdims=True)
    normal = np.stack([-e[..., 1], e[..., 0]], -1)
    return np.asarray(along, float)[..., None] * e + np.asarray(across, float)[..., None] * normal


def online_misses(
    push_nm: np.ndarray, miss_nm: np.ndarray, observed: np.ndarray, command_nm=None
) -> Predictive:
    """Each push's predicted miss (mean (k, 2) nm, scale matrix (k, 2, 2) nm^2, degrees of freedom
    (k,)) from the pushes before it (in the given order) whose misses were ``observed`` (k,)
    bool, by the module docstring's regression on their wanted vectors ``push_nm`` (k, 2) nm,
    their ``command_nm`` (k, 2) nm (``None``: each commanded as wanted; NaN where a push was not
    commanded, which counts as wanted) and misses ``miss_nm`` (k, 2) nm; NaN for a push with
    fewer than :data:`MIN_PUSHES` observed before it."""
    d = np.asarray(push_nm, float)
    c = d if command_nm is None else np.where(np.isfinite(command_nm), command_nm, d)
    X = np.column_stack([np.ones(len(d)), c / PUSH_UNIT_NM])
    miss = online_regression(X, np.asarray(miss_nm, float) - (c - d), observed, MIN_PUSHES - X.shape[1])
    return miss._replace(mean=miss.mean + (c - d))


def contact_odds(contact: np.ndarray, pushed: np.ndarray) -> np.ndarray:
    """Each push's probability of touching its particle from the pushes before it (in the given
    order) that were made (``pushed`` (k,) bool) and touched theirs (``contact`` (k,) bool):
    ``(k + 1) / (n + 2)``, Laplace's rule of succession (a uniform prior on the rate)."""
    made = np.asarray(pushed, bool)
    hit = np.asarray(contact, bool) & made
    return (np.cumsum(hit) - hit + 1.0) / (np.cumsum(made) - made + 2.0)


def odds_from_earlier(push_nm, miss_nm, contact, made, tolerance, command_nm=None) -> np.ndarray:
    """Each push's predicted success, the chance of touching (:func:`contact_odds`) times that of
    ending within ``tolerance`` (k,) nm of its goal (:func:`success_probability` of
    :func:`online_misses`), from the pushes before it (in the given order) that were ``made``
    (k,) bool; their wanted vectors ``push_nm`` (k, 2) nm, commands ``command_nm`` (k, 2) nm
    (``None``: as wanted), misses ``miss_nm`` (k, 2) nm (NaN where none was measured) and
    ``contact`` (k,) bool. NaN for a push with fewer than :data:`MIN_PUSHES` touching pushes
    before it."""
    made = np.asarray(made, bool) & np.isfinite(miss_nm).all(-1)
    touched = made & np.asarray(contact, bool)
    miss = online_misses(push_nm, miss_nm, touched, command_nm)
    return contact_odds(touched, made) * success_probability(miss, tolerance)
