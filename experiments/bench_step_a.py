"""Benchmark: step A identification time, with and without the coarse-to-fine pyramid, and against scipy.

All solve the same problem in the same run: the simulated calibration scan of
``jaxafm calibrate configs/step_a_simulated.yaml`` at ``--pixels``, the same
model, the same residuals (feature points, then images at each blur), the same
start and the same step limit per stage (scipy counts evaluations). Three runs:
optimistix's Levenberg-Marquardt on the pyramid (the stages on the scan coarsened
along its lines, halving up to the last at full resolution: ``coarsen="auto"``),
the same with every stage at full resolution (the default), and scipy's
least_squares on the pyramid, which gets the residuals and the Jacobian from
the same jitted JAX functions. Each run starts with JAX's caches cleared, so
its first identification compiles all it needs.
Each solver identifies twice in the process: the first time includes compilation,
the second reuses it (their difference is the compile time). The profile times
one forward-mode Jacobian of the image residuals and of its parts.

    python experiments/bench_step_a.py [--pixels 256] [--max-steps 30]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from benchutil import device_label, machine_info, time_jax
from jax.flatten_util import ravel_pytree

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jaxafm.config import CalibrationModel, Grating, SimulatedCalibration
from jaxafm.identify import calibration
from jaxafm.identify.step_a import simulate_calibration
from jaxafm.instrument.afm import RasterScan, raster_times, render


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
    factor = calibration.coarse_factor((scan,), "auto")
    runs = [
        (f"optimistix LM, pyramid 1/{factor} to 1", "optimistix.levenberg_marquardt", "auto"),
        ("optimistix LM, full resolution", "optimistix.levenberg_marquardt", 1),
        (f"scipy least_squares (trf), pyramid 1/{factor} to 1", "scipy.least_squares", "auto"),
    ]
    results = {}
    for name, solver, coarsen in runs:
        jax.clear_caches()
        for attempt in ("first", "again"):
            print(f"{name} ({attempt}) ...")
            t0 = time.perf_counter()
            ident = calibration.identify(
                scan,
                kind=spec.kind,
                effects=spec.effects,
                operators=spec.operators,
                solver=solver,
                coarsen=coarsen,
                max_steps=a.max_steps,
                hold_out=False,
            )
            wall = time.perf_counter() - t0
            if attempt == "first":
                results[name] = {
                    "seconds": ident.seconds,
                    "stage_seconds": [s.seconds for s in ident.stages],
                    "stage_steps": [s.steps for s in ident.stages],
                    "final_loss": ident.stages[-1].loss,
                    "converged": ident.converged,
                    "stage_path_x_rms_nm": [
                        path_error(s.model, scan, sim.measured)["path_x_rms_nm"] for s in ident.stages
                    ],
                } | path_error(ident.model, scan, sim.measured)
            else:
                results[name] |= {
                    "seconds_compiled": ident.seconds,
                    "stage_seconds_compiled": [s.seconds for s in ident.stages],
                    "compile_s": results[name]["seconds"] - ident.seconds,
                }
            print(f"  {wall:.1f} s")
    profile = jacobian_profile(scan, spec)
    print(f"\n{a.pixels}² trace/retrace pair, {a.max_steps} steps (evaluations for scipy) at most per stage")
    print(
        f"{'solver':48s} {'total':>8s} {'compiled':>9s} {'compile':>8s} {'stages (s)':>22s} "
        f"{'final loss':>11s} {'path x rms':>11s} {'max':>7s}"
    )
    for name, r in results.items():
        stages = " ".join(f"{s:6.1f}" for s in r["stage_seconds"])
        print(
            f"{name:48s} {r['seconds']:7.1f}s {r['seconds_compiled']:8.1f}s {r['compile_s']:7.1f}s "
            f"{stages:>22s} {r['final_loss']:11.3e} {r['path_x_rms_nm']:9.1f}nm {r['path_x_max_nm']:5.1f}nm"
        )
    for name, r in results.items():
        after = " / ".join(f"{e:.1f}" for e in r["stage_path_x_rms_nm"])
        print(f"{name:48s} tip path x rms after each stage: {after} nm")
    ours, full, scipy_s = (results[n]["seconds"] for n, *_ in runs)
    print(
        f"full resolution / pyramid: {full / ours:.2f}x the time; scipy / optimistix (both pyramid): "
        f"{scipy_s / ours:.2f}x; goal: identification in 30 s or less"
    )
    print(f"\none forward-mode Jacobian ({profile['parameters']} parameters, {profile['samples']} samples):")
    for part, r in profile["parts"].items():
        print(f"  {part:34s} {r['median_s']:7.3f} s  (compile {r['compile_s']:.1f} s)")
    (a.out / "metrics.json").write_text(
        json.dumps(
            {"pixels": a.pixels, "max_steps": a.max_steps, "machine": machine_info()}
            | results
            | {"jacobian_profile": profile},
            indent=1,
        )
    )
    _figure(results, a.out / "bench_step_a.png", a.pixels, device_label(machine_info()))
    print(f"wrote {a.out}/metrics.json, bench_step_a.png")


def jacobian_profile(scan, spec: CalibrationModel) -> dict:
    """Median time of one forward-mode Jacobian (every fitted parameter) of the image residuals
    at the start model, and of its parts along the chain: each axis's hysteresis (its plays
    run over blocks), hysteresis and creep, the whole scanner, the rendered heights and the
    feedback lag."""
    model = calibration.initial_model(scan, spec.kind, spec.effects, spec.operators, spec.deadzones)
    model = calibration._start_lattice(model, scan, scan.features())
    model = jax.tree.map(lambda x: jnp.array(x, dtype=float) if eqx.is_inexact_array(x) else x, model)
    raw0, rebuild = calibration.parameters(model, scan)
    x0, unravel = ravel_pytree(raw0)
    afm = model.afm(scan)
    start = model._start(afm, scan)
    u = afm.nominal_volts(jnp.asarray(scan.raster.wanted().reshape(-1, 2)))
    t = raster_times(scan.raster, scan.t0 + 0.1)
    s0 = start.scanner
    kernel = jnp.asarray(calibration.gaussian_kernel(2.0, 6))
    args = (model, (scan,), (kernel, (jnp.ones((2, scan.raster.lines, scan.raster.pixels)),)))

    def m(x):
        return rebuild(unravel(x))

    def hysteresis(x):
        return m(x).scanner.x.hysteresis.run(u[:, 0], s0.x.plays)[0]

    def axis(x):
        return m(x).scanner.x.run(u[:, 0], t, s0.x, s0.t)[0]

    def path(x):
        return m(x).scanner.run(u, t, s0, calibration.KEY)[0]

    def heights(x):
        return render(m(x).lattice, None, path(x))

    def recorded(x):
        return m(x).feedback.run(heights(x), t, start.z, s0.t)[0]

    parts = {
        "x hysteresis (plays in blocks)": hysteresis,
        "x hysteresis + creep": axis,
        "scanner (both axes, coupling, bow)": path,
        "+ rendered heights": heights,
        "+ feedback lag": recorded,
        "image residuals (+ blur)": lambda x: calibration._image_residuals(unravel(x), args),
    }
    timed = {k: time_jax(jax.jacfwd(f), x0, repeats=3)[0] for k, f in parts.items()}
    return {"parameters": int(x0.size), "samples": int(u.shape[0]), "parts": timed}


def _figure(results: dict, path: Path, pixels: int, device: str) -> None:
    fig, ax = plt.subplots(figsize=(10, 4.4), constrained_layout=True)
    names = list(results)
    stages = ["feature points", "images, blur 2 px", "images, blur 1 px"]
    left = np.zeros(len(names))
    for k, stage in enumerate(stages):
        s = np.array([results[n]["stage_seconds"][k] for n in names])
        ax.barh([n.replace(", ", ",\n") for n in names], s, left=left, label=stage)
        left += s
    ax.axvline(30, color="k", ls="--", lw=1)
    ax.text(30, -0.55, " 30 s goal", va="bottom", fontsize=8)
    for i, n in enumerate(names):
        ax.text(
            left[i],
            i,
            f" {results[n]['seconds']:.0f} s ({results[n]['compile_s']:.0f} s compiling),\n"
            f" path x rms {results[n]['path_x_rms_nm']:.1f} nm",
            va="center",
        )
    ax.set(
        xlabel=f"wall time (s, {device}, compilation included)",
        title=f"Step A identification, {pixels}² trace/retrace pair",
        xlim=(0, 1.6 * left.max()),
        ylim=(-0.6, len(names) - 0.4),
    )
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.25), ncol=3, frameon=False)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
