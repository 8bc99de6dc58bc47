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
from jaxafm.config import ConfigError, DiagnoseConfig, ScanGrating, load_config
from jaxafm.diagnose import scans as S
from jaxafm.diagnose import withheld as W
from jaxafm.diagnose.core import Rules
from jaxafm.instrument.images import AFMImage, save_image
from jaxafm.instrument.samples import Grating, Tip

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
    ramp = S.edge_shape(ScanGrating(pitch_nm=400.0, edge_width_nm=w), depth, 0.5, levels)
    np.testing.assert_allclose(ramp[0, 0], (np.array(levels) - 0.5) * w, atol=1e-3)  # rising, trace
    np.testing.assert_allclose(ramp[1, 1], -(np.array(levels) - 0.5) * w, atol=1e-3)  # falling, retrace
    tipped = S.edge_shape(ScanGrating(pitch_nm=400.0, edge_width_nm=w), depth, 0.5, levels, radius=radius)
    a = np.arctan(depth / w)
    np.testing.assert_allclose(
        tipped[0, 0] - ramp[0, 0], -radius * (1 / np.cos(a) - 1) / np.tan(a), atol=0.02
    )
    dx, lag = 0.05, 100.0
    step = S.edge_shape(ScanGrating(pitch_nm=400.0, edge_width_nm=0.01), depth, dx, levels, lag_samples=lag)
    expect = lag * dx * np.log(1 / (1 - np.array(levels)))
    np.testing.assert_allclose(step[0, 0], expect, atol=2 * dx)  # trace: lag to the right
    np.testing.assert_allclose(
        step[0, 1], -lag * dx * np.log(1 / np.array(levels)), atol=2 * dx
    )  # retrace: left


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
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["verdict"]["effect"] == "feedback_lag"
    assert doc["candidates"][0]["fitted"]["tau_s"] == pytest.approx(1e-3, rel=0.1)
    assert set(doc["skipped"]) >= {"creep", "drift", "asymmetry"}
    assert (out / "residuals.png").stat().st_size > 10_000
