"""Straightforward NumPy reference implementations: a relay grid and play loops.

A Python loop over time, NumPy over hysterons: the obvious way to write these
models. They are the baselines of the speed benchmarks and an independent
cross-check of the JAX operators in the tests.
"""

from __future__ import annotations

import numpy as np


def preisach_relay_grid(u, density, u_min, u_max, history=None):
    """Relay-grid Preisach model: every relay ``(alpha_i, beta_j)`` updated at every sample.

    Same plane and relay positions as :class:`jaxafm.Preisach` with
    ``smooth=False``; relays start from the state the plays' ``history`` gives.
    """
    density = np.asarray(density, dtype=float)
    n = density.shape[0]
    step = (u_max - u_min) / n
    centres = u_min + (np.arange(n) + 0.5) * step
    ii, jj = np.tril_indices(n)
    alpha, beta, mu = centres[ii], centres[jj], density[ii, jj]
    history = [u[0]] if history is None else list(history)
    # start: relay up iff it sits below history[0], i.e. s = (alpha+beta)/2 <= history[0]
    state = np.where((alpha + beta) / 2 <= history[0], 1.0, -1.0)
    for h in history[1:]:
        state = _relay_update(state, h, alpha, beta)
    out = np.empty(len(u))
    for t, ut in enumerate(u):
        state = _relay_update(state, ut, alpha, beta)
        out[t] = mu @ state
    return out


def _relay_update(state, ut, alpha, beta):
    state = np.where(ut >= alpha, 1.0, state)
    return np.where(ut <= beta, -1.0, state)


def pi_loop(u, thresholds, weights, offset=0.0):
    """PI operator with a Python loop over time and NumPy over the plays (start at ``u[0]``)."""
    r = np.asarray(thresholds, dtype=float)
    p = np.full(r.shape, u[0], dtype=float)
    out = np.empty(len(u))
    for t, ut in enumerate(u):
        p = np.minimum(np.maximum(p, ut - r), ut + r)
        out[t] = offset + p @ weights
    return out
