"""The independent lattice-image generator (tests/independent_lattice.py) against closed forms and
known properties of its own models -- not against jaxafm."""

import json

import numpy as np
import pytest
from independent_lattice import (
    Artefacts,
    Lattice,
    broadened_profile,
    draw_case,
    flatten,
    lag_ramp,
    log_creep,
    loop_width_closed_form,
    major_loop,
    make_axis,
    outline_distance,
    preisach,
    preisach_loop,
    relay_plane,
    rotation,
    tip_reach,
    tip_shape,
    topography,
    wall_profile,
    write_case,
)
from scipy import ndimage

LINEAR = {"loop_pct": 0, "tau_s": 0, "creep_per_decade": 0, "drift_nm_per_s": 0}


def ramps(*points, step=0.01):
    """Piecewise-linear input through ``points`` in steps of about ``step``, each point hit."""
    out = [np.array([points[0]])]
    for a, b in zip(points[:-1], points[1:]):
        out.append(np.linspace(a, b, max(int(round(abs(b - a) / step)), 1) + 1)[1:])
    return np.concatenate(out)


# ---------------------------------------------------------------------------- hysteresis
def test_preisach_runs_equal_the_relay_loop():
    """The run-by-run evaluation is the relay rule itself, on nested reversals and holds."""
    relays = relay_plane(1.5, 4.0, -1.0, 5.0, n=40, seed=3)
    rng = np.random.default_rng(0)
    turns = np.r_[0.0, 9.0, -8.0, rng.uniform(-7, 7, 12), 9.5, -9.5, 2.0]
    u = ramps(*turns, step=0.05)
    u = np.insert(u, 300, np.full(20, u[300]))  # a hold
    np.testing.assert_allclose(preisach(u, relays), preisach_loop(u, relays), atol=1e-12)


def test_preisach_loop_width_closed_form_and_monotone_branches():
    relays = relay_plane(1.5, 4.0, -1.0, 5.5, n=200, seed=1)
    amplitude = 8.0
    u, asc, desc = major_loop(relays, amplitude)
    assert np.all(np.diff(asc) >= 0) and np.all(np.diff(desc) >= 0)
    for x in (-4.0, -1.0, 0.0, 2.0, 5.0):
        i = np.argmin(np.abs(u - x))
        expected = loop_width_closed_form(u[i], amplitude, relays)
        assert desc[i] - asc[i] == pytest.approx(expected, abs=0.004)
        assert expected > 0.1


def test_preisach_branches_asymmetric_only_with_an_asymmetric_density():
    """A mirror-symmetric density gives a point-symmetric loop (``asc(u) + desc(-u)`` constant: the
    relays beyond both ends of the drive never switch and offset it), up to the relays' jitter;
    different up and down spreads do not."""
    gap = {}
    for name, (s_up, s_dn) in {"symmetric": (4.5, 4.5), "asymmetric": (3.0, 6.0)}.items():
        u, asc, desc = major_loop(relay_plane(1.5, s_up, -1.5, s_dn, n=200, seed=2), 9.0)
        gap[name] = np.ptp(asc + desc[::-1]) / (asc[-1] - asc[0])
    assert gap["symmetric"] < 0.002
    assert gap["asymmetric"] > 0.1


def test_axis_major_loop_span_and_width():
    relays = relay_plane(1.2, 4.0, -1.8, 5.0, n=150, seed=4)
    axis = make_axis(relays, gain_nm_per_v=3000.0, loop_pct=9.0, u_max=10.0)
    u, asc, desc = major_loop(relays, 10.0)
    p_asc = axis.reversible_nm_per_v * u + axis.hysteretic_nm * asc
    p_desc = axis.reversible_nm_per_v * u + axis.hysteretic_nm * desc
    assert p_asc[-1] - p_asc[0] == pytest.approx(2 * 10.0 * 3000.0, rel=1e-9)
    i = np.argmin(np.abs(u))
    assert (p_desc[i] - p_asc[i]) / (p_asc[-1] - p_asc[0]) == pytest.approx(0.09, rel=1e-9)
    assert axis.reversible_nm_per_v > 0


