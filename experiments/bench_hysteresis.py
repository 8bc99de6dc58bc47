"""Speed benchmark of the JAX hysteresis operators against NumPy baselines, old and fair.

What it measures, all in one run on one input (a fixed-seed random-amplitude
multi-cycle signal plus a filtered random walk, squashed into [0, 3.6] V):

1. Preisach, planes of n = 50 and 100 levels (n(n+1)/2 = 1275 / 5050 hysterons,
   random non-negative lower-triangular density): jitted JAX forward and
   forward+gradient of a squared-error loss w.r.t. the fitted arrays (density
   and offset; the grids stay fixed, as in a fit) and w.r.t. every array, smooth=False
   (the bare relay grid) and smooth=True (the default). NumPy baselines (tests/reference.py):
   ``preisach_relay_grid``, the O(n^2) relay grid every earlier number was measured against,
   and ``preisach_play_loop``, the fair one: the same O(n) algorithm as jaxafm (n plays in a
   Python loop over samples, then the readout of all samples at once), for either kind.
2. Prandtl-Ishlinskii with 50 plays and random positive weights vs ``pi_loop`` (the readout
   inside the loop over samples; the earlier baseline) and ``pi_play_loop`` (plays in the
   loop, readout after it).

Every speed-up is a NumPy baseline's time over the JAX forward time of the same model, and
every JAX/NumPy pair's agreement is reported. The JAX operators run the plays (the only
sequential part) in one ``lax.scan`` over blocks of samples and reduce each block with the
memoryless readout. (An ``associative_scan`` of the play clamps was also tried: on this
2-core CPU it was 1.8-2.6x slower forward and took over a minute to compile its gradient.)

JAX timings: compile (``lower().compile()``) reported beside each, one warm-up call, then the
median of ``--repeats`` calls, each ``jax.block_until_ready``-ed. NumPy timings: the median of
``--numpy-repeats`` runs on the full input (no extrapolation).

Run:  python experiments/bench_hysteresis.py [--samples 100000] [--repeats 5] [--numpy-repeats 3]
      [--out experiments/results/bench_hysteresis.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from benchutil import machine_info, time_jax
from reference import pi_loop, pi_play_loop, preisach_play_loop, preisach_relay_grid

from jaxafm import PrandtlIshlinskii, Preisach  # the model package switches JAX to float64

U_MIN, U_MAX, SEED = 0.0, 3.6, 0
GOAL_SPEEDUP, GOAL_GRAD_RATIO = 50.0, 4.0


def make_input(T: int, seed: int = SEED) -> np.ndarray:
    """Random-amplitude sine sweeps + smoothed random walk + minor loops, min-max into [U_MIN, U_MAX]."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    cycles = max(T // 2000, 2)  # 50 major cycles on 100k samples
    knots = np.linspace(0, T, 2 * cycles + 1)
    env = np.interp(t, knots, rng.uniform(0.1, 1.0, knots.size))
    win = min(501, T // 4 + 1)
    walk = np.convolve(np.cumsum(rng.standard_normal(T)), np.ones(win) / win, mode="same")
    walk = (walk - walk.mean()) / (walk.std() + 1e-12)
    x = env * np.sin(2 * np.pi * cycles * t / T) + 0.2 * walk
    x += 0.05 * np.sin(2 * np.pi * 23 * cycles * t / T + rng.uniform(0, 2 * np.pi))
    return U_MIN + (U_MAX - U_MIN) * (x - x.min()) / (x.max() - x.min())


def forward(m, u):
    return m(u)


def value_and_grad(m, u, target):  # w.r.t. every array of the module
    return eqx.filter_value_and_grad(lambda m: jnp.sum((m(u) - target) ** 2))(m)


def fitted(m):
    """The arrays a fit moves (threshold grids and plane edges stay fixed)."""
    return (m.density, m.offset) if isinstance(m, Preisach) else (m.weights, m.offset)


def value_and_grad_fitted(m, u, target):  # w.r.t. the fitted arrays only
    loss = lambda leaves: jnp.sum((eqx.tree_at(fitted, m, leaves)(u) - target) ** 2)
    return jax.value_and_grad(loss)(fitted(m))


def rates(seconds: float, T: int, hysterons: int) -> dict:
    return {"samples_per_s": T / seconds, "hysteron_updates_per_s": T * hysterons / seconds}


def time_numpy(fn, args, repeats: int):
    """Median of ``repeats`` runs of ``fn(*args)`` on the full input; returns (stats, output)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(times), "min_s": min(times), "repeats": repeats}, out


def bench_model(name, n, hyst, variants, baselines, u, target, repeats, numpy_repeats):
    """Each NumPy baseline, then JAX fwd and value+grad for each variant ("hard" = bare relays).

    ``baselines``: name -> (function, extra arguments, the JAX variant it computes, note).
    """
    T, uj, target = u.size, jnp.asarray(u), jnp.asarray(target)
    row = {"model": name, "samples": T, "plays_updated_per_sample": n, "plane_size": hyst, "numpy": {}}
    outputs = {}
    for b, (fn, args, key, note) in baselines.items():
        stats, outputs[b] = time_numpy(fn, (u, *args), numpy_repeats)
        row["numpy"][b] = {**stats, **rates(stats["median_s"], T, hyst), "model": key, "note": note}
    for key, m in variants.items():
        row[f"fwd_{key}"], y = time_jax(forward, m, uj, repeats=repeats)
        row[f"grad_{key}"], _ = time_jax(value_and_grad_fitted, m, uj, target, repeats=repeats)
        row[f"grad_all_{key}"], _ = time_jax(value_and_grad, m, uj, target, repeats=repeats)
        fwd_s = row[f"fwd_{key}"]["median_s"]
        row[f"fwd_{key}"].update(rates(fwd_s, T, hyst))
        row[f"grad_over_fwd_{key}"] = row[f"grad_{key}"]["median_s"] / fwd_s
        row[f"grad_all_over_fwd_{key}"] = row[f"grad_all_{key}"]["median_s"] / fwd_s
        for b, (*_, b_key, _) in baselines.items():
            if b_key == key:
                row[f"speedup_{key}_vs_{b}"] = row["numpy"][b]["median_s"] / fwd_s
                row[f"max_abs_diff_{key}_vs_{b}"] = float(np.max(np.abs(np.asarray(y) - outputs[b])))
    # the gradient goal uses the default model (smooth=True for Preisach)
    row["grad_over_fwd"] = row.get("grad_over_fwd_smooth", row["grad_over_fwd_hard"])
    return row


def bench_preisach(u, n, rng, repeats, numpy_repeats):
    dens = np.tril(rng.random((n, n)))
    dens *= 10.0 / dens.sum()  # 10 nm total relay weight
    hyst = n * (n + 1) // 2
    variants = {
        key: Preisach(jnp.asarray(dens), jnp.asarray(U_MIN), jnp.asarray(U_MAX), jnp.asarray(0.0), smooth)
        for key, smooth in (("hard", False), ("smooth", True))
    }
    plane = (dens, U_MIN, U_MAX)
    baselines = {
        "relay_grid": (preisach_relay_grid, plane, "hard", f"O(n^2): all {hyst} relays every sample (old)"),
        "play_loop": (preisach_play_loop, (*plane, None, False), "hard", f"O(n): {n} plays per sample"),
        "play_loop_smooth": (preisach_play_loop, (*plane, None, True), "smooth", f"O(n): {n} plays"),
    }
    target = 10.0 * (u - U_MIN) / (U_MAX - U_MIN) - 5.0
    row = bench_model(f"Preisach n={n}", n, hyst, variants, baselines, u, target, repeats, numpy_repeats)
    row["note"] = (
        f"hysteron-updates/s counts all n(n+1)/2={hyst} relays per sample for every implementation, "
        f"but only the relay grid updates every relay: jaxafm and the NumPy play loop update n={n} "
        "plays per sample (Krejci play representation)."
    )
    return row


def bench_pi(u, n, rng, repeats, numpy_repeats):
    pi = PrandtlIshlinskii.uniform(n, U_MAX - U_MIN)
    pi = eqx.tree_at(lambda m: m.weights, pi, jnp.asarray(rng.uniform(0.05, 1.0, n)))
    args = (np.asarray(pi.thresholds), np.asarray(pi.weights), 0.0)
    baselines = {
        "loop": (pi_loop, args, "hard", "readout inside the loop over samples (old)"),
        "play_loop": (pi_play_loop, args, "hard", "plays in the loop, readout after it"),
    }
    return bench_model(f"PI n={n}", n, n, {"hard": pi}, baselines, u, 5.0 * u, repeats, numpy_repeats)


def ms(s):
    return f"{1e3 * s:9.1f}"


LABELS = {
    "relay_grid": "relay grid (old)",
    "play_loop": "play loop",
    "play_loop_smooth": "play loop smooth",
    "loop": "loop (old)",
}


def print_speedups(models):
    print("\n== forward: NumPy baseline time / JAX forward time (ms; compile in s) ==")
    print(
        f"{'model':15}{'JAX model':>10}  {'NumPy baseline':18}{'numpy':>10}{'jax fwd':>10}{'compile':>9}"
        f"{'speedup':>9}{'max|diff|':>10}"
    )
    for r in models:
        for b, nb in r["numpy"].items():
            key = nb["model"]
            fwd = r[f"fwd_{key}"]
            print(
                f"{r['model']:15}{key:>10}  {LABELS[b]:18}{ms(nb['median_s']):>10}{ms(fwd['median_s'])}"
                f"{fwd['compile_s']:9.2f}{r[f'speedup_{key}_vs_{b}']:8.1f}x"
                f"{r[f'max_abs_diff_{key}_vs_{b}']:10.1e}"
            )


def print_gradients(models):
    print(
        "\n== gradients (ms; compile in s): grad = value+grad w.r.t. the fitted arrays, "
        "g_all = w.r.t. every array =="
    )
    print(
        f"{'model':15}{'JAX model':>10}{'fwd':>10}{'compile':>9}{'grad':>10}{'compile':>9}{'g/f':>6}"
        f"{'g_all':>10}{'compile':>9}{'g_all/f':>8}"
    )
    for r in models:
        for key in ("hard", "smooth"):
            if f"fwd_{key}" not in r:
                continue
            f, g, ga = r[f"fwd_{key}"], r[f"grad_{key}"], r[f"grad_all_{key}"]
            print(
                f"{r['model']:15}{key:>10}{ms(f['median_s'])}{f['compile_s']:9.2f}{ms(g['median_s'])}"
                f"{g['compile_s']:9.2f}{r[f'grad_over_fwd_{key}']:6.2f}{ms(ga['median_s'])}"
                f"{ga['compile_s']:9.2f}{r[f'grad_all_over_fwd_{key}']:8.2f}"
            )


def goals_of(models):
    """Goal name -> (value, pass, JAX compile time in s of the function the value times)."""
    goals = {}
    for r in models:
        if r["model"].startswith("Preisach"):
            for b in ("relay_grid", "play_loop"):
                v = r[f"speedup_hard_vs_{b}"]
                goals[f"{r['model']}: JAX fwd >= {GOAL_SPEEDUP:g}x NumPy {LABELS[b]}"] = (
                    v,
                    v >= GOAL_SPEEDUP,
                    r["fwd_hard"]["compile_s"],
                )
        key = "smooth" if "grad_smooth" in r else "hard"
        goals[f"{r['model']}: value+grad <= {GOAL_GRAD_RATIO:g}x fwd"] = (
            r["grad_over_fwd"],
            r["grad_over_fwd"] <= GOAL_GRAD_RATIO,
            r[f"grad_{key}"]["compile_s"],
        )
    diff = max(v for r in models[:2] for k, v in r.items() if k.startswith("max_abs_diff"))
    goals["Preisach (both kinds) matches its NumPy baselines to 1e-12 nm"] = (diff, diff <= 1e-12, None)
    return goals


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--numpy-repeats", type=int, default=3)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_hysteresis.json"))
    args = ap.parse_args()
    u, rng = make_input(args.samples), np.random.default_rng(SEED + 1)
    info = machine_info()
    print(
        f"jax {info['jax']} on {info['devices']}, {info['cpu_count']} CPUs, {info['platform']}, "
        f"load avg {info['loadavg_at_start'][0]:.1f}"
    )
    print(
        f"input: {args.samples} samples in [{u.min():.2f}, {u.max():.2f}] V; JAX median of "
        f"{args.repeats}, NumPy median of {args.numpy_repeats}"
    )

    reps = (args.repeats, args.numpy_repeats)
    models = [
        bench_preisach(u, 50, rng, *reps),
        bench_preisach(u, 100, rng, *reps),
        bench_pi(u, 50, rng, *reps),
    ]
    print_speedups(models)
    print_gradients(models)
    print(
        "   note: hysteron-updates/s (JSON) counts n(n+1)/2 relays per sample; only the relay grid updates them all."
    )

    goals = goals_of(models)
    print("\n== goals ==  (grad ratio: fitted arrays, default smooth=True model)")
    for name, (value, ok, compile_s) in goals.items():
        c = "" if compile_s is None else f"   (JAX compile {compile_s:.2f} s)"
        print(f"   {'PASS' if ok else 'FAIL'}  {name}: {value:.3g}{c}")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "machine": info,
        "samples": args.samples,
        "repeats": args.repeats,
        "numpy_repeats": args.numpy_repeats,
        "seed": SEED,
        "u_range_V": [U_MIN, U_MAX],
        "models": models,
        "goals": {k: {"value": v, "pass": bool(ok), "jax_compile_s": c} for k, (v, ok, c) in goals.items()},
        "numpy_timing": f"each NumPy baseline: median of {args.numpy_repeats} runs on the full input "
        "(no extrapolation)",
    }
    result["machine"]["loadavg_at_end"] = load = os.getloadavg()
    if max(info["loadavg_at_start"][0], load[0]) > (os.cpu_count() or 1):
        print(
            f"\nWARNING: load average {info['loadavg_at_start'][0]:.1f} -> {load[0]:.1f} exceeds the "
            f"{os.cpu_count()} CPUs: other processes share the machine, timings are noisy"
        )
    out.write_text(json.dumps(result, indent=2))
    print(f"\nsaved {out}")


if __name__ == "__main__":
    main()
