"""Diagnosis from trace/retrace grating images at two scan speeds: the edge-shape model against
closed forms, the tip image of a grating against brute force, withheld imaging effects found with
their size, a quiet control, and bad input refused with a message."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from jaxafm.cli import app
from jaxafm.config import ConfigError, DiagnoseConfig, ScanSample, load_config
from jaxafm.diagnose import scans as S
from jaxafm.diagnose import withheld as W
from jaxafm.diagnose.core import Rules
from jaxafm.diagnose.image import diagnose_image
from jaxafm.instrument.afm import AFM
from jaxafm.instrument.images import AFMImage, save_image
from jaxafm.instrument.samples import Grating, Tip
from jaxafm.model.effects import FeedbackAsymmetry, FeedbackLag

runner = CliRunner()
SMALL = dict(lines=12)  # 12 lines of 512 pixels over 2 um per image


@pytest.mark.parametrize(
    "depth, edge, radius, half_angle_deg",
    [
        (30.0, 17.0, 12.0, 20.0),  # walls less steep than the cone: the apex sphere slides along them
        (30.0, 2.0, 12.0, 20.0),  # near-vertical walls: the cone's flank hangs on the top corner
        (-30.0, 40.0, 25.0, 30.0),  # grooves with gentle walls and a blunt tip
    ],
)
def test_grating_tip_image_against_brute_force(depth, edge, radius, half_angle_deg):
    """Grating.imaged (closed form) against max_q [z(p + q) - tip(|q|)] over a dense (0.2 nm) 2-D
    grid of offsets in NumPy, on a grating turned by 0.3 rad: the brute force lies below the
    exact value by at most what its grid misses, never above it."""
    tip = Tip(jnp.asarray(radius), jnp.asarray(np.deg2rad(half_angle_deg)))
    g = Grating(
        jnp.asarray(400.0),
        jnp.asarray(depth),
        edge_width=jnp.asarray(edge),
        angle=jnp.asarray(0.3),
        phase=jnp.asarray(11.0),
    )
    grid = np.arange(-90.0, 90.01, 0.2)
    q = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)
    lift = np.asarray(tip.profile(jnp.asarray(np.hypot(q[:, 0], q[:, 1]))))
    pts = np.stack([np.linspace(-260.0, 260.0, 53), np.full(53, 35.0)], -1)
    brute = np.array([np.max(np.asarray(g.height(jnp.asarray(p + q))) - lift) for p in pts])
    exact = np.asarray(jax.jit(lambda t, p: g.imaged(t, p))(tip, jnp.asarray(pts)))
    assert np.all(exact >= brute - 1e-9)
    assert np.max(exact - brute) < 0.15  # measured 0.012, 0.061, 0.010 nm: contacts off the 0.2 nm grid
    assert np.median(exact - brute) < 0.01
    assert exact.min() == pytest.approx(min(depth, 0.0)) and exact.max() == pytest.approx(max(depth, 0.0))


def test_grating_tip_image_gradient_matches_finite_differences():
    """The closed-form image's gradient against central differences, in the tip radius, the
    grating's depth and phase, and the position."""

    def image(p):
        tip = Tip(p[0], jnp.asarray(np.deg2rad(20.0)))
        g = Grating(jnp.asarray(400.0), p[1], edge_width=jnp.asarray(17.0), phase=p[2])
        return g.imaged(tip, jnp.stack([p[3], jnp.asarray(5.0)]))

    for x in (93.0, 108.0, 118.0):  # on the wall, near and past the top corner
        p = jnp.array([12.0, 30.0, 4.0, x])
        grad = np.asarray(jax.grad(image)(p))
        h = 1e-5
        fd = [(image(p.at[i].add(h)) - image(p.at[i].add(-h))) / (2 * h) for i in range(4)]
        np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-8)
        assert np.any(np.abs(grad) > 0.1)


