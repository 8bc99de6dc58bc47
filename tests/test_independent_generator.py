"""The independent record generator (tests/independent.py) against closed forms and known
properties of its models -- not against jaxafm."""

import numpy as np
import pytest
from independent import (
    DRIVE,
    EFFECTS,
    LEVELS,
    MAGNITUDES,
    cases,
    creep,
    drift_wander,
    make_case,
    make_drive,
    pi_operator,
    play_operators,
    preisach_operator,
    rate_dependence,
    vibration,
    wandering_cases,
)


def ramps(*points, step=0.01, turns=False):
    """Piecewise-linear input through ``points`` in steps of ``step`` V (each point hit exactly);
    with ``turns``, also the index of each point."""
    out, idx = [np.array([points[0]])], [0]
    for a, b in zip(points[:-1], points[1:]):
        n = max(int(round(abs(b - a) / step)), 1)
        out.append(np.linspace(a, b, n + 1)[1:])
        idx.append(idx[-1] + n)
    u = np.concatenate(out)
    return (u, idx) if turns else u


def test_play_on_a_ramp_is_exact():
    r = 1.5
    up = np.linspace(0.0, 6.0, 601)
    down = np.linspace(6.0, -6.0, 1201)[1:]
    u = np.concatenate([up, down])
    p = play_operators(u, [r])[:, 0]
    np.testing.assert_array_equal(p[: up.size][up <= r], 0.0)  # starts at u[0] = 0: dead travel
    np.testing.assert_allclose(p[: up.size][up >= r], up[up >= r] - r, atol=1e-12)
    pd = p[up.size :]
    np.testing.assert_allclose(pd[down >= 6.0 - 2 * r], 6.0 - r, atol=1e-12)  # held at the turnaround
    np.testing.assert_allclose(pd[down <= 6.0 - 2 * r], down[down <= 6.0 - 2 * r] + r, atol=1e-12)


def test_pi_major_loop_width_closed_form():
    radii = np.array([0.0, 0.5, 1.0, 1.5, 2.0])  # all plays move for |u| <= a - 2 max(r) = 1
    w = np.array([3.0, 1.0, 0.7, 0.4, 0.2])
    a = 5.0
    u = ramps(0.0, a, -a, a, -a, step=0.005)
    y = pi_operator(u, radii, w, offset=7.0)
    # last cycle: ascending -a -> a, then descending; compare branches at u = 0 and u = 1
    n_top = np.flatnonzero(u == a)[-1]
    n_bot = np.flatnonzero(u == -a)[-2]
    asc_u, asc_y = u[n_bot : n_top + 1], y[n_bot : n_top + 1]
    desc_u, desc_y = u[n_top:], y[n_top:]
    for x in (0.0, 1.0):
        width = np.interp(x, desc_u[::-1], desc_y[::-1]) - np.interp(x, asc_u, asc_y)
        assert width == pytest.approx(2 * np.sum(w * radii), rel=1e-9)
    assert y[n_top] - y[n_bot] == pytest.approx(2 * np.sum(w * (a - radii)), rel=1e-12)


PREISACH = dict(c0=0.0, sc=6.0, h0=1.5, sh=0.6, scale=1000.0, n=40)


def test_preisach_wiping_out():
    """Extrema inside a larger excursion are wiped out: once the input passes the largest inner
    maximum (5 V), the output is the one without the inner extrema."""
    u1, k1 = ramps(0.0, 8.0, -6.0, 5.0, -2.0, 3.0, 0.0, 9.0, -4.0, turns=True)
    u2, k2 = ramps(0.0, 8.0, -6.0, 9.0, -4.0, turns=True)
    y1, y2 = preisach_operator(u1, **PREISACH), preisach_operator(u2, **PREISACH)
    rise1, rise2 = slice(k1[6], k1[7] + 1), slice(k2[2], k2[3] + 1)  # the final rises to 9 V
    x = np.linspace(0.5, 9.0, 18)
    on1 = np.interp(x, u1[rise1], y1[rise1])
    on2 = np.interp(x, u2[rise2], y2[rise2])
    past = x > 5.0
    np.testing.assert_allclose(on1[past], on2[past], atol=1e-9)
    assert np.all(np.abs(on1[x < 3] - on2[x < 3]) > 10.0)  # lower down the histories differ
    np.testing.assert_allclose(y1[k1[7] :], y2[k2[3] :], atol=1e-9)  # and all that follows


def test_preisach_return_point_memory():
    """A minor loop closes: back at its starting input, the output returns to the same point."""
    u, k = ramps(-9.0, 7.0, -3.0, 4.0, 0.5, 4.0, -3.0, turns=True)
    y = preisach_operator(u, **PREISACH)
    assert y[k[3]] == pytest.approx(y[k[5]], abs=1e-9)  # 4 V, before and after the 4 -> 0.5 -> 4 loop
    assert y[k[2]] == pytest.approx(y[k[6]], abs=1e-9)  # -3 V, the larger loop closes too
    assert y[k[3]] - y[k[4]] > 1.0  # a real loop


