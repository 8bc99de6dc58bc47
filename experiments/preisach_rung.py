"""Where the diagnosis's Preisach rung leaves its held-out gap on the independent generator's
Preisach truths: the generator's noise, its relays' switching, or the rung itself.

The generator (tests/independent.py, no jaxafm code) samples its Preisach density with one relay
at a random point of each cell of a 100 x 100 grid, so its output jumps as each relay switches.
For each Preisach-truth control of the wandering check (``independent.wandering_cases``), the
diagnosis's Preisach rung (``ActuatorRecord.fit_shape("preisach", ...)``: the factorised density
of the default 20 levels, fitted on the first 60 %) is fitted to three versions of the record and
scored on its last 40 %:

- the record as the diagnosis gets it (the relays, then 2 nm of white noise);
- the record less the generator's noise (``independent.case_noise`` of the seed): the relays alone;
- the same scanner with its density continuous over the plane (``make_case(..., relays=None)``,
  no noise): what is left is the rung's own misfit of the generator's density.

Beside them, the report's noise floor estimated from each held-out output
(``jaxafm.diagnose.report.noise_floor_nm``) and the relays' switching roughness (the record less
noise, less the continuous output; rms on the held-out part). With ``--nodes``, the same for a
rung whose profile has each of those numbers of nodes (``jaxafm.diagnose.plant.PROFILE_NODES``,
5 in the diagnosis), each one's medians.

    python experiments/preisach_rung.py --nodes 5 7 9 13     # ~10 minutes on one core

Writes ``experiments/results/independent_check_wandering/preisach_rung.json``: per case at the
diagnosis's nodes, and the medians at every count. Units: nm.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import numpy as np
from independent import DRIVE, case_noise, make_case, wandering_cases

from jaxafm.diagnose import plant
from jaxafm.diagnose import record as D
from jaxafm.diagnose.report import noise_floor_nm
from jaxafm.instrument.records import Record

OUT = Path(__file__).resolve().parents[1] / "experiments" / "results" / "independent_check_wandering"


def rung_gap_nm(d: np.ndarray) -> tuple:
    """The Preisach rung fitted to outputs ``d`` (T, 2) nm of the generator's drive: its held-out
    gap (nm rms, both axes) and the held-out output's estimated noise floor (nm)."""
    t, u = DRIVE
    data = D.ActuatorRecord.split_off(Record(t=t, u=u, d=d, meta={}), D.Nominal(kind="preisach"))
    return data.fit_shape("preisach", None).heldout_gap_nm, noise_floor_nm(data.d[data.heldout])


def case_row(case: dict) -> dict:
    """One control's gaps and floors on its three versions (module docstring)."""
    seed = case["seed"]
    record = make_case(None, "control", seed, "preisach")["d"]
    noise = case_noise(record.shape, seed)
    relays = record - noise
    continuous = make_case(None, "control", seed, "preisach", relays=None)["d"] - noise
    row = {"seed": seed}
    for name, d in (("record", record), ("relays", relays), ("continuous", continuous)):
        row[f"{name}_gap_nm"], row[f"{name}_floor_nm"] = rung_gap_nm(d)
    held = D.ActuatorRecord.split_off(Record(t=DRIVE[0], u=DRIVE[1], d=record, meta={}), D.Nominal()).heldout
    row["roughness_nm"] = float(np.sqrt(np.mean((relays - continuous)[held] ** 2)))
    return row


def medians(rows: list) -> dict:
    """Every number's median over the cases ``rows``."""
    return {k: float(np.median([r[k] for r in rows])) for k in rows[0] if k != "seed"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, nargs="+", default=[plant.PROFILE_NODES], help="profile nodes")
    args = ap.parse_args()
    controls = [c for c in wandering_cases() if c["effect"] is None and c["truth_hysteresis"] == "preisach"]
    diagnosis_nodes, out = plant.PROFILE_NODES, {"nodes": plant.PROFILE_NODES, "by_nodes": {}}
    for nodes in args.nodes:
        plant.PROFILE_NODES = nodes
        rows = []
        for case in controls:
            rows.append(case_row(case))
            print(json.dumps({"nodes": nodes} | {k: round(v, 3) for k, v in rows[-1].items()}), flush=True)
        out["by_nodes"][str(nodes)] = medians(rows)
        if nodes == diagnosis_nodes:
            out |= {"cases": rows, "median": medians(rows)}
    plant.PROFILE_NODES = diagnosis_nodes
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "preisach_rung.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out["by_nodes"], indent=1))


if __name__ == "__main__":
    main()
