"""Two libraries' BLAS in one loop: what it costs on 2 cores, in the two loops that had it.

NumPy and SciPy each ship their own OpenBLAS, each with its own threads, which spin for a
while after a call before they sleep. A loop that calls one library's BLAS, then the other's,
runs each call against the other library's spinning threads. Each loop below is timed written
both ways, the same algorithm on the same matrices, in one process, each variant's calls in a
row after a second's rest:

- **leave one block out** (:func:`jaxafm.identify.uncertainty.leave_group_out`, the Woodbury
  form: ``e_g = r_g + J_g (H - J_g^T J_g)^-1 J_g^T r_g`` for each block ``g``) on the posterior
  of the 30-level Preisach plane that ``jaxafm fit configs/piezo_sine_1hz.yaml`` fits: NumPy's
  products with SciPy's Cholesky solve, or NumPy's products and solve (what jaxafm runs);
- **the non-negative weights' pivoting** (:func:`jaxafm.identify.linear.nonnegative_solve`) of a
  50-level plane (1,275 weights) on the ramped-sine record: NumPy's ``G w`` beside SciPy's
  Cholesky, or SciPy's for both (what jaxafm runs).

    python experiments/bench_blas_threads.py [--repeats 7]

Writes ``experiments/results/bench_blas_threads/bench.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import benchutil
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxafm.identify import linear, uncertainty
from jaxafm.identify.fit import initial_operator
from jaxafm.instrument.records import read_record
from jaxafm.model.io import read_model_and_posterior
from jaxafm.model.posterior import linearise

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "jaxafm" / "data" / "real"
OUT = ROOT / "experiments" / "results" / "bench_blas_threads"
SETTLE = 20  # configs/piezo_sine_1hz.yaml's settle_s at 200 Hz
HISTORY = jnp.asarray([0.0])  # its history_v


def record(name: str):
    """One of the shipped 200 Hz piezo records (jaxafm/data/real/README.md)."""
    return read_record(
        REAL / name, input_columns=[1], output_columns=[5], sample_rate_hz=200, output_unit="um"
    )


def posterior_problem() -> tuple:
    """``(J, r, groups, H)``: the training residuals of the committed 30-level Preisach fit of the
    sine record, their Jacobian, the blocks and the Hessian that its posterior works with."""
    model, about, posterior = read_model_and_posterior(
        ROOT / "experiments" / "results" / "piezo_sine_1hz" / "model_preisach.json"
    )
    rec = record("piezo_sine_1hz.dat")
    split = rec.split(about["train_fraction"])
    y, G = linearise(model, posterior.input_span_v, posterior.output_range_nm, rec.u, rec.t, HISTORY)
    J, r = G[SETTLE:split], y[SETTLE:split] - np.asarray(rec.d)[SETTLE:split]
    groups = np.arange(len(r)) // uncertainty.correlation_length(r)
    prior = np.mean(r**2) * np.eye(J.shape[1]) / uncertainty.PRIOR_SD**2
    return J, r, groups, uncertainty.hessian(J, prior)


def woodbury(J, r, groups, H, solve) -> list:
    """Each block's left-out residuals by the Woodbury form, ``solve`` for the (k, k) systems."""
    out = []
    for g in np.unique(groups):
        Jg, rg = J[groups == g], r[groups == g]
        out.append(rg + Jg @ solve(H - Jg.T @ Jg, Jg.T @ rg))
    return out


def scipy_cholesky(a, b):
    """``a^-1 b`` by SciPy's Cholesky (LAPACK in SciPy's OpenBLAS)."""
    return scipy.linalg.cho_solve(scipy.linalg.cho_factor(a, lower=True), b)


def weights_problem(levels: int) -> linear.NormalEquations:
    """The normal equations of a ``levels``-level plane's weights on the ramped-sine record."""
    rec = record("piezo_ramped_sine_1hz.dat")
    u, d = jnp.asarray(rec.u), np.asarray(rec.d)
    model = initial_operator("preisach", u, d, operators=levels, levels=levels, deadzones=0)
    return linear.normal_equations(model, u, d, history=HISTORY, settle=SETTLE)