# ---------------------------------------------------------------------------- rate and creep
def test_rate_lag_is_exact_on_ramps():
    tau, h, v = 0.004, 0.001, 3.0
    t = np.arange(60) * h
    u = np.where(t <= 0.03, v * t, v * 0.03)  # a ramp from rest, then a hold
    y = lag_ramp(u, tau, h)
    ramp = v * (t - tau * (1 - np.exp(-t / tau)))
    at_end = v * (0.03 - tau * (1 - np.exp(-0.03 / tau)))
    hold = v * 0.03 + (at_end - v * 0.03) * np.exp(-(t - 0.03) / tau)
    np.testing.assert_allclose(y, np.where(t <= 0.03, ramp, hold), atol=1e-12)


def test_creep_after_a_step_follows_the_log_law():
    h, gamma, d0, t0 = 0.01, 0.015, 2000.0, 0.1
    t = np.arange(100_101) * h
    p = np.where(t >= 0.5, d0, 0.0)
    c = log_creep(p, gamma, h, t0)
    after = t >= 0.5
    np.testing.assert_allclose(c[after], d0 * (1 + gamma * np.log10(1 + (t[after] - 0.5) / t0)), rtol=1e-9)
    np.testing.assert_allclose(c[~after], 0.0, atol=1e-9)
    at = np.round((0.5 + np.array([10.0, 100.0, 1000.0])) / h).astype(int)
    np.testing.assert_allclose(np.diff(c[at]), gamma * d0, rtol=0.005)  # per decade, t >> t0


# ---------------------------------------------------------------------------- sample and tip
@pytest.mark.parametrize("shape,pits", [("round", True), ("square", False)])
def test_tip_broadening_equals_a_brute_force_dilation(shape, pits):
    """The 1-D reduction ``g(d)`` against ``max_s [z(p + s) - T(|s|)]`` over a dense disc of tip
    offsets s (0.25 nm apart) at points near the walls and corners: walls (80 deg) steeper than
    the tip's flank (75 deg), so the cone broadens them."""
    lat = Lattice(1000.0, 0.0, (0.0, 0.0), shape, pits, 200.0, 60.0, 100.0, 80.0, 10.0, 15.0)
    reach = tip_reach(lat.depth_nm, lat.tip_radius_nm, lat.tip_half_angle_deg)
    s = np.arange(-reach, reach + 0.125, 0.25)
    offsets = np.stack(np.meshgrid(s, s), -1).reshape(-1, 2)
    offsets = offsets[np.hypot(*offsets.T) <= reach]
    tip = tip_shape(np.hypot(*offsets.T), lat.tip_radius_nm, lat.tip_half_angle_deg)
    rng = np.random.default_rng(0)
    points = rng.uniform(-300, 300, (4000, 2))
    points = points[np.abs(outline_distance(points, lat)) < 60][:150]
    brute = np.array([np.max(wall_profile(outline_distance(p + offsets, lat), lat) - tip) for p in points])
    ours = topography(points, lat, broadened_profile(lat))
    np.testing.assert_allclose(ours, brute, atol=0.02 * lat.depth_nm)
    assert np.sqrt(np.mean((ours - brute) ** 2)) < 0.005 * lat.depth_nm
    bare = wall_profile(outline_distance(points, lat), lat)
    assert np.max(np.abs(ours - bare)) > 0.3 * lat.depth_nm  # the tip does broaden
    assert np.all(ours >= bare - 1e-9)  # and a dilation never lowers


# ---------------------------------------------------------------------------- images
def _linear_pixels(case, s, xy):
    """Pixel (col, row) of stage points through a case's linear scanner and the raster's nominal map."""
    sc = case["scanner"]
    gains = np.array([a.gain_nm_per_v for a in sc.axes])
    coupling = np.array([[1.0, sc.coupling[0]], [sc.coupling[1], 1.0]])
    volts = np.linalg.solve(coupling, xy.T).T / gains
    nominal = volts * case["meta"]["sensitivity_nm_per_v"][0] @ rotation(s.meta["angle_deg"])
    (w, h), n = s.meta["size_nm"], s.meta["pixels"]
    return (nominal + [w / 2, h / 2]) / [w / n, h / n] - 0.5


