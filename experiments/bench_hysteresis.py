"""Speed benchmark of the JAX hysteresis operators against the NumPy baselines.

What it measures, all in one run on one input (a fixed-seed random-amplitude
multi-cycle signal plus a filtered random walk, squashed into [0, 3.6] V):

1. Preisach, planes of n = 50 and 100 levels (n(n+1)/2 = 1275 / 5050 hysterons,
   random non-negative lower-triangular density): jitted JAX forward and
   forward+gradient of a squared-error loss w.r.t. the fitted arrays (density
   and offset; the grids stay fixed, as in a fit) and w.r.t. every array, smooth=False (same
   model as the relay grid, used for the speed-up) and smooth=True (the default); vs the NumPy loop
   ``preisach_relay_grid`` (tests/reference.py) timed once on the full input.
   The JAX/NumPy agreement (smooth=False) is checked and reported.
2. Prandtl-Ishlinskii with 50 plays and random positive weights vs ``pi_loop``.

The JAX operators run the plays (the only sequential part) in one ``lax.scan``
over blocks of samples and reduce each block with the memoryless readout, so a
plane of n levels costs n play updates per sample, not n(n+1)/2 relay updates.
(An ``associative_scan`` of the play clamps was also tried: on this 2-core CPU
it was 1.8-2.6x slower forward and took over a minute to compile its gradient.)

JAX timings: compile (``lower().compile()``) reported separately, one warm-up
call, then the median of ``--repeats`` calls, each ``jax.block_until_ready``-ed.

Run:  python experiments/bench_hysteresis.py [--samples 100000] [--repeats 5]
      [--out experiments/results/bench_hysteresis.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from benchutil import machine_info, time_jax
from reference import pi_loop, preisach_relay_grid

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


def bench_model(name, n, hyst, variants, np_fn, np_args, u, target, repeats):
    """NumPy baseline once, then JAX fwd and value+grad for each variant ("hard" = relay-exact)."""
    T, uj, target = u.size, jnp.asarray(u), jnp.asarray(target)
    t0 = time.perf_counter()
    y_np = np_fn(u, *np_args)  # timed once on the full input: no extrapolation
    np_s = time.perf_counter() - t0
    row = {
        "model": name,
        "samples": T,
        "plays_updated_per_sample": n,
        "plane_size": hyst,
        "hysterons": hyst,
        "numpy_s": np_s,
        "numpy": rates(np_s, T, hyst),
    }
    for key, m in variants.items():
        row[f"fwd_{key}"], y = time_jax(forward, m, uj, repeats=repeats)
        row[f"grad_{key}"], _ = time_jax(value_and_grad_fitted, m, uj, target, repeats=repeats)
        row[f"grad_all_{key}"], _ = time_jax(value_and_grad, m, uj, target, repeats=repeats)
        row[f"grad_all_over_fwd_{key}"] = row[f"grad_all_{key}"]["median_s"] / row[f"fwd_{key}"]["median_s"]
        row[f"fwd_{key}"].update(rates(row[f"fwd_{key}"]["median_s"], T, hyst))
        row[f"grad_over_fwd_{key}"] = row[f"grad_{key}"]["median_s"] / row[f"fwd_{key}"]["median_s"]
        row[f"speedup_{key}_vs_numpy"] = np_s / row[f"fwd_{key}"]["median_s"]
        if key == "hard":
            row["max_abs_diff_hard_vs_numpy"] = float(np.max(np.abs(np.asarray(y) - y_np)))
    # the gradient goal uses the default model (smooth=True for Preisach)
    row["grad_over_fwd"] = row.get("grad_over_fwd_smooth", row["grad_over_fwd_hard"])
    return row


def bench_preisach(u, n, rng, repeats):
    dens = np.tril(rng.random((n, n)))
    dens *= 10.0 / dens.sum()  # 10 nm total relay weight
    hyst = n * (n + 1) // 2
    variants = {
        key: Preisach(jnp.asarray(dens), jnp.asarray(U_MIN), jnp.asarray(U_MAX), jnp.asarray(0.0), smooth)
        for key, smooth in (("hard", False), ("smooth", True))
    }
    target = 10.0 * (u - U_MIN) / (U_MAX - U_MIN) - 5.0
    row = bench_model(
        f"Preisach n={n}", n, hyst, variants, preisach_relay_grid, (dens, U_MIN, U_MAX), u, target, repeats
    )
    row["note"] = (
        f"hysteron-updates/s counts all n(n+1)/2={hyst} relays per sample for both JAX and "
        f"NumPy, but the JAX model (Krejci play representation) updates only n={n} plays "
        "per sample; the relay grid really updates every relay."
    )
    return row


def bench_pi(u, n, rng, repeats):
    pi = PrandtlIshlinskii.uniform(n, U_MAX - U_MIN)
    pi = eqx.tree_at(lambda m: m.weights, pi, jnp.asarray(rng.uniform(0.05, 1.0, n)))
    np_args = (np.asarray(pi.thresholds), np.asarray(pi.weights), 0.0)
    return bench_model(f"PI n={n}", n, n, {"hard": pi}, pi_loop, np_args, u, 5.0 * u, repeats)


def ms(s):
    return f"{1e3 * s:9.1f}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_hysteresis.json"))
    args = ap.parse_args()
    u, rng = make_input(args.samples), np.random.default_rng(SEED + 1)
    info = machine_info()
    print(
        f"jax {info['jax']} on {info['devices']}, {info['cpu_count']} CPUs, {info['platform']}, "
        f"load avg {info['loadavg_at_start'][0]:.1f}"
    )
    print(f"input: {args.samples} samples in [{u.min():.2f}, {u.max():.2f}] V; JAX median of {args.repeats}")

    models = [
        bench_preisach(u, 50, rng, args.repeats),
        bench_preisach(u, 100, rng, args.repeats),
        bench_pi(u, 50, rng, args.repeats),
    ]
    print(
        "\n== models (times in ms; JAX fwd/grad = smooth=False unless marked; grad = value+grad w.r.t. the "
        "fitted arrays; g_all = w.r.t. every array, default model) =="
    )
    print(
        f"{'model':14}{'plays/smp':>10}{'plane':>7}{'numpy':>10}{'jax fwd':>10}{'compile':>9}"
        f"{'speedup':>9}{'fwd smth':>10}{'speedup':>9}{'grad':>10}{'grad smth':>10}{'g/f':>6}{'g/f smth':>9}"
        f"{'g_all/f':>8}{'max|diff|':>10}"
    )
    for r in models:
        sm = "fwd_smooth" in r  # Preisach only
        fs = ms(r["fwd_smooth"]["median_s"]) if sm else "-"
        ss = f"{r['speedup_smooth_vs_numpy']:8.1f}x" if sm else "-"
        gs = ms(r["grad_smooth"]["median_s"]) if sm else "-"
        gfs = f"{r['grad_over_fwd_smooth']:9.2f}" if sm else "-"
        gall = r.get("grad_all_over_fwd_smooth", r["grad_all_over_fwd_hard"])
        print(
            f"{r['model']:14}{r['plays_updated_per_sample']:>10}{r['plane_size']:>7}{ms(r['numpy_s']):>10}"
            f"{ms(r['fwd_hard']['median_s'])}{ms(r['fwd_hard']['compile_s'])}{r['speedup_hard_vs_numpy']:8.1f}x"
            f"{fs:>10}{ss:>9}{ms(r['grad_hard']['median_s']):>10}{gs:>10}"
            f"{r['grad_over_fwd_hard']:6.2f}{gfs:>9}{gall:8.2f}{r['max_abs_diff_hard_vs_numpy']:10.1e}"
        )
    print("\n   rates (JAX smooth=False fwd / NumPy):")
    for r in models:
        j, n_ = r["fwd_hard"], r["numpy"]
        print(
            f"   {r['model']:14} samples/s {j['samples_per_s']:10.3g} / {n_['samples_per_s']:9.3g}   "
            f"hysteron-updates/s {j['hysteron_updates_per_s']:10.3g} / {n_['hysteron_updates_per_s']:9.3g}"
        )
    print("   note: Preisach hysteron-updates/s counts n(n+1)/2 relays per sample; JAX updates only n plays.")

    goals = {}
    for r in models:
        if r["model"].startswith("Preisach"):
            goals[f"{r['model']}: JAX fwd >= {GOAL_SPEEDUP:g}x NumPy"] = (
                r["speedup_hard_vs_numpy"],
                r["speedup_hard_vs_numpy"] >= GOAL_SPEEDUP,
            )
        goals[f"{r['model']}: value+grad <= {GOAL_GRAD_RATIO:g}x fwd"] = (
            r["grad_over_fwd"],
            r["grad_over_fwd"] <= GOAL_GRAD_RATIO,
        )
    diff = max(r["max_abs_diff_hard_vs_numpy"] for r in models[:2])
    goals["Preisach smooth=False matches relay grid to 1e-12"] = (diff, diff <= 1e-12)
    print("\n== goals ==  (grad ratio: fitted arrays, default smooth=True model)")
    for name, (value, ok) in goals.items():
        print(f"   {'PASS' if ok else 'FAIL'}  {name}: {value:.3g}")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "machine": info,
        "samples": args.samples,
        "repeats": args.repeats,
        "seed": SEED,
        "u_range_V": [U_MIN, U_MAX],
        "models": models,
        "goals": {k: {"value": v, "pass": bool(ok)} for k, (v, ok) in goals.items()},
        "numpy_timing": "each NumPy baseline timed once on the full input (no extrapolation)",
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
