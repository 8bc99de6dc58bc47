"""Step A from sets of scans: scan angles, turned lattices, held-out features, plausibility,
default calibration, and what a set of measured images may not be."""

import functools
import json
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxafm
from jaxafm.config import CalibrationImages, CalibrationLattice, CalibrationModel, SimulatedCalibration
from jaxafm.identify import features, held_out, staged_fit
from jaxafm.identify.calibration_scan import CalibrationScan
from jaxafm.identify.plausibility import implausible
from jaxafm.identify.scan_model import DELAY_RESTART_S, ScanModelSpec
from jaxafm.identify.stages import FitPlan, StageKind
from jaxafm.identify.step_a import true_scan_model
from jaxafm.instrument.afm import AFM, Raster, default_afm, raster_scan
from jaxafm.instrument.samples import Grating as LineGrating
from jaxafm.instrument.samples import Tip
from jaxafm.jobs import Output, calibrate

GRATING = Path(jaxafm.__file__).parent / "data" / "real" / "grating_1d_nanosurf.txt"


def test_a_90_degree_raster_runs_its_lines_along_y():
    """Closed form: at 90 degrees the scan frame's (s, l) is the stage's (-l, s)."""
    r = Raster((100.0, 50.0), 10, 5, centre=(7.0, -3.0), angle_deg=90.0)
    flat = Raster((100.0, 50.0), 10, 5, centre=(7.0, -3.0))
    w, w0 = r.wanted(), flat.wanted() - np.array([7.0, -3.0])
    assert np.allclose(w[..., 0], 7.0 - w0[..., 1]) and np.allclose(w[..., 1], -3.0 + w0[..., 0])
    assert np.allclose(r.nominal([[0.0, 0.0]]), [[7.0 + 20.0, -3.0 - 45.0]])


def test_a_rotated_raster_images_a_line_grating_along_its_slow_axis():
    """Lines along y: at 0 degrees each image row crosses them; at 90 degrees every row runs
    along the lines, so the image changes from row to row, not along a row."""
    afm = AFM(default_afm().scanner.without("noise", "drift"), Tip(), jnp.full(2, 500.0), None, dilate=False)
    grating = LineGrating(jnp.asarray(1000.0), jnp.asarray(100.0))
    state = afm.initial_state()
    z = {
        a: np.asarray(raster_scan(afm, grating, state, Raster(4000.0, 32, 32, angle_deg=a)).trace)
        for a in (0.0, 90.0)
    }
    along_rows, across_rows = ({a: np.abs(np.diff(z[a], axis=k)).mean() for a in z} for k in (1, 0))
    # at 0 degrees only coupling (2 %) tilts the lines across the rows; at 90 degrees the other way
    assert along_rows[0.0] > 10 * across_rows[0.0] and np.ptp(z[0.0], axis=1).min() > 90
    assert across_rows[90.0] > 10 * along_rows[90.0] and np.ptp(z[90.0], axis=0).min() > 90


def _turned_points(angle_deg, pitch=(40.0, 40.0), n=7, noise=0.3, seed=0):
    """Sites of a lattice turned by ``angle_deg``, drawn without jaxafm, with centroid noise."""
    a = np.deg2rad(angle_deg)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    ij = np.stack([i.ravel(), j.ravel()], -1)
    q = ij * np.asarray(pitch)
    xy = q @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) + [13.0, 21.0]
    return xy + np.random.default_rng(seed).normal(0, noise, xy.shape), ij


@pytest.mark.parametrize("angle", [0.0, 1.0, 3.0, -4.0, 30.0])
def test_a_turned_lattice_is_indexed_along_its_own_axes(angle):
    xy, ij = _turned_points(angle)
    found, a = features.index_lattice(xy, (40.0, 40.0), units="nm")
    # each of the 2 x 7 x 6 neighbour vectors' angle has noise 0.3 sqrt(2) / 40 rad: 3 sigma of the mean
    assert abs(np.rad2deg(a) - angle) < np.rad2deg(3 * 0.3 * np.sqrt(2) / 40 / np.sqrt(84))
    assert np.all(np.ptp(found - ij, axis=0) == 0)  # one whole-lattice shift at most


def test_a_turned_lattice_image_drawn_without_jaxafm_gives_its_angle_and_sites():
    """Pillars of radius 3 px every 12 px on a lattice turned by 2.5 degrees, drawn with NumPy:
    the features sit on the drawn sites, indexed along the turned axes."""
    a, pitch = np.deg2rad(2.5), 12.0
    r, c = np.mgrid[:96, :96].astype(float)
    u, v = np.cos(a) * c + np.sin(a) * r, -np.sin(a) * c + np.cos(a) * r  # lattice axes, px
    du, dv = (np.mod(w - 5.0 + pitch / 2, pitch) - pitch / 2 for w in (u, v))
    f = features.lattice_features(np.clip(3.0 - np.hypot(du, dv) + 0.5, 0, 1), (pitch, pitch))
    assert abs(np.rad2deg(f.angle) - 2.5) < 0.1
    q = f.rc[:, ::-1] @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])  # (u, v) px
    offset = (q - 5.0) / pitch - f.ij
    assert np.ptp(np.round(offset), axis=0).max() == 0 and np.abs(offset - np.round(offset)).max() < 0.02


def test_lattice_sites_invert_its_coordinates():
    from jaxafm.instrument.samples import Lattice

    lattice = Lattice(
        jnp.array([1000.0, 800.0]), jnp.asarray(200.0), jnp.asarray(50.0), angle=jnp.asarray(0.3)
    )
    lattice = eqx.tree_at(lambda m: m.phase, lattice, jnp.array([130.0, -70.0]))
    ij = jnp.array([[0.0, 0.0], [2.0, -1.0], [-3.0, 4.0]])
    assert np.allclose(lattice.coordinates(lattice.sites(ij)), ij, atol=1e-12)
    assert np.allclose(lattice.height(lattice.sites(ij)), 50.0)


