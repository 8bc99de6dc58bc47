"""A drift candidate fitted by turns, as the diagnosis does, against the same model fitted at once.

The record diagnosis fits a drift as a random process by turns (``ActuatorRecord._with_wander``):
the plant by least squares to the output less the smoothed drift, the drift (``fit_wander``) to
what the plant leaves, ``WANDER_ROUNDS`` (2) times. Alternating fits of two parts that overlap (a
plant's offset and slow terms against a wander) converge slowly. The joint fit: the plant under
the wander's covariance (``fit_plant(..., whiten=Whitener.of(...))``: its residuals whitened by
the wander's Kalman filter, whose gains do not depend on the data; generalised least squares with
the wander's start and rate profiled out), the wander's ratio refitted to what the plant leaves,
1 to 3 times. On the alternating blocks the diagnosis judges a drift on, for each fit:

- the held-out gap (nm) on the blocks, and the BIC (:meth:`Wander.bic`, lower is better);
- the fitted wander's diffusion (nm^2/s) against the truth's (a walk of ``sigma`` nm/sqrt(s) has
  ``sigma^2``; an Ornstein-Uhlenbeck wander of stationary sd ``sigma`` and time constant ``tau``
  has ``2 sigma^2 / tau`` over times short against ``tau``);
- the smoothed drift's error against the generator's true drift on the held-out blocks (nm rms,
  each axis's mean over the training blocks removed: the plant's offset takes it);

and the oracle: the nominal fitted to the record less the true drift (no wander model), whose
held-out gap is what a perfect drift estimate would leave. PI truths under the PI nominal, so
that no hysteresis rung is involved. Records: ``tests/independent.py`` (no jaxafm code).

    python experiments/drift_rounds.py            # ~3 minutes on 2 cores

Writes ``experiments/results/drift_rounds/{rounds.json, rounds.png}``. Units: nm, s.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import matplotlib

matplotlib.use("Agg")
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from independent import make_case

from jaxafm.diagnose import record as D
from jaxafm.diagnose.plant import fit_plant
from jaxafm.diagnose.wander import Whitener, fit_wander
from jaxafm.instrument.records import Record

OUT = Path(__file__).parent / "results" / "drift_rounds"
#: (seed, truth, wander) of the wandering check's middle cases (``independent.wandering_cases``)
CASES = ((30103, "pi", "walk"), (30111, "pi", "walk"), (31104, "pi", "ou"))
ROUNDS = (2, 5, 20, 50, 150)  # the fit by turns
JOINT_ROUNDS = (1, 2, 3)  # the joint fit: the wander's ratio re-estimated this many times


def blocked(d: np.ndarray, case: dict) -> D.ActuatorRecord:
    """The record ``d`` on the alternating blocks the diagnosis judges a drift on."""
    rec = Record(t=case["t"], u=case["u"], d=d, meta={"source": "independent generator"})
    return D.ActuatorRecord.split_off(rec, D.Nominal(kind="pi")).blocked


def true_diffusion(wander: dict) -> float:
    """The truth's wander diffusion (nm^2/s) over times short against its time constant."""
    s = wander["sigma"]
    return s**2 if wander["kind"] == "walk" else 2 * s**2 / wander["tau_s"]


def fitted(data: D.ActuatorRecord, nominal, rounds: int, joint: bool) -> tuple:
    """The plant and the wander fitted ``rounds`` times, by turns (the diagnosis's own
    ``_with_wander``) or ``joint`` (the plant under the wander's covariance); ``(residual less the
    drift (T, k) nm, the wander)``."""
    if not joint:
        fit = data._with_wander(nominal, rounds=rounds)
        return fit.residual, fit.wander
    u, t, d = jnp.asarray(data.u), jnp.asarray(data.record.t), jnp.asarray(data.d)
    weight = jnp.asarray(data.train, dtype=float)
    plant, r = nominal.plant, nominal.residual
    for _ in range(rounds):
        w = fit_wander(r, data.record.t, data.train)
        whiten = Whitener.of(data.record.t, data.train, w.ratio, w.coloured_ratio, w.coloured_time_s)
        plant, pred, _ = fit_plant(plant, u, t, d, weight, data.history, data.max_steps, whiten)
        r = data.d - np.asarray(pred)
    wander = fit_wander(r, data.record.t, data.train)
    return r - wander.level, wander


