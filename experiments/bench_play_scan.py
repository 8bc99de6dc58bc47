"""Plays over time sample by sample (``lax.scan``) against an associative scan, on the CPU and
on a GPU: which one to run where, measured.

A play's update is a clamp, ``p_t = clip(p_{t-1}, u_t - r, u_t + r)``, and clamps compose into
clamps: ``clip(clip(y, a, b), c, d) = clip(y, clip(a, c, d), clip(b, c, d))`` for ``a <= b``,
``c <= d``. The plays over a whole record are then the prefix composition of the pairs
``(u_t - r, u_t + r)``, an associative scan of depth O(log T) (``jax.lax.associative_scan``),
applied to the start: ``P_t = clip(p_0, A_t, B_t)``. A clamp only selects, so both give the
same numbers bit for bit.

For each record length T and ``--plays`` plays (radii evenly over half the drive span, as
``jaxafm`` lays a PI model's), both jitted: the plays ``P`` (T, n) (``jaxafm.model.hysteresis
.play`` against the associative scan), and a PI readout ``y = P w`` with the gradient of a
squared error with respect to the weights and the drive (the inverse's and the fits' need).
Compile time (``lower().compile()``) beside the median of ``--repeats`` runs; the largest
difference between the two (0: the same numbers).

    python experiments/bench_play_scan.py                    # this machine's default JAX device
    JAX_PLATFORMS=cpu python experiments/bench_play_scan.py  # the CPU where a GPU is present

Writes ``experiments/results/bench_play_scan/<device>.json`` and, from every such file there,
``scaling.png`` (time per sample against T, log-log).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxafm import plots
from jaxafm.model.hysteresis import associative_plays, play

OUT = Path(__file__).resolve().parent / "results" / "bench_play_scan"
LENGTHS = (1_000, 10_000, 100_000, 1_000_000)


def associative_play(u: jax.Array, radii: jax.Array) -> jax.Array:
    """The plays (T, n) of radii ``radii`` for the drive ``u`` (T,), every play at ``u[0]``
    before it (``jaxafm``'s start), by the associative scan of clamps (module docstring;
    ``jaxafm.model.hysteresis.associative_plays``)."""
    return associative_plays(u, radii, jnp.broadcast_to(u[0], radii.shape))


@contextlib.contextmanager
def forced_path(module, associative: bool):
    """``module.time_parallel`` answering ``associative`` inside the block: a stage picks its path
    when it is traced, so a function traced inside runs that path."""
    before = module.time_parallel
    module.time_parallel = lambda: associative
    try:
        yield
    finally:
        module.time_parallel = before


def drive(T: int, seed: int = 0) -> np.ndarray:
    """A random-amplitude triangle-like drive in [0, 3.6] V with minor loops."""
    rng = np.random.default_rng(seed)
    knots = np.cumsum(rng.uniform(20, 200, T // 20 + 2))
    values = rng.uniform(0.0, 3.6, knots.size)
    return np.interp(np.arange(T), knots - knots[0], values)


def timed(f, *args, repeats: int) -> tuple:
    """``(compile s, median run s, output)`` of jitted ``f``."""
    start = time.perf_counter()
    compiled = jax.jit(f).lower(*args).compile()
    compile_s = time.perf_counter() - start
    out = jax.block_until_ready(compiled(*args))
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - start)
    return compile_s, statistics.median(runs), out


def path_timings(name: str, T: int, forward, fargs: tuple, grad, gargs: tuple, repeats: int) -> tuple:
    """One path of a time-parallel benchmark at ``T`` samples: ``(columns, output, gradient)``,
    the columns its compile and median run times (:func:`timed`) and samples/s, forward
    (``forward(*fargs)``) and with a gradient (``grad(*gargs)``)."""
    c, r, y = timed(forward, *fargs, repeats=repeats)
    cg, rg, g = timed(grad, *gargs, repeats=repeats)
    columns = {f"{name}_compile_s": c, f"{name}_run_s": r, f"{name}_samples_per_s": T / r}
    columns |= {f"{name}_grad_compile_s": cg, f"{name}_grad_run_s": rg, f"{name}_grad_samples_per_s": T / rg}
    return columns, y, g


def relative_differences(sequential: tuple, associative: tuple) -> dict:
    """The largest differences between two paths' ``(output, gradients)``, relative to the
    sequential path's largest value."""
    (ys, gs), (ya, ga) = sequential, associative
    return {
        "max_relative_difference": float(jnp.max(jnp.abs(ys - ya)) / jnp.max(jnp.abs(ys))),
        "max_relative_gradient_difference": float(
            max(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)) for a, b in zip(gs, ga))
        ),
    }


