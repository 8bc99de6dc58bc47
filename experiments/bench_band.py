"""How long a prediction band takes: each model `jaxafm fit configs/piezo_sine_1hz.yaml` saves
(with its posterior), asked for its 90 % band over a 20,000-sample drive, in one process, on the
CPU (issue goal: under a second on 2 cores).

The drive is the shipped record's input (``piezo_sine_1hz.dat``, 200 Hz) repeated to 20,000
samples (100 s), its times at 200 Hz. Each model's first call compiles the linearisation
(:func:`~jaxafm.model.posterior.linearise`: the prediction and its Jacobian in the model's raw
parameters, by forward mode) and forms the band (:func:`~jaxafm.model.posterior.band`); the
second and later calls, on another drive of the same length, reuse the compiled code. Both are
reported, the later ones as the median of ``--repeats``, and the linearisation's tracing and XLA
compilation timed apart (lowered and compiled once more after the calls, its caches cleared). The
linearisation compiles at XLA's backend optimisation level 0
(:data:`~jaxafm.model.posterior.ONE_SHOT`); beside it, the same lowered program compiled at
XLA's default level (3), with the median run of each compiled program over ``--repeats`` calls.

    python experiments/bench_band.py [--samples 20000] [--repeats 5]

Writes ``experiments/results/bench_band/bench.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import benchutil
import jax
import numpy as np

from jaxafm.instrument.records import read_record
from jaxafm.model.io import read_model_and_posterior
from jaxafm.model.posterior import _linearise, band

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "experiments" / "results" / "piezo_sine_1hz"
OUT = ROOT / "experiments" / "results" / "bench_band"
KINDS = ("line", "pi", "gpi", "preisach", "gpi_creep", "gpi_lag_creep")
RATE_HZ = 200.0


def drive(samples: int, shift: int = 0) -> tuple:
    """``(u, t)``: the shipped record's input (V), from sample ``shift`` on, repeated to
    ``samples``, and its times (s) at :data:`RATE_HZ`."""
    record = read_record(
        ROOT / "jaxafm" / "data" / "real" / "piezo_sine_1hz.dat",
        input_columns=[1],
        output_columns=[5],
        sample_rate_hz=RATE_HZ,
        output_unit="um",
    )
    u = np.roll(np.asarray(record.u, float), -shift)
    return np.resize(u, samples), np.arange(samples) / RATE_HZ


def time_band(kind: str, samples: int, repeats: int) -> dict:
    """The first call's and the later calls' wall time (s) of one model's 90 % band."""
    model, _, posterior = read_model_and_posterior(MODELS / f"model_{kind}.json")
    u, t = drive(samples)
    start = time.perf_counter()
    first = band(model, posterior, u, t, level=0.9)
    first_s = time.perf_counter() - start
    later = []
    for k in range(repeats):
        u, t = drive(samples, shift=37 * (k + 1))
        start = time.perf_counter()
        band(model, posterior, u, t, level=0.9)
        later.append(time.perf_counter() - start)
    jax.clear_caches()
    start = time.perf_counter()
    args = (model, u, t, None, posterior.input_span_v, posterior.output_range_nm)
    lowered = _linearise.lower(*args)
    traced = time.perf_counter()
    one_shot = lowered.compile()
    compiled = time.perf_counter()
    default = lowered.compile(compiler_options={"xla_backend_optimization_level": 3})
    return {
        "trace_s": traced - start,
        "compile_s": compiled - traced,
        "compile_default_level_s": time.perf_counter() - compiled,
        "run_s": run_time(one_shot, args, repeats),
        "run_default_level_s": run_time(default, args, repeats),
        "parameters": int(posterior.covariance.shape[0]),
        "first_call_s": first_s,
        "later_call_median_s": statistics.median(later),
        "later_call_max_s": max(later),
        "band_width_nm_mean": first.width(),
    }


def run_time(compiled, args: tuple, repeats: int) -> float:
    """The median wall time (s) of ``repeats`` calls of a compiled linearisation, results fetched."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=20_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    out = {"machine": benchutil.machine_info(), "samples": args.samples, "models": {}}
    for kind in KINDS:
        row = out["models"][kind] = time_band(kind, args.samples, args.repeats)
        print(
            f"{kind:14s} {row['parameters']:3d} parameters: first call {row['first_call_s']:.2f} s "
            f"(compiling included), later {row['later_call_median_s'] * 1e3:.0f} ms median "
            f"({row['later_call_max_s'] * 1e3:.0f} ms worst); linearisation traced in {row['trace_s']:.2f} s, "
            f"compiled in {row['compile_s']:.2f} s (XLA's default level: {row['compile_default_level_s']:.2f} s), "
            f"run in {row['run_s'] * 1e3:.0f} ms ({row['run_default_level_s'] * 1e3:.0f} ms); mean 90 % width "
            f"{row['band_width_nm_mean']:.0f} nm"
        )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "bench.json").write_text(json.dumps(out, indent=1))
    print(f"wrote {OUT / 'bench.json'}")


if __name__ == "__main__":
    main()
