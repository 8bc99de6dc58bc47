"""Tests of the rate-independent hysteresis operators (jaxafm.model.hysteresis).

Every expected value comes from outside the code under test: Preisach
properties (wiping-out, congruency of minor loops, saturation), the NumPy
reference implementations in ``tests/reference.py``, closed forms, analytic
inverses checked by composition, central finite differences, and parameters
recovered from simulated noisy data by ordinary least squares.

All sequences have the same length ``T`` and all PI operators ``N_PI`` plays,
all Preisach planes ``N_LEVELS`` levels, so the jitted functions compile only a
handful of times.
"""

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference

from jaxafm import Deadzone, GeneralizedPI, PrandtlIshlinskii, Preisach
from jaxafm.model.hysteresis import play

T = 600  # samples in every input sequence
N_PI = 8  # plays of every PI operator
N_LEVELS = 10  # levels of every Preisach plane
U_MIN, U_MAX = -5.2, 4.9  # Preisach plane; relay centres are not on the 0.05 V grid below
GRID = 0.05  # V, step of the turning-point paths


def strong(tree):
    """Every float array as a strongly typed float64 array, so jitted calls do not recompile
    for weak types (``jnp.asarray(1.0)``, ``jnp.full(T, 1.0)``)."""
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=jnp.float64) if eqx.is_inexact_array(x) else x, tree)


@eqx.filter_jit
def _run(op, u, history):
    return op(u, history)


def run(op, u, history=None):
    """``op(u, history)``, jitted once per operator structure and input shape."""
    return _run(strong(op), strong(jnp.asarray(u)), None if history is None else strong(jnp.asarray(history)))


# ---------------------------------------------------------------- helpers


def path(points, length=T, h=GRID):
    """Monotone ramps through ``points`` on the grid ``k * h`` (k integer), padded in front.

    Every sample is ``k * h`` for an integer ``k``, so two paths through the
    same voltages hold bitwise-identical samples there. The front padding
    repeats ``points[0]``; plays start there, so it changes no state.
    """
    ks = [int(round(p / h)) for p in points]
    seq = [ks[0]]
    for a, b in zip(ks[:-1], ks[1:]):
        step = 1 if b > a else -1
        seq.extend(range(a + step, b + step, step))
    if len(seq) > length:
        raise AssertionError(f"path needs {len(seq)} samples > {length}")
    seq = [ks[0]] * (length - len(seq)) + seq
    return jnp.asarray(np.array(seq, dtype=float) * h)


def random_density(seed, n=N_LEVELS):
    rng = np.random.default_rng(seed)
    return np.tril(rng.uniform(0.0, 1.0, (n, n)))


def preisach(density, smooth, offset=0.7):
    return Preisach(jnp.asarray(density), jnp.asarray(U_MIN), jnp.asarray(U_MAX), jnp.asarray(offset), smooth)


def random_pi(seed, positive=True, offset=0.4):
    rng = np.random.default_rng(seed)
    r = np.concatenate([[0.0], np.sort(rng.uniform(0.1, 4.0, N_PI - 1))])
    if positive:
        w = np.concatenate([[rng.uniform(0.5, 1.5)], rng.uniform(0.0, 0.5, N_PI - 1)])
    else:
        w = rng.normal(0.0, 1.0, N_PI)
    return PrandtlIshlinskii(jnp.asarray(r), jnp.asarray(w), jnp.asarray(offset))


def random_walk(seed, scale=0.4, amplitude=5.0):
    rng = np.random.default_rng(seed)
    u = np.cumsum(rng.normal(0.0, scale, T))
    return jnp.asarray(amplitude * u / np.max(np.abs(u)))


def pi_like_operators():
    """Operators for the Preisach-property tests: Preisach (both kinds) and PI."""
    return {
        "preisach_smooth": preisach(random_density(1), True),
        "preisach_relays": preisach(random_density(1), False),
        "pi": random_pi(2),
    }


OPS = pi_like_operators()