def test_edge_shape_closed_forms():
    """Ramp: level l crosses at (l - 1/2) w. Tip on a ramp of slope angle a (away from its
    corners): the image is the ramp lifted by R (1/cos a - 1), so mid levels move by
    -R (1/cos a - 1) / tan a. Lag on a sharp step, fine sampling: level l crosses
    lambda ln(1 / (1 - l)) after the step, lambda = lag_samples dx, in the scan direction."""
    levels = (0.3, 0.5, 0.7)
    w, depth, radius = 17.32, 30.0, 8.0
    ramp = S.edge_shape(ScanSample(pitch_nm=400.0, edge_width_nm=w), depth, 0.5, levels)
    np.testing.assert_allclose(ramp[0, 0], (np.array(levels) - 0.5) * w, atol=1e-3)  # rising, trace
    np.testing.assert_allclose(ramp[1, 1], -(np.array(levels) - 0.5) * w, atol=1e-3)  # falling, retrace
    tipped = S.edge_shape(ScanSample(pitch_nm=400.0, edge_width_nm=w), depth, 0.5, levels, radius=radius)
    a = np.arctan(depth / w)
    np.testing.assert_allclose(
        tipped[0, 0] - ramp[0, 0], -radius * (1 / np.cos(a) - 1) / np.tan(a), atol=0.02
    )
    dx, lag = 0.05, 100.0
    step = S.edge_shape(ScanSample(pitch_nm=400.0, edge_width_nm=0.01), depth, dx, levels, lag_samples=lag)
    expect = lag * dx * np.log(1 / (1 - np.array(levels)))
    np.testing.assert_allclose(step[0, 0], expect, atol=2 * dx)  # trace: lag to the right
    np.testing.assert_allclose(
        step[0, 1], -lag * dx * np.log(1 / np.array(levels)), atol=2 * dx
    )  # retrace: left


def test_edge_shape_asymmetric_feedback_closed_form():
    """FeedbackAsymmetry on a sharp step, fine sampling: the recorded height approaches the
    surface as exp(-t / tau), tau_fall where the tip goes down (a falling edge in trace, a rising
    one in retrace), tau_rise where it goes up. Level l of a step up in time crosses
    tau ln(1 / (1 - l)) after the step, of a step down tau ln(1 / l), along the scan."""
    levels = np.array((0.3, 0.5, 0.7))
    dx, rise, fall = 0.05, 20.0, 100.0
    grating = ScanSample(pitch_nm=400.0, edge_width_nm=0.01)
    step = S.edge_shape(grating, 30.0, dx, tuple(levels), asymmetry_samples=(rise, fall))
    up, down = np.log(1 / (1 - levels)), np.log(1 / levels)
    np.testing.assert_allclose(step[0, 0], rise * dx * up, atol=2 * dx)  # rising edge, trace: up
    np.testing.assert_allclose(step[1, 0], fall * dx * down, atol=2 * dx)  # falling edge, trace: down
    np.testing.assert_allclose(step[0, 1], -fall * dx * down, atol=2 * dx)  # rising edge, retrace: down
    np.testing.assert_allclose(step[1, 1], -rise * dx * up, atol=2 * dx)  # falling edge, retrace: up


def test_level_crossings_of_a_rise_after_an_unsettled_fall():
    """A grating row written in NumPy: each line's top (30 nm) falls as 30 exp(-u / 70 nm) and
    has not settled (1.7 nm left) when the next rise, a 20 nm linear ramp, begins 200 nm later;
    pitch 400 nm, a sample every 4 nm. The fall's tail crosses the low levels within a quarter
    pitch of the rise: each edge's crossings must be its own, on the exact curves (ramp:
    linear, exact under linear interpolation; tail: lambda ln(30 / level))."""
    dx, lam, w, pitch = 4.0, 70.0, 20.0, 400.0
    x = dx * np.arange(500)
    u = np.mod(x - 48.0, pitch)
    z0 = 30 * np.exp(-200 / lam)
    row = np.where(u < 200, 30 * np.exp(-u / lam), np.minimum(z0 + (30 - z0) * (u - 200) / w, 30.0))
    image = np.tile(row, (10, 1))
    re = S.row_edges(image, (dx, dx))
    got = S.edge_levels(image, re, S.LEVELS) * dx
    lo, hi = np.percentile(row, [10, 90])
    level = lo + np.array(S.LEVELS) * (hi - lo)
    e = re.edges
    first = e.row == 0
    for xe, rising in zip(e.x_nm[first], e.rising[first]):
        start = 48.0 + pitch * np.floor((xe - 48.0) / pitch)  # the line's fall
        expect = start + (200 + (level - z0) / (30 - z0) * w if rising else lam * np.log(30 / level))
        np.testing.assert_allclose(got[first][e.x_nm[first] == xe][0], expect, atol=0.1)
    rise_mid = 200 + (level[2] - z0) / (30 - z0) * w
    assert rise_mid - lam * np.log(30 / level[0]) < pitch / 4  # the tail's crossing is near the rise


