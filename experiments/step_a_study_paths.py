"""Step A's tip path against the simulated truth, for each scanner of a finished study.

Each model the study saved in ``scanners/`` is driven along its scanner's calibration scan (the
study's own: ``jaxafm.jobs.study.scanner_draws`` and ``calibration.simulate`` of the config the
study's run manifest records) and compared with the simulator's true tip path, trace and
retrace, x and y rms after the one rigid shift no image sees. A model that fits the calibration
images yet misplaces the tip by hundreds of nm shows here, where the study's own figures show
only what the landmarks and the local scans made of it.

    python experiments/step_a_study_paths.py experiments/results/study

writes ``experiments/results/step_a_study_paths/study.json`` (named after the study's folder).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import equinox as eqx
from bench_step_a import path_error

from jaxafm.config import StudyConfig
from jaxafm.identify.scan_model import ScanModelSpec, nominal_scan_model
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("study", type=Path, help="a finished study's output folder")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "step_a_study_paths")
    a = ap.parse_args()
    manifest = read_manifest(a.study)
    if manifest is None:
        raise SystemExit(f"{a.study}: no run manifest: not a study's output folder")
    cfg = StudyConfig.model_validate(manifest["config"])
    spec = cfg.calibration
    rows = []
    for s, params in enumerate(job.scanner_draws(cfg)):
        saved = a.study / "scanners" / f"model_{s:05d}.json"
        if not saved.is_file():
            rows.append({"scanner": s, "path_rms_nm": None})
            continue
        scans, sim = calibration_scans(spec.simulate, spec.grating, default_afm(**params))
        rows.append({"scanner": s, "path_rms_nm": path_rms(load_model(saved), scans[0], sim.measured)})
        print(
            f"scanner {s:2d}: x {rows[-1]['path_rms_nm'][0]:9.2f} nm  y {rows[-1]['path_rms_nm'][1]:9.2f} nm rms",
            flush=True,
        )
    a.out.mkdir(parents=True, exist_ok=True)
    out = a.out / f"{a.study.resolve().name}.json"
    out.write_text(json.dumps({"study": a.study.resolve().name, "scanners": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