def _centroids(z, pits):
    """Height-weighted centres (col, row) of the features not touching the border."""
    weight = -z if pits else z
    labels, n = ndimage.label(weight > 1e-6)
    out = []
    for k in range(1, n + 1):
        rows, cols = np.nonzero(labels == k)
        if rows.min() > 0 and cols.min() > 0 and rows.max() < z.shape[0] - 1 and cols.max() < z.shape[1] - 1:
            r, c = ndimage.center_of_mass(weight, labels, k)
            out.append((c, r))
    return np.array(out)


@pytest.mark.parametrize(
    "feature,angle,direction", [("round_pillars", 0.0, "up"), ("square_pits", 90.0, "down")]
)
def test_linear_scanner_puts_features_at_the_mapped_sites(feature, angle, direction):
    case = draw_case(
        5,
        feature=feature,
        pixels=128,
        line_rates_hz=(1.0,),
        angles_deg=(angle,),
        direction=direction,
        magnitudes=LINEAR,
        artefacts=False,
    )
    s = case["scans"][0]
    expected = _linear_pixels(case, s, case["truth"]["sites_nm"])
    for z in (s.trace, s.retrace):
        found = _centroids(z, case["meta"]["pits"])
        assert len(found) >= 9
        err = np.min(np.linalg.norm(found[:, None] - expected[None], axis=-1), axis=1)
        assert np.max(err) < 0.1  # px: the centroid of a sampled feature with near-vertical walls
    np.testing.assert_allclose(s.trace, s.retrace, atol=1e-9)
    cols, rows = np.meshgrid(np.arange(128), np.arange(128))
    pixels = _linear_pixels(case, s, s.truth["tip_trace_nm"].reshape(-1, 2))
    np.testing.assert_allclose(pixels, np.stack([cols, rows], -1).reshape(-1, 2), atol=1e-9)  # exactly
    inside = ~np.isnan(s.truth["sites_px_trace"][:, 0])
    assert inside.sum() >= 16
    np.testing.assert_allclose(s.truth["sites_px_trace"][inside], expected[inside], atol=1e-6)


def test_rate_independent_without_the_lag_and_loop_grows_with_line_rate():
    rates = (0.5, 2.0, 4.0)
    common = dict(feature="round_pits", pixels=64, line_rates_hz=rates, angles_deg=(0.0,), artefacts=False)
    still = draw_case(
        7, magnitudes={"loop_pct": 8, "tau_s": 0, "creep_per_decade": 0, "drift_nm_per_s": 0}, **common
    )
    paths = [s.truth["tip_trace_full_nm"] for s in still["scans"]]
    np.testing.assert_allclose(paths[1], paths[0], atol=1e-6)
    np.testing.assert_allclose(paths[2], paths[0], atol=1e-6)
    tau = 2e-3
    lagged = draw_case(
        7, magnitudes={"loop_pct": 8, "tau_s": tau, "creep_per_decade": 0, "drift_nm_per_s": 0}, **common
    )
    shift, speed = [], []
    for s in lagged["scans"]:
        shift.append(_row_shift_px(flatten(s.retrace), flatten(s.trace)))
        tip = s.truth["tip_trace_full_nm"][:, :, 0]
        speed.append(np.mean(tip[:, -1] - tip[:, 0]) / (tip.shape[1] * s.meta["sample_time_s"]))
    px = lagged["scans"][0].meta["size_nm"][0] / 64
    assert shift[0] > 3 and np.all(np.diff(shift) > 0)  # a loop, growing with the line rate
    expected = 2 * tau * (np.array(speed) - speed[0]) / px
    np.testing.assert_allclose(np.array(shift) - shift[0], expected, rtol=0.15, atol=0.1)


def _row_shift_px(a, b):
    """The shift (px) that best lays ``b`` on ``a`` along the rows: ``b(x + s) = a(x)``."""
    a, b = a - a.mean(), b - b.mean()
    n = a.shape[1]
    xc = np.fft.irfft(np.fft.rfft(a, 4 * n) * np.conj(np.fft.rfft(b, 4 * n)), 4 * n).sum(0)
    xc = np.r_[xc[-n:], xc[: n + 1]]
    k = int(np.argmax(xc))
    y0, y1, y2 = xc[k - 1 : k + 2]
    return -(k - n + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2))