def test_afm_names_and_drops_the_feedback_asymmetry():
    afm = AFM(
        W.simulated_scanner(None, 0.0, 0.0), Tip(jnp.asarray(10.0), jnp.asarray(0.3)), jnp.full(2, 500.0)
    )
    asym = eqx_replace(afm, FeedbackAsymmetry(jnp.asarray(1e-4), jnp.asarray(1e-3)))
    lag = eqx_replace(afm, FeedbackLag(jnp.asarray(1e-3)))
    assert "feedback_asymmetry" in asym.effects and "feedback_lag" not in asym.effects
    assert "feedback_lag" in lag.effects and "feedback_asymmetry" not in lag.effects
    assert asym.without("feedback_asymmetry").feedback is None
    assert asym.without("feedback_lag").feedback is not None
    assert lag.without("feedback_asymmetry").feedback is not None


def eqx_replace(afm, feedback):
    import equinox as eqx

    return eqx.tree_at(lambda a: a.feedback, afm, feedback, is_leaf=lambda v: v is None)


@pytest.fixture(scope="module")
def control():
    return S.diagnose_scans(
        W.simulate_scans(None, 0.0, 3, **SMALL), W.SIM_GRATING, S.CANDIDATES, 0.6, Rules()
    )


def test_control_gives_no_significant_effect(control):
    assert control.verdict is None
    assert control.nominal.heldout_gap_nm < 0.6
    # the nominal scale: 400 nm of grating span 1 / (minor-loop gain) nominal nm
    assert 1.1 < control.data.scale < 1.5


@pytest.mark.parametrize(
    "effect, magnitude, fitted, key, rtol",
    [
        ("feedback_lag", 3e-4, 3e-4, "tau_s", 0.1),
        ("tip", 25.0, 25.0, "tip_radius_nm", 0.25),
        ("rate_dependence", 3e-3, 3e-3, "tau_s", 0.1),
        # tau_fall 1 ms, tau_rise 0.1 ms: the falling edges smear by 5-20 nm at 5-20 um/s
        ("feedback_asymmetry", 1e-3, 1e-3, "tau_fall_s", 0.1),
    ],
)
def test_withheld_imaging_effect_is_found_with_its_size(effect, magnitude, fitted, key, rtol):
    res = S.diagnose_scans(
        W.simulate_scans(effect, magnitude, 5, **SMALL), W.SIM_GRATING, S.CANDIDATES, 0.6, Rules()
    )
    assert res.verdict == effect
    top = res.candidates[0]
    assert top.effect == effect and top.shrink_pct > 60
    assert top.fit.fitted[key] == pytest.approx(fitted, rel=rtol)


LOOKALIKES = ("rate_dependence", "feedback_lag", "coupling")


def test_lattice_scan_set_finds_a_withheld_feedback_lag():
    """A 2-D pit lattice (rows between the pits' rows cross none): the rows across the pits are
    used, each with its own chord, and a 0.3 ms lag is found with its size."""
    pairs = W.simulate_scans("feedback_lag", 3e-4, 4, sample="lattice")
    res = S.diagnose_scans(pairs, W.SIM_LATTICE, LOOKALIKES, 0.6, Rules())
    assert res.verdict == "feedback_lag"
    assert res.data.groups is not None and res.data.describe()["source"].endswith("2-D lattice")
    assert len(np.unique(res.data.crossings.row)) < pairs[0].trace.shape[0]  # rows between pits left out
    top = res.candidates[0]
    assert top.shrink_pct > 60 and top.fit.fitted["tau_s"] == pytest.approx(3e-4, rel=0.1)


def test_short_rows_and_unequal_line_counts():
    """Rows with about 2.3 periods (1200 nominal nm, 920 nm of a 400 nm grating), the speeds with 12
    and 16 lines: the lag is found; one short-row image is diagnosed too."""
    slow = W.simulate_scans("feedback_lag", 1e-3, 6, line_rates_hz=(1.0,), lines=12, size_nm=1200.0)
    fast = W.simulate_scans("feedback_lag", 1e-3, 7, line_rates_hz=(4.0,), lines=16, size_nm=1200.0)
    res = S.diagnose_scans(slow + fast, W.SIM_GRATING, LOOKALIKES, 0.6, Rules())
    assert [p.trace.shape[0] for p in res.data.pairs] == [12, 16]
    assert res.verdict == "feedback_lag"
    assert res.candidates[0].fit.fitted["tau_s"] == pytest.approx(1e-3, rel=0.15)
    image = diagnose_image(AFMImage(fast[0].trace, fast[0].pixel_size), ["coupling"], 0.6)
    assert image.nominal.heldout_gap_nm < 2.0