# ---------------------------------------------------------------- 1. wiping-out


@pytest.mark.parametrize("name", sorted(OPS))
def test_wiping_out_fig3(name):
    """Fig. 3: after {u1, u2, u3, u4, u5} with u3 < u5 < u1 the output equals that after {u1, u2, u5}.

    u1 = 4 (max), u2 = -4 (min), u3 = 2 < u1, u4 = -1 > u2, u5 = 3 wipes out (u3, u4).
    Not only the end point: every sample of the last ramp with u >= u3 must agree.
    """
    op = OPS[name]
    ya = run(op, path([0.0, 4.0, -4.0, 2.0, -1.0, 3.0]))
    yb = run(op, path([0.0, 4.0, -4.0, 3.0]))
    k = int(round((3.0 - 2.0) / GRID)) + 1  # samples at u = 2.00 .. 3.00 at the end of both
    scale = float(np.ptp(np.asarray(ya)))
    np.testing.assert_allclose(ya[-k:], yb[-k:], rtol=0, atol=1e-12 * scale)
    # before the last ramp passes u3 the (u3, u4) loop is still remembered: at u = 0
    j = int(round(2.0 / GRID))
    assert abs(float(ya[-k - j] - yb[-k - j])) > 1e-4 * scale


@pytest.mark.parametrize("name", sorted(OPS))
def test_no_wiping_out_below_u3(name):
    """Negative control: u5 = 1.2 < u3 = 2 does not wipe out (u3, u4), so the outputs differ.

    (Relays with alpha in (1.2, 2] and beta in [-4, -1) are up after the first
    sequence and down after the second; the plane has relays there.)
    """
    op = OPS[name]
    ya = run(op, path([0.0, 4.0, -4.0, 2.0, -1.0, 1.2]))
    yb = run(op, path([0.0, 4.0, -4.0, 1.2]))
    scale = float(np.ptp(np.asarray(ya)))
    assert abs(float(ya[-1] - yb[-1])) > 1e-3 * scale


# ---------------------------------------------------------------- 2. congruency


@pytest.mark.parametrize("name", sorted(OPS))
def test_minor_loops_congruent(name):
    """Minor loops u_a -> u_b -> u_a from different histories differ by a constant shift.

    Both histories end descending to u_a = -1.5 from a maximum above u_b = 1,
    so every relay with alpha <= u_b is in the same state at the loop start and
    only relays with alpha > u_b (which the loop never touches) differ.
    """
    op = OPS[name]
    loop = [-1.5, 1.0, -1.5]
    y1 = run(op, path([0.0, 4.5] + loop))
    y2 = run(op, path([0.0, -4.0, 3.0, -2.5, 2.0] + loop))
    n = 2 * int(round(2.5 / GRID)) + 1
    l1, l2 = np.asarray(y1[-n:]), np.asarray(y2[-n:])
    d = l1 - l2
    loop_size = np.ptp(l1)
    assert loop_size > 0.05 * np.ptp(np.asarray(y1))  # a real loop, not a flat line
    assert np.ptp(d) <= 1e-9 * loop_size
    # the histories really left different states (else the test proves nothing)
    assert abs(d.mean()) > 1e-3 * loop_size


# ---------------------------------------------------------------- 3. relay grid


@pytest.mark.parametrize("history", [None, (0.0, 3.6), (-6.0, 5.5, -1.3)])
def test_preisach_relays_equal_numpy_relay_grid(history):
    rng = np.random.default_rng(3)
    u = rng.uniform(-6.0, 6.0, T)
    d = random_density(4)
    h = None if history is None else jnp.asarray(history)
    y = run(preisach(d, False, offset=0.0), jnp.asarray(u), h)
    ref = reference.preisach_relay_grid(u, d, U_MIN, U_MAX, history)
    np.testing.assert_allclose(np.asarray(y), ref, rtol=0, atol=1e-10 * d.sum())