def test_trace_and_retrace_meet_at_the_line_reversals():
    case = draw_case(
        11,
        feature="round_pillars",
        pixels=64,
        line_rates_hz=(2.0,),
        angles_deg=(0.0,),
        artefacts=False,
        magnitudes={"tau_s": 0},
    )
    s = case["scans"][0]
    assert case["truth"]["scanner"]["axes"][0]["loop_pct"] >= 5
    tr, rt = s.truth["tip_trace_full_nm"][..., 0], s.truth["tip_retrace_full_nm"][..., 0]
    px = s.meta["size_nm"][0] / s.meta["pixels"]
    mid = tr.shape[1] // 2
    assert np.min(rt[:, mid] - tr[:, mid]) > 5 * px  # the loop, open in the middle of every line
    assert np.max(np.abs(rt[:, -1] - tr[:, -1])) < 0.5 * px  # closed where trace turns to retrace
    assert np.max(np.abs(tr[1:, 0] - rt[:-1, 0])) < 0.5 * px  # and where retrace turns to the next trace


def test_background_is_removed_by_a_plane_and_quadratic_fit():
    common = dict(
        feature="square_pits", pixels=64, line_rates_hz=(1.0,), angles_deg=(0.0,), magnitudes=LINEAR
    )
    clean = draw_case(13, artefacts=False, **common)["scans"][0]
    tilted = draw_case(
        13, artefacts=Artefacts(tilt_nm=350.0, tilt_direction_deg=30.0, bow_nm=-150.0), **common
    )
    s = tilted["scans"][0]
    assert np.ptp(s.trace - clean.trace) > 300
    for z, ref in ((s.trace, clean.trace), (s.retrace, clean.retrace)):
        np.testing.assert_allclose(flatten(z), ref, atol=1e-6)


def test_artefacts_spikes_saturation_offsets_noise():
    common = dict(
        feature="round_pillars", pixels=64, line_rates_hz=(1.0,), angles_deg=(0.0,), magnitudes=LINEAR
    )
    clean = draw_case(17, artefacts=False, **common)["scans"][0]
    art = Artefacts(line_offset_nm=5.0, noise_nm=0.0, spikes=3, saturated=2)
    s = draw_case(17, artefacts=art, **common)["scans"][0]
    spikes, saturated = s.truth["spikes"], s.truth["saturated"]
    assert spikes.sum() == 3 and saturated.sum() == 2
    images = np.stack([s.trace, s.retrace])
    np.testing.assert_array_equal(images[saturated], s.truth["ceiling_nm"])
    assert images.max() == s.truth["ceiling_nm"]
    diff = images - np.stack([clean.trace, clean.retrace])
    rows = np.median(diff, axis=2)  # (2, lines): one offset per line and direction
    depth = draw_case(17, artefacts=False, **common)["truth"]["lattice"]["depth_nm"]
    assert np.all(np.abs(diff[spikes] - rows[np.nonzero(spikes)[:2]]) >= depth * 0.99)
    plain = ~(spikes | saturated)
    np.testing.assert_allclose(diff[plain], np.broadcast_to(rows[..., None], diff.shape)[plain], atol=1e-9)
    assert 3.5 < np.std(rows) < 8.0 and np.corrcoef(rows)[0, 1] > 0.5  # shared by trace and retrace
    np.testing.assert_allclose(rows.T, s.truth["line_offsets_nm"], atol=1e-9)
    noisy = draw_case(17, artefacts=Artefacts(noise_nm=2.0), **common)["scans"][0]
    assert np.std(noisy.trace - clean.trace) == pytest.approx(2.0, rel=0.1)


