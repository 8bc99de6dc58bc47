"""The plays and the first-order lags as associative scans over time
(jaxafm.model.hysteresis.associative_plays, jaxafm.model.effects.associative_lags) against the
sample-by-sample scans: the same numbers and the same derivatives, and every play operator and
lag stage the same whichever path runs it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxafm.model import effects as E
from jaxafm.model import hysteresis as H
from jaxafm.model.scanner import default_scanner

ASSOCIATIVE = H.associative_plays
LAGS = E.associative_lags


def drive(T: int, seed: int) -> jax.Array:
    """A random walk with reversals of every size (minor loops in major ones), in V."""
    rng = np.random.default_rng(seed)
    return jnp.asarray(np.cumsum(rng.normal(0.0, 0.3, T)) + rng.normal(0.0, 0.05, T))


def traced_afresh(f, *args):
    """``f(*args)`` under a ``jit`` of its own, traced again on every call (a new function each
    time): which path runs, sequential or associative, is chosen while tracing."""
    return jax.jit(lambda *a: f(*a))(*args)


def sequential(u, radii, start):
    return jax.lax.scan(H._play_step(radii), start, u)[1]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_associative_plays_equal_the_sequential_ones_bit_for_bit(seed):
    """A clamp only selects one of its arguments, so both paths give the same floats."""
    u = drive(500, seed)
    radii = jnp.linspace(0.0, 2.0, 12)
    start = H.play_state(radii, jnp.asarray([0.0, 3.0, -1.0]))  # a start with a history
    np.testing.assert_array_equal(H.associative_plays(u, radii, start), sequential(u, radii, start))


def test_their_gradients_agree_with_each_other_and_with_finite_differences():
    """d(loss)/d(drive) and d(loss)/d(radii) of a PI readout by both paths, and against central
    differences (float64, step 1e-6 V: the plays are piecewise linear, so away from a kink the
    differences are exact to round-off; the drive is random, so no sample sits on one)."""
    u = drive(200, 3)
    radii = jnp.linspace(0.1, 1.5, 8)
    w = jnp.linspace(1.0, 0.3, 8)
    target = jnp.sin(jnp.arange(200) / 9.0)

    def loss(path, u, radii):
        start = H.play_state(radii, u[:1])
        return jnp.sum((path(u, radii, start) @ w - target) ** 2)

    ga = jax.jit(jax.grad(lambda u, r: loss(H.associative_plays, u, r), argnums=(0, 1)))(u, radii)
    gs = jax.jit(jax.grad(lambda u, r: loss(sequential, u, r), argnums=(0, 1)))(u, radii)
    along = jax.jit(lambda u: loss(sequential, u, radii))
    for a, s in zip(ga, gs):
        np.testing.assert_allclose(a, s, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(s))))
    h = 1e-6
    for i in (5, 77, 150):
        e = jnp.zeros_like(u).at[i].set(h)
        fd = (along(u + e) - along(u - e)) / (2 * h)
        assert float(ga[0][i]) == pytest.approx(float(fd), rel=1e-6, abs=1e-6)


@pytest.mark.parametrize(
    "operator",
    [
        lambda: H.PrandtlIshlinskii.with_loop_width(10, 20.0, 10_000.0, 0.15),
        lambda: default_scanner().x.hysteresis,
        lambda: H.Preisach.uniform(8, -10.0, 10.0, total=5_000.0),
    ],
    ids=["pi", "gpi", "preisach"],
)
def test_every_play_operator_is_the_same_on_the_time_parallel_path(operator, monkeypatch):
    """The operators run through play_map (or play): forced onto the associative path on this
    CPU, their outputs equal the sequential path's to round-off of the readout's sums."""
    op = operator()
    u = 8.0 * jnp.sin(jnp.linspace(0.0, 12.0, 400)) * jnp.linspace(1.0, 0.2, 400)
    plain = np.asarray(op(u))
    ran = []
    monkeypatch.setattr(H, "time_parallel", lambda: True)
    monkeypatch.setattr(H, "associative_plays", lambda *a: ran.append(1) or ASSOCIATIVE(*a))
    parallel = np.asarray(op(u))
    assert ran, "the associative path did not run"
    np.testing.assert_allclose(parallel, plain, rtol=1e-12, atol=1e-9)


def lag_inputs(T: int = 500, seed: int = 0) -> tuple:
    """A random-walk drive (nm) on irregular sample times (s) through lags from 1 ms to 1000 s
    (a creep bank's span and a rate lag's), started off rest."""
    rng = np.random.default_rng(seed)
    t = jnp.asarray(np.cumsum(rng.uniform(1e-3, 2e-2, T)))
    v = jnp.asarray(np.cumsum(rng.normal(0.0, 1.0, T)))
    return v, t, jnp.logspace(-3, 3, 9), jnp.asarray(rng.normal(0.0, 5.0, 9))


def test_associative_lags_equal_the_sequential_ones_and_so_do_their_gradients(monkeypatch):
    """Affine steps compose into affine steps: the associative scan gives the sequential lags to
    round-off (the sums run in another order), and so does the gradient of a loss with respect
    to the drive, the time constants and the start."""
    v, t, taus, z0 = lag_inputs()
    w = jnp.linspace(0.2, 1.0, 9)

    def loss(v, taus, z0):
        out, z = E.lowpass(v, t, taus, z0, None, w)
        return jnp.sum(jnp.sin(out / 50.0)) + jnp.sum(z)

    def both(v, taus, z0):
        return E.lowpass(v, t, taus, z0, None, w), jax.grad(loss, (0, 1, 2))(v, taus, z0)

    plain = traced_afresh(both, v, taus, z0)
    monkeypatch.setattr(E, "time_parallel", lambda: True)
    ran = []
    monkeypatch.setattr(E, "associative_lags", lambda *a: ran.append(1) or LAGS(*a))
    parallel = traced_afresh(both, v, taus, z0)
    assert ran, "the associative path did not run"
    for a, b in zip(jax.tree.leaves(parallel), jax.tree.leaves(plain)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(b))))


def test_a_step_through_the_associative_lags_is_the_closed_form(monkeypatch):
    """A step ``d0`` at ``t[0]`` from rest: ``z_k = d0 (1 - exp(-(t - t0) / tau_k))`` exactly."""
    monkeypatch.setattr(E, "time_parallel", lambda: True)
    t = jnp.linspace(0.0, 50.0, 1001)
    taus = jnp.asarray([0.1, 3.0, 40.0])
    d0 = 7.0
    _, z = E.lowpass(jnp.full(t.shape, d0), t, taus, jnp.zeros(3), t0=-1e-12)
    Z = E.associative_lags(jnp.full(t.shape, d0), jnp.diff(t, prepend=-1e-12), taus, jnp.zeros(3))
    np.testing.assert_allclose(
        Z, d0 * (1 - np.exp(-(np.asarray(t)[:, None] + 1e-12) / np.asarray(taus))), atol=1e-12
    )
    np.testing.assert_allclose(z, Z[-1], atol=1e-12)


LAG_STAGES = {
    "creep": E.Creep.logarithmic(0.02),
    "rate_dependence": E.RateDependence(jnp.asarray(2e-3)),
    "rate_dependence, linear hold": E.RateDependence(jnp.asarray(2e-3), hold="linear"),
}


@pytest.mark.parametrize("stage", LAG_STAGES)
def test_every_lag_stage_is_the_same_on_the_time_parallel_path(stage, monkeypatch):
    """Creep and the rate lag (either hold): forced onto the associative path on this CPU, their
    outputs equal the sequential path's to round-off."""
    module = LAG_STAGES[stage]
    v, t, _, _ = lag_inputs(seed=1)
    plain = np.asarray(module(v, t))
    monkeypatch.setattr(E, "time_parallel", lambda: True)
    np.testing.assert_allclose(np.asarray(module(v, t)), plain, rtol=1e-12, atol=1e-10)


