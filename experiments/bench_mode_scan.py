"""The scanner's vibration mode over time sample by sample (``lax.scan``) against an associative
scan of its 2 x 2 affine steps, on the CPU and on a GPU: which one to run where, measured.

The mode's step maps its (position, velocity) state affinely, ``s -> M s + (I - M) (v, 0)`` with
``M = exp(A dt)`` (``jaxafm.model.effects.Vibration``), and affine maps compose into affine maps,
so the mode over a whole record is the prefix composition of the steps, an associative scan of
depth O(log T) over 2 x 2 matrices (``jaxafm.model.effects.associative_mode``).

For each record length T, both paths of ``Vibration.run`` jitted: the positions (forward), and
the gradient of a squared error with respect to the frequency, the damping and the drive (a
fit's need). Compile time (``lower().compile()``) beside the median of ``--repeats`` runs; the
largest difference between the two paths.

    python experiments/bench_mode_scan.py                    # this machine's default JAX device
    JAX_PLATFORMS=cpu python experiments/bench_mode_scan.py  # the CPU where a GPU is present

Writes ``experiments/results/bench_mode_scan/<device>.json`` (the docs' table ``mode_scan``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from bench_play_scan import device_name, forced_path, path_timings, relative_differences, summary

from jaxafm.model import effects

OUT = Path(__file__).resolve().parent / "results" / "bench_mode_scan"
LENGTHS = (1_000, 10_000, 100_000, 300_000)
PATHS = {"sequential": False, "associative": True}


def mode_on(path: str):
    """``Vibration.run``'s positions forced onto one path: the choice is made when traced."""

    def f(v, t, frequency, damping):
        with forced_path(effects, PATHS[path]):
            return effects.Vibration(frequency, damping).run(v, t, jnp.stack([v[0], 0.0]), t[0])[0]

    return f


def measure(T: int, repeats: int) -> dict:
    """Both paths at one record length: the positions, and a loss's gradient. A 10 kHz drive
    (a random walk, nm) through a 1 kHz mode of damping 0.05."""
    rng = np.random.default_rng(0)
    t = jnp.asarray(np.arange(T) * 1e-4)
    v = jnp.asarray(np.cumsum(rng.normal(0.0, 1.0, T)))
    frequency, damping = jnp.asarray(1e3), jnp.asarray(0.05)
    target = jnp.asarray(np.sin(np.arange(T) / 50.0))
    row, outs = {"T": T}, {}
    for name in PATHS:
        f = mode_on(name)
        loss = lambda fr, dm, v, f=f: jnp.sum((f(v, t, fr, dm) - target) ** 2)
        forward = lambda v: f(v, t, frequency, damping)
        grad = jax.grad(loss, argnums=(0, 1, 2))
        columns, y, grads = path_timings(name, T, forward, (v,), grad, (frequency, damping, v), repeats)
        outs[name] = (y, grads)
        row |= columns
    return row | relative_differences(outs["sequential"], outs["associative"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--lengths", type=int, nargs="+", default=list(LENGTHS))
    args = ap.parse_args()
    name = device_name()
    rows = []
    for T in args.lengths:
        rows.append(measure(T, args.repeats))
        r = rows[-1]
        print(summary(f"{name} T={T:>8d}", r), flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    out = OUT / f"{name}.json"
    out.write_text(json.dumps({"device": name, "jax": jax.__version__, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