def test_feedback_lag_moves_features_by_tau_along_each_line():
    """A first-order z lag moves each feature's first moment by tau: the trace's forward, the
    retrace's back, by ``tau / dt`` px (one nominal pixel per sample)."""
    common = dict(feature="round_pits", pixels=64, line_rates_hz=(2.0,), angles_deg=(0.0,), magnitudes=LINEAR)
    clean = draw_case(19, artefacts=False, **common)["scans"][0]
    tau = 0.5 * clean.meta["sample_time_s"]
    s = draw_case(19, artefacts=Artefacts(feedback_tau_s=tau), **common)["scans"][0]
    centres = _centroids(clean.trace, pits=True)
    assert len(centres) >= 9
    cols = np.arange(clean.trace.shape[1])
    for z, sign in ((s.trace, 1.0), (s.retrace, -1.0)):
        for c, r in centres:
            win = -z[int(round(r)) - 3 : int(round(r)) + 4, int(round(c)) - 6 : int(round(c)) + 7]
            moment = np.sum(win * cols[int(round(c)) - 6 : int(round(c)) + 7]) / np.sum(win)
            ref = -clean.trace[int(round(r)) - 3 : int(round(r)) + 4, int(round(c)) - 6 : int(round(c)) + 7]
            ref_moment = np.sum(ref * cols[int(round(c)) - 6 : int(round(c)) + 7]) / np.sum(ref)
            assert moment - ref_moment == pytest.approx(sign * tau / clean.meta["sample_time_s"], abs=0.01)


# ---------------------------------------------------------------------------- cases and files
def test_unidentifiable_cases_say_why():
    one = draw_case(23, pixels=32, unidentifiable="one_speed", artefacts=False)
    assert len(one["scans"]) == 1 and "rate" in one["truth"]["unidentifiable"]
    few = draw_case(23, pixels=64, unidentifiable="few_features", feature="square_pits", artefacts=False)
    assert len(few["scans"]) == 1 and len(few["truth"]["sites_nm"]) == 9
    assert few["scans"][0].meta["size_nm"][0] == pytest.approx(3 * few["meta"]["pitch_nm"])
    assert (
        draw_case(23, pixels=32, line_rates_hz=(1.0,), angles_deg=(0.0,))["truth"]["unidentifiable"] is None
    )
    series = draw_case(23, pixels=32, line_rates_hz=(1.0, 2.0), angles_deg=(0.0,), few_features=True)
    assert [s.meta["line_rate_hz"] for s in series["scans"]] == [1.0, 2.0]
    assert len(series["truth"]["sites_nm"]) == 9 and series["truth"]["unidentifiable"] is None
    with pytest.raises(ValueError, match="unidentifiable"):
        draw_case(23, unidentifiable="blurry")


def test_written_files_read_back_with_their_metadata(tmp_path):
    from jaxafm.instrument.images import read_image

    case = draw_case(29, pixels=32, line_rates_hz=(1.0, 4.0), angles_deg=(0.0, 90.0))
    again = draw_case(29, pixels=32, line_rates_hz=(1.0, 4.0), angles_deg=(0.0, 90.0))
    np.testing.assert_array_equal(case["scans"][3].retrace, again["scans"][3].retrace)  # one seed, one case
    written = write_case(case, tmp_path / "npz")
    doc = json.loads(written["data"].read_text())
    assert [e["line_rate_hz"] for e in doc["data"]["scans"]] == [1.0, 4.0, 1.0, 4.0]
    assert [e["angle_deg"] for e in doc["data"]["scans"]] == [0.0, 0.0, 90.0, 90.0]
    for (trace, retrace), s in zip(written["images"], case["scans"]):
        for path, z, direction in ((trace, s.trace, "trace"), (retrace, s.retrace, "retrace")):
            image = read_image(path)
            np.testing.assert_array_equal(image.z, z)
            assert image.size == pytest.approx(tuple(s.meta["size_nm"]))
            assert (
                image.meta["direction"] == direction and image.meta["line_rate_hz"] == s.meta["line_rate_hz"]
            )
    truth = np.load(tmp_path / "npz" / "truth.npz")
    np.testing.assert_array_equal(truth["scan2_tip_trace_nm"], case["scans"][2].truth["tip_trace_nm"])
    tiff = write_case(case, tmp_path / "tif", fmt="tiff", truth=False)
    entry = json.loads(tiff["data"].read_text())["data"]["scans"][1]["retrace"]
    given = {k: v for k, v in entry.items() if k != "path"}
    image = read_image(tmp_path / "tif" / entry["path"], **given)
    np.testing.assert_allclose(image.z, case["scans"][1].retrace, rtol=1e-6, atol=1e-3)
