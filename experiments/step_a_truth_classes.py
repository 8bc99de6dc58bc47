"""Step A alone on a study's scanners: the stages it ran and its tip path against the simulated
truth, on the first calibration scan it fitted (the first angle at the first line rate) and on
the same scan at a quarter of that rate.

Each scanner is the study's (``jaxafm.jobs.study.scanner_draws``: its truth class and drawn
parameters); step A is the study's (``calibration`` of the config), with the chord stage's step
limit, the line rates and the model's effects optionally changed. The tip path error is x, rms
over the image after the one rigid shift no image sees (``bench_step_a.path_error``).

    python experiments/step_a_truth_classes.py --scanners 0 2 3 14
    python experiments/step_a_truth_classes.py --scanners 3 --chord-steps 150
    python experiments/step_a_truth_classes.py --scanners 14 --rates 1 4 \\
        --effects asymmetry creep coupling bow feedback_lag rate_dependence
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from bench_step_a import path_error

from jaxafm.config import StudyConfig, load_config
from jaxafm.instrument.afm import default_afm
from jaxafm.jobs import study as job
from jaxafm.jobs.calibrate import calibration_scans, identify_model

ROOT = Path(__file__).resolve().parents[1]


def step_a(cfg: StudyConfig, s: int, chord_steps, rates, effects) -> dict:
    """Step A on scanner ``s`` of ``cfg`` with the changes asked for; its log and tip paths."""
    params = job.scanner_draws(cfg)[s]
    spec = cfg.calibration
    simulate = spec.simulate.model_copy(update={"line_rate_hz": rates[0] if len(rates) == 1 else rates})
    model = spec.model if effects is None else spec.model.model_copy(update={"effects": effects})
    solver, steps = spec.solver, spec.solver.max_steps
    if isinstance(
        steps, list
    ):  # one chord stage per line rate (``chord_steps`` or the first limit), then the images'
        steps = [chord_steps or steps[0]] * len(rates) + steps[1:]
        solver = solver.model_copy(update={"max_steps": steps})
    afm = default_afm(**params)
    scans, sim = calibration_scans(simulate, spec.grating, afm)
    lines = []
    began = time.perf_counter()
    ident = identify_model(scans, model, solver, spec.grating, lines.append)
    seconds = time.perf_counter() - began
    first = spec.simulate.angles_deg[:1]  # the paths along the first angle's scan, whatever else step A saw
    scans, sim = calibration_scans(
        spec.simulate.model_copy(update={"angles_deg": first, "line_rate_hz": rates[0]}), spec.grating, afm
    )
    slow_scans, slow = calibration_scans(
        spec.simulate.model_copy(update={"angles_deg": first, "line_rate_hz": rates[0] / 4, "seed": 5}),
        spec.grating,
        afm,
    )
    lag = ident.model.scanner.x.rate_dependence
    return {
        "scanner": s,
        "truth": {k: v for k, v in params.items() if k != "drift_nm_per_min"},
        "chord_steps": chord_steps,
        "line_rates_hz": list(rates),
        "effects": list(model.effects),
        "seconds": seconds,
        "stages_kept": list(ident.accepted),
        "fitted_rate_tau_s": None if lag is None else float(lag.tau),
        "tip_path": path_error(ident.model, scans[0], sim.measured),
        "tip_path_quarter_rate": path_error(ident.model, slow_scans[0], slow.measured),
        "log": [str(line) for line in lines],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "study_classes.yaml")
    ap.add_argument("--scanners", type=int, nargs="+", required=True)
    ap.add_argument("--chord-steps", type=int, default=None, help="the chord stages' step limit")
    ap.add_argument(
        "--rates", type=float, nargs="+", default=None, help="line rates, Hz (default: the config's)"
    )
    ap.add_argument("--effects", nargs="+", default=None, help="the model's effects (default: the config's)")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "step_a_truth_classes")
    a = ap.parse_args()
    cfg = load_config(a.config, StudyConfig)
    rates = a.rates or cfg.calibration.simulate.line_rates_hz
    a.out.mkdir(parents=True, exist_ok=True)
    for s in a.scanners:
        r = step_a(cfg, s, a.chord_steps, rates, a.effects)
        changes = [f"chords{a.chord_steps}"] if a.chord_steps else []
        changes += ["rates" + "_".join(f"{v:g}" for v in rates)] if a.rates else []
        name = "_".join([f"scanner_{s:02d}", *changes, *(a.effects or [])])
        (a.out / f"{name}.json").write_text(json.dumps(r, indent=1))
        print(
            f"scanner {s} ({r['truth']['truth_class']}): step A {r['seconds']:.0f} s, stages kept {r['stages_kept']}, "
            f"tip path {r['tip_path']['path_x_rms_nm']:.2f} nm rms "
            f"({r['tip_path_quarter_rate']['path_x_rms_nm']:.2f} nm at a quarter of the rate)"
            + (f", fitted lag {1e3 * r['fitted_rate_tau_s']:.2f} ms" if r["fitted_rate_tau_s"] else "")
        )


if __name__ == "__main__":
    main()
