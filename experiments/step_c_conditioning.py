"""Which part of step A's model leaves step C's centre off along y, and what a conditioning line
along y does about it, on one scanner of a finished study.

The scanner's first ``--trials`` trials of A+B+C are run again as the study ran them (its
survey, its learning from step C's finds, its draws) with step A's model replaced, part by
part, by the simulator's truth (without drift and noise, which no model knows): the fitted
model; the true scanner; the true scanner with the fitted y play weights of one radius, or of
the others, or with the fitted creep. Then the fitted model with the local scan's first line
along y conditioning the scanner (``local_scan.condition_y``). For each: the share of trials
within 0.1 R, and the mean and rms of step C's true miss along x and y (``ABC_miss``), over all
trials and over those verified in 3 lines.

    python experiments/step_c_conditioning.py [--study experiments/results/study_0_90] [--scanner 14] [--trials 64]

Writes ``experiments/results/step_c_conditioning/<study>_scanner_<s>.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh
from step_a_study_paths import finished_study_config

from jaxafm.instrument.afm import default_afm
from jaxafm.jobs import study as job
from jaxafm.jobs.folder import Output
from jaxafm.jobs.run import workspace_layout
from jaxafm.model.io import load_model, save_model
from jaxafm.study.monte_carlo import run_chunk

ROOT = Path(__file__).resolve().parents[1]


def y_weights(which):
    """A swap of the y play weights at the indices ``which`` (the fitted ones into the truth)."""
    return lambda truth, fitted: eqx.tree_at(
        lambda m: m.y.hysteresis.pi.weights,
        truth,
        truth.y.hysteresis.pi.weights.at[which].set(fitted.y.hysteresis.pi.weights[which]),
    )


def creep(truth, fitted):
    """The truth with the fitted creep on both axes."""
    return eqx.tree_at(lambda m: (m.x.creep, m.y.creep), truth, (fitted.x.creep, fitted.y.creep))


#: name -> (the model from (truth, fitted), condition_y)
VARIANTS = {
    "fitted": (lambda truth, fitted: fitted, False),
    "true scanner": (lambda truth, fitted: truth, False),
    "true, fitted y play of radius 0": (y_weights(np.array([0])), False),
    "true, fitted y play of the 2nd radius": (y_weights(np.array([1])), False),
    "true, fitted y plays of the other radii": (y_weights(np.arange(2, 16)), False),
    "true, fitted creep": (creep, False),
    "fitted, condition_y": (lambda truth, fitted: fitted, True),
}


def summary(r: dict, draws: dict) -> dict:
    """Success within 0.1 R and step C's miss (nm) per axis, over all trials and the 3-line ones."""
    miss = np.stack([r["ABC_miss_x_nm"], r["ABC_miss_y_nm"]], -1)
    ok = np.linalg.norm(miss, axis=1) <= 0.1 * draws["radius_nm"]
    out = {"within_0p1R_pct": 100 * float(np.mean(ok)), "lines_mean": float(np.mean(r["ABC_lines"]))}
    for name, rows in (("all", np.ones(len(ok), bool)), ("three_lines", r["ABC_lines"] == 3)):
        m = miss[rows]
        out[name] = {
            "trials": int(rows.sum()),
            "mean_nm": np.mean(m, axis=0).tolist() if len(m) else None,
            "rms_nm": np.sqrt(np.mean(m**2, axis=0)).tolist() if len(m) else None,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--study", type=Path, default=ROOT / "experiments" / "results" / "study_0_90")
    ap.add_argument("--scanner", type=int, default=14)
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "step_c_conditioning")
    a = ap.parse_args()
    cfg = finished_study_config(a.study)
    s = a.scanner
    params = job.scanner_draws(cfg)[s]
    truth = default_afm(**params).scanner.without("drift", "noise")
    fitted = load_model(a.study / "scanners" / f"model_{s:05d}.json")
    _, _, D = workspace_layout(cfg)
    first = s * cfg.trials_per_scanner
    draws = {k: v[first : first + a.trials] for k, v in job.trial_draws(cfg, D).items()}
    mesh = Mesh(np.array(jax.devices()), ("trials",))
    rows = {}
    for name, (model_of, condition_y) in VARIANTS.items():
        local = cfg.local_scan.model_copy(update={"condition_y": condition_y})
        run_cfg = cfg.model_copy(update={"local_scan": local})
        settings = dataclasses.replace(job.trial_settings(run_cfg), push=None)
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "scanners").mkdir()
            save_model(model_of(truth, fitted), Path(tmp) / "scanners" / f"model_{s:05d}.json")
            surveys, _ = job.prepare_scanner(run_cfg, a.study, s, params, Output(tmp), lambda m: None)
        r = run_chunk({"A+B": surveys["A+B"]}, draws, mesh, settings)
        rows[name] = summary(r, draws)
        q = rows[name]
        print(
            f"{name:42s} within 0.1 R {q['within_0p1R_pct']:5.1f} %, lines {q['lines_mean']:.2f}; miss x, y: "
            f"mean {q['all']['mean_nm'][0]:+.2f} {q['all']['mean_nm'][1]:+.2f}, rms {q['all']['rms_nm'][0]:.2f} "
            f"{q['all']['rms_nm'][1]:.2f} nm; {q['three_lines']['trials']} in 3 lines",
            flush=True,
        )
    a.out.mkdir(parents=True, exist_ok=True)
    out = a.out / f"{a.study.resolve().name}_scanner_{s}.json"
    setup = {"study": a.study.resolve().name, "scanner": s, "trials": a.trials}
    out.write_text(json.dumps({"setup": setup, "variants": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
