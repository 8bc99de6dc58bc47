"""Benchmark: Monte-Carlo study throughput (trials per minute), batched against one by one.

(a) Steps B+C with a fixed identified model: one scanner (``default_afm``) with the
    stored step-A model, pressed and surveyed once (``configs/study.yaml``'s layout);
    each trial goes to its particle through the landmark map (A+B), runs the local
    scan and moves to the centre it found. Batches of ``--batches`` trials on one and
    on two host devices, and the same trials one at a time in a Python loop (batch
    of 1 per call), in the same run.
(b) The full pipeline with step A per scanner: the calibration scan, identification,
    the A+B survey, then ``--full`` trials of (a) on that scanner.
Where the time goes: the per-sample cost of each part of a trial (true scanner, the
model's numerical inverse and its twin, the tip image) in batches, and how many
samples a trial runs (a vmapped local scan runs as many lines as its slowest trial).

    python experiments/bench_study.py [--batches 16 64 256 1024] [--loop 16] [--full 256]

Two host devices come from XLA_FLAGS, set here before JAX starts; on a 2-core CPU they
share the same two cores.
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

import argparse
import json
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import yaml
from jax.sharding import Mesh

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from benchutil import machine_info, time_jax

from jaxafm.config import StudyConfig
from jaxafm.identify.inverse import numerical_inverse
from jaxafm.instrument.afm import default_afm, render
from jaxafm.instrument.samples import Particles
from jaxafm.model.io import load_model
from jaxafm.study import monte_carlo as study

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "experiments" / "results" / "paper" / "model_scanner.json"


def config(trials: int, model_file) -> StudyConfig:
    raw = yaml.safe_load((ROOT / "configs" / "study.yaml").read_text())
    raw |= {
        "trials": trials,
        "trials_per_scanner": trials,
        "chunk": trials,
        "stages": ["A+B", "A+B+C"],
        "scanner": {},
    }
    raw["calibration"] = raw.get("calibration", {}) | {"model_file": model_file and str(model_file)}
    return StudyConfig.model_validate(raw)


def timed_chunks(cfg, contexts, draws, batch: int, mesh: Mesh, calls: int) -> dict:
    """Warm-up batches until both passes of the local scan have compiled (a batch with a trial
    that needed the second pass), then ``calls`` batches of new trials: trials per minute."""
    part = lambda k: {n: v[k * batch : (k + 1) * batch] for n, v in draws.items()}
    t0 = time.perf_counter()
    for k in range(8):
        r = study.run_chunk(cfg, contexts, part(k), mesh)
        if np.any(~r["ABC_found"] & (r["ABC_lines"] > study.FIRST_PASS_LINES)):
            break
    warm_s, used = time.perf_counter() - t0, k + 1
    t0 = time.perf_counter()
    lines = [study.run_chunk(cfg, contexts, part(used + k), mesh)["ABC_lines"] for k in range(calls)]
    s = (time.perf_counter() - t0) / calls
    lines = np.stack(lines)
    return {
        "batch": batch,
        "devices": mesh.size,
        "seconds_per_batch": s,
        "trials_per_min": 60 * batch / s,
        "warm_up_s": warm_s,
        "warm_up_batches": used,
        "lines_mean": float(lines.mean()),
        "second_pass_pct": 100 * float(np.mean(lines > study.FIRST_PASS_LINES)),
        "lines_max_mean": float(lines.max(1).mean()),
    }


def python_loop(cfg, contexts, draws, n: int, mesh: Mesh) -> dict:
    """The same trials one per call, after a warm-up on a trial that needs both passes."""
    one = lambda k: {m: v[k : k + 1] for m, v in draws.items()}
    for k in range(len(draws["trial"])):
        r = study.run_chunk(cfg, contexts, one(k), mesh)
        if r["ABC_lines"][0] > study.FIRST_PASS_LINES:
            break
    t0 = time.perf_counter()
    for j in range(k + 1, k + 1 + n):
        study.run_chunk(cfg, contexts, one(j), mesh)
    s = (time.perf_counter() - t0) / n
    return {"seconds_per_trial": s, "trials_per_min": 60 / s, "trials": n, "warm_up_trials": k + 1}


def parts_per_sample(batch: int, samples: int = 2048) -> dict:
    """Seconds per sample per trial of each part of a trial's drive, in batches of ``batch``."""
    afm, model = default_afm(), load_model(MODEL)
    t = jnp.arange(1, samples + 1) * 2e-3
    wanted = jnp.stack([300 * jnp.sin(t * 20), 200 * jnp.cos(t * 13)], -1)
    W = wanted + jnp.arange(batch)[:, None, None] * 0.1
    U = W / afm.sensitivity
    cycle = jnp.array([[-10.0, -10.0], [10.0, 10.0]])
    state, twin = (
        afm.scanner.initial_state(jnp.zeros(2), history=cycle),
        model.initial_state(jnp.zeros(2), history=cycle),
    )
    keys = jax.random.split(jax.random.key(0), batch)
    parts = Particles(jnp.zeros((1, 2)), jnp.array([20.0]))
    fns = {
        "true scanner": (jax.vmap(lambda u, k: afm.scanner.run(u, t, state, k)[0]), (U, keys)),
        "model twin": (jax.vmap(lambda u: model.run(u, t, twin)[0]), (U,)),
        "numerical inverse": (
            jax.vmap(lambda w: numerical_inverse(model, w, t, twin, jnp.zeros(2), 10.0)[0]),
            (W,),
        ),
        "tip image (closed form)": (jax.vmap(lambda w: render(parts, afm.tip, w)), (W,)),
    }
    return {
        name: time_jax(f, *args, repeats=3)[0]["median_s"] / (batch * samples)
        for name, (f, args) in fns.items()
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[16, 64, 256, 1024])
    ap.add_argument("--calls", type=int, default=2, help="timed batches per point")
    ap.add_argument("--loop", type=int, default=16, help="trials in the Python loop")
    ap.add_argument(
        "--full", type=int, default=256, help="trials on the scanner of the full pipeline (0: skip)"
    )
    ap.add_argument("--out", type=Path, default=Path("experiments/results/bench_study"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    devices = jax.devices()
    result = {"machine": machine_info()}
    tmp = Path(tempfile.mkdtemp())

    print("(a) B+C with a fixed model: step A's stored model, one survey ...")
    n = max(a.batches) * (a.calls + 8)
    cfg = config(n, MODEL)
    contexts, info = study.prepare_scanner(
        cfg, ROOT / "configs" / "study.yaml", 0, study.scanner_draws(cfg)[0], tmp, print
    )
    draws = study.trial_draws(cfg, study._layout(cfg)[2])
    rows = []
    for d in sorted({1, len(devices)}):
        mesh = Mesh(np.array(devices[:d]), ("trials",))
        for b in a.batches:
            rows.append(timed_chunks(cfg, contexts, draws, b, mesh, a.calls))
            r = rows[-1]
            print(
                f"  {d} device(s), batch {b:5d}: {r['trials_per_min']:8.0f} trials/min "
                f"(warm-up {r['warm_up_s']:.0f} s; "
                f"lines mean {r['lines_mean']:.1f}, {r['second_pass_pct']:.1f} % of trials in the second pass)"
            )
    loop = python_loop(cfg, contexts, draws, a.loop, Mesh(np.array(devices[:1]), ("trials",)))
    best = max(rows, key=lambda r: r["trials_per_min"])
    print(
        f"  Python loop, one trial per call: {loop['trials_per_min']:.0f} trials/min; best batch "
        f"{best['batch']} on {best['devices']} device(s) is {best['trials_per_min'] / loop['trials_per_min']:.0f}x "
        f"that; goal 10,000 trials/min: {'met' if best['trials_per_min'] >= 1e4 else 'NOT met'}"
    )
    result |= {"bc_fixed_model": rows, "python_loop": loop, "best": best}

    print("where the time goes (seconds per sample per trial, batch of", best["batch"], "):")
    costs = parts_per_sample(best["batch"])
    for k, v in costs.items():
        print(f"  {k:26s} {v * 1e6:7.3f} us")
    ls = cfg.local_scan
    line = 16 + 2 * ls.points
    samples = {
        "gotos": 2 * 64,
        "local scan (mean trial)": best["lines_mean"] * line,
        "first pass (every trial)": study.FIRST_PASS_LINES * line,
    }
    print(
        f"  samples per trial: 2 moves of 64, local scan lines of {line} samples: mean {best['lines_mean']:.1f} "
        f"lines; the first pass runs up to {study.FIRST_PASS_LINES} for every trial of the batch, the second "
        f"all {ls.max_lines} for {best['second_pass_pct']:.1f} % of them"
    )
    result |= {"seconds_per_sample": costs, "samples_per_trial": samples}

    if a.full:
        print(f"(b) the full pipeline: step A on a new scanner, then {a.full} trials ...")
        cfg = config(a.full, None)
        t0 = time.perf_counter()
        contexts, info = study.prepare_scanner(
            cfg, ROOT / "configs" / "study.yaml", 0, study.scanner_draws(cfg)[0], tmp / "full", print
        )
        prep = time.perf_counter() - t0
        draws = study.trial_draws(cfg, study._layout(cfg)[2])
        mesh = Mesh(np.array(devices), ("trials",))
        t0 = time.perf_counter()
        study.run_chunk(cfg, contexts, draws, mesh)
        trials_s = time.perf_counter() - t0
        full = {
            "trials": a.full,
            "step_a_fit_s": info["step_a_fit_s"],
            "prepare_s": prep,
            "trials_s": trials_s,
            "trials_per_min": 60 * a.full / (prep + trials_s),
        }
        print(
            f"  step A + surveys {prep:.0f} s (identification {info['step_a_fit_s']:.0f} s), trials {trials_s:.0f} s "
            f"(compilation included): {full['trials_per_min']:.0f} trials/min"
        )
        result["full_pipeline"] = full
    (a.out / "bench.json").write_text(json.dumps(result, indent=1))
    figure(result, a.out / "bench_study.png")
    print(f"wrote {a.out}/bench.json, bench_study.png")


def figure(result: dict, path: Path) -> None:
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    rows = result["bc_fixed_model"]
    for d in sorted({r["devices"] for r in rows}):
        rr = [r for r in rows if r["devices"] == d]
        ax.plot(
            [r["batch"] for r in rr],
            [r["trials_per_min"] for r in rr],
            "o-",
            label=f"{d} device(s), vmapped batch",
        )
    ax.axhline(
        result["python_loop"]["trials_per_min"],
        color="gray",
        ls="--",
        label="Python loop, one trial per call",
    )
    ax.axhline(1e4, color="k", ls=":", label="goal: 10,000 trials/min")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="trials per batch",
        ylabel="trials per minute",
        title="Steps B+C with a fixed model (2-core CPU)",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    costs = result["seconds_per_sample"]
    bx.barh(list(costs), [v * 1e6 for v in costs.values()])
    bx.set(xlabel="µs per sample per trial (batched)", title="Where a trial's time goes, per drive sample")
    if "full_pipeline" in result:
        f = result["full_pipeline"]
        bx.text(
            0.98,
            0.02,
            f"full pipeline, {f['trials']} trials per scanner:\nstep A + surveys {f['prepare_s']:.0f} s, "
            f"trials {f['trials_s']:.0f} s\n= {f['trials_per_min']:.0f} trials/min",
            transform=bx.transAxes,
            ha="right",
            va="bottom",
            fontsize=8,
        )
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