def test_preisach_congruency():
    """Minor loops between the same input extrema are congruent whatever came before."""
    cycle = ramps(-2.0, 3.0, -2.0)[1:]
    loops = []
    for history in (ramps(0.0, 9.0, -2.0), ramps(0.0, -9.0, 6.0, -2.0)):
        u = np.concatenate([history, cycle])
        y = preisach_operator(u, **PREISACH)[history.size - 1 :]
        loops.append(y - y[0])
    np.testing.assert_allclose(loops[0], loops[1], atol=1e-9)
    assert np.ptp(loops[0]) > 10


def test_preisach_density_symmetric_loop():
    """A symmetric density and a symmetric drive give a point-symmetric major loop."""
    u = ramps(0.0, 9.0, -9.0, 9.0, step=0.05)
    y = preisach_operator(u, **(PREISACH | {"n": 100}))
    top = np.flatnonzero(u == 9.0)[-1]
    bot = np.flatnonzero(u == -9.0)[-1]
    asc_u, asc_y = u[bot : top + 1], y[bot : top + 1]
    desc_u, desc_y = u[np.flatnonzero(u == 9.0)[0] : bot + 1], y[np.flatnonzero(u == 9.0)[0] : bot + 1]
    x = np.linspace(-7, 7, 15)
    asc = np.interp(x, asc_u, asc_y)
    desc = np.interp(-x, desc_u[::-1], desc_y[::-1])
    np.testing.assert_allclose(asc, -desc, atol=0.02 * np.ptp(y))  # up to the relays' jitter


def test_rate_lag_step_response_is_exact():
    dt, tau = 1e-3, 0.004
    d = np.concatenate([[0.0], np.ones(100)])  # at rest at 0, step held from sample 1
    y = rate_dependence(d, tau, dt)
    n = np.arange(d.size)
    expected = np.where(n >= 1, 1 - np.exp(-(n - 1) * dt / tau), 0.0)
    np.testing.assert_allclose(y, expected, atol=1e-12)


def test_creep_step_response_per_decade():
    dt, gamma, d0 = 1e-3, 0.02, 100.0
    t = np.arange(200_001) * dt
    d = np.where(t > 0, d0, 0.0)
    y = creep(d, gamma, dt)
    tt = np.array([0.1, 1.0, 10.0, 100.0])
    yy = y[np.round(tt / dt).astype(int) + 1]
    slopes = np.diff(yy)  # per decade
    np.testing.assert_allclose(slopes, gamma * d0, rtol=0.03)  # the lag bank's ripple
    closed = d0 * (1 + gamma * np.log10(tt / 0.01))
    np.testing.assert_allclose(yy, closed, atol=0.5 * gamma * d0)  # "roughly": up to a constant
    with_constant = d0 * (1 + gamma * (np.log10(tt / 0.01) + np.euler_gamma / np.log(10) + 1 / 8))
    np.testing.assert_allclose(yy, with_constant, atol=0.05 * gamma * d0)


def test_vibration_step_overshoot_and_ringing():
    f0, zeta, dt = 300.0, 0.05, 1e-6
    p = np.concatenate([[0.0], np.ones(200_000)])
    x = vibration(p, f0, zeta, dt)
    overshoot = x.max() - 1.0
    assert overshoot == pytest.approx(np.exp(-np.pi * zeta / np.sqrt(1 - zeta**2)), rel=1e-3)
    crossings = np.flatnonzero(np.diff(np.sign(x[1:30_000] - 1.0)) != 0) * dt
    period = 2 * np.mean(np.diff(crossings))
    wd = 2 * np.pi * f0 * np.sqrt(1 - zeta**2)
    assert 2 * np.pi / period == pytest.approx(wd, rel=1e-3)
    assert x[-1] == pytest.approx(1.0, abs=1e-3)


def test_drive_and_cases_shape():
    t, u = DRIVE
    assert t.shape == (6000,) and u.shape == (6000, 2)
    assert np.allclose(np.diff(t), 1e-3)
    assert 8.9 < np.abs(u).max() <= 9.0 + 1e-12
    assert not np.allclose(u[:, 0], u[:, 1])
    t2, u2 = make_drive(1.0, 500.0)
    assert u2.shape == (500, 2)
    cs = cases(5, 20)
    assert len(cs) == len(EFFECTS) * len(LEVELS) * 5 + 20
    diff = [c["truth_hysteresis"] != c["nominal_kind"] for c in cs]
    assert abs(sum(diff) - len(cs) / 2) <= 0.5
    for c in cs:
        if c["effect"] == "asymmetry":
            assert c["truth_hysteresis"] == c["nominal_kind"] == "pi"
    kinds = {(c["truth_hysteresis"], c["nominal_kind"]) for c in cs if c["effect"] is not None}
    assert kinds == {("pi", "pi"), ("preisach", "preisach"), ("pi", "preisach"), ("preisach", "pi")}