@pytest.mark.parametrize("turns", [(0.0, -3.5, 0.0), (0.0, 4.5, -3.5, 2.5, -1.5, 0.5)])
def test_smooth_preisach_continuous_at_exact_switching_inputs(turns):
    """Turning points exactly on relay centres (0.5 V steps on a 10-level [-5, 5] V plane):
    the smooth model's output equals its limit from inputs nudged 1e-9 V off the centres
    (the bare relay grid settles such ties by rounding, as its docstring says)."""
    d = np.tril(np.ones((N_LEVELS, N_LEVELS)))
    op = Preisach(jnp.asarray(d), jnp.asarray(-5.0), jnp.asarray(5.0), jnp.asarray(0.0), True)
    ramps = [np.linspace(a, b, 21)[1:] for a, b in zip(turns[:-1], turns[1:])]
    u = np.concatenate([np.full(T - 20 * len(ramps), turns[0])] + ramps)
    y = np.asarray(run(op, jnp.asarray(u)))
    for nudge in (1e-9, -1e-9):
        y_near = np.asarray(run(op, jnp.asarray(u + nudge)))
        np.testing.assert_allclose(y, y_near, rtol=0, atol=1e-6 * d.sum())


# ---------------------------------------------------------------- 4. smooth vs relays, saturation


def test_relays_jump_by_row_mass_smooth_is_continuous():
    """On a rising ramp from below u_min the relay grid jumps once per alpha_i, by 2 * row mass.

    The smoothed model instead moves at most ``h * sum_k 2 max_j M[k, j] / D``
    per sample (each play line slides at rate 1, spreading relay mass over D).
    Both saturate at ``offset -+ total mass`` outside the plane.
    """
    d = random_density(5)
    offset = 0.7
    u = jnp.linspace(U_MIN - 1.0, U_MAX + 1.0, T)
    h = float(u[1] - u[0])
    D = (U_MAX - U_MIN) / N_LEVELS
    total = d.sum()

    y_relay = np.asarray(run(preisach(d, False, offset), u))
    jumps = np.diff(y_relay)
    big = jumps[np.abs(jumps) > 1e-12 * total]
    np.testing.assert_allclose(big, 2 * d.sum(axis=1), rtol=1e-12)  # one per row, in order
    assert (jumps > -1e-12).all()

    y_smooth = np.asarray(run(preisach(d, True, offset), u))
    # masses along play line k: relay (j + k, j)
    line_max = [max(d[j + k, j] for j in range(N_LEVELS - k)) for k in range(N_LEVELS)]
    bound = h * 2 * sum(line_max) / D
    steps = np.diff(y_smooth)
    assert steps.max() <= bound * (1 + 1e-12)
    assert steps.min() >= -1e-12 * total
    assert steps.max() < 0.25 * big.max()

    for y in (y_relay, y_smooth):
        np.testing.assert_allclose(y[0], offset - total, rtol=1e-13)
        np.testing.assert_allclose(y[-1], offset + total, rtol=1e-13)


def test_preisach_smooth_equals_spread_relays():
    """smooth=True against its definition (relay weight spread evenly over +-D/2 along the
    play line), evaluated as a grid of m = 80 sub-relays per relay.

    On each play line only the relay the play sits on is partly up, and the
    midpoint rule misses its up-fraction by at most 1/(2m): so
    |difference| <= sum_k max_j M[k, j] / m (M[k, j] = density[j + k, j]).
    """
    rng = np.random.default_rng(9)
    u = rng.uniform(-6.0, 6.0, T)
    d = random_density(8)
    m = 80
    y = np.asarray(run(preisach(d, True, offset=0.0), jnp.asarray(u)))
    line_max = [max(d[j + k, j] for j in range(N_LEVELS - k)) for k in range(N_LEVELS)]
    bound = sum(line_max) / m
    assert np.abs(y - reference.preisach_spread_relays(u, d, U_MIN, U_MAX, m)).max() <= bound * (1 + 1e-9)
    assert bound < 0.01 * np.ptp(y)