MODE = E.associative_mode


def test_the_associative_mode_equals_the_sequential_one_and_so_do_its_gradients(monkeypatch):
    """The vibration mode's steps are affine in its (position, velocity) state, 2 x 2 maps that
    compose into 2 x 2 maps: the associative scan gives the sequential positions and final state
    to round-off, and so does the gradient of a loss with respect to the drive, the frequency,
    the damping and the start; both gradients agree with central differences."""
    v, t, _, _ = lag_inputs(seed=2)
    t = t / 10  # 0.1-2 ms a sample: a 200 Hz mode rings over tens of samples
    start = jnp.asarray([3.0, -2e3])

    def loss(v, frequency, damping, start):
        out, s = E.Vibration(frequency, damping).run(v, t, start, t[0] - 1e-3)
        return jnp.sum(jnp.sin(out / 20.0)) + s[0] + 1e-3 * s[1]

    args = (v, jnp.asarray(200.0), jnp.asarray(0.05), start)

    def both(*a):
        return E.Vibration(a[1], a[2]).run(a[0], t, a[3], t[0] - 1e-3), jax.grad(loss, (0, 1, 2, 3))(*a)

    plain = traced_afresh(both, *args)
    monkeypatch.setattr(E, "time_parallel", lambda: True)
    ran = []
    monkeypatch.setattr(E, "associative_mode", lambda *a: ran.append(1) or MODE(*a))
    parallel = traced_afresh(both, *args)
    assert ran, "the associative path did not run"
    for a, b in zip(jax.tree.leaves(parallel), jax.tree.leaves(plain)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(b))))
    grads = parallel[1]
    compiled = jax.jit(loss)
    for k, h in ((1, 1e-3), (2, 1e-6)):
        up, down = list(args), list(args)
        up[k], down[k] = args[k] + h, args[k] - h
        fd = (compiled(*up) - compiled(*down)) / (2 * h)
        np.testing.assert_allclose(grads[k], fd, rtol=1e-5)


