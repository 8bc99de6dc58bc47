"""Step A on lattice images made by the independent generator (tests/independent_lattice.py,
which shares no code with jaxafm's simulator): the files a user would give, read and identified
as ``jaxafm calibrate`` does, scored against the generator's truth.

The full study (twenty and more cases, speed series) is ``experiments/step_a_independent.py``;
these are two of its cases at a small size."""

import json
from pathlib import Path

import independent_lattice as G
import numpy as np
import pytest

from jaxafm.config import CalibrateConfig
from jaxafm.identify.scan_model import ScanModelSpec, feature_reach, nominal_scan_model
from jaxafm.identify.selection import supported_dead_zones
from jaxafm.identify.stages import StageKind
from jaxafm.jobs.calibrate import identify_model, read_calibration

MODEL = {"name": "gpi", "kind": "gpi", "operators": 16, "deadzones": 3}


def _identify(
    case: dict, folder: Path, effects: list, select: bool = True, operators: int = 16, lengths: bool = False
):
    files = G.write_case(case, folder)
    given = json.loads(Path(files["data"]).read_text())
    cfg = CalibrateConfig(
        data=given["data"],
        grating=given["grating"],
        models=[MODEL | {"effects": effects, "operators": operators}],
        solver={"coarsen": "auto", "max_steps": 100, "select": select, "chord_lengths": lengths},
        compensate=None,
    )
    scans = read_calibration(cfg.data, cfg.grating, folder / "c.yaml", log=lambda *_: None)
    said = []
    return (
        scans,
        (lambda: identify_model(scans, cfg.models[0], cfg.solver, cfg.grating, said.append, measured=True)),
        said,
    )


def _path_error_px(model, scans, case) -> float:
    """rms (px) of the fitted tip path against the generator's over every pixel, after the one
    rigid motion (turn and shift) no image can see."""
    fitted = np.concatenate([np.asarray(p).reshape(-1, 2) for scan in scans for p in model.paths(scan)])
    true = np.concatenate(
        [
            np.asarray(s.truth[f"tip_{k}_nm"]).reshape(-1, 2)
            for s in case["scans"]
            for k in ("trace", "retrace")
        ]
    )
    a, b = fitted - fitted.mean(axis=0), true - true.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    r = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    e = a @ r - b
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) / scans[0].raster.pixel_size[0]


@pytest.mark.parametrize("lengths", [False, True])
def test_a_drawn_scanner_is_recovered_from_one_scan(tmp_path, lengths):
    """A Preisach scanner with drive lag, creep, coupling and drift, a lattice of rounded pits or
    pillars with sloped walls under a broadened tip, a plane, a bow, line offsets, spikes and
    noise, one 0-degree scan: the model step A keeps puts the held-out features where they are
    to a third of the raw images' error or better and within 0.3 px, and its tip path over the
    scan is nearer the true one than a third of the nominal calibration's distance from it; so
    too with the chords' lengths fitted (``solver.chord_lengths``)."""
    case = G.draw_case(3, "fine", line_rates_hz=(1.0,), angles_deg=(0.0,), pixels=64)
    scans, run, said = _identify(
        case,
        tmp_path,
        ["creep", "coupling", "bow", "feedback_lag"],
        select=False,
        operators=4,
        lengths=lengths,
    )
    ident = run()
    assert ident.model.chord_lengths is lengths
    v = ident.validation
    pixel = scans[0].raster.pixel_size[0]
    assert StageKind.IMAGES not in ident.kinds, "measured images: the chord stages alone by default"
    assert ident.plausible, (ident.failures, said[-5:])
    assert v["held_out_rms_nm"] <= min(v["held_out_raw_rms_nm"] / 3, 0.3 * pixel), said[-3:]
    nominal = nominal_scan_model(scans[0], ident.spec, scans)
    assert _path_error_px(ident.model, scans, case) < _path_error_px(nominal, scans, case) / 3


def test_a_three_by_three_lattice_is_refused_or_reduced_with_the_reason(tmp_path):
    """Nine features, half of them held out, give about 20 training coordinates; a four-play
    scanner with creep, coupling, bow and feedback lag has as many parameters: step A refuses, or
    keeps a smaller model and its log says which rungs the data did not support."""
    # 32 px over the three pitches (~11 px a pitch) finds the same features as 64 px; at 64 px the
    # chord stage is coarsened to 32 px a line anyway, and the finer image only slowed the rest
    case = G.draw_case(901, "fine", pixels=32, unidentifiable="few_features")
    effects = ["creep", "coupling", "bow", "feedback_lag"]
    _, run, said = _identify(case, tmp_path, effects, operators=4)
    try:
        ident = run()
    except ValueError as e:
        assert "feature" in str(e) or "determine" in str(e)
        return
    kept = ident.spec
    assert kept.operators < 4 or set(kept.effects) < set(effects) or ident.failures, kept
    assert any("model ladder" in line and "not kept" in line for line in said)


def test_the_dead_zones_sit_inside_the_features_reach_and_as_many_as_it_holds(tmp_path):
    """A lattice of pitch P filling an image of half width W / 2 has a feature within P of every
    border, so its chords reach between W / 2 - P and W / 2 from the centre; the model ladder's
    dead zones sit inside that reach (none beyond the last chord, where no data holds its
    weight), and on a lattice reaching about two pitches from the centre, one a side (their
    stretches must hold a pitch), which the note says."""
    case = G.draw_case(5, "fine", line_rates_hz=(1.0,), angles_deg=(0.0, 90.0), pixels=64)
    scans, _, _ = _identify(case, tmp_path, ["asymmetry", "coupling"])
    half, pitch = scans[0].raster.size[0] / 2, min(scans[0].pitch)
    configured = ScanModelSpec(kind="gpi", effects=("asymmetry", "coupling"), operators=4, deadzones=3)
    spec, note = supported_dead_zones(configured, scans)
    assert spec.deadzones == 1 and "pitch" in note
    for k in (0, 1):
        below, above = feature_reach(scans)[k]
        assert half - pitch < above <= half and -half <= below < -(half - pitch)
        zones = getattr(nominal_scan_model(scans[0], spec, scans).scanner, "xy"[k]).hysteresis.deadzone
        assert below < float(zones.lower.min()) and float(zones.upper.max()) < above