def test_preisach_roughness_is_the_second_differences_of_a_polynomial_density():
    """Closed forms, in units of ``total`` over the ``n (n + 1) / 2`` relays: a density linear in
    ``alpha`` and ``beta`` below the diagonal, with any ridge on the diagonal that is linear along
    it, has no roughness (the ridge is the reversible part, not continued by its neighbours);
    ``c i^2`` below the diagonal has ``2 c`` along ``alpha`` and 0 along ``beta``; ``c k^2`` on
    the diagonal ``2 c`` there."""
    n = N_LEVELS
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    below, diagonal = (i > j).astype(float), np.eye(n)
    unit = 3.0 / (n * (n + 1) / 2)  # total = 3 nm
    rough = lambda d: np.asarray(preisach(d * unit, True).roughness(3.0))
    along_alpha = np.sum((i - 1 > j) & (i + 1 < n))
    along_beta = np.sum((j >= 1) & (j + 1 < i))
    assert rough(np.zeros((n, n))).size == along_alpha + along_beta + n - 2
    flat = (2.0 + 0.3 * i - 0.2 * j) * below + (9.0 - 0.5 * i) * diagonal
    np.testing.assert_allclose(rough(flat), 0.0, atol=1e-12)
    curved = rough(0.25 * i**2 * below)
    np.testing.assert_allclose(curved[:along_alpha], 0.5, rtol=1e-12)
    np.testing.assert_allclose(curved[along_alpha:], 0.0, atol=1e-12)
    np.testing.assert_allclose(rough(0.25 * i**2 * diagonal)[along_alpha + along_beta :], 0.5, rtol=1e-12)


def test_far_outside_plane_saturates():
    """History far above / below the plane: every relay up / down (both kinds)."""
    d = random_density(6)
    for smooth in (True, False):
        op = preisach(d, smooth, offset=-1.0)
        up = run(op, jnp.full(T, 50.0))
        down = run(op, jnp.full(T, -50.0))
        np.testing.assert_allclose(up, -1.0 + d.sum(), rtol=1e-13)
        np.testing.assert_allclose(down, -1.0 - d.sum(), rtol=1e-13)


# ---------------------------------------------------------------- 5. PI vs reference


@pytest.mark.parametrize("seed", [0, 1])
def test_pi_equals_numpy_play_loop(seed):
    pi = random_pi(10 + seed, positive=False, offset=1.3)
    u = random_walk(20 + seed)
    y = run(pi, u)
    ref = reference.pi_loop(np.asarray(u), np.asarray(pi.thresholds), np.asarray(pi.weights), 1.3)
    np.testing.assert_allclose(np.asarray(y), ref, rtol=0, atol=1e-12 * np.abs(ref).max())


# ---------------------------------------------------------------- 6. analytic inverses


def output_history(op, history):
    """Forward outputs at the history points, from a run padded in front to length T.

    The padding repeats history[0], where every play starts, so it changes nothing,
    and the run reuses the compiled length-T function.
    """
    h = np.asarray(history, dtype=float)
    padded = np.concatenate([np.full(T - h.size, h[0]), h])
    return run(op, jnp.asarray(padded))[-h.size :]


def mixed_sign_pi():
    """Weights with negative entries whose partial sums stay positive (inverse exists)."""
    r = jnp.linspace(0.0, 3.5, N_PI)
    w = jnp.array([1.0, 0.3, -0.2, 0.25, -0.15, 0.1, 0.2, -0.1])
    assert (np.cumsum(np.asarray(w)) > 0).all()
    return PrandtlIshlinskii(r, w, jnp.asarray(-2.0))