def test_a_wrong_pitch_names_the_pitch_the_features_show():
    xy, _ = _turned_points(2.0)
    with pytest.raises(
        ValueError, match=r"lie 39\.\d nm apart \(median\), but the stated pitch is 64 x 64 nm"
    ):
        features.index_lattice(xy, (64.0, 64.0), units="nm")


@functools.cache
def _scans(angles=(0.0, 90.0), rotation=2.0, pits=False):
    spec = SimulatedCalibration(
        pixels=64, size_nm=6000, angles_deg=list(angles), lattice_rotation_deg=rotation
    )
    return calibrate.calibration_scans(spec, CalibrationLattice(pitch_nm=1000, pits=pits, rotation_deg="fit"))


@pytest.mark.parametrize("pits", [False, True])
def test_features_of_both_scans_sit_on_the_true_lattice(pits):
    """Through the true scanner every feature of both scans (trace and retrace, indexed in
    nominal stage coordinates) lies near a whole lattice coordinate, one shift per scan."""
    scans, sim = _scans(pits=pits)
    true = true_scan_model(sim)
    for scan in scans:
        ft, fr = scan.features()
        e = np.concatenate([np.asarray(x) for x in true.site_errors(scan, [(ft.rc, ft.ij), (fr.rc, fr.ij)])])
        shift = np.round(np.median(e, axis=0))
        assert np.abs(e - shift).max() < 0.15  # pitches: centroid noise of 8 px features


def test_held_out_residual_separates_the_true_scanner_from_a_wrong_one():
    """The true scanner scores the chords' noise (a few nm at 94 nm pixels); one whose x gain
    is 2 % off misplaces the held-out features by about 2 % of their distance from the centre."""
    scans, sim = _scans(angles=(0.0,), rotation=0.0)
    ft, fr = scans[0].features()
    odd = lambda f: f.chord_indices()[:, 1] % 2 == 1
    test = [
        [(f.chords.ends[odd(f)], f.chord_indices()[odd(f)], f.chords.along_lines[odd(f)]) for f in (ft, fr)]
    ]
    true = true_scan_model(sim)
    e = np.asarray(true.site_errors(scans[0], [(ft.rc, ft.ij)])[0])  # indices from 0: the true lattice's
    shift = np.round(np.median(e, axis=0)).astype(int)
    test = [[(ends, ij + shift, along) for ends, ij, along in images] for images in test]
    wrong = eqx.tree_at(
        lambda m: m.scanner.x.hysteresis.pi.weights, true, 1.02 * true.scanner.x.hysteresis.pi.weights
    )
    floor, off = held_out.held_out_rms(true, scans, test), held_out.held_out_rms(wrong, scans, test)
    assert floor < 12.0 and off > 25.0


def test_training_masks_cover_a_quarter_pitch_about_even_rows():
    """Closed form: bands of half a pitch about every other row are a quarter of the area (up
    to the partial bands at the image's ends: half a band each over more than 5 pitches)."""
    scans, sim = _scans(angles=(0.0,), rotation=0.0)
    (train,), (held,) = held_out.split_masks(true_scan_model(sim), scans, hold_out=True)
    assert abs(float(np.mean(train)) - 0.25) < 0.5 / 5 and abs(float(np.mean(held)) - 0.25) < 0.5 / 5
    assert float(np.max(train * held)) == 0.0
    (full,), none = held_out.split_masks(true_scan_model(sim), scans, hold_out=False)
    assert float(np.min(full)) == 1.0 and none is None


@pytest.mark.parametrize("after", [50.0, 30.0])
def test_an_image_stage_that_worsens_the_held_out_features_is_not_kept(monkeypatch, after):
    """Rejected beyond 3 / sqrt(2 n) of the best: 10 nm -> 30 or 50 nm is far beyond it (no
    fit saw the held-out features: no pixel's slack)."""
    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    after_each_stage = iter([10.0, after])  # nm: the feature stage, then the image stage
    monkeypatch.setattr(staged_fit, "held_out_rms", lambda *a: next(after_each_stage))
    monkeypatch.setattr(staged_fit, "validate", lambda *a: {})
    ident = staged_fit.identify(
        scans,
        ScanModelSpec(kind="pi", effects=(), operators=4),
        FitPlan(max_steps=3, blur_px=(1.5,), select=False),
        log=lambda *_: None,
    )
    assert ident.accepted == (True, False) and ident.held_out_nm == (10.0, after)
    assert eqx.tree_equal(ident.model, ident.stages[0].model)
    assert f"REJECTED: the held-out features got worse (10.00 -> {after:.2f} nm)" in ident.stages[1].message


@pytest.mark.parametrize("after", [50.0, 30.0])
def test_with_no_site_held_out_the_training_features_judge_an_image_stage(monkeypatch, after):
    """``hold_out: false`` leaves no held-out feature: the training features (every site) judge
    an image stage by the same rule, and the held-out residual stays NaN. The chord stage fitted
    them, so a rise within a quarter of a 94 nm pixel beyond their uncertainty (10 nm x (1 +
    3 / sqrt(2 n)) + 23 nm, n > 18 sites) is kept: 30 nm is, 50 nm is not."""
    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    after_each_stage, judged = iter([10.0, after]), []

    def training_rms(model, fitted, part):
        judged.append(sum(len(ij) for images in part for _, ij, _ in images))
        return next(after_each_stage)

    monkeypatch.setattr(staged_fit, "held_out_rms", training_rms)
    monkeypatch.setattr(staged_fit, "validate", lambda *a: {})
    ident = staged_fit.identify(
        scans,
        ScanModelSpec(kind="pi", effects=(), operators=4),
        FitPlan(max_steps=3, blur_px=(1.5,), select=False, hold_out=False),
        log=lambda *_: None,
    )
    trace, retraces = scans[0].feature_matches()
    every, _ = held_out.split_chords([[trace, retraces[0]]], False)
    assert judged == [sum(len(ij) for _, ij, _ in every[0])] * 2  # every chord of the scan
    assert np.isnan(ident.held_out_nm).all()
    if after == 30.0:
        assert ident.accepted == (True, True) and "REJECTED" not in ident.stages[1].message
        return
    assert ident.accepted == (True, False)
    assert eqx.tree_equal(ident.model, ident.stages[0].model)
    assert "REJECTED: the training features got worse (10.00 -> 50.00 nm)" in ident.stages[1].message


