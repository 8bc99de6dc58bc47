"""Push success over at least 200 randomised targets: A+B+C and the push on several particle fields.

Each field is a new random set of particles (positions jittered, radii uniform in 5-50 nm) and new
push goals, on the instrument of ``configs/paper.yaml`` with the scanner model that ``jaxafm run``
identified (its ``model_scanner.json``). Only the A+B stage runs (it goes on to step C and the push).

    python experiments/push_study.py --model experiments/results/paper/model_scanner.json --fields 3

Writes ``experiments/results/push_study/metrics.json`` and one folder per field.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml

from jaxafm.config import RunConfig
from jaxafm.jobs import run as run_job
from jaxafm.jobs import run_folder

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "paper.yaml")
    ap.add_argument(
        "--model", type=Path, default=ROOT / "experiments" / "results" / "paper" / "model_scanner.json"
    )
    ap.add_argument("--fields", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "push_study")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()
    raw = yaml.safe_load(args.config.read_text())
    results = []
    for field in range(args.fields):
        raw["calibration"]["model_file"] = str(args.model.resolve())
        raw["stages"] = ["A+B"]
        raw["particles"]["seed"] = 100 + field
        raw["seed"] = 100 + field
        cfg = RunConfig.model_validate(raw)
        out = args.out / f"field_{field}"
        print(f"--- field {field} (particle seed {cfg.particles.seed})")
        with run_folder(out, "run", args.config, cfg, overwrite=args.overwrite) as folder:
            m = run_job.run(cfg, args.config, folder.output)
        results.append(m)
    n = sum(m["push_trials"] for m in results)
    success = sum(round(m["push_success_pct"] * m["push_trials"] / 100) for m in results)
    within = sum(round(m["ABC_within_0p1R_pct"] * m["push_trials"] / 100) for m in results)
    summary = {
        "fields": args.fields,
        "push_trials": n,
        "push_successes": success,
        "push_success_pct": 100 * success / n,
        "ABC_within_0p1R_pct": 100 * within / n,
        "ABC_error_over_radius_max": max(m["ABC_error_over_radius_max"] for m in results),
        "AB_polynomial_error_max_nm": max(m["AB_polynomial_error_max_nm"] for m in results),
        "AB_polynomial_error_median_nm_per_field": [m["AB_polynomial_error_median_nm"] for m in results],
        "push_error_max_nm": max(m["push_error_max_nm"] for m in results),
    }
    (args.out / "metrics.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