def test_make_case_truth_and_control():
    short = make_drive(0.5, 1000.0)
    c = make_case(None, "control", 3, "pi", drive=short)
    d = make_case("coupling", "high", 3, "pi", drive=short)
    assert c["d"].shape == (500, 2) and c["truth"]["effect"] is None
    c_mag = d["truth"]["effect_parameters"]["c"]
    assert 0.8 * MAGNITUDES["coupling"][2] <= c_mag <= 1.2 * MAGNITUDES["coupling"][2]
    x, y = c["d"][:, 0] - c["truth"]["offsets_nm"][0], c["d"][:, 1] - c["truth"]["offsets_nm"][1]
    # same seed: same hysteresis and noise; coupling acts on the noise-free outputs
    assert np.sqrt(np.mean((d["d"][:, 0] - c["d"][:, 0] - c_mag * y) ** 2)) < 0.05 * c_mag * np.std(y) + 0.1
    assert (
        np.sqrt(np.mean((d["d"][:, 1] - c["d"][:, 1] + 0.6 * c_mag * x) ** 2)) < 0.1 * c_mag * np.std(x) + 0.1
    )
    a = make_case("asymmetry", "middle", 3, "preisach", drive=short)
    assert a["truth"]["hysteresis"] == "pi"
    for axis in c["truth"]["axes"]:
        assert 0.10 <= axis["width_fraction"] <= 0.25


def test_the_relay_grid_converges_to_the_continuous_density_as_it_refines():
    """The same Preisach case on grids of 100 and 200 cells a side and with the density
    continuous over the plane (a closed form in the error function, one play per relay width):
    the same draws (density, offsets, noise), and the grid's output converges to the continuous
    one, as a stratified sample of a smooth density does (each relay's jump, at a random point
    of its cell, smaller on the finer grid); what the 100-cell grid adds is small against the
    output's span but not against the 2 nm noise."""
    short = make_drive(0.5, 1000.0)
    got = {n: make_case(None, "control", 5, "preisach", drive=short, relays=n) for n in (100, 200, None)}
    assert got[100]["truth"] == got[None]["truth"]
    rough = {n: np.sqrt(np.mean((got[n]["d"] - got[None]["d"]) ** 2)) for n in (100, 200)}
    assert rough[100] > 2 * rough[200] > 0
    assert 0.5 < rough[100] < 0.01 * np.ptp(got[None]["d"])


@pytest.mark.parametrize("kind", ["walk", "ou"])
def test_drift_wander_spreads_as_its_process_says(kind):
    """Over 2000 draws at uneven times: a walk of sigma nm/sqrt(s) has variance sigma^2 t; an
    Ornstein-Uhlenbeck process from 0 has sigma^2 (1 - exp(-2 t / tau)) and lag covariance
    exp(-|dt| / tau) times the earlier variance. 2000 draws: a variance's relative standard
    error is sqrt(2 / 2000) = 3 %, a covariance's sqrt((var_i var_j + cov^2) / 2000); bounds of
    4 of them."""
    rng = np.random.default_rng(0)
    t = np.r_[0.0, np.cumsum(rng.uniform(0.5, 1.5, 40))]
    sigma, tau = 3.0, 10.0
    w = np.stack([drift_wander(t, kind, sigma, tau, rng) for _ in range(2000)])
    assert np.all(w[:, 0] == 0)
    var = w[:, 1:].var(axis=0)
    if kind == "walk":
        np.testing.assert_allclose(var, sigma**2 * t[1:], rtol=0.12)
    else:
        expected = sigma**2 * (1 - np.exp(-2 * t[1:] / tau))
        np.testing.assert_allclose(var, expected, rtol=0.12)
        i, j = 10, 30
        cov, truth = np.mean(w[:, i] * w[:, j]), np.exp(-(t[j] - t[i]) / tau) * expected[i - 1]
        se = np.sqrt((expected[i - 1] * expected[j - 1] + truth**2) / len(w))
        assert cov == pytest.approx(truth, abs=4 * se)


def test_a_wandering_drift_adds_its_process_to_the_straight_drift():
    """The same seed with and without a wander differs by the wander alone, ``w[0] = 0``."""
    plain = make_case("drift", "middle", 5, "pi")
    walked = make_case("drift", "middle", 5, "pi", wander="walk")
    w = walked["d"] - plain["d"]
    assert np.all(w[0] == 0) and walked["truth"]["effect_parameters"]["wander"]["sigma"] == 5.0
    assert np.std(np.diff(w[:, 0])) == pytest.approx(5.0 * np.sqrt(1e-3), rel=0.1)  # 6000 steps: 2 %


def test_wandering_cases_are_balanced():
    cs = wandering_cases(12, 20)
    assert len(cs) == 3 * 3 * 12 + 20 and len({c["seed"] for c in cs}) == len(cs)
    assert sum(c["effect"] is None for c in cs) == 20
    assert all(c["nominal_kind"] == "pi" for c in cs)
    assert sum(c["truth_hysteresis"] == "preisach" for c in cs) == len(cs) // 2