def test_an_image_stage_after_the_chords_renders_edges_as_late_as_the_chords_saw_them(monkeypatch):
    """The chord stage fits the edge delay, not the feedback lag it renders with; the image stage
    starts from the lag that delays a sharp step's half-height crossing by that delay (closed
    form for a first-order lag: ``1 - exp(-t / tau) = 1/2``), found here on a finely sampled step."""
    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    starts, fit_stage = [], staged_fit.fit_stage

    def recording(stage, model, *args):
        starts.append((stage.kind, model))
        return fit_stage(stage, model, *args)

    monkeypatch.setattr(staged_fit, "fit_stage", recording)
    monkeypatch.setattr(staged_fit, "validate", lambda *a: {})
    ident = staged_fit.identify(
        scans,
        ScanModelSpec(kind="pi", effects=("feedback_lag",), operators=4),
        FitPlan(max_steps=3, blur_px=(1.5,), select=False),
        log=lambda *_: None,
    )
    delay = float(ident.stages[0].model.edge_delay)
    assert delay > 2 * DELAY_RESTART_S, delay  # a delay the chords fitted, not the floor
    image_start = next(model for kind, model in starts if kind is StageKind.IMAGES)
    t = np.linspace(0.0, 20 * delay, 200_001)
    z = np.asarray(image_start.feedback(jnp.asarray((t > 0).astype(float)), jnp.asarray(t)))
    crossing = np.interp(0.5, z, t)  # z rises monotonically
    np.testing.assert_allclose(crossing, delay, atol=2 * (t[1] - t[0]))


@functools.cache
def _small_fit():
    """A four-play PI with coupling and creep fitted to the features of one 0-degree scan of the
    simulated default scanner, half of the features held out."""
    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    spec = ScanModelSpec(kind="pi", effects=("coupling", "creep"), operators=4)
    ident = staged_fit.identify(
        scans, spec, FitPlan(max_steps=20, blur_px=(), select=False), log=lambda *_: None
    )
    return scans, ident


def test_path_sd_is_the_spread_of_paths_drawn_from_the_covariance():
    """The delta method's tip-path sd (``path_sd``) against Monte Carlo: paths of raw parameters
    drawn from ``eps^2`` times the chord covariance (``eps`` small, so the path is linear in
    them), each brought onto the mean path by its best rigid motion (Kabsch, as the experiments
    score paths), their rms spread per pixel over ``eps``. 400 draws estimate an sd to about
    1 / sqrt(800) = 3.5 %: per pixel within 20 %, over the image within 7 %."""
    from jax.flatten_util import ravel_pytree

    from jaxafm.identify.identifiability import chord_covariance, path_sd

    scans, ident = _small_fit()
    sd = path_sd(ident.model, scans, ident.chords)[0].ravel()
    model = ident.model.as_float64()
    raw, rebuild = model.free_parameters(scans[0])
    flat, unravel = ravel_pytree(raw)
    eps = 1e-4
    C = chord_covariance(model, scans, ident.chords)
    draws = np.random.default_rng(3).multivariate_normal(np.asarray(flat), eps**2 * C, 400)
    paths = jax.jit(jax.vmap(lambda x: jnp.stack(rebuild(unravel(x)).paths(scans[0])).reshape(-1, 2)))
    p = np.asarray(paths(jnp.asarray(draws)))
    mean = p.mean(axis=0)
    centred = mean - mean.mean(axis=0)
    aligned = []
    for q in p:
        u, _, vt = np.linalg.svd((q - q.mean(axis=0)).T @ centred)
        r = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
        aligned.append((q - q.mean(axis=0)) @ r - centred)
    spread = np.sqrt(np.mean(np.sum(np.asarray(aligned) ** 2, axis=2), axis=0)) / eps
    assert sd.max() > 0
    np.testing.assert_allclose(spread, sd, rtol=0.2)
    assert abs(np.sqrt(np.mean(spread**2)) / np.sqrt(np.mean(sd**2)) - 1) < 0.07


def test_the_share_of_the_path_variance_a_quantity_settles_is_its_gaussian_conditioning():
    """``settles`` against the Gaussian conditioning written out: knowing a quantity ``q`` with
    gradient ``g`` turns the parameters' covariance ``C`` into ``C - C g g^T C / g^T C g``; the
    path variance lost is the share, never negative nor above 100 %."""
    from jax.flatten_util import ravel_pytree

    from jaxafm.identify.calibration_scan import drive_range
    from jaxafm.identify.identifiability import (
        PATH_SAMPLES,
        _path_gradients,
        chord_covariance,
        identifiability,
    )
    from jaxafm.identify.quantities import quantities

    scans, ident = _small_fit()
    model = ident.model.as_float64()
    found = identifiability(model, scans, ident.chords, drive_range(scans))
    C = chord_covariance(model, scans, ident.chords)
    raw, rebuild = model.free_parameters(scans[0])
    flat, unravel = ravel_pytree(raw)
    defined = quantities(model, scans, drive_range(scans))
    keys = [d.key for d in defined]
    q = lambda x: jnp.stack([d.of(rebuild(unravel(x))) for d in defined])
    G = np.asarray(jax.jacfwd(q)(flat))
    P = np.concatenate([g.reshape(-1, 2, g.shape[-1]) for g in _path_gradients(model, scans, PATH_SAMPLES)])
    total = np.einsum("nij,jk,nik->", P, C, P)
    np.testing.assert_allclose(found.path_rms_nm, np.sqrt(total / len(P)), rtol=1e-10)
    for key, g in zip(keys, G):
        conditioned = C - np.outer(C @ g, C @ g) / (g @ C @ g)
        expected = 100 * (1 - np.einsum("nij,jk,nik->", P, conditioned, P) / total)
        assert abs(found.settles[key] - expected) < 1e-6 * 100, key
        assert -1e-9 <= found.settles[key] <= 100 + 1e-9, key


