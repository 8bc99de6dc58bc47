"""Benchmark: step A identification time, optimistix Levenberg-Marquardt against scipy's least_squares.

Both solve the same problem in the same run: the simulated calibration scan of
``jaxafm calibrate configs/step_a_simulated.yaml`` at ``--pixels``, the same
model, the same residuals (feature points, then images at each blur), the same
start and the same step limit per stage (scipy counts evaluations). scipy
gets the residuals and the Jacobian from the same jitted JAX functions.
Times include compilation.

    python experiments/bench_step_a.py [--pixels 256] [--max-steps 30]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jaxafm.config import CalibrationModel, Grating, SimulatedCalibration
from jaxafm.identify import calibration
from jaxafm.identify.step_a import simulate_calibration
from jaxafm.instrument.afm import RasterScan


def path_error(model: calibration.ScanModel, scan, truth: RasterScan) -> dict:
    """Fitted against true tip path over the image (nm), the unobservable mean shift removed."""
    paths = zip(model.paths(scan), ("path_trace", "path_retrace"))
    e = np.stack([np.asarray(p) - np.asarray(getattr(truth, k)) for p, k in paths])
    e = e - e.reshape(-1, 2).mean(axis=0)
    return {
        "path_x_rms_nm": float(np.sqrt(np.mean(e[..., 0] ** 2))),
        "path_x_max_nm": float(np.abs(e[..., 0]).max()),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=256)
    ap.add_argument("--max-steps", type=int, default=30)
    ap.add_argument("--out", type=Path, default=Path("experiments/results/bench_step_a"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    (scan,), sim = simulate_calibration(SimulatedCalibration(pixels=a.pixels), Grating(rotation_deg=0.0))
    spec = CalibrationModel(name="gpi")
    runs = [
        ("optimistix LM", "optimistix.levenberg_marquardt"),
        ("scipy least_squares (trf)", "scipy.least_squares"),
    ]
    results = {}
    for name, solver in runs:
        print(f"{name} ...")
        ident = calibration.identify(
            scan,
            kind=spec.kind,
            effects=spec.effects,
            operators=spec.operators,
            solver=solver,
            max_steps=a.max_steps,
            hold_out=False,
        )
        results[name] = {
            "seconds": ident.seconds,
            "stage_seconds": [s.seconds for s in ident.stages],
            "stage_steps": [s.steps for s in ident.stages],
            "final_loss": ident.stages[-1].loss,
            "converged": ident.converged,
        } | path_error(ident.model, scan, sim.measured)
    print(f"\n{a.pixels}² trace/retrace pair, {a.max_steps} steps (evaluations for scipy) at most per stage")
    print(
        f"{'solver':28s} {'total':>8s} {'stages (s)':>22s} {'final loss':>11s} {'path x rms':>11s} {'max':>7s}"
    )
    for name, r in results.items():
        stages = " ".join(f"{s:6.1f}" for s in r["stage_seconds"])
        print(
            f"{name:28s} {r['seconds']:7.1f}s {stages:>22s} {r['final_loss']:11.3e} "
            f"{r['path_x_rms_nm']:9.1f}nm {r['path_x_max_nm']:5.1f}nm"
        )
    ours, scipy_s = (results[n]["seconds"] for n, _ in runs)
    print(f"scipy / optimistix: {scipy_s / ours:.2f}x the time; goal: identification under 60 s")
    (a.out / "metrics.json").write_text(
        json.dumps({"pixels": a.pixels, "max_steps": a.max_steps} | results, indent=1)
    )
    _figure(results, a.out / "bench_step_a.png", a.pixels)
    print(f"wrote {a.out}/metrics.json, bench_step_a.png")


def _figure(results: dict, path: Path, pixels: int) -> None:
    fig, ax = plt.subplots(figsize=(8, 3.8), constrained_layout=True)
    names = list(results)
    stages = ["feature points", "images, blur 2 px", "images, blur 1 px"]
    left = np.zeros(len(names))
    for k, stage in enumerate(stages):
        s = np.array([results[n]["stage_seconds"][k] for n in names])
        ax.barh(names, s, left=left, label=stage)
        left += s
    ax.axvline(60, color="k", ls="--", lw=1)
    ax.text(60, -0.55, " 60 s goal", va="bottom", fontsize=8)
    for i, n in enumerate(names):
        ax.text(
            left[i],
            i,
            f" {results[n]['seconds']:.0f} s in all, path x rms {results[n]['path_x_rms_nm']:.1f} nm",
            va="center",
        )
    ax.set(
        xlabel="wall time (s, 2-core CPU, compilation included)",
        title=f"Step A identification, {pixels}² trace/retrace pair",
        xlim=(0, 1.5 * left.max()),
        ylim=(-0.6, len(names) - 0.4),
    )
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.25), ncol=3, frameon=False)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
