"""Benchmark: step A identification time and accuracy, the geodesic Levenberg-Marquardt against
optimistix's and scipy's solvers on the same problem.

All solve the same problem in the same run: the simulated calibration scan of
``jaxafm calibrate configs/step_a_simulated.yaml`` at ``--pixels``, the same model (``--effects``)
and residuals, the same start, the same stages (the features' chords, ``--coarsen`` pixels of a
line averaged into one, 1 as ``jaxafm calibrate`` does, then the images at full resolution
blurred by ``--blur`` px) and the same step limit per stage (``--steps``; scipy counts
evaluations). Runs: jaxafm's geodesic Levenberg-Marquardt (:mod:`jaxafm.identify.geodesic`),
optimistix's Levenberg-Marquardt, scipy's least_squares (its residuals and Jacobian from the
same jitted JAX functions). Each run starts with JAX's and jaxafm's caches of compiled functions
cleared, so its first identification compiles all it needs; it identifies twice, and the second
time reuses the compilation (their difference is the compile time). Accuracy is the fitted tip
path against the simulation's true one (x, rms over the image, nm) on ``--seeds`` scans that
differ in the noise and drift (the first one timed). The profile times one forward-mode Jacobian
of the image residuals and of its parts.

    python experiments/bench_step_a.py [--pixels 256] [--steps 100,14] [--coarsen 1] [--blur 1] [--seeds 3]
        [--effects asymmetry,creep,coupling,bow,feedback_lag]
        [--runs geodesic,optimistix,scipy] [--profile 3] [--verbose]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from benchutil import device_label, machine_info, time_jax
from jax.flatten_util import ravel_pytree

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jaxafm.config import CalibrationLattice, CalibrationModel, SimulatedCalibration
from jaxafm.config.calibrate import CALIBRATION_EFFECTS
from jaxafm.identify import fit, geodesic, stages
from jaxafm.identify.image_ops import gaussian_kernel
from jaxafm.identify.scan_model import KEY, ScanModel, ScanModelSpec, nominal_scan_model, start_lattice
from jaxafm.identify.staged_fit import identify as identify_scanner
from jaxafm.identify.stages import FitPlan
from jaxafm.instrument.afm import RasterScan, raster_times, render
from jaxafm.jobs.calibrate import calibration_scans


def path_error(model: ScanModel, scan, truth: RasterScan) -> dict:
    """Fitted against true tip path over the image (nm), the unobservable mean shift removed."""
    paths = zip(model.paths(scan), ("path_trace", "path_retrace"))
    e = np.stack([np.asarray(p) - np.asarray(getattr(truth, k)) for p, k in paths])
    e = e - e.reshape(-1, 2).mean(axis=0)
    return {
        "path_x_rms_nm": float(np.sqrt(np.mean(e[..., 0] ** 2))),
        "path_x_max_nm": float(np.abs(e[..., 0]).max()),
        "path_y_rms_nm": float(np.sqrt(np.mean(e[..., 1] ** 2))),
    }


RUNS = ("geodesic", "optimistix", "scipy")


def cleared() -> None:
    """Forget every compiled function: JAX's caches and jaxafm's caches of jitted solver functions."""
    jax.clear_caches()
    geodesic.compiled.cache_clear()
    fit.clear_caches()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=256)
    ap.add_argument("--steps", default="100,14", help="step limits, the chord stage's first")
    ap.add_argument("--blur", default="1", help="the image stages' blurs (px), comma-separated")
    ap.add_argument(
        "--coarsen",
        default="1",
        help="pixels of a line the chord stage averages into one (1, 2, 4, ... or auto)",
    )
    ap.add_argument("--seeds", type=int, default=3, help="scans (simulation seeds) to measure accuracy on")
    ap.add_argument(
        "--runs", default=",".join(RUNS), help=f"which runs, comma-separated, of {', '.join(RUNS)}"
    )
    ap.add_argument(
        "--profile", type=int, default=3, help="repeats of each profiled Jacobian (0: no profile)"
    )
    ap.add_argument(
        "--effects",
        default=",".join(CALIBRATION_EFFECTS),
        help="the model's effects besides hysteresis, comma-separated (default: step A's)",
    )
    ap.add_argument("--verbose", action="store_true", help="print the first identification's stages")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/bench_step_a"))
    a = ap.parse_args()
    unknown = set(a.runs.split(",")) - set(RUNS)
    if unknown:
        ap.error(f"--runs {a.runs}: unknown {', '.join(sorted(unknown))}; allowed: {', '.join(RUNS)}")
    a.out.mkdir(parents=True, exist_ok=True)
    blur = tuple(float(b) for b in a.blur.split(","))
    steps = [int(s) for s in a.steps.split(",")]
    coarsen = a.coarsen if a.coarsen == "auto" else int(a.coarsen)
    scans = [
        calibration_scans(
            SimulatedCalibration(pixels=a.pixels, seed=seed), CalibrationLattice(rotation_deg=0.0)
        )
        for seed in range(a.seeds)
    ]
    spec = CalibrationModel(name="gpi", effects=[e for e in a.effects.split(",") if e])
    geo, lm = "jaxafm.geodesic_levenberg_marquardt", "optimistix.levenberg_marquardt"
    limits = ",".join(map(str, steps))
    every = {
        "geodesic": (f"jaxafm geodesic LM, steps {limits}", geo, steps),
        "optimistix": (f"optimistix LM, steps {limits}", lm, steps),
        "scipy": (f"scipy least_squares (trf), evaluations {limits}", "scipy.least_squares", steps),
    }
    runs = [every[k] for k in RUNS if k in a.runs.split(",")]
    results = {}
    for name, solver, limit in runs:
        cleared()

        def identify(scan, solver=solver, limit=limit, log=lambda s: None):
            return identify_scanner(
                scan,
                ScanModelSpec(spec.kind, tuple(spec.effects), spec.operators),
                FitPlan(solver, blur, coarsen, limit, hold_out=False, select=False),
                log=log,
            )

        (scan,), sim = scans[0]
        print(f"{name} ...", flush=True)
        first = identify(scan, log=print if a.verbose else lambda s: None)
        print(f"  first identification {first.seconds:.1f} s", flush=True)
        again = identify(scan)
        results[name] = {
            "seconds": first.seconds,
            "seconds_compiled": again.seconds,
            "compile_s": first.seconds - again.seconds,
            "stage_seconds": [s.seconds for s in first.stages],
            "stage_seconds_compiled": [s.seconds for s in again.stages],
            "stage_steps": [s.steps for s in first.stages],
            "final_loss": first.stages[-1].loss,
            "converged": first.converged,
            "stage_path_x_rms_nm": [
                path_error(s.model, scan, sim.measured)["path_x_rms_nm"] for s in first.stages
            ],
        } | path_error(first.model, scan, sim.measured)
        seeds = [results[name]["path_x_rms_nm"]]
        for (scan,), sim in scans[1:]:
            seeds.append(path_error(identify(scan).model, scan, sim.measured)["path_x_rms_nm"])
        results[name] |= {"path_x_rms_nm_by_seed": seeds}
        r = results[name]
        print(
            f"  {r['seconds']:.1f} s ({r['compile_s']:.1f} s compiling); path x rms by seed "
            + " ".join(f"{e:.2f}" for e in seeds)
            + " nm",
            flush=True,
        )
    profile = jacobian_profile(scans[0][0][0], spec, a.profile) if a.profile else None
    print(
        f"\n{a.pixels}² trace/retrace pair; stages: chords, then images blurred by "
        f"{', '.join(f'{b:g}' for b in blur)} px; {a.seeds} scans"
    )
    print(
        f"{'solver':48s} {'total':>8s} {'compiled':>9s} {'compile':>8s} {'stages (s)':>16s} "
        f"{'final loss':>11s} {'path x rms (median, max over scans)':>36s}"
    )
    for name, r in results.items():
        stages = " ".join(f"{s:6.1f}" for s in r["stage_seconds"])
        by_seed = r["path_x_rms_nm_by_seed"]
        print(
            f"{name:48s} {r['seconds']:7.1f}s {r['seconds_compiled']:8.1f}s {r['compile_s']:7.1f}s "
            f"{stages:>16s} {r['final_loss']:11.3e} {np.median(by_seed):20.2f} nm {max(by_seed):6.2f} nm"
        )
    for name, r in results.items():
        after = " / ".join(f"{e:.1f}" for e in r["stage_path_x_rms_nm"])
        print(f"{name:48s} tip path x rms after each stage (first scan): {after} nm")
    ours, others = results[runs[0][0]]["seconds"], [results[n]["seconds"] for n, *_ in runs[1:]]
    print(
        f"time against the {runs[0][0]}: "
        + "".join(f"{n}: {t / ours:.2f}x; " for (n, *_), t in zip(runs[1:], others))
        + "goal: identification in 30 s or less"
    )
    if profile:
        print(
            f"\none forward-mode Jacobian ({profile['parameters']} parameters, {profile['samples']} samples):"
        )
        for part, r in profile["parts"].items():
            print(f"  {part:34s} {r['median_s']:7.3f} s  (compile {r['compile_s']:.1f} s)")
    (a.out / "metrics.json").write_text(
        json.dumps(
            {"pixels": a.pixels, "steps": steps, "coarsen": coarsen, "blur_px": blur, "seeds": a.seeds}
            | {"effects": spec.effects}
            | {"machine": machine_info()}
            | results
            | {"jacobian_profile": profile},
            indent=1,
        )
    )
    _figure(results, a.out / "bench_step_a.png", a.pixels, device_label(machine_info()))
    print(f"wrote {a.out}/metrics.json, bench_step_a.png")


def jacobian_profile(scan, spec: CalibrationModel, repeats: int) -> dict:
    """Median time of one forward-mode Jacobian (every fitted parameter) of the image residuals
    at the start model, and of its parts along the chain: each axis's hysteresis (its plays
    run over blocks), hysteresis and creep, the whole scanner, the rendered heights and the
    feedback lag."""
    model = nominal_scan_model(
        scan, ScanModelSpec(spec.kind, tuple(spec.effects), spec.operators, spec.deadzones)
    )
    model = start_lattice(model, scan, scan.features()).as_float64()
    raw0, rebuild = model.free_parameters(scan)
    x0, unravel = ravel_pytree(raw0)
    afm = model.afm(scan)
    start = model.start(afm, scan)
    u = afm.nominal_volts(jnp.asarray(scan.raster.wanted().reshape(-1, 2)))
    t = raster_times(scan.raster, scan.t0 + 0.1)
    s0 = start.scanner
    kernel = jnp.asarray(gaussian_kernel(2.0, 6))
    args = (model, (scan,), (kernel, (jnp.ones((2, scan.raster.lines, scan.raster.pixels)),)))

    def m(x):
        return rebuild(unravel(x))

    def hysteresis(x):
        return m(x).scanner.x.hysteresis.run(u[:, 0], s0.x.plays)[0]

    def axis(x):
        return m(x).scanner.x.run(u[:, 0], t, s0.x, s0.t)[0]

    def path(x):
        return m(x).scanner.run(u, t, s0, KEY)[0]

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
        "image residuals (+ blur)": lambda x: stages.image_residuals(unravel(x), args),
    }
    timed = {k: time_jax(jax.jacfwd(f), x0, repeats=repeats)[0] for k, f in parts.items()}
    return {"parameters": int(x0.size), "samples": int(u.shape[0]), "parts": timed}


def _figure(results: dict, path: Path, pixels: int, device: str) -> None:
    fig, ax = plt.subplots(figsize=(10, 4.6), constrained_layout=True)
    names = list(results)
    rows = [n.replace(", ", ",\n") for n in names]
    stages = len(results[names[0]]["stage_seconds"])
    left = np.zeros(len(names))
    parts = [(f"stage {k + 1}: " + ("chords" if k == 0 else "images"), k) for k in range(stages)]
    for label, k in parts + [("outside the stages (start, checks)", None)]:
        s = np.array(
            [
                results[n]["seconds"] - sum(results[n]["stage_seconds"])
                if k is None
                else results[n]["stage_seconds"][k]
                for n in names
            ]
        )
        ax.barh(rows, s, left=left, label=label, color=None if k is not None else "0.75")
        left += s
    ax.axvline(30, color="k", ls="--", lw=1, label="30 s goal")
    for i, n in enumerate(names):
        by_seed = results[n]["path_x_rms_nm_by_seed"]
        ax.text(
            left[i] + 0.5,
            i,
            f"{results[n]['seconds']:.1f} s ({results[n]['compile_s']:.1f} s compiling)\n"
            f"path x rms {np.median(by_seed):.2f} nm (max {max(by_seed):.2f}) over {len(by_seed)} scans",
            va="center",
            fontsize=8,
            bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8, "pad": 1},
        )
    ax.invert_yaxis()
    ax.set(
        xlabel=f"wall time of the first identification (s, {device}, compilation included)",
        title=f"Step A identification, {pixels}² trace/retrace pair: the same stages and step limits",
        xlim=(0, 1.75 * left.max()),
    )
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=4, frameon=False)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