def test_a_stated_quantity_is_fitted_under_its_prior():
    """A quantity the user states (``known``) is a Gaussian prior on it. Stated at the value the
    chords alone fit, with an sd a fiftieth of theirs, the fit stays there and what the chords
    determine of it is the two combined, ``(1 / sd_data^2 + 1 / sd^2)^-1/2``, to 1 % (the
    cluster-robust covariance, its scores' spread in place of the residuals' and a unit prior on
    every raw parameter, parts in a thousand from the Gaussian's closed form).
    Stated 3 % off, it takes the fit most of the way there (a prior 2,500 times the data's
    precision: the constraint it tends to); stated 1,000 times wider than the data's sd, the
    fit is the one without it, to a twentieth of what the data determine. (_small_fit's model,
    each fit run to convergence: some 100 steps.)"""
    from jaxafm.identify.calibration_scan import drive_range
    from jaxafm.identify.identifiability import identifiability

    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    drive = drive_range(scans)

    def fitted(*known):
        spec = ScanModelSpec(kind="pi", effects=("coupling", "creep"), operators=4, known=known)
        ident = staged_fit.identify(
            scans, spec, FitPlan(max_steps=300, blur_px=(), select=False), log=lambda *_: None
        )
        assert ident.converged
        found = identifiability(ident.model, scans, ident.chords, drive).quantities
        return next(q for q in found if q.key == "y_gain_nm_per_v")

    data = fitted()
    fitted = lambda value, sd, fit=fitted: fit(("y_gain_nm_per_v", value, sd))
    sd = data.sd / 50
    there = fitted(data.value, sd)
    assert abs(there.value - data.value) < 0.05 * sd, (there.value, data.value, sd)
    np.testing.assert_allclose(there.sd, (data.sd**-2 + sd**-2) ** -0.5, rtol=0.01)
    stated = 1.03 * data.value
    off = fitted(stated, sd)
    assert abs(off.value - stated) < 0.1 * abs(stated - data.value), (off.value, stated, data.value)
    loose = fitted(stated, 1000 * data.sd)
    assert abs(loose.value - data.value) < 0.05 * data.sd, (loose.value, data.value, data.sd)


def test_a_path_the_scans_leave_more_open_than_a_feature_is_placed_and_the_task_allows_is_refused():
    """Refused when the path's sd (rms over the images, here sqrt((300² + 400²) / 1) = 500 nm)
    exceeds both the held-out features' predicted error and the path tolerance, naming the
    quantity that would settle most of it and how to state it; not refused at or below either,
    nor without held-out features to compare with."""
    from jaxafm.identify.identifiability import Determination, Quantity
    from jaxafm.identify.plausibility import unsettled

    loops = [
        Quantity("y_loop_pct_of_travel", "y loop at mid-drive", 41.2, 0.6, "% of travel"),
        Quantity("x_gain_nm_per_v", "x gain", 1855.0, 25.0, "nm/V"),
    ]
    wide = Determination(
        loops, np.array([300.0, 400.0]), {"y_loop_pct_of_travel": 80.0, "x_gain_nm_per_v": 15.0}
    )
    said = unsettled(wide, {"held_out_predicted_rms_nm": 110.0}, 50.0)
    assert len(said) == 1 and "500 nm" in said[0] and "y loop at mid-drive" in said[0] and "80 %" in said[0]
    assert "50 nm the path may be open" in said[0]
    assert "known: {y_loop_pct_of_travel: [value, sd]}" in said[0]
    assert unsettled(wide, {"held_out_predicted_rms_nm": 500.0}, 50.0) == []
    assert unsettled(wide, {"held_out_predicted_rms_nm": 110.0}, 500.0) == []
    assert unsettled(wide, {}, 50.0) == []


def test_the_default_path_tolerance_is_a_tenth_of_the_finest_pixel():
    """Closed form: images of 64 and 32 px over 5 µm (78.125 and 156.25 nm pixels) tolerate
    7.8125 nm; a stated tolerance is kept as given."""
    from types import SimpleNamespace

    from jaxafm.identify.plausibility import path_tolerance_nm

    scans = [SimpleNamespace(raster=SimpleNamespace(pixel_size=(5000 / n, 5000 / n))) for n in (64, 32)]
    assert path_tolerance_nm(scans) == pytest.approx(7.8125)
    assert path_tolerance_nm(scans, 3.0) == 3.0


@pytest.mark.parametrize(
    "angles, expected", [((0.0,), "1, 0"), ((90.0,), "0, 1"), ((45.0,), "a/(a+b)"), ((0.0, 90.0), "1, 1")]
)
def test_line_strokes_are_the_lines_reach_against_the_axis_range(angles, expected):
    """Closed form: a line spans ``a = dx (pixels + 2 m - 1)`` along the fast axis, the lines
    ``b = dy (lines - 1)`` along the slow one. At 0 degrees a line sweeps all of x and none of y;
    at 45 degrees both axes' ranges are ``(a + b) / sqrt 2`` and a line's ``a / sqrt 2`` of it."""
    from types import SimpleNamespace

    from jaxafm.identify.calibration_scan import line_strokes
    from jaxafm.instrument.afm import Raster

    scans = tuple(
        SimpleNamespace(
            raster=Raster((1000.0, 1000.0), 20, 12, overscan=0.1, angle_deg=a), sensitivity=(50.0, 50.0)
        )
        for a in angles
    )
    r = scans[0].raster
    a, b = r.pixel_size[0] * (r.pixels + 2 * r.margin - 1), r.pixel_size[1] * (r.lines - 1)
    want = {"1, 0": [1, 0], "0, 1": [0, 1], "a/(a+b)": [a / (a + b)] * 2, "1, 1": [1, 1]}[expected]
    np.testing.assert_allclose(line_strokes(scans), want, atol=1e-12)