def test_lattice_needs_its_pitch(tmp_path):
    """A lattice whose pitch is unknown: the key, the value and what is allowed, before any work."""
    cfg = tmp_path / "c.yaml"
    pairs = (
        "  pairs:\n    - {trace: a.txt, retrace: b.txt, line_rate_hz: 1}\n"
        "    - {trace: c.txt, retrace: d.txt, line_rate_hz: 4}\n"
    )
    for pitch, shown in (
        ("", "None"),
        ("  pitch_nm: unknown\n", "'unknown'"),
        ("  pitch_nm: [400, 0]\n", "0"),
    ):
        cfg.write_text(
            "scans:\n  grating:\n    kind: lattice\n    edge_width_nm: 17\n"
            + pitch.replace("  p", "    p")
            + pairs
        )
        with pytest.raises(ConfigError) as err:
            load_config(cfg, DiagnoseConfig)
        text = str(err.value)
        assert "scans.grating.pitch_nm" in text and shown in text and "allowed" in text, text
    cfg.write_text("image:\n  path: g.txt\n  kind: lattice\n")
    with pytest.raises(ConfigError, match=r"image\.pitch_nm[^\n]*lattice[^\n]*None[^\n]*allowed"):
        load_config(cfg, DiagnoseConfig)


def test_scan_set_needs_two_speeds():
    pairs = W.simulate_scans(None, 0.0, 0, line_rates_hz=(1.0, 1.0), **SMALL)
    with pytest.raises(ValueError, match="needs trace/retrace pairs at two or more"):
        S.diagnose_scans(pairs[:1], W.SIM_GRATING, S.CANDIDATES, 0.6, Rules())
    with pytest.raises(ValueError, match="all pairs have the scan speed"):
        S.diagnose_scans(pairs, W.SIM_GRATING, S.CANDIDATES, 0.6, Rules())


def test_scan_config_errors(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "scans:\n  pairs:\n    - {trace: a.txt, retrace: b.txt, line_rate_hz: 1}\n"
        "    - {trace: c.txt, retrace: d.txt, line_rate_hz: 4}\n"
    )
    with pytest.raises(ConfigError, match="scans.grating is required"):
        load_config(cfg, DiagnoseConfig)
    cfg.write_text("scans:\n  simulate: {withheld: creep, magnitude: 0.01}\n")
    with pytest.raises(ConfigError, match="withheld"):
        load_config(cfg, DiagnoseConfig)
    cfg.write_text("scans:\n  simulate: {withheld: tip, line_rates_hz: [1, 4]}\n")
    with pytest.raises(ConfigError, match="magnitude must be > 0"):
        load_config(cfg, DiagnoseConfig)


def test_cli_diagnoses_scan_files(tmp_path):
    """Pairs saved as image files and read back through the config: the verdict and outputs."""
    pairs = W.simulate_scans("feedback_lag", 1e-3, 2, **SMALL)
    entries = []
    for i, (p, rate) in enumerate(zip(pairs, (1.0, 4.0))):
        for side in ("trace", "retrace"):
            save_image(AFMImage(getattr(p, side), p.pixel_size), tmp_path / f"{side}{i}.npz")
        entries.append(
            f"    - {{trace: trace{i}.npz, retrace: retrace{i}.npz, line_rate_hz: {rate}, overscan: 0.1}}"
        )
    cfg = tmp_path / "d.yaml"
    cfg.write_text(
        "scans:\n  grating: {pitch_nm: 400, edge_width_nm: 17.32}\n  pairs:\n" + "\n".join(entries) + "\n"
    )
    out = tmp_path / "out"
    result = runner.invoke(app, ["diagnose", str(cfg), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "scans.pairs[1]: scanned line_rate_hz 4.0 (given), overscan 0.1 (given)" in result.output
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["verdict"]["effect"] == "feedback_lag"
    assert doc["candidates"][0]["fitted"]["tau_s"] == pytest.approx(1e-3, rel=0.1)
    assert set(doc["skipped"]) >= {"creep", "drift", "asymmetry"}
    assert (out / "residuals.png").stat().st_size > 10_000