class NumpyProduct:
    """``scipy.linalg.blas`` as :func:`~jaxafm.identify.linear.nonnegative_solve` sees it, its
    ``dsymv`` (``G w``) by NumPy's BLAS instead."""

    @staticmethod
    def dsymv(alpha, a, x, lower=0):
        return alpha * (a @ x)


def nonnegative_with_numpy_product(ne: linear.NormalEquations) -> tuple:
    """:func:`~jaxafm.identify.linear.nonnegative_solve` with ``G w`` by NumPy's BLAS."""
    real = linear.blas
    linear.blas = NumpyProduct
    try:
        return linear.nonnegative_solve(ne.gram, ne.rhs)
    finally:
        linear.blas = real


def one_after_another(variants: dict, repeats: int, rest_s: float = 1.0) -> tuple:
    """Each variant's wall times (s) over ``repeats`` calls in a row and its last result; before
    each variant's calls, ``rest_s`` without work, so that no thread of the variant before it still
    spins."""
    times, results = {}, {}
    for name, call in variants.items():
        time.sleep(rest_s)
        times[name] = []
        for _ in range(repeats):
            start = time.perf_counter()
            results[name] = call()
            times[name].append(time.perf_counter() - start)
    return times, results


def summary(times: list) -> dict:
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "times_s": times}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    loops = []

    J, r, groups, H = posterior_problem()
    times, got = one_after_another(
        {
            "numpy products, scipy Cholesky": lambda: woodbury(J, r, groups, H, scipy_cholesky),
            "numpy throughout (jaxafm)": lambda: woodbury(J, r, groups, H, np.linalg.solve),
        },
        args.repeats,
    )
    a, b = (np.concatenate(v) for v in got.values())
    ours = np.concatenate(list(uncertainty.leave_group_out(J, r, groups, prior=H - J.T @ J, H=H).values()))
    loops.append(
        {
            "loop": "leave one block out",
            "problem": f"30-level Preisach plane, {J.shape[1]} parameters, {len(r)} samples, "
            f"{groups.max() + 1} blocks",
            "largest_difference_nm": float(np.abs(a - b).max()),
            "jaxafm_equals_numpy_variant": bool(np.array_equal(ours, b)),
            "variants": {name: summary(t) for name, t in times.items()},
        }
    )

    ne = weights_problem(50)
    times, got = one_after_another(
        {
            "numpy G w, scipy Cholesky": lambda: nonnegative_with_numpy_product(ne),
            "scipy throughout (jaxafm)": lambda: linear.nonnegative_solve(ne.gram, ne.rhs),
        },
        args.repeats,
    )
    (wa, sa, _), (wb, sb, _) = got.values()
    loops.append(
        {
            "loop": "non-negative weights' pivoting",
            "problem": f"50-level Preisach plane, {len(ne.rhs)} weights, {ne.samples} samples",
            "pivoting_steps": [sa, sb],
            "largest_relative_difference": float(np.abs(wa - wb).max() / np.abs(wb).max()),
            "variants": {name: summary(t) for name, t in times.items()},
        }
    )

    for loop in loops:
        print(f"{loop['loop']} ({loop['problem']}):")
        for name, s in loop["variants"].items():
            print(
                f"  {name:34s} median {1e3 * s['median_s']:7.1f} ms  ({1e3 * s['min_s']:.1f}-{1e3 * s['max_s']:.1f})"
            )
    OUT.mkdir(parents=True, exist_ok=True)
    doc = {"machine": benchutil.machine_info(), "repeats": args.repeats, "loops": loops}
    (OUT / "bench.json").write_text(json.dumps(doc, indent=1))
    print(f"wrote {OUT / 'bench.json'}")


if __name__ == "__main__":
    main()
