"""First-order lags over time sample by sample (``lax.scan``) against an associative scan, on the
CPU and on a GPU: which one to run where, measured.

A lag's step is affine, ``z -> a z + b`` (``a = exp(-dt / tau)``, ``b = (1 - a) v``), and affine
maps compose into affine maps, so the lags over a whole record are the prefix composition of the
steps, an associative scan of depth O(log T) (``jaxafm.model.effects.associative_lags``). The
rate dependence is one lag, a creep bank several (``--lags``, time constants evenly in log
from 0.1 s to 1000 s as ``Creep.logarithmic``'s).

For each record length T, both paths of ``jaxafm.model.effects.lowpass`` jitted: the lags'
weighted sum (forward), and the gradient of a squared error with respect to the time constants
and the drive (the fits' need). Compile time (``lower().compile()``) beside the median of
``--repeats`` runs; the largest difference between the two paths.

    python experiments/bench_lag_scan.py                    # this machine's default JAX device
    JAX_PLATFORMS=cpu python experiments/bench_lag_scan.py  # the CPU where a GPU is present

Writes ``experiments/results/bench_lag_scan/<device>.json`` and, from every such file there,
``scaling.png`` (time per sample against T, log-log).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from bench_play_scan import device_name, forced_path, path_timings, relative_differences, summary

from jaxafm import plots
from jaxafm.model import effects

OUT = Path(__file__).resolve().parent / "results" / "bench_lag_scan"
LENGTHS = (1_000, 10_000, 100_000, 1_000_000)
PATHS = {"sequential": False, "associative": True}


def lowpass_on(path: str):
    """``lowpass`` forced onto one path: the choice is made when it is traced."""

    def f(v, t, taus, w):
        with forced_path(effects, PATHS[path]):
            return effects.lowpass(v, t, taus, jnp.zeros_like(taus), None, w)[0]

    return f


def measure(T: int, lags: int, repeats: int) -> dict:
    """Both paths at one record length: the lags' weighted sum, and a loss's gradient."""
    rng = np.random.default_rng(0)
    t = jnp.asarray(np.arange(T) * 1e-3)  # 1 kHz
    v = jnp.asarray(np.cumsum(rng.normal(0.0, 1.0, T)))
    taus = jnp.logspace(-1, 3, lags) if lags > 1 else jnp.asarray([2e-3])
    w = jnp.full(lags, 0.01)
    target = jnp.asarray(np.sin(np.arange(T) / 50.0))
    row, outs = {"T": T, "lags": lags}, {}
    for name in PATHS:
        f = lowpass_on(name)
        loss = lambda taus, v, f=f: jnp.sum((f(v, t, taus, w) - target) ** 2)
        grad = jax.grad(loss, argnums=(0, 1))
        columns, y, grads = path_timings(name, T, lambda v: f(v, t, taus, w), (v,), grad, (taus, v), repeats)
        outs[name] = (y, grads)
        row |= columns
    return row | relative_differences(outs["sequential"], outs["associative"])


def figure(path: Path) -> None:
    """Run time per sample against T for every device file present, both paths, forward and
    forward + gradient, one line per number of lags."""
    fig, (ax, axg) = plots.subplots(1, 2, figsize=(13, 5.2), sharey=True)
    for i, file in enumerate(sorted(OUT.glob("*.json"))):
        doc = json.loads(file.read_text())
        for lags, marker in ((1, "o"), (9, "s")):
            rows = [r for r in doc["rows"] if r["lags"] == lags]
            T = np.array([r["T"] for r in rows])
            for name, line in (("sequential", "-"), ("associative", "--")):
                label = f"{doc['device']}: {name}, {lags} lag{'s' if lags > 1 else ''}"
                style = dict(color=f"C{i}", marker=marker, linestyle=line, label=label)
                ax.loglog(T, [r[f"{name}_run_s"] / r["T"] for r in rows], **style)
                axg.loglog(T, [r[f"{name}_grad_run_s"] / r["T"] for r in rows], **style)
    ax.set(xlabel="samples T", ylabel="run time per sample [s]", title="lags (forward)")
    axg.set(xlabel="samples T", title="loss and gradient (time constants, drive)")
    for a in (ax, axg):
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lags", type=int, nargs="+", default=[1, 9])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--lengths", type=int, nargs="+", default=list(LENGTHS))
    args = ap.parse_args()
    name = device_name()
    rows = []
    for lags in args.lags:
        for T in args.lengths:
            rows.append(measure(T, lags, args.repeats))
            r = rows[-1]
            print(summary(f"{name} lags={lags} T={T:>8d}", r), flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    out = OUT / f"{name}.json"
    out.write_text(json.dumps({"device": name, "jax": jax.__version__, "rows": rows}, indent=1))
    figure(OUT / "scaling.png")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
