"""The fair NumPy baselines of the speed benchmarks (tests/reference.py) against jaxafm and the
definitions.

``preisach_play_loop`` is the Preisach model the way jaxafm computes it (n plays, O(n) per sample),
written again in plain NumPy: it must equal jaxafm's ``Preisach`` (both kinds, with and without a
history) and the model's definition (the O(n^2) relay grid, or for the smooth kind its weight
spread over sub-relays). ``pi_play_loop`` (``play_loop`` with a history, read out) must equal the JAX PI operator, and
``linear_recurrence`` (the lags and the drift's wander of the vectorised raster scan) the closed
form of a constant recurrence. The vectorised raster scan itself is checked in
tests/test_reference_scan.py.

Tolerances come from float64 round-off (``EPS``), each stated where it is used.
"""

import jax.numpy as jnp
import numpy as np
import pytest
import reference

from jaxafm import PrandtlIshlinskii, Preisach

EPS = np.finfo(float).eps
T, N = 600, 10  # samples; Preisach levels
BLOCK = 64  # samples per block of the NumPy play loops: several blocks, so their joins are checked
U_MIN, U_MAX = -5.2, 4.9  # the plane; the inputs leave it on both sides
HISTORIES = [None, (0.0, 3.6), (-6.0, 5.5, -1.3)]


def random_input(seed):
    return np.random.default_rng(seed).uniform(-6.0, 6.0, T)


def random_density(seed):
    return np.tril(np.random.default_rng(seed).uniform(0.0, 1.0, (N, N)))


def preisach_bound(density, offset=0.0):
    """Round-off bound of a Preisach output: it is a signed sum of the density entries (and the
    offset) that each implementation forms through at most 2N + 2 roundings per entry (cumulative
    sum along a play line, the sum over lines, doubling and the total), on values up to
    ``2 sum(density)``; twice for two independent implementations, and twice again for the
    smooth readout's interpolation inside a relay: ``16 (N + 1) eps (sum(density) + |offset|)``."""
    return 16 * (N + 1) * EPS * (density.sum() + abs(offset))


@pytest.mark.parametrize("smooth", [False, True])
@pytest.mark.parametrize("history", HISTORIES)
def test_preisach_play_loop_equals_jax(smooth, history):
    u, d, offset = random_input(1), random_density(2), 0.7
    op = Preisach(jnp.asarray(d), jnp.asarray(U_MIN), jnp.asarray(U_MAX), jnp.asarray(offset), smooth)
    y = np.asarray(op(jnp.asarray(u), None if history is None else jnp.asarray(history)))
    ref = offset + reference.preisach_play_loop(u, d, U_MIN, U_MAX, history, smooth, BLOCK)
    np.testing.assert_allclose(y, ref, rtol=0, atol=preisach_bound(d, offset))
    assert np.ptp(ref) > 0.5 * d.sum()  # the input runs the loop through most of the plane


@pytest.mark.parametrize("history", HISTORIES)
def test_preisach_play_loop_equals_relay_grid(history):
    """The play representation against the definition: every relay of the grid, every sample."""
    u, d = random_input(3), random_density(4)
    ref = reference.preisach_relay_grid(u, d, U_MIN, U_MAX, history)
    got = reference.preisach_play_loop(u, d, U_MIN, U_MAX, history, block=BLOCK)
    np.testing.assert_allclose(got, ref, rtol=0, atol=preisach_bound(d))


def test_smooth_preisach_play_loop_equals_spread_relays():
    """smooth=True against its definition, m sub-relays per relay: on each play line only the relay
    the play sits in is partly up, and the midpoint rule misses its up-fraction by at most 1/(2m),
    so ``|difference| <= sum_k max_j M[k, j] / m`` (``M[k, j] = density[j + k, j]``)."""
    u, d, m = random_input(5), random_density(6), 40
    got = reference.preisach_play_loop(u, d, U_MIN, U_MAX, smooth=True)
    bound = sum(max(d[j + k, j] for j in range(N - k)) for k in range(N)) / m
    assert np.abs(got - reference.preisach_spread_relays(u, d, U_MIN, U_MAX, m)).max() <= bound + (
        preisach_bound(d)
    )
    # not vacuous: the smooth output differs from the bare relays by more than the bound
    assert np.abs(got - reference.preisach_play_loop(u, d, U_MIN, U_MAX)).max() > 10 * bound


@pytest.mark.parametrize("history", HISTORIES)
def test_pi_play_loop_equals_jax_pi(history):
    """``pi_play_loop`` (``offset + play_loop(u, r, history) @ w``, the fair PI baseline) against
    the JAX PI operator;
    the plays are exact (max/min of ``u -+ r``), the readout sums N terms: ``2 N eps sum|w p|``."""
    rng = np.random.default_rng(7)
    r = np.concatenate([[0.0], np.sort(rng.uniform(0.1, 4.0, N - 1))])
    w, offset, u = rng.normal(0.0, 1.0, N), 1.3, random_input(8)
    y = PrandtlIshlinskii(jnp.asarray(r), jnp.asarray(w), jnp.asarray(offset))(
        jnp.asarray(u), None if history is None else jnp.asarray(history)
    )
    bound = 2 * (N + 1) * EPS * (abs(offset) + np.abs(reference.play_loop(u, r, history)) @ np.abs(w)).max()
    ref = reference.pi_play_loop(u, r, w, offset, history, BLOCK)
    np.testing.assert_allclose(np.asarray(y), ref, rtol=0, atol=bound)


@pytest.mark.parametrize("K", [None, 3])
def test_linear_recurrence_closed_form(K):
    """``z_n = a z_{n-1} + b`` with constant ``a``, ``b``: ``z_n = a^(n+1) z0 + b (1 - a^(n+1)) / (1 - a)``.
    Each step rounds twice on a contracting recurrence (|a| < 1), and the closed form rounds a
    few times per term: ``8 T eps`` times the largest |z|, ``|b| / (1 - a)`` and ``|z0|``."""
    n = np.arange(T)
    a, b, z0 = np.array([0.999, 0.9, 0.5]), np.array([0.3, -2.0, 1.0]), np.array([5.0, -1.0, 0.0])
    if K is None:
        a, b, z0 = a[0], b[0], z0[0]
        A, B = np.full(T, a), np.full(T, b)
        want = a ** (n + 1) * z0 + b * (1 - a ** (n + 1)) / (1 - a)
    else:
        A, B = np.tile(a, (T, 1)), np.tile(b, (T, 1))
        want = a ** (n + 1)[:, None] * z0 + b * (1 - a ** (n + 1)[:, None]) / (1 - a)
    got = reference.linear_recurrence(A, B, z0)
    assert got.shape == want.shape
    scale = np.maximum(np.abs(b / (1 - a)), np.abs(z0))
    np.testing.assert_allclose(got, want, rtol=0, atol=8 * T * EPS * np.max(scale))
