"""Step A's tip path against the simulated truth, for each scanner of a finished study.

Each model the study saved in ``scanners/`` is driven along its scanner's first calibration scan
(the study's own: ``jaxafm.jobs.study.scanner_draws`` and the first angle and line rate of
``calibration.simulate`` of the config the study's run manifest records, the same scan whatever
else the study scans) and compared with the simulator's true tip path, trace and retrace, x and
y rms after the one rigid shift no image sees. A model that fits the calibration images yet
misplaces the tip by hundreds of nm shows here, where the study's own figures show only what
the landmarks and the local scans made of it. Beside it, which of the matchings of the
retrace's lattice indices that step A tries at the line reversal is the right one
(``CalibrationScan.feature_matches``, one to three: the one whose trace and retrace features lie
on the same true lattice sites through the simulator's scanner), or none.

    python experiments/step_a_study_paths.py experiments/results/study

writes ``experiments/results/step_a_study_paths/study.json`` (named after the study's folder).
``--angle`` and ``--line-rate`` drive the models along a scan at another angle or line rate (the
file then named ``study_90deg_2Hz.json``, say): a model fitted at one rate can misplace the tip at
another.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import equinox as eqx
import numpy as np
from bench_step_a import path_error

from jaxafm.config import StudyConfig
from jaxafm.identify.scan_model import ScanModelSpec, nominal_scan_model
from jaxafm.identify.step_a import true_scan_model
from jaxafm.instrument.afm import default_afm
from jaxafm.jobs import study as job
from jaxafm.jobs.calibrate import calibration_scans
from jaxafm.jobs.folder import read_manifest
from jaxafm.model.io import load_model

ROOT = Path(__file__).resolve().parents[1]


def path_rms(scanner, scan, truth) -> list:
    """x and y rms (nm) of ``scanner``'s tip path along ``scan`` less the true one, over trace and
    retrace, after their mean difference (the rigid shift) is taken out
    (``bench_step_a.path_error`` through a scan model carrying ``scanner``)."""
    model = eqx.tree_at(lambda m: m.scanner, nominal_scan_model(scan, ScanModelSpec()), scanner)
    e = path_error(model, scan, truth)
    return [e["path_x_rms_nm"], e["path_y_rms_nm"]]


def one_scan(calibration, angle: float, rate: float, afm) -> tuple:
    """``(scan, Simulation)``: the one calibration scan of a study's ``calibration`` config at
    ``angle`` (degrees) and ``rate`` (Hz), of the simulated AFM ``afm``."""
    spec = calibration.simulate.model_copy(update={"angles_deg": [angle], "line_rate_hz": rate})
    (scan,), sim = calibration_scans(spec, calibration.grating, afm)
    return scan, sim


def right_matching(scan, sim, wide_loop: bool = False) -> str:
    """Which retrace matching of ``scan`` that step A tries (``"first"``, ``"second"``, with
    ``wide_loop`` also ``"third"``, or ``"none"``) puts its trace and retrace features on the same
    lattice sites through the true scanner of ``sim``."""
    true = true_scan_model(sim)
    trace, retraces = scan.feature_matches(wide_loop)
    for name, retrace in zip(("first", "second", "third"), retraces):
        e = true.site_errors(scan, [(trace.rc, trace.ij), (retrace.rc, retrace.ij)])
        if len({tuple(np.round(np.median(np.asarray(x), axis=0))) for x in e}) == 1:
            return name
    return "none"


def finished_study_config(folder: Path) -> StudyConfig:
    """The config a finished study in ``folder`` ran with, from its run manifest."""
    manifest = read_manifest(folder)
    if manifest is None:
        raise SystemExit(f"{folder}: no run manifest: not a study's output folder")
    return StudyConfig.model_validate(manifest["config"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("study", type=Path, help="a finished study's output folder")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "step_a_study_paths")
    ap.add_argument("--angle", type=float, help="scan angle (degrees); default: the study's first")
    ap.add_argument("--line-rate", type=float, help="line rate (Hz); default: the study's first")
    a = ap.parse_args()
    cfg = finished_study_config(a.study)
    spec = cfg.calibration
    angle = spec.simulate.angles_deg[0] if a.angle is None else a.angle
    rate = spec.simulate.line_rates_hz[0] if a.line_rate is None else a.line_rate
    rows = []
    for s, params in enumerate(job.scanner_draws(cfg)):
        saved = a.study / "scanners" / f"model_{s:05d}.json"
        scan, sim = one_scan(spec, angle, rate, default_afm(**params))
        right = right_matching(scan, sim, spec.solver.wide_loop)
        if not saved.is_file():
            rows.append({"scanner": s, "path_rms_nm": None, "right_matching": right})
            print(f"scanner {s:2d}: no model saved; right matching {right}", flush=True)
            continue
        x, y = path_rms(load_model(saved), scan, sim.measured)
        rows.append({"scanner": s, "path_rms_nm": [x, y], "right_matching": right})
        print(f"scanner {s:2d}: x {x:9.2f} nm  y {y:9.2f} nm rms; right matching {right}", flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    suffix = "" if a.angle is None and a.line_rate is None else f"_{angle:g}deg_{rate:g}Hz"
    out = a.out / f"{a.study.resolve().name}{suffix}.json"
    scan = {"angle_deg": angle, "line_rate_hz": rate}
    out.write_text(json.dumps({"study": a.study.resolve().name, "scan": scan, "scanners": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