def scores(
    data: D.ActuatorRecord, rounds: int, residual, wander, parameters: int, true_drift, seconds
) -> dict:
    """The numbers of one fit (module docstring)."""
    ho, tr = data.heldout, data.train
    err = wander.level - true_drift
    err = err - err[tr].mean(0)
    return {
        "rounds": rounds,
        "heldout_gap_nm": float(np.sqrt(np.mean(residual[ho] ** 2))),
        "bic": wander.bic(parameters),
        "diffusion_nm2_per_s": wander.diffusion.tolist(),
        "drift_error_heldout_nm": np.sqrt(np.mean(err[ho] ** 2, 0)).tolist(),
        "seconds": seconds,
    }


def run(seed: int, truth: str, wander: str) -> dict:
    case = make_case("drift", "middle", seed, truth, wander=wander)
    still = make_case("drift", "middle", seed, truth, magnitude=0.0)  # same hysteresis and noise
    true_drift = case["d"] - still["d"]
    data = blocked(case["d"], case)
    nominal = data.fit_nominal()
    rows = {"by_turns": [], "joint": []}
    k = nominal.parameters + 2 * nominal.residual.shape[1]
    for name, counts in (("by_turns", ROUNDS), ("joint", JOINT_ROUNDS)):
        for rounds in counts:
            t0 = time.perf_counter()
            residual, wander = fitted(data, nominal, rounds, joint=name == "joint")
            rows[name].append(scores(data, rounds, residual, wander, k, true_drift, time.perf_counter() - t0))
    for name, fits in rows.items():
        for row in fits:
            print(
                f"  seed {seed}, {name}, {row['rounds']:3d} rounds: gap {row['heldout_gap_nm']:.2f} nm, "
                f"BIC {row['bic']:.0f}",
                flush=True,
            )
    oracle = blocked(case["d"] - true_drift, case).fit_nominal()
    params = case["truth"]["effect_parameters"]
    return {
        "seed": seed,
        "truth_hysteresis": truth,
        "wander": params["wander"],
        "true_diffusion_nm2_per_s": true_diffusion(params["wander"]),
        "blocks": data.blocks,
        "nominal_heldout_gap_nm": nominal.heldout_gap_nm,
        "oracle_heldout_gap_nm": oracle.heldout_gap_nm,
        **rows,
    }


def figure(results: list, path: Path) -> None:
    """Gap and fitted diffusion against the rounds of the fit by turns (lines), the joint fit's
    (squares at its rounds), the oracle's gap and the truth's diffusion (dotted)."""
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.6))
    for k, r in enumerate(results):
        c, label = f"C{k}", f"seed {r['seed']} ({r['wander']['kind']})"
        for name, style, lab in (("by_turns", "o-", label + ", by turns"), ("joint", "s--", "joint")):
            n = [row["rounds"] for row in r[name]]
            ax[0].plot(n, [row["heldout_gap_nm"] for row in r[name]], style, color=c, label=lab)
            ax[1].plot(n, [np.mean(row["diffusion_nm2_per_s"]) for row in r[name]], style, color=c, label=lab)
        ax[0].axhline(r["oracle_heldout_gap_nm"], color=c, ls=":", lw=1)
        ax[1].axhline(r["true_diffusion_nm2_per_s"], color=c, ls=":", lw=1)
    ax[0].set(xscale="log", xlabel="rounds", ylabel="held-out gap on the blocks (nm)")
    ax[0].set_title("drift candidate's gap (dotted: nominal on the record less the true drift)", fontsize=9)
    ax[1].set(xscale="log", yscale="log", xlabel="rounds", ylabel="wander diffusion, mean of axes (nm²/s)")
    ax[1].set_title("fitted wander (dotted: the truth's)", fontsize=9)
    for a in ax:
        a.grid(alpha=0.3)
    fig.legend(*ax[0].get_legend_handles_labels(), loc="lower center", ncol=6, fontsize=8)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    results = [run(*c) for c in CASES]
    units = {"gap": "nm", "diffusion": "nm^2/s", "time": "s"}
    (OUT / "rounds.json").write_text(json.dumps({"cases": results, "units": units}, indent=1))
    figure(results, OUT / "rounds.png")
    for r in results:
        turns, joint = r["by_turns"], r["joint"]
        print(
            f"seed {r['seed']}: by turns {turns[0]['heldout_gap_nm']:.2f} nm ({turns[0]['rounds']} rounds) -> "
            f"{turns[-1]['heldout_gap_nm']:.2f} nm ({turns[-1]['rounds']}); joint "
            f"{joint[-1]['heldout_gap_nm']:.2f} nm ({joint[-1]['rounds']}); oracle "
            f"{r['oracle_heldout_gap_nm']:.2f} nm; nominal {r['nominal_heldout_gap_nm']:.2f} nm"
        )


if __name__ == "__main__":
    main()