def test_a_loop_no_line_traces_is_not_determined_whatever_its_sd():
    """One 0-degree scan drives the y piezo one way within an image: the y loop the fit reports
    is the model class's extrapolation from one branch, not determined, and says why; the x loop,
    swept by every line, keeps the verdict of its sd."""
    _, ident = _small_fit()
    q = {q.key: q for q in ident.quantities}
    assert not q["y_loop_pct_of_travel"].determined and "y piezo" in q["y_loop_pct_of_travel"].unmeasured
    assert q["x_loop_pct_of_travel"].unmeasured == ""
    assert "extrapolates" in q["y_loop_pct_of_travel"].line()


def test_held_out_features_fall_in_their_predicted_ellipses_as_often_as_stated():
    """The held-out features sit between the training ones (a checkerboard), so their offsets
    are drawn like the training features' (the chords' noise, the features' irregularity, the
    model's error between the features) plus the parameters' error: the predicted 90 % and 50 %
    ellipses hold 90 % and 50 % of them to within three binomial standard deviations of the
    count, and the rms the fit predicts is the offsets' own to within the sampling error of an
    rms over n features of 2-D offsets, 1 / sqrt(4 n), four times over (the features' noise
    differs along and across the lines). The parameters alone (a sixth of the prediction here)
    would fail it."""
    _, ident = _small_fit()
    v = ident.validation
    n = v["held_out_points"]
    assert n >= 20
    for level in (50, 90):
        p = level / 100
        assert abs(v[f"held_out_coverage_{level}_pct"] - level) <= 100 * 3 * np.sqrt(p * (1 - p) / n), v
    ratio = v["held_out_predicted_rms_nm"] / v["held_out_offsets_rms_nm"]
    assert abs(np.log(ratio)) <= 4 / np.sqrt(4 * n), v


def test_feature_points_average_each_features_chords_along_and_across_the_lines():
    """Closed form: per image and feature, the mean over its chords along the lines and over
    those across; a feature with chords one way only is left out, the padding is not counted."""
    from jaxafm.identify.identifiability import feature_points
    from jaxafm.identify.stages import PaddedChords

    def image(ij, along, weight):
        n = len(ij)
        return PaddedChords(
            np.zeros((n, 2, 2)), np.asarray(ij, float), np.asarray(along), np.asarray(weight, float)
        )

    first = image([[0, 0], [0, 0], [0, 0], [1, 0], [0, 0]], [True, True, False, True, True], [1, 1, 1, 1, 0])
    second = image([[0, 0], [0, 0], [0, 0]], [True, False, False], [1, 1, 1])
    values = np.array([1.0, 3.0, 5.0, 7.0, 100.0, 2.0, 4.0, 6.0])
    keys, means = feature_points(((first, second),), values)
    np.testing.assert_allclose(means, [[2.0, 5.0], [2.0, 5.0]])
    np.testing.assert_array_equal(keys, [[0, 0, 0], [1, 0, 0]])


def test_the_ellipse_quantile_holds_its_level_of_a_gaussian():
    """``-2 ln(1 - level)``, the chi-square quantile with two degrees of freedom, against 200,000
    draws of a correlated 2-D Gaussian (sampling error of a fraction about 0.001)."""
    from jaxafm.identify.identifiability import ellipse_quantile

    C = np.array([[4.0, 1.5], [1.5, 1.0]])
    x = np.random.default_rng(0).multivariate_normal([0, 0], C, 200_000)
    d2 = np.einsum("ni,ij,nj->n", x, np.linalg.inv(C), x)
    for level in (0.5, 0.9, 0.99):
        assert abs(np.mean(d2 <= ellipse_quantile(level)) - level) < 0.005


def test_implausible_models_are_named():
    scans, sim = _scans(angles=(0.0,), rotation=0.0)
    true = true_scan_model(sim)
    assert implausible(true, scans) == []
    pi = lambda m: m.scanner.x.hysteresis.pi
    weights = pi(true).weights
    tripled = eqx.tree_at(lambda m: pi(m).weights, true, 3 * weights)
    falling = eqx.tree_at(lambda m: pi(m).weights, true, weights.at[0].set(-1.0))
    creep = true.scanner.x.creep
    backwards = eqx.tree_at(lambda m: m.scanner.x.creep.weights, true, -jnp.abs(creep.weights) - 0.01)
    assert any("times its width" in f for f in implausible(tripled, scans))
    assert any("creep runs against the move" in f for f in implausible(backwards, scans))
    assert any("branch falls" in f for f in implausible(falling, scans))


def test_image_stages_that_leave_an_implausible_scanner_give_way_to_the_last_plausible_stage():
    """A chord stage that left the true scanner, then image stages whose scanner travels three
    times the image: the chord stage's model is kept and the image stages are marked rejected;
    a chord stage's implausible model, or no plausible stage before, is reported as it is."""
    from jaxafm.identify.fit import FitResult
    from jaxafm.identify.staged_fit import _StagedFit
    from jaxafm.identify.stages import StageKind

    scans, sim = _scans(angles=(0.0,), rotation=0.0)
    true = true_scan_model(sim)
    pi = lambda m: m.scanner.x.hysteresis.pi
    tripled = eqx.tree_at(lambda m: pi(m).weights, true, 3 * pi(true).weights)

    def staged(models, kinds):
        said = []
        fit = _StagedFit(scans, None, 1, [], said.append, models[-1], [], [], [], None)
        fit.results = [FitResult(m, "", True, 1, 0.0, 0.0, "") for m in models]
        fit.kinds, fit.accepted = list(kinds), [True] * len(models)
        return fit, fit.fall_back(), said

    chords, images = StageKind.CHORDS, StageKind.IMAGES
    fit, failures, said = staged([true, tripled, tripled], [chords, images, images])
    assert failures == [] and fit.model is true and fit.accepted == [True, False, False]
    assert "REJECTED stages 2, 3" in said[0] and "the model of stage 1 is kept" in said[0]
    for models, kinds in (([true, tripled], [images, chords]), ([tripled, tripled], [chords, images])):
        fit, failures, said = staged(models, kinds)
        assert any("times its width" in f for f in failures) and fit.model is tripled and not said


