"""The simulated AFM: state carried between actions, raster geometry and timing, feedback lag,
drift in real time, press and line scans, range errors, jit/vmap/grad."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxafm.instrument.afm import (
    AFM,
    Raster,
    default_afm,
    line_scan,
    move,
    press,
    raster_scan,
    render,
)
from jaxafm.instrument.samples import Grating, Indented, Particles, Plane, Tip
from jaxafm.model.effects import Drift, FeedbackLag
from jaxafm.model.hysteresis import Linear
from jaxafm.model.scanner import Axis, Scanner, default_scanner

SENS = 500.0  # nm/V


def ideal_afm(**fields) -> AFM:
    """A perfect instrument: linear axes at exactly the nominal sensitivity, no tip, no lag."""
    axis = Axis(Linear(jnp.asarray(SENS), jnp.zeros(())))
    afm = AFM(Scanner(axis, axis), Tip(), jnp.full(2, SENS), dilate=False)
    return dataclasses.replace(afm, **fields)


GRATING = Grating(jnp.asarray(1000.0), jnp.asarray(100.0), edge_width=jnp.asarray(200.0))


def test_scanner_run_in_two_halves_equals_one_run():
    scanner = default_scanner().without("noise")
    scanner = eqx.tree_at(
        lambda s: s.drift, scanner, Drift(jnp.array([0.05, -0.03]), jnp.zeros(2), jnp.zeros(()))
    )
    t = jnp.linspace(0.0, 4.0, 401)
    u = 9 * jnp.stack([jnp.sin(2 * jnp.pi * t), jnp.cos(3 * jnp.pi * t) * jnp.exp(-t / 3)], axis=-1)
    history = jnp.array([[-10.0, -10.0], [10.0, 10.0]])
    whole = jax.jit(lambda u, t, k, h: scanner(u, t, key=k, history=h))(u, t, jax.random.key(0), history)
    state = scanner.initial_state(u[0], t[0], history)
    run = jax.jit(lambda u, t, s, k: scanner.run(u, t, s, k))
    first, state = run(u[:150], t[:150], state, jax.random.key(1))
    second, _ = run(u[150:], t[150:], state, jax.random.key(2))
    np.testing.assert_allclose(jnp.concatenate([first, second]), whole, rtol=0, atol=1e-9)


def test_scanner_run_refuses_to_go_back_in_time():
    scanner = default_scanner()
    state = scanner.initial_state(jnp.zeros(2), 5.0)
    with pytest.raises(ValueError, match="before the state's last sample"):
        scanner.run(jnp.zeros((3, 2)), jnp.array([1.0, 2.0, 3.0]), state, jax.random.key(0))


def test_afm_drive_checks_its_times_before_compiling():
    afm = ideal_afm()
    state = afm.initial_state(t0=2.0)
    with pytest.raises(ValueError, match="strictly increasing"):
        afm.drive(GRATING, jnp.zeros((3, 2)), jnp.array([3.0, 2.5, 4.0]), state)
    with pytest.raises(ValueError, match="before the state's last sample"):
        afm.drive(GRATING, jnp.zeros((3, 2)), jnp.array([1.0, 2.5, 4.0]), state)


def test_ideal_instrument_images_the_sample_at_the_nominal_pixels():
    afm = ideal_afm()
    raster = Raster((3000.0, 2000.0), 24, 6, line_rate=2.0, centre=(100.0, -50.0))
    scan = raster_scan(afm, GRATING, afm.initial_state(), raster)
    x0, y0 = raster.origin
    xs = x0 + 125.0 * np.arange(24)
    ys = y0 + 2000.0 / 6 * np.arange(6)
    assert np.allclose(raster.pixel_size, (125.0, 2000.0 / 6)) and np.isclose(x0, 100 - 1500 + 62.5)
    nominal = np.stack(np.meshgrid(xs, ys), axis=-1)
    for d in ("trace", "retrace"):
        np.testing.assert_allclose(getattr(scan, f"path_{d}"), nominal, atol=1e-9)
        np.testing.assert_allclose(getattr(scan, d), GRATING.height(jnp.asarray(nominal)), atol=1e-9)


def test_raster_timing_and_down_direction():
    afm = ideal_afm()
    raster = Raster((1000.0, 1000.0), 10, 4, line_rate=5.0, overscan=0.2, direction="down")
    state = afm.initial_state(t0=3.0)
    scan = raster_scan(afm, GRATING, state, raster, move_time=0.5)
    n = 10 + 2 * 2  # samples per direction with 2 over-scan samples at each end
    dt = 1 / (2 * 5.0 * n)
    assert np.isclose(raster.sample_time, dt)
    t = np.asarray(scan.t_trace)
    np.testing.assert_allclose(np.diff(t, axis=1), dt, rtol=1e-9)  # within a trace line
    # down: the first line scanned is the top row; each line takes 1 / line_rate
    np.testing.assert_allclose(t[::-1, 0] - t[-1, 0], np.arange(4) * 0.2, atol=1e-12)
    assert np.isclose(t[-1, 0], 3.0 + 0.5 + 3 * dt)  # after the move and 2 over-scan samples
    rt = np.asarray(scan.t_retrace)
    assert np.all(rt[:, 0] > rt[:, -1])  # the retrace reaches its left end last
    assert np.isclose(scan.state.scanner.t, rt[0, 0] + 2 * dt)  # the bottom line's retrace ends the scan


def test_feedback_lag_shifts_edges_by_speed_times_delay_in_opposite_directions():
    tau = 2e-3
    afm = ideal_afm(feedback=FeedbackLag(jnp.asarray(tau)))
    raster = Raster((4000.0, 100.0), 400, 1, line_rate=1.0)
    scan = raster_scan(afm, GRATING, afm.initial_state(), raster)
    dt, dx = raster.sample_time, raster.pixel_size[0]
    # a first-order lag held per sample trails a ramp by dt / (exp(dt / tau) - 1) s
    shift = dx / dt * dt / np.expm1(dt / tau)
    truth = np.asarray(GRATING.height(jnp.asarray(scan.path_trace[0])))
    x = np.asarray(scan.path_trace[0, :, 0])

    def rising_edges(z):  # x where z crosses half depth going up with x, by linear interpolation
        i = np.nonzero((z[:-1] < 50) & (z[1:] >= 50))[0]
        return x[i] + (50 - z[i]) / (z[i + 1] - z[i]) * dx

    ref = rising_edges(truth)
    assert ref.size >= 3
    np.testing.assert_allclose(rising_edges(np.asarray(scan.trace[0])) - ref, shift, atol=0.05)
    np.testing.assert_allclose(rising_edges(np.asarray(scan.retrace[0])) - ref, -shift, atol=0.05)


def test_a_default_instrument_without_z_lag_records_the_height_where_the_tip_is():
    # feedback_tau 0: no z lag, so every recorded height is the sample's height under the
    # tip's true position, seen through the tip, at the same sample (with the default 1 ms lag
    # the pulse is read late: test_feedback_lag_shifts_edges_...)
    afm = default_afm(feedback_tau=0.0).without("drift", "noise")
    assert "feedback_lag" not in afm.effects
    R = 30.0
    sample = Particles(jnp.array([[100.0, 50.0]]), jnp.array([R]))
    h, path, _ = line_scan(
        afm, sample, afm.initial_state(), jnp.array([-100.0, 50.0]), jnp.array([300.0, 50.0]), 401, 1000.0
    )
    assert float(jnp.max(h)) > R  # the line crosses the particle
    np.testing.assert_allclose(h, render(sample, afm.tip, path), atol=1e-9)


def test_drift_acts_in_real_time_between_scans():
    v = np.array([0.4, -0.2])  # nm/s
    afm = ideal_afm()
    afm = eqx.tree_at(
        lambda a: a.scanner.drift,
        afm,
        Drift(jnp.asarray(v), jnp.zeros(2), jnp.zeros(())),
        is_leaf=lambda n: n is None,
    )
    raster = Raster((2000.0, 2000.0), 16, 4, line_rate=2.0)
    first = raster_scan(afm, GRATING, afm.initial_state(), raster, key=jax.random.key(0))
    _, later = move(afm, GRATING, first.state, first.state.u, duration=100.0, key=jax.random.key(1))
    second = raster_scan(afm, GRATING, later, raster, key=jax.random.key(2))
    gap = np.asarray(second.t_trace - first.t_trace)
    np.testing.assert_allclose(second.path_trace - first.path_trace, gap[..., None] * v, atol=1e-9)


def test_press_leaves_an_indent_where_the_tip_really_is_and_a_rescan_finds_it():
    afm = default_afm().without("feedback_lag", "noise")
    sample = Indented.empty(Plane(), afm.tip, capacity=4)
    state = afm.initial_state()
    _, state = move(afm, sample, state, afm.nominal_volts(jnp.array([400.0, 300.0])), key=jax.random.key(0))
    sample, state, xy = press(afm, sample, state, 30.0, key=jax.random.key(1))
    assert int(sample.count) == 1
    assert np.isclose(sample.height(xy), -30.0)
    nominal = np.array([400.0, 300.0])
    assert 10 < np.linalg.norm(np.asarray(xy) - nominal) < 2000  # the scanner's error, not the wanted spot
    # a perfect instrument scanning a line through the true spot finds the pit there, 30 nm deep
    ideal = ideal_afm()
    h, path, _ = line_scan(
        ideal,
        sample,
        ideal.initial_state(),
        jnp.array([xy[0] - 100, xy[1]]),
        jnp.array([xy[0] + 100, xy[1]]),
        201,
        400.0,
    )
    i = int(np.argmin(np.asarray(h)))
    assert abs(float(path[i, 0] - xy[0])) <= 0.5 and np.isclose(h[i], -30.0, atol=0.1)


def test_press_needs_an_indentable_sample():
    afm = ideal_afm()
    with pytest.raises(TypeError, match="Indented.empty"):
        press(afm, GRATING, afm.initial_state(), 5.0)


def test_line_scan_over_a_particle_without_tip_gives_its_diameter():
    afm = ideal_afm()
    R = 40.0
    sample = Particles(jnp.array([[100.0, 50.0]]), jnp.array([R]))
    h, path, state = line_scan(
        afm, sample, afm.initial_state(), jnp.array([-200.0, 50.0]), jnp.array([400.0, 50.0]), 601, 1000.0
    )
    width = np.ptp(np.asarray(path[np.asarray(h) > 1e-9, 0]))
    assert abs(width - 2 * R) <= 2.0 + 1e-9  # 1 nm sampling, the ends at r = R are at zero height
    assert np.isclose(float(jnp.max(h)), 2 * R)
    assert np.allclose(state.u, afm.nominal_volts(jnp.array([400.0, 50.0])))
    # with the tip on, the particle looks wider (dilation) but no taller
    h_tip, _, _ = line_scan(
        dataclasses.replace(afm, dilate=True),
        sample,
        afm.initial_state(),
        jnp.array([-200.0, 50.0]),
        jnp.array([400.0, 50.0]),
        601,
        1000.0,
    )
    assert np.count_nonzero(np.asarray(h_tip) > 1e-6) > np.count_nonzero(np.asarray(h) > 1e-9) + 20
    assert float(jnp.max(h_tip)) <= 2 * R + 1e-6


def test_scan_outside_the_drive_range_is_refused():
    afm = default_afm()
    with pytest.raises(ValueError, match=r"beyond the scanner's range of \+-10 V"):
        raster_scan(afm, GRATING, afm.initial_state(), Raster((12000.0, 1000.0), 8, 2))
    with pytest.raises(ValueError, match="beyond the scanner's range"):
        line_scan(afm, GRATING, afm.initial_state(), jnp.zeros(2), jnp.array([0.0, 6000.0]), 10, 100.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(size=(0.0, 100.0)), "size must be > 0"),
        (dict(pixels=1), "pixels >= 2"),
        (dict(line_rate=0.0), "line_rate must be > 0"),
        (dict(overscan=-0.1), "overscan"),
        (dict(direction="left"), "direction"),
    ],
)
def test_bad_raster_settings_are_named(kwargs, match):
    settings = dict(size=(100.0, 100.0), pixels=8, lines=2)
    with pytest.raises(ValueError, match=match):
        Raster(**{**settings, **kwargs})


def test_effects_are_listed_and_switch_off():
    afm = default_afm()
    assert {"tip", "feedback_lag", "hysteresis", "creep", "drift", "noise"} <= afm.effects
    bare = afm.without("tip", "feedback_lag", "noise")
    assert not {"tip", "feedback_lag", "noise"} & bare.effects
    assert "hysteresis" in bare.effects
    with pytest.raises(ValueError, match="unknown effect"):
        afm.without("tilt")


def test_raster_is_jittable_vmappable_and_its_gradient_matches_finite_differences():
    afm = default_afm().without("noise", "drift")
    raster = Raster((3000.0, 1000.0), 16, 3, line_rate=4.0)
    state = afm.initial_state()

    def loss(coupling):
        a = eqx.tree_at(lambda m: m.scanner.coupling.xy, afm, coupling)
        return jnp.mean(raster_scan(a, GRATING, state, raster).trace)

    c0 = afm.scanner.coupling.xy
    g = jax.jit(jax.grad(loss))(c0)
    eps = 1e-4
    fd = (loss(c0 + eps) - loss(c0 - eps)) / (2 * eps)
    assert abs(float(g) - float(fd)) <= 1e-4 * abs(float(fd)) + 1e-6 and abs(float(fd)) > 1e-2

    phases = jnp.array([0.0, 250.0])
    batch = jax.vmap(
        lambda p: raster_scan(afm, eqx.tree_at(lambda s: s.phase, GRATING, p), state, raster).trace
    )(phases)
    one = raster_scan(afm, eqx.tree_at(lambda s: s.phase, GRATING, phases[1]), state, raster).trace
    np.testing.assert_allclose(batch[1], one, atol=1e-9)
