"""Step A's model class on the real lattices: the Preisach plane against the generalised PI.

The three shipped Nanosurf lattices (jaxafm/data/real/README.md), each identified as its
``configs/calibrate_nanosurf_NAME.yaml`` says but with a Preisach plane of up to 16 levels as
the richest model (``kind: preisach``; its default effects, the generalised PI's less
``asymmetry``), through the ladder as ``jaxafm calibrate`` climbs it. Beside each, the
generalised PI's committed run of the same configuration (``experiments/results/
calibrate_nanosurf_NAME/metrics.json``): the held-out features' residual (nm) raw and corrected,
their local pitch spread (%) raw and corrected, the largest error of a distance between them
(%), and the model the ladder kept. No truth is known here: the held-out features are the
check.

    python experiments/step_a_real_classes.py [--lattices square_pits round_pits round_pillars]

writes experiments/results/step_a_real_classes/metrics.json (a table of docs/step_a.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

from jaxafm.config import CalibrateConfig
from jaxafm.config.common import load_config
from jaxafm.identify.fit import clear_caches
from jaxafm.jobs.calibrate import identification_metrics, identify_model, read_calibration

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "step_a_real_classes"
LATTICES = ("square_pits", "round_pits", "round_pillars")
#: what every real-lattice table keeps of an identification's model (``identification_metrics``' keys)
MODEL_KEPT = ("model_kind", "model_operators", "model_effects", "plausible", "fit_s")
#: what the table keeps of each identification
KEPT = (
    "held_out_rms_nm",
    "held_out_raw_rms_nm",
    "held_out_pitch_std_raw_pct",
    "held_out_pitch_std_corrected_pct",
    "held_out_distance_error_max_corrected_pct",
) + MODEL_KEPT
#: the richest model of the Preisach rows: a plane of up to 16 levels, its default effects
PREISACH = {"name": "preisach", "kind": "preisach", "levels": 16}


def identified(
    lattice: str,
    kept: tuple,
    model: dict | None = None,
    solver: dict | None = None,
    grating: dict | None = None,
    more=None,
) -> dict:
    """The lattice's configuration identified as ``jaxafm calibrate`` does (measured images), its
    first model updated with ``model``, its solver with ``solver`` and its grating with
    ``grating``: the ``kept`` metrics, and what ``more(ident, scans) -> dict`` adds."""
    path = ROOT / "configs" / f"calibrate_nanosurf_{lattice}.yaml"
    cfg = load_config(path, CalibrateConfig)
    spec = cfg.models[0].model_validate(model) if model else cfg.models[0]
    settings = cfg.solver.model_copy(update=solver or {})
    lattice_spec = cfg.grating.model_copy(update=grating or {})
    jax.clear_caches()
    clear_caches()
    scans = read_calibration(cfg.data, lattice_spec, path, log=lambda *_: None)
    ident = identify_model(scans, spec, settings, lattice_spec, log=print, measured=True)
    m = identification_metrics(ident)
    return {k: m[k] for k in kept} | (more(ident, scans) if more else {})


def committed(lattice: str, kept: tuple = KEPT) -> dict:
    """The generalised PI's committed run of the lattice's configuration: its ``kept`` metrics."""
    m = json.loads(
        (ROOT / "experiments" / "results" / f"calibrate_nanosurf_{lattice}" / "metrics.json").read_text()
    )
    return {k: m[f"gpi_{k}"] for k in kept}


def run_lattices(out: Path, description: str, row, line) -> None:
    """The command line of a real-lattice study (``--lattices``, default all three): for each
    lattice its ``row(lattice)`` (a dict of named results) printed, one ``line(lattice, name,
    result)`` each, and written into ``out``/metrics.json beside the lattices already there,
    after each."""
    a = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--lattices", nargs="+", default=list(LATTICES), choices=LATTICES)
    args = a.parse_args()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "metrics.json"
    rows = json.loads(path.read_text()) if path.exists() else {}
    for lattice in args.lattices:
        rows[lattice] = row(lattice)
        for name, r in rows[lattice].items():
            print(line(lattice, name, r), flush=True)
        path.write_text(json.dumps(rows, indent=1))


def _line(lattice: str, name: str, r: dict) -> str:
    return (
        f"{lattice} {name}: held-out features {r['held_out_raw_rms_nm']:.1f} nm raw -> "
        f"{r['held_out_rms_nm']:.1f} nm; pitch spread {r['held_out_pitch_std_raw_pct']:.2f} % -> "
        f"{r['held_out_pitch_std_corrected_pct']:.2f} %; distances "
        f"{r['held_out_distance_error_max_corrected_pct']:.2f} % at most; "
        f"kept {r['model_kind']} {r['model_operators']} + {', '.join(r['model_effects'])}"
    )


def main() -> None:
    run_lattices(
        OUT,
        __doc__,
        lambda lattice: {"gpi": committed(lattice), "preisach": identified(lattice, KEPT, model=PREISACH)},
        _line,
    )


if __name__ == "__main__":
    main()