@pytest.mark.parametrize("kind", ["pi", "preisach"])
def test_a_model_without_dead_zones_leaves_asymmetry_out_of_its_default_effects(kind):
    """``asymmetry`` is a generalised PI's dead zones: a PI or Preisach model named without effects
    fits the others (its ladder would otherwise try a rung that changes nothing)."""
    assert "asymmetry" in CalibrationModel(name="g").effects
    effects = CalibrationModel(name="m", kind=kind).effects
    assert "asymmetry" not in effects and {"creep", "coupling", "bow", "feedback_lag"} <= set(effects)


def test_default_sensitivity_from_the_stated_range_or_the_images():
    # pixel centres reach +-(4000 - 62.5) nm, the over-scan 6 px of 125 nm more: +-4687.5 nm
    rasters = [Raster(8000.0, 64, 64, overscan=0.1)]
    ranged = CalibrationImages(
        scans=[{"trace": "t", "retrace": "r", "line_rate_hz": 1}], scan_range_nm=100_000
    )
    assert calibrate.nominal_sensitivity(ranged, rasters, log=lambda *_: None) == (5000.0, 5000.0)
    bare = ranged.model_copy(update={"scan_range_nm": None})
    assert calibrate.nominal_sensitivity(bare, rasters, log=lambda *_: None) == pytest.approx(
        (468.75, 468.75)
    )
    given = ranged.model_copy(update={"sensitivity_nm_per_v": [400.0, 400.0]})
    with pytest.raises(ValueError, match=r"needs \+-11.7 V"):
        calibrate.nominal_sensitivity(given, rasters, log=lambda *_: None)
    small = ranged.model_copy(update={"scan_range_nm": [5000.0]})
    with pytest.raises(ValueError, match="smaller than the images"):
        calibrate.nominal_sensitivity(small, rasters, log=lambda *_: None)


def _write_pair(tmp_path, name, z, size):
    """``z`` as a trace and, a pixel later along the lines, as its retrace (jaxafm's image files)."""
    from jaxafm.instrument.images import AFMImage, save_image

    for k, zz in (("trace", z), ("retrace", np.roll(z, 1, axis=1))):
        save_image(
            AFMImage(
                np.asarray(zz, dtype=float), (size / z.shape[1], size / z.shape[0]), meta={"direction": k}
            ),
            tmp_path / f"{name}_{k}.npz",
        )


def _calibrate(tmp_path, data: str, extra: str = ""):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"data: {data}\ngrating: {{pitch_nm: 1000}}\n{extra}output: {tmp_path / 'out'}\n")
    return subprocess.run(
        [sys.executable, "-c", "from jaxafm.cli import main; main()", "calibrate", str(cfg)],
        capture_output=True,
        text=True,
    )


def test_a_set_of_measured_scans_of_different_sizes_is_refused(tmp_path):
    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    z = np.asarray(scans[0].trace)
    _write_pair(tmp_path, "a", z, 6000.0)
    _write_pair(tmp_path, "b", z[:48, :48], 4500.0)
    pair = "{{trace: {n}_trace.npz, retrace: {n}_retrace.npz, line_rate_hz: 1, angle_deg: {a}}}"
    data = f"{{scans: [{pair.format(n='a', a=0)}, {pair.format(n='b', a=90)}]}}"
    proc = _calibrate(tmp_path, data)
    assert proc.returncode == 2 and "data.scans.1" in proc.stderr and "must have one size" in proc.stderr
    assert not (tmp_path / "out").exists()


def test_a_speed_series_with_one_speed_twice_is_refused_before_the_run(tmp_path):
    """Two scans at one angle and one line rate are not a speed series: the error names the
    angle, the rate and how often it was given, and nothing is written."""
    z = np.asarray(_scans(angles=(0.0,), rotation=0.0)[0][0].trace)
    _write_pair(tmp_path, "a", z, 6000.0)
    pair = "{trace: a_trace.npz, retrace: a_retrace.npz, line_rate_hz: 1, angle_deg: 0}"
    proc = _calibrate(tmp_path, f"{{scans: [{pair}, {pair}]}}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    said = "line_rate_hz 1 is given 2 times (scans.0 and scans.1)"
    assert "data: scans:" in proc.stderr and said in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "out").exists()


def test_a_set_whose_scans_show_different_pitches_names_the_scan(tmp_path):
    """Two scans of one size said to show one lattice, the second of a lattice of half the
    pitch: the run names that scan and the spacing it shows before it writes anything."""
    z = np.asarray(_scans(angles=(0.0,), rotation=0.0)[0][0].trace)
    spec = SimulatedCalibration(pixels=64, size_nm=6000, angles_deg=[0.0], lattice_rotation_deg=0.0)
    fine, _ = calibrate.calibration_scans(spec, CalibrationLattice(pitch_nm=500, rotation_deg="fit"))
    _write_pair(tmp_path, "a", z, 6000.0)
    _write_pair(tmp_path, "b", np.asarray(fine[0].trace), 6000.0)
    pair = "{{trace: {n}_trace.npz, retrace: {n}_retrace.npz, line_rate_hz: {r}, angle_deg: 0}}"
    data = f"{{scans: [{pair.format(n='a', r=1)}, {pair.format(n='b', r=2)}]}}"
    proc = _calibrate(tmp_path, data)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "2 Hz" in proc.stderr and "stated pitch is 1000" in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "out").exists()


