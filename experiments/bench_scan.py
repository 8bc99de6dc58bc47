"""Speed benchmark of a whole raster scan: JAX forward, JAX forward+gradient, two NumPy baselines.

The scan: ``default_afm()`` with all its effects on (GPI hysteresis with dead
zones, creep, coupling, bow, drift with wander, noise, tip dilation, feedback
lag; it has no rate dependence) imaging ``Grating(pitch 3000 nm, depth 550 nm)``
over 9000 x 9000 nm, ``--pixels`` x ``--lines`` (trace and retrace), line rate
1 Hz, from rest at 0 V after the initialisation cycle. The over-scan is 5 % of
the width at each end (``Raster``'s default 10 % would need 10800 nm, beyond the
scanner's +-5000 nm). One image includes the 32-sample move to its first point.

(a) JAX forward: ``jaxafm.instrument.afm.raster_scan`` jitted; compile time separate,
    one warm-up call, then the median of ``--repeats`` calls.
(b) JAX forward+gradient: value and gradient of ``mean(trace^2 + retrace^2) / 2``
    with respect to every float array of the AFM (scanner, tip, calibration,
    feedback: ``eqx.filter_value_and_grad``), jitted and timed the same way.
(c) NumPy loop (the old baseline): ``raster_scan_numpy`` (tests/reference.py), a Python loop
    over samples that does every stage inside the loop, fed the same random draws; its
    output is checked against (a). Timed once. By default a few lines are timed first
    and the whole image is run if that projects under ``--numpy-budget`` s; otherwise
    (or with ``--numpy-lines N``) only the first lines are run and the time is scaled up
    to the image (linear in lines: the loop does the same work per sample), which the
    output and the JSON say.
(d) NumPy vectorised (the fair baseline): ``raster_scan_numpy(..., vectorised=True)``, a
    Python loop over samples only for the sequential stages (the plays of both axes; the
    creep lags with the drift's wander; the feedback lag), and the readout, coupling, bow,
    noise and the tip image of all samples at once. The whole image, median of
    ``--numpy-repeats`` runs; one more run, not counted, times its sequential loops.

float64 only: jaxafm switches JAX to float64 on import and its modules cast
their inputs to ``float``, so a float32 run would need changes elsewhere.

Run:  python experiments/bench_scan.py [--pixels 512] [--lines N] [--repeats 3] [--numpy-repeats 3]
      [--numpy-lines N] [--numpy-budget 180] [--out experiments/results/bench_scan.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from benchutil import machine_info, time_jax
from reference import (
    numpy_grating_image,
    numpy_grating_images,
    numpy_height,
    raster_normals,
    raster_scan_numpy,
)

from jaxafm.instrument.afm import Raster, default_afm, raster_scan
from jaxafm.instrument.samples import Grating

SIZE_NM, PITCH_NM, DEPTH_NM, LINE_RATE_HZ, OVERSCAN, SEED = 9000.0, 3000.0, 550.0, 1.0, 0.05, 0
HISTORY = [[-10.0, -10.0], [10.0, 10.0]]  # the initialisation cycle; the scan starts at rest at 0 V
MOVE_SAMPLES = 32  # raster_scan's move to the first point


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # ru_maxrss is KiB on Linux


def run_numpy(afm, height, raster, normals, lines, tip_image, vectorised=False):
    t0 = time.perf_counter()
    out = raster_scan_numpy(
        afm,
        height,
        raster,
        *normals,
        history=HISTORY,
        move_samples=MOVE_SAMPLES,
        lines=lines,
        probe=tip_image,
        vectorised=vectorised,
    )
    return time.perf_counter() - t0, out


def run_vectorised(afm, sample, raster, normals, repeats):
    """The vectorised NumPy scan: median of ``repeats`` whole images, then one more run that
    times its sequential loops (``clamp_loop``: the plays; ``linear_recurrence``: the lags and
    the drift's wander)."""
    import reference  # here, after benchutil put tests/ on the path: the module whose loops are timed

    args = (afm, numpy_height(sample), raster, normals, None, numpy_grating_images(sample, afm.tip))
    times = [run_numpy(*args, vectorised=True)[0] for _ in range(repeats)]
    loops = {"clamp_loop": 0.0, "linear_recurrence": 0.0}
    originals = {name: getattr(reference, name) for name in loops}

    def timed(name):
        def fn(*a, **kw):
            t0 = time.perf_counter()
            out = originals[name](*a, **kw)
            loops[name] += time.perf_counter() - t0
            return out

        return fn

    try:
        for name in loops:
            setattr(reference, name, timed(name))
        total, out = run_numpy(*args, vectorised=True)
    finally:
        for name, fn in originals.items():
            setattr(reference, name, fn)
    stats = {
        "median_s": statistics.median(times),
        "min_s": min(times),
        "max_s": max(times),
        "repeats": repeats,
        "profiled_run_s": total,
        "sequential_loops_s": {
            "plays (clamp_loop)": loops["clamp_loop"],
            "lags and wander": loops["linear_recurrence"],
        },
    }
    return stats, out


def run_loop(args, afm, sample, raster, normals):
    """The NumPy loop over samples (the old baseline): on the whole image, or on its first lines
    scaled up to it when a probe of 2 lines projects over ``--numpy-budget`` (or with
    ``--numpy-lines``). Returns the timing record and the scan's output."""
    lines, per_line = raster.lines, 2 * (raster.pixels + 2 * raster.margin)
    height, tip_image = numpy_height(sample), numpy_grating_image(sample, afm.tip)
    run_numpy(afm, height, raster, normals, 0, tip_image)  # warm-up: the move only
    probe = None
    if args.numpy_lines is not None:
        np_lines, how = min(args.numpy_lines, lines), "--numpy-lines"
    else:
        k = min(lines, 2)
        probe_s, _ = run_numpy(afm, height, raster, normals, k, tip_image)
        projected = probe_s * lines / k
        probe = {"lines": k, "s": probe_s, "projected_full_s": projected}
        np_lines = lines if projected <= args.numpy_budget else max(k, int(args.numpy_budget / probe_s * k))
        np_lines, how = min(np_lines, lines), f"probe of {k} lines projected {projected:.0f} s"
    np_s, ref = run_numpy(afm, height, raster, normals, np_lines, tip_image)
    scaled = np_lines < lines
    np_image_s = np_s * (lines * per_line + MOVE_SAMPLES) / (np_lines * per_line + MOVE_SAMPLES)
    print(
        f"(c) NumPy loop        {np_image_s:9.3f} s  "
        + (
            f"SCALED UP from {np_lines} of {lines} lines timed ({np_s:.1f} s; {how})"
            if scaled
            else f"(whole image timed; {how})"
        )
    )
    record = {
        "image_s": np_image_s,
        "timed_s": np_s,
        "lines_timed": np_lines,
        "scaled_up": scaled,
        "how": how,
        "probe": probe,
        "timing": (
            f"timed once on the first {np_lines} of {lines} lines (plus the move) and scaled up by samples"
            if scaled
            else "timed once on the whole image (no extrapolation)"
        ),
    }
    return record, ref


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pixels", type=int, default=512)
    ap.add_argument("--lines", type=int, default=None, help="default: --pixels")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--numpy-repeats", type=int, default=3, help="runs of the vectorised NumPy scan")
    ap.add_argument(
        "--numpy-lines",
        type=int,
        default=None,
        help="time NumPy on only the first N lines and scale up (default: decide from a probe)",
    )
    ap.add_argument(
        "--numpy-budget",
        type=float,
        default=180.0,
        help="s: without --numpy-lines, run NumPy on the whole image if it projects under this",
    )
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_scan.json"))
    args = ap.parse_args()
    lines = args.pixels if args.lines is None else args.lines

    afm = default_afm()
    sample = Grating(jnp.asarray(PITCH_NM), jnp.asarray(DEPTH_NM))
    raster = Raster(
        size=(SIZE_NM, SIZE_NM), pixels=args.pixels, lines=lines, line_rate=LINE_RATE_HZ, overscan=OVERSCAN
    )
    state = afm.initial_state(history=HISTORY)
    key = jax.random.key(SEED)
    per_line = 2 * (raster.pixels + 2 * raster.margin)
    samples = MOVE_SAMPLES + lines * per_line

    info = machine_info()
    print(
        f"jax {info['jax']} on {info['devices']}, {info['cpu_count']} CPUs, {info['platform']}, "
        f"load avg {info['loadavg_at_start'][0]:.1f}"
    )
    print(
        f"scan: {args.pixels} x {lines} px (trace + retrace), {SIZE_NM:g} nm, {LINE_RATE_HZ:g} Hz lines, "
        f"{samples} samples ({MOVE_SAMPLES} move + {lines} x {per_line}); effects {sorted(afm.effects)}"
    )

    def forward(afm, sample, state, key):
        out = raster_scan(afm, sample, state, raster, key=key)
        return out.trace, out.retrace, out.path_trace, out.path_retrace

    def loss(afm, sample, state, key):
        out = raster_scan(afm, sample, state, raster, key=key)
        return 0.5 * (jnp.mean(out.trace**2) + jnp.mean(out.retrace**2))

    def value_and_grad(afm, sample, state, key):
        return eqx.filter_value_and_grad(loss)(afm, sample, state, key)

    fwd, (trace, retrace, path_trace, path_retrace) = time_jax(
        forward, afm, sample, state, key, repeats=args.repeats
    )
    print(f"(a) JAX forward       {fwd['median_s']:9.3f} s  (compile {fwd['compile_s']:.1f} s)")
    grad, (value, g) = time_jax(value_and_grad, afm, sample, state, key, repeats=args.repeats)
    grad_norm = float(
        jnp.sqrt(sum(jnp.sum(x**2) for x in jax.tree.leaves(eqx.filter(g, eqx.is_inexact_array))))
    )
    n_params = sum(x.size for x in jax.tree.leaves(eqx.filter(afm, eqx.is_inexact_array)))
    print(
        f"(b) JAX forward+grad  {grad['median_s']:9.3f} s  (compile {grad['compile_s']:.1f} s; "
        f"loss {float(value):.4g} nm^2, |grad| {grad_norm:.3g} over {n_params} parameters)"
    )
    rss_jax = peak_rss_gib()

    normals = raster_normals(key, raster, MOVE_SAMPLES)
    loop, ref = run_loop(args, afm, sample, raster, normals)
    np_lines, np_image_s = loop["lines_timed"], loop["image_s"]
    vec, vec_out = run_vectorised(afm, sample, raster, normals, args.numpy_repeats)
    print(
        f"(d) NumPy vectorised  {vec['median_s']:9.3f} s  (whole image, median of {args.numpy_repeats}; "
        "loops over samples: "
        + ", ".join(f"{k} {v:.2f} s" for k, v in vec["sequential_loops_s"].items())
        + ")"
    )

    jax_images = {"trace": trace, "retrace": retrace, "path_trace": path_trace, "path_retrace": path_retrace}
    diff = {
        name: float(np.max(np.abs(np.asarray(a)[:np_lines] - ref[name]))) for name, a in jax_images.items()
    }
    diff_vec = {name: float(np.max(np.abs(np.asarray(a) - vec_out[name]))) for name, a in jax_images.items()}
    diff_loops = {name: float(np.max(np.abs(vec_out[name][:np_lines] - ref[name]))) for name in jax_images}
    speedup, speedup_vec = np_image_s / fwd["median_s"], vec["median_s"] / fwd["median_s"]
    grad_ratio = grad["median_s"] / fwd["median_s"]
    scaled = loop["scaled_up"]
    print(f"\n== per image (times in s; JAX: median of {args.repeats}) ==")
    print(f"{'':26}{'time':>10}{'us/sample':>11}{'compile':>9}")
    for name, t_s, c in (
        ("JAX forward", fwd["median_s"], fwd["compile_s"]),
        ("JAX forward+grad", grad["median_s"], grad["compile_s"]),
        ("NumPy loop" + (" (scaled)" if scaled else ""), np_image_s, None),
        ("NumPy vectorised", vec["median_s"], None),
    ):
        print(f"{name:26}{t_s:10.3f}{1e6 * t_s / samples:11.2f}{'-' if c is None else f'{c:.1f}':>9}")
    c_fwd = f"(JAX forward compile {fwd['compile_s']:.1f} s)"
    print(f"\nNumPy loop / JAX forward        {speedup:8.1f}x   {c_fwd}")
    print(f"NumPy vectorised / JAX forward  {speedup_vec:8.1f}x   {c_fwd}")
    print(
        f"JAX grad / JAX forward          {grad_ratio:8.2f}x   (JAX grad compile {grad['compile_s']:.1f} s)"
    )
    for label, d in (
        (f"|JAX - NumPy loop| over the {np_lines} lines", diff),
        ("|JAX - NumPy vectorised| over the image", diff_vec),
        (f"|NumPy vectorised - loop| over the {np_lines} lines", diff_loops),
    ):
        print(f"max {label}: " + ", ".join(f"{k} {v:.1e} nm" for k, v in d.items()))
    print(f"peak RSS {peak_rss_gib():.2f} GiB (after JAX: {rss_jax:.2f} GiB)")

    result = {
        "machine": info,
        "pixels": args.pixels,
        "lines": lines,
        "repeats": args.repeats,
        "numpy_repeats": args.numpy_repeats,
        "seed": SEED,
        "scan": {
            "size_nm": SIZE_NM,
            "line_rate_hz": LINE_RATE_HZ,
            "overscan": OVERSCAN,
            "margin_samples": raster.margin,
            "samples_per_image": samples,
            "move_samples": MOVE_SAMPLES,
            "sample": {"grating_pitch_nm": PITCH_NM, "grating_depth_nm": DEPTH_NM},
            "effects": sorted(afm.effects),
            "history": HISTORY,
            "dtype": "float64",
        },
        "jax_forward": fwd,
        "jax_forward_grad": grad,
        "grad": {
            "loss": "mean(trace^2 + retrace^2) / 2 nm^2",
            "wrt": "every float array of the AFM",
            "parameters": int(n_params),
            "loss_value": float(value),
            "grad_norm": grad_norm,
        },
        "numpy": loop,
        "numpy_vectorised": vec,
        "numpy_over_jax_forward": speedup,
        "numpy_vectorised_over_jax_forward": speedup_vec,
        "grad_over_forward": grad_ratio,
        "max_abs_diff_jax_vs_numpy_nm": diff,
        "max_abs_diff_jax_vs_numpy_vectorised_nm": diff_vec,
        "max_abs_diff_numpy_vectorised_vs_loop_nm": diff_loops,
        "peak_rss_gib": peak_rss_gib(),
        "peak_rss_gib_after_jax": rss_jax,
    }
    result["machine"]["loadavg_at_end"] = load = os.getloadavg()
    if max(info["loadavg_at_start"][0], load[0]) > (os.cpu_count() or 1):
        print(
            f"\nWARNING: load average {info['loadavg_at_start'][0]:.1f} -> {load[0]:.1f} exceeds the "
            f"{os.cpu_count()} CPUs: other processes share the machine, timings are noisy"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"\nsaved {out}")


if __name__ == "__main__":
    main()
