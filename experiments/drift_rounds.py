"""How far a drift candidate's alternating fit is from its joint optimum, on the independent generator.

The record diagnosis fits a drift as a random process by turns (``ActuatorRecord._with_wander``):
the plant refitted to the output less the smoothed drift, the drift (``fit_wander``) to what the
plant leaves, ``WANDER_ROUNDS`` times. Alternating fits of two coupled parts converge slowly where
the parts overlap (a plant's offset and slow hysteresis terms against a wander). This script runs
the drift candidate on the alternating blocks the diagnosis judges it on, with more and more
rounds, and reports for each count:

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
import matplotlib.pyplot as plt
import numpy as np
from independent import make_case

from jaxafm.diagnose import record as D
from jaxafm.instrument.records import Record

OUT = Path(__file__).parent / "results" / "drift_rounds"
#: (seed, truth, wander) of the wandering check's middle cases (``independent.wandering_cases``)
CASES = ((30103, "pi", "walk"), (30111, "pi", "walk"), (31104, "pi", "ou"))
ROUNDS = (2, 5, 20, 50, 150)


def blocked(d: np.ndarray, case: dict) -> D.ActuatorRecord:
    """The record ``d`` on the alternating blocks the diagnosis judges a drift on."""
    rec = Record(t=case["t"], u=case["u"], d=d, meta={"source": "independent generator"})
    return D.ActuatorRecord.split_off(rec, D.Nominal(kind="pi")).blocked


def true_diffusion(wander: dict) -> float:
    """The truth's wander diffusion (nm^2/s) over times short against its time constant."""
    s = wander["sigma"]
    return s**2 if wander["kind"] == "walk" else 2 * s**2 / wander["tau_s"]


def run(seed: int, truth: str, wander: str) -> dict:
    case = make_case("drift", "middle", seed, truth, wander=wander)
    still = make_case("drift", "middle", seed, truth, magnitude=0.0)  # same hysteresis and noise
    true_drift = case["d"] - still["d"]
    data = blocked(case["d"], case)
    nominal = data.fit_nominal()
    ho, tr = data.heldout, data.train
    rows = []
    for rounds in ROUNDS:
        t0 = time.perf_counter()
        fit = data._with_wander(nominal, rounds=rounds)
        err = fit.wander.level - true_drift
        err = err - err[tr].mean(0)
        rows.append(
            {
                "rounds": rounds,
                "heldout_gap_nm": fit.heldout_gap_nm,
                "bic": fit.bic,
                "diffusion_nm2_per_s": fit.wander.diffusion.tolist(),
                "drift_error_heldout_nm": np.sqrt(np.mean(err[ho] ** 2, 0)).tolist(),
                "seconds": time.perf_counter() - t0,
            }
        )
        print(
            f"  seed {seed}, {rounds:3d} rounds: gap {fit.heldout_gap_nm:.2f} nm, BIC {fit.bic:.0f}",
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
        "rounds": rows,
    }


def figure(results: list, path: Path) -> None:
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for k, r in enumerate(results):
        c = f"C{k}"
        n = [row["rounds"] for row in r["rounds"]]
        label = f"seed {r['seed']} ({r['wander']['kind']})"
        ax[0].plot(n, [row["heldout_gap_nm"] for row in r["rounds"]], "o-", color=c, label=label)
        ax[0].axhline(r["oracle_heldout_gap_nm"], color=c, ls=":", lw=1)
        q = [np.mean(row["diffusion_nm2_per_s"]) for row in r["rounds"]]
        ax[1].plot(n, q, "o-", color=c, label=label)
        ax[1].axhline(r["true_diffusion_nm2_per_s"], color=c, ls=":", lw=1)
    ax[0].set(xscale="log", xlabel="alternating rounds", ylabel="held-out gap on the blocks (nm)")
    ax[0].set_title("drift candidate's gap (dotted: nominal on record less true drift)", fontsize=9)
    ax[1].set(
        xscale="log",
        yscale="log",
        xlabel="alternating rounds",
        ylabel="wander diffusion, mean of axes (nm²/s)",
    )
    ax[1].set_title("fitted wander (dotted: the truth's)", fontsize=9)
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    results = [run(*c) for c in CASES]
    (OUT / "rounds.json").write_text(
        json.dumps({"cases": results, "units": {"gap": "nm", "diffusion": "nm^2/s"}}, indent=1)
    )
    figure(results, OUT / "rounds.png")
    for r in results:
        first, last = r["rounds"][0], r["rounds"][-1]
        print(
            f"seed {r['seed']}: gap {first['heldout_gap_nm']:.2f} nm ({first['rounds']} rounds) -> "
            f"{last['heldout_gap_nm']:.2f} nm ({last['rounds']}); oracle {r['oracle_heldout_gap_nm']:.2f} nm; "
            f"nominal {r['nominal_heldout_gap_nm']:.2f} nm"
        )


if __name__ == "__main__":
    main()