def test_the_real_1d_grating_is_refused_with_the_reason(tmp_path):
    """The shipped Nanosurf image (lines; its retrace alone, which a trace a pixel earlier along
    the lines joins) cannot identify a 2-D scanner: step A says why before it touches the
    output folder."""
    from jaxafm.instrument.images import AFMImage, read_image, save_image

    real = read_image(GRATING)
    save_image(AFMImage(np.roll(real.z, -1, axis=1), real.pixel_size), tmp_path / "trace.npz")
    proc = _calibrate(
        tmp_path, "{trace: trace.npz, retrace: builtin:grating_1d_nanosurf.txt, line_rate_hz: 1}"
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "lines of a 1-D grating" in proc.stderr and "fit_line_grating" in proc.stderr
    assert not (tmp_path / "out").exists()


def test_a_lattice_that_does_not_fill_the_image_is_refused():
    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    z = np.asarray(scans[0].trace).copy()
    z[:, 40:] = np.median(z)  # the right third bare
    bare = CalibrationScan(z, z, scans[0].raster, 1000.0, (500.0, 500.0), 10.0)
    with pytest.raises(ValueError, match=r"the lattice covers only rows .* crop the image"):
        bare.features()


def test_an_implausible_fit_saves_no_model(tmp_path, monkeypatch):
    from jaxafm.config import CalibrateConfig

    monkeypatch.setattr(staged_fit, "implausible", lambda *a: ["the tip travels 9 µm over a 3 µm image"])
    # the validation figure's image placed on the fitted path: a PI model without coupling moves
    # each axis alone, so its path is a rectangular grid, whose Delaunay triangulation
    # (scipy's griddata in calibrate._placed) is degenerate and took 0.02 to 15 s (measured, on
    # one path). Not what this test checks: the image on the nominal grid stands in (the CLI
    # run of test_step_a places a fitted path with coupling through the real one).
    extent = lambda xy: (xy[..., 0].min(), xy[..., 0].max(), xy[..., 1].min(), xy[..., 1].max())
    monkeypatch.setattr(calibrate, "_placed", lambda path, z: (z, extent(path)))
    cfg = CalibrateConfig(
        simulate={"pixels": 64, "size_nm": 6000},  # the scans of _scans((0.0,), 0.0): compiled already
        models=[{"name": "pi", "kind": "pi", "operators": 4, "effects": []}],
        # the configured model alone, no ladder (whose rungs this check does not need)
        solver={"max_steps": 3, "blur_px": [], "select": False},  # the chord stage of the test above
        compensate=None,
    )
    with pytest.raises(ValueError, match="failed the plausibility checks.*pi: the tip travels 9 µm"):
        calibrate.run(cfg, tmp_path / "c.yaml", Output(tmp_path), log=lambda *_: None)
    assert not (tmp_path / "model_pi.json").exists() and (tmp_path / "metrics.json").is_file()


def test_a_compensated_scan_the_inverse_refuses_is_reported_and_the_rest_is_written(tmp_path, monkeypatch):
    """A compensated scan 20 % wider than the calibration on each side needs drives beyond the
    range the model was fitted over: its inverse refuses them. The run goes on, writes the model,
    the uncompensated scan's errors and the refusal into metrics.json, then fails naming it."""
    from jaxafm.config import CalibrateConfig

    for check in ("implausible", "unvalidated", "undetermined", "unsettled"):  # a 3-step fit: the
        monkeypatch.setattr(staged_fit, check, lambda *a, **k: [])  # compensation is the point here
    extent = lambda xy: (xy[..., 0].min(), xy[..., 0].max(), xy[..., 1].min(), xy[..., 1].max())
    monkeypatch.setattr(calibrate, "_placed", lambda path, z: (z, extent(path)))  # as the test above
    cfg = CalibrateConfig(
        simulate={"pixels": 64, "size_nm": 6000},
        models=[{"name": "pi", "kind": "pi", "operators": 4, "effects": []}],
        solver={"max_steps": 3, "blur_px": [], "select": False},
        compensate={"scan_fraction": 1.0, "overscan": 0.2, "inverses": ["analytic"], "paper_baseline": False},
    )
    with pytest.raises(
        ValueError, match=r"compensated scan of pi \+ analytic was refused: .*outside the range"
    ):
        calibrate.run(cfg, tmp_path / "c.yaml", Output(tmp_path), log=lambda *_: None)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert "outside the range" in metrics["pi_analytic_refused"]
    assert "uncompensated_linearity_error_trace_pct" in metrics and (tmp_path / "model_pi.json").is_file()


@pytest.mark.parametrize(
    "data, match",
    [
        (
            "{scans: [{trace: a, retrace: b, line_rate_hz: 1, angle_deg: 90}, "
            "{trace: c, retrace: d, line_rate_hz: 1, angle_deg: 90}]}",
            r"data: scans: the scan at angle_deg 90 and line_rate_hz 1 is given 2 times",
        ),
        (
            "{trace: a, retrace: b, line_rate_hz: 1, scans: [{trace: a, retrace: b, line_rate_hz: 1}]}",
            "not both",
        ),
        ("{trace: a}", "missing retrace"),
        ("{trace: a, retrace: b, line_rate_hz: 1, scan_range_nm: -5}", "data.scan_range_nm.0"),
    ],
)
def test_a_bad_scan_set_names_the_key(tmp_path, data, match):
    from jaxafm.config import CalibrateConfig, ConfigError, load_config

    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"data: {data}\n")
    with pytest.raises(ConfigError, match=match):
        load_config(cfg, CalibrateConfig)


