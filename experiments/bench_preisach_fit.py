"""Time and peak memory of a Preisach fit: 50 levels (1,275 relays) on 20,000 training samples.

What it measures, each fit in a fresh process (so that its peak memory is its own), side by side
in one run on one record: the simulated actuator's record (``jaxafm fit``'s ``simulate``:
hysteresis with an asymmetric loop, 0.1 % noise), 20,000 samples to train on and the next
13,334 held out.

- ``jaxafm.nnls``: the exact non-negative least squares of :mod:`jaxafm.identify.linear`
  (normal equations streamed over blocks of samples, block principal pivoting);
- ``dense + scipy nnls``: the fair baseline, the same problem solved the way the diagnosis's start
  does it: the whole design matrix (T, 1,275) built at once, scipy's Lawson-Hanson ``nnls``;
- ``optimistix.bfgs``: ``jaxafm fit``'s default for a Preisach model before the exact fit;
- ``optimistix.levenberg_marquardt``: capped at ``--lm-steps`` (it had not converged after 200
  steps and 462 s on this problem).

Each fit runs twice in its process, the exact fit ``1 + --repeats`` times: the first call
compiles, the median of the others is the fit's time once compiled. Peak memory is the process's
peak resident set (``ru_maxrss``), before the fit (JAX, the record) and after each call.

Run:  python experiments/bench_preisach_fit.py [--samples 20000] [--levels 50] [--lm-steps 20] [--repeats 5]
      [--out experiments/results/bench_preisach_fit.json]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from benchutil import machine_info

from jaxafm.config.fit import SimulatedData
from jaxafm.identify.fit import error_metrics, fit_operator, initial_operator
from jaxafm.jobs.fit import simulate_record

RUNS = ("jaxafm.nnls", "dense + scipy nnls", "optimistix.bfgs", "optimistix.levenberg_marquardt")
GOAL_S, GOAL_GB = 1.0, 0.5
TRAIN_FRACTION = 0.6


def peak_mb() -> float:
    """The process's peak resident set so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def record(samples: int):
    """The simulated actuator's record with ``samples`` training samples (200 Hz) and the rest held out."""
    total = int(np.ceil(samples / TRAIN_FRACTION))
    rec, _ = simulate_record(SimulatedData(duration_s=total / 200.0, effects=["hysteresis", "asymmetry"]))
    return np.asarray(rec.u)[:total], np.asarray(rec.d)[:total]


def dense_nnls(start, u, d):
    """The fair baseline: the design matrix at once and scipy's ``nnls`` (``_nnls_start``'s way)."""
    import jax.numpy as jnp
    from scipy.optimize import nnls

    t0 = time.perf_counter()
    a = np.asarray(start.design_matrix(jnp.asarray(u)))
    a = np.concatenate([a, np.ones((len(u), 1)), -np.ones((len(u), 1))], 1)
    scale = np.linalg.norm(a, axis=0) + 1e-12
    w = nnls(a / scale, d, maxiter=50 * a.shape[1])[0] / scale
    model = start.with_weights(jnp.asarray(w[:-2]), jnp.asarray(w[-2] - w[-1]))
    return model, time.perf_counter() - t0, "scipy nnls on the dense design matrix"


def one(run: str, samples: int, levels: int, lm_steps: int, repeats: int) -> dict:
    """One run's two calls in this process; printed as JSON for the parent."""
    u, d = record(samples)
    n = samples
    start = initial_operator("preisach", u[:n], d[:n], levels=levels)
    out = {"run": run, "peak_before_mb": peak_mb(), "calls": []}
    for _ in range(1 + (repeats if run == "jaxafm.nnls" else 1)):
        if run == "dense + scipy nnls":
            model, seconds, message = dense_nnls(start, u[:n], d[:n])
        else:
            steps = lm_steps if "levenberg" in run else 2000
            res = fit_operator(start, u[:n], d[:n], solver=run, max_steps=steps)
            model, seconds, message = res.model, res.seconds, res.message
        pred = np.asarray(model(u))
        out["calls"].append(
            {
                "seconds": seconds,
                "peak_mb": peak_mb(),
                "message": message,
                "train_rms_nm": error_metrics(pred[:n], d[:n])["rms_error_nm"],
                "heldout_rms_nm": error_metrics(pred[n:], d[n:])["rms_error_nm"],
            }
        )
    if run == "jaxafm.nnls":
        out["parts"] = parts(start, u[:n], d[:n])
    return out


