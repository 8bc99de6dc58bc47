"""Step A of chosen scanners of a study, identified again with its log: what each stage did (its
loss, the retrace matchings it compared and their losses, the training features), where a
study, which keeps only the model, says nothing of it.

Each scanner is the study's own (``jaxafm.jobs.study.scanner_draws`` of the config), scanned and
identified as the study does (``jaxafm.jobs.calibrate.calibration_scans``,
``jaxafm.jobs.run.identify_scanner``); ``--max-steps`` replaces the config's
``calibration.solver.max_steps`` (one number, or one per stage, comma-separated); ``--lag-hold
zero`` steps step A's lag through the zero hold (``jaxafm.identify.scan_model.LAG_HOLD``), the
hold jaxafm's simulated truth steps its own through.

    python experiments/step_a_study_log.py configs/study_wide_0_90_wide_loop.yaml 3 6 8
    python experiments/step_a_study_log.py configs/study_wide_0_90_wide_loop.yaml 3 6 --max-steps 30,120,60,100
    python experiments/step_a_study_log.py configs/study_wide_0_90_wide_loop.yaml 8 --max-steps 120,30,60,100
    python experiments/step_a_study_log.py configs/study_classes_speed.yaml 2 14 --lag-hold zero

writes ``experiments/results/step_a_study_log/<config>_<scanners>[_steps_<max-steps>][_zero_hold].json``:
each scanner's draws, its log lines, its step A time, and the model's tip path against the
truth along the 0 degree calibration scan at each of the config's line rates (x and y rms after
the rigid shift, ``step_a_study_paths.path_rms``); and the delays it fitted (:func:`fitted_delays`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from unittest import mock

from pydantic import ValidationError
from step_a_study_paths import one_scan, path_rms

from jaxafm.config import StudyConfig, load_config
from jaxafm.identify import scan_model
from jaxafm.instrument.afm import default_afm
from jaxafm.jobs import run
from jaxafm.jobs import study as job
from jaxafm.jobs.calibrate import calibration_scans, identify_model
from jaxafm.jobs.run import ImplausibleModel, identify_scanner
from jaxafm.model.effects import HOLDS

OUT = Path(__file__).resolve().parent / "results" / "step_a_study_log"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", type=Path)
    ap.add_argument("scanners", type=int, nargs="+")
    ap.add_argument("--max-steps", default=None, help="solver.max_steps, e.g. 40 or 30,120,60,100")
    ap.add_argument("--lag-hold", choices=HOLDS, default=scan_model.LAG_HOLD, help="the hold of step A's lag")
    args = ap.parse_args()
    cfg = load_config(args.config, StudyConfig)
    if args.max_steps:  # validated as the config's own would be (one step limit or one per stage)
        steps = [int(v) for v in args.max_steps.split(",")]
        calibration = cfg.calibration.model_dump()
        calibration["solver"]["max_steps"] = steps[0] if len(steps) == 1 else steps
        try:
            calibration = type(cfg.calibration).model_validate(calibration)
        except ValidationError as e:
            raise SystemExit(f"--max-steps {args.max_steps}: {e.errors()[0]['msg']}") from None
        cfg = cfg.model_copy(update={"calibration": calibration})
    draws = job.scanner_draws(cfg)
    rows = []
    for s in args.scanners:
        params = draws[s]
        print(f"scanner {s}: {params}", flush=True)
        lines = []
        log = lambda m: (lines.append(m), print("   ", m, flush=True))
        afm = default_afm(**params)  # the truth class's scanner, as the study draws it
        scans, _ = calibration_scans(cfg.calibration.simulate, cfg.calibration.grating, afm)
        began = time.perf_counter()
        identified = []  # identify_scanner keeps the scanner alone; its whole model is kept here
        keeping = lambda *a, **k: identified.append(identify_model(*a, **k)) or identified[-1]
        try:
            with (
                mock.patch.object(run, "identify_model", keeping),
                mock.patch.object(scan_model, "LAG_HOLD", args.lag_hold),
            ):
                scanner, _ = identify_scanner(cfg, scans, args.config, log)
        except ImplausibleModel as e:
            scanner = None
            log(f"refused: {e}")
        seconds = time.perf_counter() - began
        delays = fitted_delays(identified[-1].model) if identified else {}
        if delays:
            log("fitted delays: " + ", ".join(f"{k} {v:.3f}" for k, v in delays.items()))
        paths = {} if scanner is None else tip_paths(cfg, afm, scanner)
        for rate, (x, y) in paths.items():
            log(f"tip path along the 0 degree scan at {rate} Hz: x {x:.2f} nm, y {y:.2f} nm rms")
        rows.append(
            {
                "scanner": s,
                "draws": params,
                "log": lines,
                "seconds": seconds,
                "path_rms_nm": paths,
                "delays_ms": delays,
            }
        )
    name = f"{args.config.stem}_{'_'.join(map(str, args.scanners))}"
    name += f"_steps_{args.max_steps.replace(',', '_')}" if args.max_steps else ""
    name += f"_{args.lag_hold}_hold" if args.lag_hold != scan_model.LAG_HOLD else ""
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"{name}.json"
    path.write_text(
        json.dumps(
            {
                "config": str(args.config),
                "max_steps": args.max_steps,
                "lag_hold": args.lag_hold,
                "scanners": rows,
            },
            indent=1,
        )
    )
    print(f"wrote {path}")


def fitted_delays(model) -> dict:
    """The delays (ms) step A's whole ``model`` fitted: the drive's lag per axis
    (``rate_dependence``), and the z signal's lag (``feedback_lag``) with the chords' edge delay,
    those the model has."""
    out = {}
    for a in ("x", "y"):
        lag = getattr(model.scanner, a).rate_dependence
        if lag is not None:
            out[f"rate_lag_{a}_ms"] = 1e3 * float(lag.tau)
    if model.feedback is not None:
        out["feedback_lag_ms"] = 1e3 * float(model.feedback.tau)
        out["edge_delay_ms"] = 1e3 * float(model.edge_delay)
    return out


def tip_paths(cfg: StudyConfig, afm, scanner) -> dict:
    """x and y rms (nm) of ``scanner``'s tip path less the true one along the 0 degree
    calibration scan at each of the config's line rates, keyed by the rate (Hz)."""
    paths = {}
    for rate in cfg.calibration.simulate.line_rates_hz:
        scan, sim = one_scan(cfg.calibration, 0.0, rate, afm)
        paths[f"{rate:g}"] = path_rms(scanner, scan, sim.measured)
    return paths


if __name__ == "__main__":
    main()