def test_a_step_through_the_associative_mode_is_the_closed_form(monkeypatch):
    """A step ``d0`` at ``t0`` from rest: ``x = d0 (1 - e^(-sigma t) (cos(wd t) + sigma / wd
    sin(wd t)))``, ``sigma = zeta w0``, ``wd = w0 sqrt(1 - zeta^2)``."""
    monkeypatch.setattr(E, "time_parallel", lambda: True)
    t = jnp.linspace(0.0, 0.05, 2001)
    f, zeta, d0 = 300.0, 0.1, 7.0
    x, _ = E.Vibration(jnp.asarray(f), jnp.asarray(zeta)).run(jnp.full(t.shape, d0), t, jnp.zeros(2), -1e-12)
    w0 = 2 * np.pi * f
    sigma, wd = zeta * w0, w0 * np.sqrt(1 - zeta**2)
    tt = np.asarray(t) + 1e-12
    closed = d0 * (1 - np.exp(-sigma * tt) * (np.cos(wd * tt) + sigma / wd * np.sin(wd * tt)))
    np.testing.assert_allclose(x, closed, atol=1e-10 * d0)


def test_the_linear_hold_lag_equals_its_sequential_self_and_finite_differences_in_tau(monkeypatch):
    """The first-order-hold rate lag on both paths: outputs, final state and the gradient of a
    loss in ``tau`` and the drive agree to round-off, and the gradient in ``tau`` matches central
    differences, with sample times from ``tau / 2`` to ``10 tau``."""
    v, t, _, _ = lag_inputs(seed=3)

    def loss(tau, v):
        lag = E.RateDependence(tau, hold="linear")
        out, state = lag.run(v, t, jnp.asarray([v[0] + 1.0, v[0] - 2.0]), t[0] - 1e-3)
        return jnp.sum(jnp.sin(out / 30.0)) + state[0]

    tau = jnp.asarray(2e-3)

    def both(tau, v):
        return loss(tau, v), jax.grad(loss, argnums=(0, 1))(tau, v)

    plain = traced_afresh(both, tau, v)
    monkeypatch.setattr(E, "time_parallel", lambda: True)
    parallel = traced_afresh(both, tau, v)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(parallel)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)
    e = 1e-8
    compiled = jax.jit(loss)
    fd = (compiled(tau + e, v) - compiled(tau - e, v)) / (2 * e)
    assert float(plain[1][0]) == pytest.approx(float(fd), rel=1e-5)