@pytest.mark.parametrize(
    "text, match",
    [
        ("simulate: {angles_deg: [0, 0]}\n", "simulate: .*each scan angle once"),
        ("simulate: {lattice_rotation_deg: 60}\n", "simulate.lattice_rotation_deg"),
        ("simulate: {}\ngrating: {rotation_deg: 50}\n", "grating.rotation_deg"),
        ("simulate: {}\ngrating: {rotation_deg: fitted}\n", "grating.rotation_deg"),
        (
            "simulate: {}\nmodels: [{name: m, known: {y_gain: [1940, 40]}}]\n",
            "known: 'y_gain' is not a quantity.*y_gain_nm_per_v",
        ),
        (
            "simulate: {}\nmodels: [{name: m, known: {y_gain_nm_per_v: [1940, 0]}}]\n",
            r"known: y_gain_nm_per_v: \[1940.0, 0.0\] needs .*sd > 0",
        ),
        (
            "simulate: {}\nmodels: [{name: m, known: {y_gain_nm_per_v: [1940]}}]\n",
            "models.0.known.y_gain_nm_per_v",
        ),
        (
            "simulate: {}\nmodels: [{name: m, effects: [coupling], known: {x_creep_per_decade: [0.01, 0.005]}}]\n",
            r"known: x_creep_per_decade needs the effect 'creep' among effects \(coupling\)",
        ),
        (
            "simulate: {}\nmodels: [{name: m, known: {coupling_yx: [0.01, 0.005]}}]\n",
            "models m: known: coupling_yx cannot be stated while grating.rotation_deg is 'fit'",
        ),
    ],
)
def test_bad_angles_name_the_key(tmp_path, text, match):
    from jaxafm.config import CalibrateConfig, ConfigError, load_config

    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(cfg, CalibrateConfig)


def test_an_image_without_its_size_is_refused_before_the_run(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    scans, _ = _scans(angles=(0.0,), rotation=0.0)
    for k in ("t", "r"):
        tifffile.imwrite(tmp_path / f"{k}.tif", np.asarray(scans[0].trace, dtype=np.float32))
    proc = _calibrate(tmp_path, "{trace: t.tif, retrace: r.tif, line_rate_hz: 1}")
    assert proc.returncode == 2 and "size" in proc.stderr and "t.tif" in proc.stderr, proc.stderr[-1500:]
    assert not (tmp_path / "out").exists()


def test_a_later_scans_lattice_shift_is_found_through_a_model_loose_across_the_lattice():
    """A later scan's features seen through the first scan's model: a whole shift of (1, -2)
    sites, plus the model's error growing linearly to 0.6 pitch at the lattice's edge, plus
    noise. Rounding the offsets alone splits them between shifts; with the trend taken out
    every feature gives the shift. Offsets that follow no shift and no trend (scans of
    different lattices) still do not agree."""
    from jaxafm.identify.staged_fit import _index_shift

    rng = np.random.default_rng(0)
    ij = np.stack(np.meshgrid(np.arange(-3, 4), np.arange(-3, 4)), axis=-1).reshape(-1, 2).astype(float)
    d = np.array([1.0, -2.0]) + ij @ np.array([[0.2, 0.05], [-0.05, 0.2]]) + rng.normal(0, 0.05, ij.shape)
    assert float(np.mean(np.all(np.round(d) == np.round(np.median(d, axis=0)), axis=1))) < 0.8
    shift, agree = _index_shift(d, ij)
    assert shift.tolist() == [1.0, -2.0] and agree >= 0.95
    _, agree = _index_shift(rng.uniform(-1.5, 1.5, ij.shape), ij)
    assert agree < 0.8


def _placed_by_the_true_scanner():
    """The chords of a 0-degree scan of the simulated lattice, trace and retrace, placed where
    the true scanner's tip crossed them (:func:`held_out.placed_chords`)."""
    scans, sim = _scans(angles=(0.0,), rotation=0.0)
    found = [[scans[0].feature_matches()[0], scans[0].feature_matches()[1][0]]]
    every, _ = held_out.split_chords(found, hold_out=False)
    return held_out.placed_chords(true_scan_model(sim), scans, every)


def _remapped(placed, y_map):
    """``placed`` with every chord end's y coordinate replaced by ``y_map(y)``."""
    out = []
    for tips, ij, along in placed[0]:
        tips = tips.copy()
        tips[..., 1] = y_map(tips[..., 1])
        out.append((tips, ij, along))
    return [out]


def test_feature_widths_scale_with_the_path_that_places_them():
    """Closed form: stretching the path 10 % along y widens every feature 10 % across the lines
    (the chords across a 0-degree scan's lines run along y) and leaves the widths along them,
    and so every spread, as they were (to the square of the chords' small tilt off the axes);
    through the true scanner the lattice's features are one width to within a pixel (94 nm) of
    edge noise."""
    placed = _placed_by_the_true_scanner()
    along, across = held_out.feature_widths(placed)
    assert len(along) >= 20 and len(across) >= 20
    assert np.std(along) < 94.0 and np.std(across) < 94.0
    stretched = held_out.feature_widths(_remapped(placed, lambda y: 1.1 * y))
    # to the square of the chords' tilt off the axes (the scanner's coupling, ~1e-2)
    np.testing.assert_allclose(stretched[0], along, rtol=1e-3)
    np.testing.assert_allclose(stretched[1], 1.1 * across, rtol=1e-3)
    from jaxafm.identify.plausibility import uneven_widths

    assert not uneven_widths(held_out.width_metrics(placed, _remapped(placed, lambda y: 1.1 * y)))


def test_a_path_that_runs_unevenly_across_the_features_is_refused():
    """A path that runs up to 40 % too fast and too slow along y, in a wave 2.7 pitches long (so
    the features sit at every phase of it), makes the features' widths across the lines spread
    about 28 % (0.4 / sqrt 2) where the true path leaves a few %: the width check names that
    direction, and only it."""
    from jaxafm.identify.plausibility import uneven_widths

    placed = _placed_by_the_true_scanner()
    wave = 2.7 * 1000.0  # nm
    uneven = _remapped(placed, lambda y: y + 0.4 * wave / (2 * np.pi) * np.sin(2 * np.pi * y / wave))
    m = held_out.width_metrics(placed, uneven)
    assert m["feature_width_spread_across_corrected_pct"] > 15.0, m
    failures = uneven_widths(m)
    assert len(failures) == 1 and "widths across the lines less uniform" in failures[0], failures
