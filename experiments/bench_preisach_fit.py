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
peak resident set (:func:`peak_mb`) before the first fit (Python, JAX and the solvers' libraries
imported, the record loaded from a file the parent simulated) and after each fit; the training
and held-out rms of the last fit are scored after them all. After the exact fit's calls, its
posterior is made as ``jaxafm fit`` makes it (:func:`jaxafm.jobs.fit._posterior`: the
linearisation over the whole record, the AR(1) posterior from the training part, the band over
the record), timed, and the peak read again.

Run:  python experiments/bench_preisach_fit.py [--samples 20000] [--levels 50] [--lm-steps 20] [--repeats 5]
      [--out experiments/results/bench_preisach_fit.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from benchutil import machine_info

from jaxafm.identify.fit import error_metrics, fit_operator, initial_operator

RUNS = ("jaxafm.nnls", "dense + scipy nnls", "optimistix.bfgs", "optimistix.levenberg_marquardt")
GOAL_S, GOAL_GB = 1.0, 0.5
TRAIN_FRACTION = 0.6


def peak_mb() -> float:
    """The process's peak resident set so far (MiB): Linux's ``VmHWM``, which starts afresh with
    the process's program (``ru_maxrss`` keeps the parent's peak across ``exec``), else ``ru_maxrss``."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def record(samples: int):
    """The simulated actuator's record with ``samples`` training samples (200 Hz) and the rest held out."""
    from jaxafm.config.fit import SimulatedData
    from jaxafm.jobs.fit import simulate_record

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


def one(run: str, path: str, samples: int, levels: int, lm_steps: int, repeats: int) -> dict:
    """One run's calls in this process, on the record saved at ``path``; printed as JSON for the
    parent. The peak is read after each fit, before its prediction is scored."""
    with np.load(path) as saved:
        u, d = saved["u"], saved["d"]
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
        out["calls"].append({"seconds": seconds, "peak_mb": peak_mb(), "message": message})
    pred = np.asarray(model(u))  # after every fit: its compilation is not the fits' memory
    out["train_rms_nm"] = error_metrics(pred[:n], d[:n])["rms_error_nm"]
    out["heldout_rms_nm"] = error_metrics(pred[n:], d[n:])["rms_error_nm"]
    if run == "jaxafm.nnls":
        out["posterior"] = posterior(model, u, d, n)
        out["parts"] = parts(start, u[:n], d[:n])
    return out


def posterior(model, u, d, n: int) -> dict:
    """The fitted ``model``'s posterior and band as ``jaxafm fit`` makes them, on the record's
    first ``n`` samples (the training part) and over all of it: wall time (s), compiling included,
    and the process's peak after it (MiB)."""
    from jaxafm.instrument.records import Record
    from jaxafm.jobs.fit import _posterior

    record = Record(np.arange(len(u)) / 200.0, u, d, {"source": "bench_preisach_fit"})
    post, _, seconds = _posterior(model, record, n, 0, None)
    return {"seconds": seconds, "peak_mb": peak_mb(), "parameters": int(post.covariance.shape[0])}


def parts(start, u, d, repeats: int = 5) -> dict:
    """The exact fit's two parts, each the median of ``repeats`` compiled calls (s): the normal
    equations (the plays and the streamed Gram matrix) and the non-negative solve; on the same
    normal equations, the rank of the Gram matrix, scipy's Lawson-Hanson ``nnls`` (the fallback)
    and the solve at other ridges (steps, seconds, how it ended, training rms)."""
    import scipy.linalg as sl
    from scipy.optimize import nnls

    from jaxafm.identify import linear

    eq_s, solve_s = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        eq = linear.normal_equations(start, u, d)
        t1 = time.perf_counter()
        linear.nonnegative_solve(eq.gram, eq.rhs)
        eq_s.append(t1 - t0)
        solve_s.append(time.perf_counter() - t1)
    scale = np.sqrt(np.diag(eq.gram))
    G = eq.gram / np.outer(scale, scale) + linear.RIDGE * np.eye(len(scale))
    eigen = np.linalg.eigvalsh(eq.gram / np.outer(scale, scale))
    t0 = time.perf_counter()
    L = np.linalg.cholesky(G)
    nnls(L.T, sl.solve_triangular(L, eq.rhs / scale, lower=True), maxiter=50 * len(scale))
    scipy_s = time.perf_counter() - t0
    ridges = {}
    for ridge in (1e-4, 1e-6, 1e-8):
        t0 = time.perf_counter()
        w, steps, how = linear.nonnegative_solve(eq.gram, eq.rhs, ridge=ridge)
        seconds = time.perf_counter() - t0
        rms = np.sqrt(max(eq.centred_ss - 2 * eq.rhs @ w + w @ eq.gram @ w, 0.0) / eq.samples)
        ridges[f"{ridge:g}"] = {"steps": steps, "seconds": seconds, "how": how, "train_rms_nm": rms}
    return {
        "normal_equations_s": float(np.median(eq_s)),
        "solve_s": float(np.median(solve_s)),
        "repeats": repeats,
        "gram_rank": int(np.sum(eigen > 1e-9 * eigen[-1])),
        "weights": len(scale),
        "scipy_nnls_same_gram_s": scipy_s,
        "ridges": ridges,
    }


def child_run(run: str, saved: Path, a) -> dict:
    """One run in a fresh process on the record ``saved``; prints its line and returns its result."""
    args = [sys.executable, __file__, "--one", run, "--record", str(saved), "--samples", str(a.samples)]
    args += ["--levels", str(a.levels), "--lm-steps", str(a.lm_steps), "--repeats", str(a.repeats)]
    child = subprocess.run(args, capture_output=True, text=True, check=False)
    if child.returncode:
        sys.exit(f"run {run!r} failed:\n{child.stderr[-3000:]}")
    r = json.loads(child.stdout.strip().splitlines()[-1])
    first, last = r["calls"][0], r["calls"][-1]
    r["compiled_s"] = float(np.median([c["seconds"] for c in r["calls"][1:]]))
    peak = max(c["peak_mb"] for c in r["calls"])
    print(
        f"{run:32s} first {first['seconds']:8.2f} s, compiled {r['compiled_s']:8.2f} s "
        f"(median of {len(r['calls']) - 1}), peak {r['peak_before_mb']:.0f} -> {peak:.0f} MiB, "
        f"train rms {r['train_rms_nm']:.4f} nm, held-out {r['heldout_rms_nm']:.4f} nm "
        f"({last['message']})",
        flush=True,
    )
    if "parts" in r:
        met = r["compiled_s"] <= GOAL_S and peak * 2**20 / 1e9 <= GOAL_GB
        print(
            f"{'':32s} median of {r['parts']['repeats']}: normal equations "
            f"{r['parts']['normal_equations_s']:.3f} s, solve {r['parts']['solve_s']:.3f} s; goal <= "
            f"{GOAL_S:g} s compiled and <= {GOAL_GB:g} GB (1e9 bytes) peak: {'met' if met else 'NOT met'}"
        )
        q = r["posterior"]
        print(
            f"{'':32s} its posterior ({q['parameters']} parameters) as jaxafm fit makes it: "
            f"{q['seconds']:.2f} s, compiling included; peak after it {q['peak_mb']:.0f} MiB"
        )
        p = r["parts"]
        print(
            f"{'':32s} Gram matrix rank {p['gram_rank']} of {p['weights']}; scipy's nnls on it "
            f"{p['scipy_nnls_same_gram_s']:.2f} s; "
            + "; ".join(
                f"ridge {k}: {v['how']}, {v['steps']} steps, {v['seconds']:.2f} s, rms {v['train_rms_nm']:.6f} nm"
                for k, v in p["ridges"].items()
            )
        )
    return r


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=20000, help="training samples")
    p.add_argument("--levels", type=int, default=50)
    p.add_argument("--lm-steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5, help="compiled calls of jaxafm.nnls (median)")
    p.add_argument("--runs", default=",".join(RUNS), help=f"comma-separated, from {RUNS}")
    p.add_argument("--out", default="experiments/results/bench_preisach_fit.json")
    p.add_argument("--one", help=argparse.SUPPRESS)  # a child process: one run
    p.add_argument("--record", help=argparse.SUPPRESS)  # the child's record (.npz)
    a = p.parse_args()
    if a.one:
        print(json.dumps(one(a.one, a.record, a.samples, a.levels, a.lm_steps, a.repeats)))
        return
    runs = [r for r in a.runs.split(",") if r]
    unknown = [r for r in runs if r not in RUNS]
    if unknown:
        p.error(f"unknown run {unknown[0]!r} in --runs; one of {', '.join(RUNS)}")
    results = {"machine": machine_info(), "samples": a.samples, "levels": a.levels, "lm_steps": a.lm_steps}
    results["relays"] = a.levels * (a.levels + 1) // 2
    results["runs"] = []
    print(f"Preisach fit: {a.levels} levels ({results['relays']} relays), {a.samples} training samples")
    with tempfile.TemporaryDirectory() as folder:
        saved = Path(folder) / "record.npz"
        np.savez(saved, **dict(zip("ud", record(a.samples))))
        for run in runs:
            results["runs"].append(child_run(run, saved, a))
    results["machine"]["loadavg_at_end"] = list(os.getloadavg())
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(results, indent=1))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