def parts(start, u, d, repeats: int = 5) -> dict:
    """The exact fit's two parts, each the median of ``repeats`` compiled calls (s): the normal
    equations (the plays and the streamed Gram matrix) and the non-negative solve."""
    from jaxafm.identify import linear

    eq_s, solve_s = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        eq = linear.normal_equations(start, u, d)
        t1 = time.perf_counter()
        linear.nonnegative_solve(eq.gram, eq.rhs)
        eq_s.append(t1 - t0)
        solve_s.append(time.perf_counter() - t1)
    return {
        "normal_equations_s": float(np.median(eq_s)),
        "solve_s": float(np.median(solve_s)),
        "repeats": repeats,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=20000, help="training samples")
    p.add_argument("--levels", type=int, default=50)
    p.add_argument("--lm-steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5, help="compiled calls of jaxafm.nnls (median)")
    p.add_argument("--runs", default=",".join(RUNS), help=f"comma-separated, from {RUNS}")
    p.add_argument("--out", default="experiments/results/bench_preisach_fit.json")
    p.add_argument("--one", help=argparse.SUPPRESS)  # a child process: one run
    a = p.parse_args()
    if a.one:
        print(json.dumps(one(a.one, a.samples, a.levels, a.lm_steps, a.repeats)))
        return
    runs = [r for r in a.runs.split(",") if r]
    unknown = [r for r in runs if r not in RUNS]
    if unknown:
        p.error(f"unknown run {unknown[0]!r} in --runs; one of {', '.join(RUNS)}")
    results = {"machine": machine_info(), "samples": a.samples, "levels": a.levels, "lm_steps": a.lm_steps}
    results["relays"] = a.levels * (a.levels + 1) // 2
    results["runs"] = []
    print(f"Preisach fit: {a.levels} levels ({results['relays']} relays), {a.samples} training samples")
    for run in runs:
        args = [sys.executable, __file__, "--one", run, "--samples", str(a.samples)]
        args += ["--levels", str(a.levels), "--lm-steps", str(a.lm_steps), "--repeats", str(a.repeats)]
        child = subprocess.run(args, capture_output=True, text=True, check=False)
        if child.returncode:
            sys.exit(f"run {run!r} failed:\n{child.stderr[-3000:]}")
        r = json.loads(child.stdout.strip().splitlines()[-1])
        results["runs"].append(r)
        first, second = r["calls"][0], r["calls"][-1]
        r["compiled_s"] = float(np.median([c["seconds"] for c in r["calls"][1:]]))
        print(
            f"{run:32s} first {first['seconds']:8.2f} s, compiled {r['compiled_s']:8.2f} s "
            f"(median of {len(r['calls']) - 1}), "
            f"peak {r['peak_before_mb']:.0f} -> {max(c['peak_mb'] for c in r['calls']):.0f} MB, "
            f"train rms {second['train_rms_nm']:.4f} nm, held-out {second['heldout_rms_nm']:.4f} nm "
            f"({second['message']})",
            flush=True,
        )
        if "parts" in r:
            print(
                f"{'':32s} median of {r['parts']['repeats']}: normal equations "
                f"{r['parts']['normal_equations_s']:.3f} s, solve {r['parts']['solve_s']:.3f} s"
            )
    results["machine"]["loadavg_at_end"] = list(__import__("os").getloadavg())
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(results, indent=1))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
