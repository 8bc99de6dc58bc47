"""A push's odds of success, predicted before it is made from the pushes already checked on the
same scanner (the pushing task of paper section IV).

Every push's miss ``m`` (nm), the particle's final centre minus its goal, is measured along the
push, ``a = m . e``, and across it, ``c = m . n`` (``e`` the push's unit direction, ``n`` it
turned by +90 degrees), against a reference outside the instrument's frame (in a study: the
truth). A check in the instrument's own frame cannot see that frame's scale error over the
push: on the study's test scanner it measured misses of 0.3-3.8 nm where the true ones were
4.9-13.6 nm. Each component is modelled as linear
in the push's distance ``L`` plus scatter,

    a = alpha_0 + alpha_1 L + eps_a,        c = gamma_0 + gamma_1 L + eps_c,

``alpha_1`` the drive's scale error over the push, ``gamma_1`` the push line's rotation, the
intercepts and scatter what the centring and the contact add. After ``n`` checked pushes each
component's least-squares fit gives the next push's miss the Student-t predictive of a linear
regression under a flat prior: mean ``x beta``, scale ``s sqrt(1 + x (X^T X)^-1 x^T)``, ``n - 2``
degrees of freedom (``s^2`` the residuals' RSS / (n - 2)). The push succeeds when its miss lies
within the tolerance ``T``:

    P = int_{-T}^{T} p_c(c) [F_a(sqrt(T^2 - c^2)) - F_a(-sqrt(T^2 - c^2))] dc,

``p_c`` the across component's density and ``F_a`` the along one's distribution function, by
Gauss-Legendre quadrature (:func:`success_probability`). The two components are taken as
independent.

A push whose tip misses the particle leaves it where it was, a miss of the whole distance that
no scatter of the pushes that touched it describes: the regression learns from the pushes that
made contact, and the odds are those of contact, by Laplace's rule of succession over the
earlier pushes (``(k + 1) / (n + 2)`` after ``k`` contacts in ``n``, :func:`contact_odds`), times
those of landing within the tolerance.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import stats

from .online import online_regression

#: pushes checked on a scanner before its next push is given odds (the predictive needs n - 2 >= 3)
MIN_PUSHES = 5
#: Gauss-Legendre nodes over the across component of :func:`success_probability`
NODES = 64


class Miss(NamedTuple):
    """A push's predicted miss (nm): along the push (``along``, ``along_scale``) and across it
    (``across``, ``across_scale``), each a Student-t of ``dof`` degrees of freedom with that
    mean and scale. Fields may be arrays (one per push)."""

    along: np.ndarray
    along_scale: np.ndarray
    across: np.ndarray
    across_scale: np.ndarray
    dof: np.ndarray


def success_probability(miss: Miss, tolerance) -> np.ndarray:
    """The probability that a push whose miss is ``miss`` ends within ``tolerance`` (nm) of its
    goal (module docstring); one value per push."""
    x, w = np.polynomial.legendre.leggauss(NODES)
    T = np.asarray(tolerance, float)[..., None]
    c = T * x  # across, from -T to T
    half = np.sqrt(np.maximum(T**2 - c**2, 0.0))
    dof, a, sa = (np.asarray(v, float)[..., None] for v in (miss.dof, miss.along, miss.along_scale))
    ac, sc = (np.asarray(v, float)[..., None] for v in (miss.across, miss.across_scale))
    inside = stats.t.cdf((half - a) / sa, dof) - stats.t.cdf((-half - a) / sa, dof)
    density = stats.t.pdf((c - ac) / sc, dof) / sc
    return np.clip(np.sum(w * T * density * inside, axis=-1), 0.0, 1.0)


def components(miss_nm: np.ndarray, direction: np.ndarray) -> tuple:
    """A push's miss (k, 2) nm along and across its unit ``direction`` (k, 2): ``(a, c)``, each (k,)."""
    along = np.sum(miss_nm * direction, axis=-1)
    across = miss_nm[..., 1] * direction[..., 0] - miss_nm[..., 0] * direction[..., 1]
    return along, across


def online_misses(distance: np.ndarray, along: np.ndarray, across: np.ndarray, observed: np.ndarray) -> Miss:
    """Each push's predicted miss from the pushes before it (in the given order) whose misses were
    ``observed``, as the module docstring's regression gives it
    (:func:`~jaxafm.position.online.online_regression`); NaN for a push with fewer than
    :data:`MIN_PUSHES` observed before it. ``distance``, ``along``, ``across`` (k,) nm."""
    L = np.asarray(distance, float) / 100.0  # per 100 nm: X^T X of order one
    X = np.stack([np.ones_like(L), L], -1)
    pred = online_regression(X, np.stack([along, across], -1), observed, MIN_PUSHES - X.shape[1])
    sd = np.sqrt(np.diagonal(pred.cov, axis1=1, axis2=2))
    return Miss(pred.mean[:, 0], sd[:, 0], pred.mean[:, 1], sd[:, 1], pred.dof)


def contact_odds(contact: np.ndarray, pushed: np.ndarray) -> np.ndarray:
    """Each push's probability of touching its particle from the pushes before it (in the given
    order) that were made (``pushed`` (k,) bool) and touched theirs (``contact`` (k,) bool):
    ``(k + 1) / (n + 2)``, Laplace's rule of succession (a uniform prior on the rate)."""
    made = np.asarray(pushed, bool)
    hit = np.asarray(contact, bool) & made
    return (np.cumsum(hit) - hit + 1.0) / (np.cumsum(made) - made + 2.0)


def odds_from_earlier(distance, along, across, contact, made, tolerance) -> np.ndarray:
    """Each push's predicted success, the chance of touching (:func:`contact_odds`) times that of
    ending within ``tolerance`` (k,) nm of its goal (:func:`success_probability` of
    :func:`online_misses`), from the pushes before it (in the given order) that were ``made``
    (k,) bool; their ``distance``, miss ``along`` and ``across`` (k,) nm and ``contact`` (k,) bool.
    NaN for a push with fewer than :data:`MIN_PUSHES` touching pushes before it."""
    made = np.asarray(made, bool) & np.isfinite(along) & np.isfinite(across)
    touched = made & np.asarray(contact, bool)
    miss = online_misses(distance, along, across, touched)
    return contact_odds(touched, made) * success_probability(miss, tolerance)
