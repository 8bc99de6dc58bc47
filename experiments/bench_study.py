"""Benchmark: Monte-Carlo study throughput (trials per minute), batched against one by one.

(a) Steps B+C with a fixed identified model: one scanner (``default_afm``) with the
    stored step-A model, pressed and surveyed once (``configs/study.yaml``'s layout);
    each trial goes to its particle through the landmark map (A+B), runs the local
    scan and moves to the centre it found. Batches of ``--batches`` trials on one and
    on two host devices; the same trials one at a time in a Python loop (batch of 1 per
    call); and the best batch again with step A's inverse as it was before, sample by
    sample (``tests/reference.py``) with the twin running the model again: all in the same
    run, each with its warm-up (compilation) time.
(b) The full pipeline with step A per scanner: the calibration scan, identification,
    the A+B survey, then ``--full`` trials of (a) on that scanner.
Where the time goes: a batch split into its jitted calls (the local scan's first pass for
every trial, the second pass for the few still searching), the survey-image lookup of the
particles (``image_position``) and the rest of ``run_chunk`` (Python, eager JAX);
the per-sample cost of each part of one drive (a local-scan line) in batches; and how
many samples a trial runs (a vmapped local scan runs as many lines as its slowest trial).

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
from contextlib import contextmanager
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import yaml
from jax.sharding import Mesh

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from benchutil import device_label, machine_info, time_jax
from reference import numerical_inverse_per_sample

import jaxafm.position.positioning as positioning
from jaxafm.config import StudyConfig
from jaxafm.identify.inverse import inverse_and_state
from jaxafm.instrument.afm import render
from jaxafm.instrument.samples import Particles
from jaxafm.jobs import Output
from jaxafm.jobs import study as job
from jaxafm.jobs.run import workspace_layout
from jaxafm.study import monte_carlo as study

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "experiments" / "results" / "paper" / "model_scanner.json"
GOAL = 30_000  # B+C trials per minute on 2 cores (issue 21)


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
        r = study.run_chunk(contexts, part(k), mesh, job.trial_settings(cfg))
        if k == 0:
            first = time.perf_counter() - t0  # compilation, mostly
        if np.any(~r["ABC_found"] & (r["ABC_lines"] > study.FIRST_PASS_LINES)):
            break
    warm_s, used = time.perf_counter() - t0, k + 1
    t0 = time.perf_counter()
    lines = [
        study.run_chunk(contexts, part(used + k), mesh, job.trial_settings(cfg))["ABC_lines"]
        for k in range(calls)
    ]
    s = (time.perf_counter() - t0) / calls
    lines = np.stack(lines)
    return {
        "batch": batch,
        "devices": mesh.size,
        "seconds_per_batch": s,
        "trials_per_min": 60 * batch / s,
        "warm_up_s": warm_s,
        "first_batch_s": first,
        "warm_up_batches": used,
        "lines_mean": float(lines.mean()),
        "second_pass_pct": 100 * float(np.mean(lines > study.FIRST_PASS_LINES)),
        "lines_max_mean": float(lines.max(1).mean()),
    }


def python_loop(cfg, contexts, draws, n: int, mesh: Mesh) -> dict:
    """The same trials one per call, after a warm-up on a trial that needs both passes."""
    one = lambda k: {m: v[k : k + 1] for m, v in draws.items()}
    t0 = time.perf_counter()
    for k in range(len(draws["trial"])):
        r = study.run_chunk(contexts, one(k), mesh, job.trial_settings(cfg))
        if r["ABC_lines"][0] > study.FIRST_PASS_LINES:
            break
    warm_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for j in range(k + 1, k + 1 + n):
        study.run_chunk(contexts, one(j), mesh, job.trial_settings(cfg))
    s = (time.perf_counter() - t0) / n
    return {
        "seconds_per_trial": s,
        "trials_per_min": 60 / s,
        "trials": n,
        "warm_up_trials": k + 1,
        "warm_up_s": warm_s,
    }


@contextmanager
def old_inverse():
    """Positioning with step A's inverse as it was before: sample by sample
    (``reference.numerical_inverse_per_sample``), the twin's state from running the model
    again. JAX's caches are cleared on the way in and out, so the trials compile with it
    and afterwards without it; yields a list that grows each time the old inverse is traced."""
    new, traced = positioning.inverse_and_state, []

    def old(model, wanted, t, state, u0, u_max):
        traced.append(len(t))
        u, saturated = numerical_inverse_per_sample(model, wanted, t, state, u0, u_max)
        return u, saturated, model.run(u, t, state)[1]

    jax.clear_caches()
    positioning.inverse_and_state = old
    try:
        yield traced
    finally:
        positioning.inverse_and_state = new
        jax.clear_caches()


@contextmanager
def every_pixel():
    """``study.nearest_pixel`` replaced by the search of every pixel (the lookup as it was)."""
    fast = study.nearest_pixel
    study.nearest_pixel = lambda path, point: jnp.divmod(
        jnp.argmin(jnp.sum((path - point) ** 2, -1)), path.shape[1]
    )
    study.image_position.clear_cache()
    try:
        yield
    finally:
        study.nearest_pixel = fast
        study.image_position.clear_cache()


def batch_breakdown(cfg, contexts, draws, batch: int, mesh: Mesh, calls: int) -> dict:
    """Seconds per batch (after :func:`timed_chunks` warmed it up) in the jitted trial calls,
    the local scan's first pass (every trial) and second pass (those still searching, in
    small batches); in ``study.image_position`` (where each particle shows in the survey image,
    timed alone on the same trials); and in the rest of ``study.run_chunk`` (Python, eager JAX)."""
    spent, trials = {"first_pass_s": 0.0, "second_pass_s": 0.0}, study.trials
    part = lambda k: {n: v[k * batch : (k + 1) * batch] for n, v in draws.items()}

    def timed(*args, **kw):
        t0 = time.perf_counter()
        out = jax.block_until_ready(trials(*args, **kw))
        first = args[9].max_lines <= study.FIRST_PASS_LINES  # args[9]: the LocalScan
        spent["first_pass_s" if first else "second_pass_s"] += time.perf_counter() - t0
        return out

    study.trials = timed
    try:
        t0 = time.perf_counter()
        for k in range(calls):
            study.run_chunk(contexts, part(k), mesh, job.trial_settings(cfg))
        total = (time.perf_counter() - t0) / calls
    finally:
        study.trials = trials
    work, mean_path = workspace_layout(cfg)[0], contexts["A+B"].mean_path
    locate = jax.vmap(study.image_position, (None, None, None, 0))
    place = lambda k: np.asarray(
        locate(
            mean_path,
            jnp.asarray(work.origin),
            jnp.asarray(work.pixel_size),
            jnp.stack([part(k)["x_nm"], part(k)["y_nm"]], -1),
        )[0]
    )
    place(0)
    t0 = time.perf_counter()
    for k in range(calls):
        place(k)
    out = {k: v / calls for k, v in spent.items()} | {"batch": batch, "total_s": total}
    out["image_position_s"] = (time.perf_counter() - t0) / calls
    # the same lookup searching every pixel (as before nearest_pixel): its time, and the same positions?
    with every_pixel():
        place(0)
        t0 = time.perf_counter()
        before = [place(k) for k in range(calls)]
        out["image_position_every_pixel_s"] = (time.perf_counter() - t0) / calls
    out["image_position_max_difference_nm"] = float(
        max(np.abs(place(k) - b).max() for k, b in enumerate(before))
    )
    return out | {"other_s": total - out["first_pass_s"] - out["second_pass_s"] - out["image_position_s"]}


def parts_per_sample(pos, stand, batch: int, samples: int = 400) -> dict:
    """Seconds per sample per trial of each part of one drive of ``samples`` (a local-scan
    line) of the study's positioner ``pos`` from ``stand``, vmapped over ``batch`` trials on
    one device; the inverse as it is and as it was (sample by sample, twin run again)."""
    t = stand.afm.scanner.t + jnp.arange(1, samples + 1) * 2.6e-3
    line = jnp.stack([jnp.linspace(-100.0, 100.0, samples), jnp.zeros(samples)], -1)
    W = stand.wanted + line + jnp.arange(batch)[:, None, None] * 0.5
    U = jax.vmap(lambda w: pos.volts(w, t, stand)[0])(W)
    keys = jax.random.split(jax.random.key(0), batch)
    near = jax.vmap(lambda c: Particles(c[None], jnp.array([20.0])))(
        jnp.broadcast_to(stand.wanted, (batch, 2))
    )
    model, u_max, frame = pos.model, pos.afm.u_max, pos.frame

    def before(w, t, s):
        u, _ = numerical_inverse_per_sample(model, w, t, s.twin, s.afm.u, u_max)
        return u, model.run(u, t, s.twin)[1]

    fns = {
        "instrument: scanner, tip image, feedback": (
            lambda u, k, p, t, s: pos.afm.drive(p, u, t, s.afm, k)[:2],
            (U, keys, near),
        ),
        "true scanner (in the instrument)": (
            lambda u, k, t, s: pos.afm.scanner.run(u, t, s.afm.scanner, k)[0],
            (U, keys),
        ),
        "tip image (in the instrument)": (lambda p, w, t, s: render(p, pos.afm.tip, w), (near, W)),
        "landmark map (step B)": (lambda w, t, s: frame(w), (W,)),
        "step A inverse + twin state": (
            lambda w, t, s: inverse_and_state(model, frame(w), t, s.twin, s.afm.u, u_max)[::2],
            (W,),
        ),
        "before: inverse per sample + twin run": (lambda w, t, s: before(frame(w), t, s), (W,)),
    }
    out = {}
    for name, (f, args) in fns.items():
        g = jax.vmap(f, (0,) * len(args) + (None, None))
        stats = time_jax(g, *args, t, stand, repeats=5)[0]
        out[name] = {"us": 1e6 * stats["median_s"] / (batch * samples), "compile_s": stats["compile_s"]}
    return out


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
    contexts, info = job.prepare_scanner(
        cfg, ROOT / "configs" / "study.yaml", 0, job.scanner_draws(cfg)[0], Output(tmp), print
    )
    draws = job.trial_draws(cfg, workspace_layout(cfg)[2])
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
    mesh = Mesh(np.array(devices[: best["devices"]]), ("trials",))
    split = batch_breakdown(cfg, contexts, draws, best["batch"], mesh, a.calls)
    print(
        f"where a batch of {best['batch']} spends its {split['total_s']:.3f} s: "
        f"first pass {split['first_pass_s']:.3f} s, "
        f"second pass {split['second_pass_s']:.3f} s (jitted calls), image_position {split['image_position_s']:.3f} s "
        f"(searching every pixel: {split['image_position_every_pixel_s']:.3f} s; positions equal to "
        f"{split['image_position_max_difference_nm']:.1e} nm), "
        f"the rest of run_chunk {split['other_s']:.3f} s"
    )
    with old_inverse() as traced:
        old = timed_chunks(cfg, contexts, draws, best["batch"], mesh, a.calls)
    assert traced, "the trials did not compile again with the old inverse"
    print(
        f"  Python loop, one trial per call: {loop['trials_per_min']:.0f} trials/min "
        f"(warm-up {loop['warm_up_s']:.0f} s)\n"
        f"  best: batch {best['batch']} on {best['devices']} device(s), {best['trials_per_min']:.0f} trials/min, "
        f"{best['trials_per_min'] / loop['trials_per_min']:.0f}x the loop; with the inverse as it was (per sample, "
        f"twin run again): {old['trials_per_min']:.0f} trials/min (warm-up {old['warm_up_s']:.0f} s, first batch "
        f"{old['first_batch_s']:.0f} s against {best['first_batch_s']:.0f} s); "
        f"goal {GOAL:,} trials/min: {'met' if best['trials_per_min'] >= GOAL else 'NOT met'}"
    )
    result |= {"bc_fixed_model": rows, "python_loop": loop, "best": best, "old_inverse": old}

    per_device = -(-best["batch"] // best["devices"])
    print(f"per drive sample and trial (one local-scan line, {per_device} trials on one device, us):")
    ctx = contexts["A+B"]
    costs = parts_per_sample(ctx.positioner, ctx.stand, per_device)
    for k, v in costs.items():
        print(f"  {k:42s} {v['us']:7.3f}   (compile {v['compile_s']:.1f} s)")
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
    result |= {"batch_split": split, "us_per_sample": costs, "samples_per_trial": samples}

    if a.full:
        print(f"(b) the full pipeline: step A on a new scanner, then {a.full} trials ...")
        cfg = config(a.full, None)
        t0 = time.perf_counter()
        contexts, info = job.prepare_scanner(
            cfg, ROOT / "configs" / "study.yaml", 0, job.scanner_draws(cfg)[0], Output(tmp / "full"), print
        )
        prep = time.perf_counter() - t0
        draws = job.trial_draws(cfg, workspace_layout(cfg)[2])
        mesh = Mesh(np.array(devices), ("trials",))
        t0 = time.perf_counter()
        study.run_chunk(contexts, draws, mesh, job.trial_settings(cfg))
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
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 4.8), constrained_layout=True)
    rows = result["bc_fixed_model"]
    for d in sorted({r["devices"] for r in rows}):
        rr = [r for r in rows if r["devices"] == d]
        tpm = [r["trials_per_min"] for r in rr]
        ax.plot([r["batch"] for r in rr], tpm, "o-", label=f"{d} device(s), vmapped batch")
    old = result["old_inverse"]
    ax.plot(old["batch"], old["trials_per_min"], "kx", ms=9, label="best batch, inverse per sample (before)")
    ax.axhline(
        result["python_loop"]["trials_per_min"],
        color="gray",
        ls="--",
        label="Python loop, one trial per call",
    )
    ax.axhline(GOAL, color="k", ls=":", label=f"goal: {GOAL:,} trials/min")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="trials per batch",
        ylabel="trials per minute",
        title=f"Steps B+C with a fixed model ({device_label(result['machine'])})",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    costs = result["us_per_sample"]
    names = list(costs)[::-1]
    bx.barh(names, [costs[k]["us"] for k in names])
    bx.set(
        xlabel="µs per sample per trial (one line, batched)",
        title="One drive of a trial, per sample",
        xlim=(0, 2.2 * max(costs[k]["us"] for k in names)),  # the bars left, the text right
    )
    sp = result["batch_split"]
    text = (
        f"a batch of {sp['batch']}: {sp['total_s']:.2f} s =\nfirst pass {sp['first_pass_s']:.2f} + second pass "
        f"{sp['second_pass_s']:.2f}\n+ image_position {sp['image_position_s']:.2f} + the rest {sp['other_s']:.2f}"
    )
    if "full_pipeline" in result:
        f = result["full_pipeline"]
        text += (
            f"\n\nfull pipeline, {f['trials']} trials per scanner:\nstep A + surveys {f['prepare_s']:.0f} s, "
            f"trials {f['trials_s']:.0f} s\n= {f['trials_per_min']:.0f} trials/min"
        )
    bx.text(0.98, 0.78, text, transform=bx.transAxes, ha="right", va="top", fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