def summary(head: str, r: dict) -> str:
    """A benchmark row in a line: both paths' samples/s and compile times, their differences."""
    return (
        f"{head}: {r['sequential_samples_per_s']:.3g} (sequential) vs "
        f"{r['associative_samples_per_s']:.3g} samples/s (associative); gradient "
        f"{r['sequential_grad_samples_per_s']:.3g} vs {r['associative_grad_samples_per_s']:.3g}; "
        f"compile {r['sequential_compile_s']:.2f} vs {r['associative_compile_s']:.2f} s (gradient "
        f"{r['sequential_grad_compile_s']:.2f} vs {r['associative_grad_compile_s']:.2f} s); relative "
        f"difference {r['max_relative_difference']:.1e}, gradient {r['max_relative_gradient_difference']:.1e}"
    )


def device_name() -> str:
    """The default JAX device as the result files are named: ``cpu``, or the platform and the
    device's kind (``gpu_nvidia_h200``)."""
    device = jax.devices()[0]
    kind = "" if device.platform == "cpu" else f"_{device.device_kind}"
    return f"{device.platform}{kind}".lower().replace(" ", "_")


def measure(T: int, plays: int, repeats: int) -> dict:
    """Both methods at one record length: forward plays, and a PI readout's loss and gradient."""
    u = jnp.asarray(drive(T))
    radii = jnp.linspace(0.0, 1.8, plays, endpoint=False)
    w = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, plays))
    target = jnp.asarray(np.sin(np.arange(T) / 50.0))
    methods = {"sequential": lambda u: play(u, radii), "associative": lambda u: associative_play(u, radii)}
    row = {"T": T, "plays": plays}
    outs = {}
    for name, plays_of in methods.items():
        loss = lambda w, u, plays_of=plays_of: jnp.sum((plays_of(u) @ w - target) ** 2)
        grad = jax.value_and_grad(loss, argnums=(0, 1))
        columns, P, (_, grads) = path_timings(name, T, plays_of, (u,), grad, (w, u), repeats)
        outs[name] = (P, grads)
        row |= columns
    (Ps, gs), (Pa, ga) = outs["sequential"], outs["associative"]
    row["max_plays_difference"] = float(jnp.max(jnp.abs(Ps - Pa)))
    row["max_gradient_difference"] = float(max(jnp.max(jnp.abs(a - b)) for a, b in zip(gs, ga)))
    return row


def figure(path: Path) -> None:
    """Run time per sample against T for every device file present, both methods, forward and
    forward + gradient."""
    fig, (ax, axg) = plots.subplots(1, 2, figsize=(13, 5.2), sharey=True)
    for i, file in enumerate(sorted(OUT.glob("*.json"))):
        doc = json.loads(file.read_text())
        T = np.array([r["T"] for r in doc["rows"]])
        for name, style in (("sequential", "-o"), ("associative", "--s")):
            label = f"{doc['device']}: {name}"
            ax.loglog(
                T, [r[f"{name}_run_s"] / r["T"] for r in doc["rows"]], style, color=f"C{i}", label=label
            )
            axg.loglog(
                T, [r[f"{name}_grad_run_s"] / r["T"] for r in doc["rows"]], style, color=f"C{i}", label=label
            )
    ax.set(xlabel="samples T", ylabel="run time per sample [s]", title="plays (forward)")
    axg.set(xlabel="samples T", title="PI readout: loss and gradient (weights, drive)")
    for a in (ax, axg):
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plays", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--lengths", type=int, nargs="+", default=list(LENGTHS))
    ap.add_argument("--out", type=Path, default=None, help="the JSON file (default: results/<device>.json)")
    args = ap.parse_args()
    name = device_name()
    rows = []
    for T in args.lengths:
        rows.append(measure(T, args.plays, args.repeats))
        r = rows[-1]
        print(
            f"{name} T={T:>8d}: plays {r['sequential_samples_per_s']:.3g} (sequential) vs "
            f"{r['associative_samples_per_s']:.3g} samples/s (associative); gradient "
            f"{r['sequential_grad_samples_per_s']:.3g} vs {r['associative_grad_samples_per_s']:.3g}; compile "
            f"{r['sequential_compile_s']:.2f} vs {r['associative_compile_s']:.2f} s (gradient "
            f"{r['sequential_grad_compile_s']:.2f} vs {r['associative_grad_compile_s']:.2f} s); "
            f"difference {r['max_plays_difference']:.1e}, gradient {r['max_gradient_difference']:.1e}",
            flush=True,
        )
    out = args.out or OUT / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"device": name, "jax": jax.__version__, "rows": rows}, indent=1))
    if out.parent == OUT:
        figure(OUT / "scaling.png")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