@pytest.mark.parametrize("which", ["random", "mixed_sign"])
@pytest.mark.parametrize("history", [None, (0.0, 3.6, -2.0)])
def test_pi_inverse_round_trip(which, history):
    pi = random_pi(30) if which == "random" else mixed_sign_pi()
    inv = pi.inverse()
    u = random_walk(31)
    hu = None if history is None else jnp.asarray(history)
    hy = None if history is None else output_history(pi, history)  # forward *output* history
    y = run(pi, u, hu)
    np.testing.assert_allclose(run(inv, y, hy), u, rtol=0, atol=1e-9 * np.ptp(np.asarray(u)))

    rng = np.random.default_rng(32)
    y_want = jnp.asarray(np.cumsum(rng.normal(0, 0.3, T)))
    y_want = y_want * float(np.ptp(np.asarray(y))) / float(np.ptp(np.asarray(y_want)))
    u_cmd = run(inv, y_want, hy)
    np.testing.assert_allclose(
        run(pi, u_cmd, hu), y_want, rtol=0, atol=1e-9 * float(np.ptp(np.asarray(y_want)))
    )


def asymmetric_deadzone(centre=0.0):
    return Deadzone(
        jnp.asarray(1.0),
        jnp.array([1.0, 3.0]),
        jnp.array([-0.2, 0.35]),
        jnp.array([-1.0, -2.5]),
        jnp.array([0.25, -0.3]),
        jnp.asarray(centre),
    )


def deadzone_numpy(z, slope, upper, uw, lower, lw, c=0.0):
    """S(z) = c + g0 (z - c) + sum g_i max(z - c - d_i, 0) + sum g_-i min(z - c - d_-i, 0)."""
    x = z - c
    out = c + slope * x
    for d, g in zip(upper, uw):
        out = out + g * np.maximum(x - d, 0.0)
    for d, g in zip(lower, lw):
        out = out + g * np.minimum(x - d, 0.0)
    return out


@eqx.filter_jit
def _apply(op, z):
    return op(z)


def apply(op, z):
    return _apply(strong(op), strong(z))


@pytest.mark.parametrize("centre", [0.0, 1.5])
def test_deadzone_closed_form_and_inverse(centre):
    dz = asymmetric_deadzone(centre)
    z = np.linspace(-10.0, 10.0, T)
    s = np.asarray(apply(dz, jnp.asarray(z)))
    np.testing.assert_allclose(
        s,
        deadzone_numpy(z, 1.0, [1.0, 3.0], [-0.2, 0.35], [-1.0, -2.5], [0.25, -0.3], centre),
        rtol=0,
        atol=1e-12,
    )
    inv = dz.inverse()
    np.testing.assert_allclose(apply(inv, jnp.asarray(s)), z, rtol=0, atol=1e-12 * 20)
    np.testing.assert_allclose(apply(dz, apply(inv, jnp.asarray(z))), z, rtol=0, atol=1e-12 * 20)


@pytest.mark.parametrize("history, centre", [(None, 0.0), ((0.0, 3.6, -2.0), 0.0), (None, -0.5)])
def test_generalized_pi_inverse_round_trip(history, centre):
    gpi = GeneralizedPI(random_pi(40, offset=0.3), asymmetric_deadzone(centre))
    inv = gpi.inverse()
    u = random_walk(41)
    hu = None if history is None else jnp.asarray(history)
    hy = None if history is None else output_history(gpi, history)
    y = run(gpi, u, hu)
    # the output crosses dead-zone thresholds on both sides, so the inverse bends it back
    assert np.asarray(y).min() < centre - 2.5 and np.asarray(y).max() > centre + 1.0
    np.testing.assert_allclose(run(inv, y, hy), u, rtol=0, atol=1e-9 * np.ptp(np.asarray(u)))
    y_want = 0.9 * y[::-1]
    np.testing.assert_allclose(
        run(gpi, run(inv, y_want, hy), hu), y_want, rtol=0, atol=1e-9 * float(np.ptp(np.asarray(y)))
    )


# ---------------------------------------------------------------- 7. inverse existence


