"""How far a fitted scanner's small loops are from the true scanner's, axis by axis.

After the initialisation cycle, both scanners (drift and noise off) go to 0 V and sweep a small
triangle of +-a V; the travel of the last rising sweep is compared. Step A's calibration raster
reverses x every line but moves y one way only, so y's small loops are not in its data.

    python experiments/minor_loops.py [--model experiments/results/paper/model_scanner.json]
        [--out experiments/results/minor_loops.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxafm
from jaxafm.model.io import load_model

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--model", type=Path, default=ROOT / "experiments" / "results" / "paper" / "model_scanner.json"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "minor_loops.json")
    args = ap.parse_args()
    true = jaxafm.default_scanner().without("drift", "noise")
    fit = load_model(args.model)
    cycle = jnp.array([[-10.0, -10.0], [10.0, 10.0]])
    rows = []
    print(
        f"{'sweep [V]':>10s} {'true x':>9s} {'fit x':>9s} {'ratio x':>8s} {'true y':>9s} {'fit y':>9s} {'ratio y':>8s}"
    )
    for a in (0.1, 0.2, 0.4, 1.0, 3.0):
        u1 = np.concatenate([np.linspace(10, 0, 200), np.linspace(0, -a, 50), np.linspace(-a, a, 100)])
        u, t = jnp.asarray(np.stack([u1, u1], -1)), 1.0 + 1e-3 * jnp.arange(len(u1))
        travel = [
            np.asarray(m(u, t, history=cycle))[-1] - np.asarray(m(u, t, history=cycle))[249]
            for m in (true, fit)
        ]
        ratio = travel[1] / travel[0]
        rows.append(
            {
                "sweep_v": 2 * a,
                "true_nm": travel[0].tolist(),
                "fit_nm": travel[1].tolist(),
                "ratio": ratio.tolist(),
            }
        )
        print(
            f"{2 * a:10.1f} {travel[0][0]:8.1f}nm {travel[1][0]:8.1f}nm {ratio[0]:8.3f} "
            f"{travel[0][1]:8.1f}nm {travel[1][1]:8.1f}nm {ratio[1]:8.3f}"
        )
    args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