def test_pi_inverse_missing_raises_with_index():
    pi = PrandtlIshlinskii(
        jnp.array([0.0, 1.0, 2.0, 3.0]), jnp.array([1.0, -0.5, -0.6, 0.2]), jnp.asarray(0.0)
    )
    with pytest.raises(ValueError, match=r"i=2"):  # partial sums 1, 0.5, -0.1, 0.1
        pi.inverse()
    pi = PrandtlIshlinskii(jnp.array([0.0, 1.0]), jnp.array([1.0, -1.0]), jnp.asarray(0.0))
    with pytest.raises(ValueError, match=r"i=1"):  # zero partial sum: loading curve flat
        pi.inverse()


def test_pi_inverse_needs_zero_first_threshold():
    pi = PrandtlIshlinskii(jnp.array([0.1, 1.0]), jnp.array([1.0, 0.5]), jnp.asarray(0.0))
    with pytest.raises(ValueError, match="thresholds"):
        pi.inverse()


@pytest.mark.parametrize("side", ["upper", "lower"])
def test_deadzone_inverse_missing_raises(side):
    bad, ok = jnp.array([-0.5, -0.7]), jnp.array([0.1, 0.1])  # 1 - 0.5 - 0.7 < 0
    uw, lw = (bad, ok) if side == "upper" else (ok, bad)
    dz = Deadzone(jnp.asarray(1.0), jnp.array([1.0, 2.0]), uw, jnp.array([-1.0, -2.0]), lw)
    with pytest.raises(ValueError, match=side):
        dz.inverse()


# ---------------------------------------------------------------- 8. bad input


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("name", sorted(OPS))
def test_non_finite_input_rejected(bad, name):
    u = np.linspace(-1.0, 1.0, 20)
    u[7] = bad
    with pytest.raises(ValueError, match="input u"):
        OPS[name](jnp.asarray(u))


def test_non_finite_history_rejected():
    with pytest.raises(ValueError, match="history"):
        OPS["pi"](jnp.zeros(5), jnp.array([0.0, np.nan]))


def test_negative_density_rejected():
    d = random_density(7)
    d[3, 1] = -0.1
    with pytest.raises(ValueError, match="Preisach.density"):
        preisach(d, True)


def test_density_above_diagonal_rejected():
    d = random_density(7)
    d[1, 3] = 0.2
    with pytest.raises(ValueError, match=r"density\[1, 3\].*diagonal"):
        preisach(d, True)


def test_non_square_density_rejected():
    with pytest.raises(ValueError, match="square"):
        Preisach(jnp.zeros((3, 4)), jnp.asarray(0.0), jnp.asarray(1.0), jnp.asarray(0.0))


@pytest.mark.parametrize("thresholds", [[0.0, 0.5, 0.3], [0.0, 0.5, 0.5], [-0.1, 0.5, 1.0]])
def test_bad_thresholds_rejected(thresholds):
    with pytest.raises(ValueError, match="thresholds"):
        PrandtlIshlinskii(jnp.asarray(thresholds), jnp.ones(3), jnp.asarray(0.0))


def test_threshold_weight_shape_mismatch_rejected():
    with pytest.raises(ValueError, match="same shape"):
        PrandtlIshlinskii(jnp.array([0.0, 1.0]), jnp.ones(3), jnp.asarray(0.0))


@pytest.mark.parametrize("u_min, u_max", [(1.0, 1.0), (2.0, -2.0)])
def test_empty_plane_rejected(u_min, u_max):
    with pytest.raises(ValueError, match="u_max > u_min"):
        Preisach(jnp.eye(3), jnp.asarray(u_min), jnp.asarray(u_max), jnp.asarray(0.0))


# ---------------------------------------------------------------- 9. jit / vmap / grad


def test_vmap_pi_over_weight_batch_equals_loop():
    base = random_pi(50)
    u = random_walk(51)
    rng = np.random.default_rng(52)
    W = jnp.asarray(rng.uniform(0.0, 1.0, (5, N_PI)))

    def f(w):
        return PrandtlIshlinskii(base.thresholds, w, base.offset)(u)

    batched = jax.jit(jax.vmap(f))(W)
    for i in range(W.shape[0]):
        ref = reference.pi_loop(
            np.asarray(u), np.asarray(base.thresholds), np.asarray(W[i]), float(base.offset)
        )
        np.testing.assert_allclose(batched[i], ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def check_directional(f, grad, x, v, eps, rtol=1e-5):
    """``grad . v`` against the central difference ``(f(x + eps v) - f(x - eps v)) / (2 eps)``.

    All in NumPy (``f`` takes and the loss returns NumPy values), so nothing here is
    differentiated or compiled.
    """
    x, v = np.asarray(x), np.asarray(v, dtype=float)
    want = (f(x + eps * v) - f(x - eps * v)) / (2 * eps)
    got = float(np.vdot(np.asarray(grad), v))
    assert abs(want) > 1e-8
    assert abs(got - want) <= rtol * abs(want), (got, want)


def loss_np(y, c):
    """The scalar loss, in NumPy for the finite differences."""
    y = np.asarray(y)
    return float(np.sum(c * y) + 0.5 * np.mean(y**2))


def test_preisach_grad_matches_finite_differences():
    """jax.grad w.r.t. density, offset, u_min, u_max (smooth plane) vs central differences.

    The finite differences go through the plain forward model (fields replaced
    with ``eqx.tree_at``) and a NumPy loss, so they share no code with the gradient.
    """
    rng = np.random.default_rng(60)
    u = jnp.asarray(rng.uniform(-6.0, 6.0, T))
    c = rng.normal(0.0, 1.0, T)
    base = preisach(random_density(61), True, offset=0.3)
    fields = (lambda p: p.density, lambda p: p.offset, lambda p: p.u_min, lambda p: p.u_max)

    @jax.jit
    def grad(params):
        def loss(params):
            density, offset, u_min, u_max = params
            y = Preisach(density, u_min, u_max, offset, True)(u)
            return jnp.sum(c * y) + 0.5 * jnp.mean(y**2)

        return jax.grad(loss)(params)

    params = tuple(strong(f(base)) for f in fields)
    g = grad(params)

    def along(i):
        return lambda x: loss_np(run(eqx.tree_at(fields[i], base, jnp.asarray(x)), u), c)

    d = params[0]
    for _ in range(2):  # random lower-triangular directions
        v = np.tril(rng.normal(0.0, 1.0, (N_LEVELS, N_LEVELS)))
        check_directional(along(0), g[0], d, v, 1e-4)
    for i, j in [(0, 0), (7, 2)]:
        v = np.zeros((N_LEVELS, N_LEVELS))
        v[i, j] = 1.0
        check_directional(along(0), g[0], d, v, 1e-4)
    # offset, u_min, u_max (piecewise smooth: small step so no kink falls inside it)
    for i in (1, 2, 3):
        check_directional(along(i), g[i], params[i], 1.0, 1e-7)
    assert abs(float(g[2])) > 1e-3 and abs(float(g[3])) > 1e-3  # the plane edges matter


def test_pi_grad_matches_finite_differences():
    rng = np.random.default_rng(70)
    u = random_walk(71)
    c = rng.normal(0.0, 1.0, T)
    base = random_pi(72)

    @jax.jit
    def grad(params):
        def loss(params):
            y = PrandtlIshlinskii(params[0], params[1], base.offset)(u)
            return jnp.sum(c * y) + 0.5 * jnp.mean(y**2)

        return jax.grad(loss)(params)

    params = (base.thresholds, base.weights)
    gr, gw = grad(params)

    def by_w(w):
        return loss_np(run(eqx.tree_at(lambda p: p.weights, base, jnp.asarray(w)), u), c)

    def by_r(r):
        return loss_np(run(eqx.tree_at(lambda p: p.thresholds, base, jnp.asarray(r)), u), c)

    for _ in range(2):
        check_directional(by_w, gw, params[1], rng.normal(0.0, 1.0, N_PI), 1e-6)
        v = rng.normal(0.0, 1.0, N_PI)
        v[0] = 0.0  # r_0 = 0 is a kink
        check_directional(by_r, gr, params[0], v, 1e-7)
    for i in (1, 4, N_PI - 1):
        e = np.eye(N_PI)[i]
        check_directional(by_w, gw, params[1], e, 1e-6)
        check_directional(by_r, gr, params[0], e, 1e-7)


# ---------------------------------------------------------------- 10. parameter recovery


def test_pi_weights_recovered_by_least_squares():
    """Simulate y = PI[u] + noise, fit weights and offset by OLS on the play matrix, which
    NumPy builds sample by sample (``reference.play_loop``), not the plays under test.

    With Gaussian noise of std sigma, the OLS estimate is unbiased with
    covariance sigma^2 (A^T A)^-1, A = [P, 1]. Tolerance: every parameter within
    5 standard errors (two-sided probability ~6e-7 each, so a correct model
    fails essentially never; the seed is fixed anyway), the residual std within
    15% of sigma (its relative standard error is ~1/sqrt(2 T) = 3%), and,
    as a plain-number statement, each weight within 0.02 nm/V of the truth.
    """
    r = jnp.linspace(0.0, 3.5, N_PI)
    w_true = np.array([0.9, 0.35, 0.1, 0.25, 0.05, 0.2, 0.15, 0.3])
    pi = PrandtlIshlinskii(r, jnp.asarray(w_true), jnp.asarray(0.8))
    t = np.linspace(0.0, 1.0, T)
    # several amplitudes (decaying and growing envelopes) so every play is exercised
    u = 5.0 * np.sin(2 * np.pi * 6 * t) * (0.25 + 0.75 * np.abs(np.cos(2 * np.pi * 1.5 * t)))
    sigma = 0.02  # nm, about 0.2% of the ~10 nm output range
    rng = np.random.default_rng(80)
    y = np.asarray(run(pi, jnp.asarray(u))) + sigma * rng.normal(size=T)

    P = reference.play_loop(u, np.asarray(r))  # the design matrix from NumPy, not jaxafm's plays
    A = np.column_stack([P, np.ones(T)])
    theta, *_ = np.linalg.lstsq(A, y, rcond=None)
    se = sigma * np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    truth = np.concatenate([w_true, [0.8]])
    z = (theta - truth) / se
    assert np.abs(z).max() < 5.0, z
    resid = y - A @ theta
    assert abs(resid.std() / sigma - 1.0) < 0.15
    assert np.abs(theta[:-1] - w_true).max() < 0.02
    assert np.ptp(y) > 5.0


def test_an_eager_play_and_operator_are_compiled_once_per_shape(caplog):
    """``play`` and an operator called outside ``jit`` (a prediction, a fit's plays) reuse their
    compiled scans: a second call with new values of the same shapes compiles nothing (a scan
    step or readout made afresh each call was traced and compiled every time, and kept one more
    executable)."""
    u = jnp.sin(jnp.linspace(0.0, 9.0, T))
    other = jnp.cos(jnp.linspace(0.0, 5.0, T))
    pi = PrandtlIshlinskii(jnp.linspace(0.0, 0.9, N_PI), jnp.full(N_PI, 2.0), jnp.asarray(1.0))
    pi2 = PrandtlIshlinskii(jnp.linspace(0.0, 0.95, N_PI), jnp.full(N_PI, 3.0), jnp.asarray(0.0))
    first = (play(u, pi.radii()), pi(u), preisach(random_density(1), False)(u))
    compiled = (play(other, pi2.radii()), pi2(other), preisach(random_density(2), False, offset=0.1))
    with jax.log_compiles(True), caplog.at_level(logging.WARNING):
        again = (play(other, pi2.radii()), pi2(other), compiled[2](other))
    assert [a.shape for a in again] == [b.shape for b in first] == [(T, N_PI), (T,), (T,)]
    np.testing.assert_array_equal(again[1], compiled[1])
    assert not [r.getMessage()[:80] for r in caplog.records if "Compiling" in r.getMessage()]
