"""Step A on 2-D lattices of pits and of pillars turned by 0 to 3 degrees on the stage.

For each lattice (the default simulated AFM, its scanner unknown to the fit) step A
identifies the scanner and the lattice's rotation together (``rotation_deg: fit``) from a
0 + 90 degree scan pair, holding out half the lattice sites (a checkerboard). Reported per case: the fitted
rotation against the true one (both measured from the direction the x piezo moves the
tip, the gauge the fit fixes: the stage angle less atan(coupling.yx)), the held-out
feature residual (nm) beside the floor the images set for that measure (the simulator's own
tip path in place of the model, ``step_a.held_out_floor``), the fitted tip path against the
simulator's (``step_a.tip_path_error``), the held-out local pitch spread raw and corrected, and
whether step A saved the fit (and why not).

    python experiments/step_a_lattices.py [--pixels 64] [--max-steps 40]
        [--out experiments/results/step_a_lattices]

Writes ``metrics.json`` and prints the table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from jaxafm.config import CalibrationLattice, CalibrationModel, CalibrationSolver, SimulatedCalibration
from jaxafm.identify import step_a
from jaxafm.jobs import calibrate

ROOT = Path(__file__).resolve().parents[1]
ROTATIONS_DEG = (0.0, 1.5, 3.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pixels", type=int, default=64)
    ap.add_argument("--max-steps", type=int, default=40)
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "step_a_lattices")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    spec = CalibrationModel(name="gpi", kind="gpi", operators=16, deadzones=3)
    # step A's default solver and image stages, on the configured model as it is (no ladder)
    solver = CalibrationSolver(max_steps=args.max_steps, select=False)
    rows = []
    for pits in (False, True):
        grating = CalibrationLattice(pitch_nm=1000, pits=pits, rotation_deg="fit")
        for rot in ROTATIONS_DEG:
            sim_spec = SimulatedCalibration(
                pixels=args.pixels, angles_deg=[0.0, 90.0], lattice_rotation_deg=rot
            )
            scans, sim = calibrate.calibration_scans(sim_spec, grating)
            kind = "pits" if pits else "pillars"
            print(f"{kind}, turned {rot:g} deg: identifying ...", flush=True)
            ident = calibrate.identify_model(scans, spec, solver, grating, log=lambda *_: None)
            m = calibrate.identification_metrics(ident) | step_a.parameters_vs_truth(sim, ident.model)
            row = {
                "lattice": kind,
                "rotation_deg": rot,
                "true_rotation_from_x_axis_deg": m["true_lattice_rotation_deg"],
                "fit_rotation_deg": m["lattice_rotation_deg"],
                "rotation_error_deg": m["lattice_rotation_deg"] - m["true_lattice_rotation_deg"],
                "held_out_rms_nm": m["held_out_rms_nm"],
                "held_out_floor_nm": step_a.held_out_floor(sim, scans),
                "tip_path_rms_nm": step_a.tip_path_error(sim, ident.model, scans).tolist(),
                "held_out_pitch_std_raw_pct": m["held_out_pitch_std_raw_pct"],
                "held_out_pitch_std_corrected_pct": m["held_out_pitch_std_corrected_pct"],
                "plausible": m["plausible"],
                "failures": m["failures"],
                "path_sd_rms_nm": m.get("path_sd_rms_nm"),
                "path_tolerance_nm": m.get("path_tolerance_nm"),
                "stages_accepted": m["stages_accepted"],
                "fit_s": m["fit_s"],
            }
            rows.append(row)
            print(
                "  "
                + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items())
            )
    (args.out / "metrics.json").write_text(json.dumps(rows, indent=1))
    head = (
        f"{'lattice':8s} {'turn':>5s} {'true':>7s} {'fit':>7s} {'error':>7s} {'held-out':>9s} {'floor':>9s}"
    )
    head += f" {'raw':>6s} {'corr.':>6s}"
    print("\n" + head + "\n" + "-" * len(head))
    for r in rows:
        print(
            f"{r['lattice']:8s} {r['rotation_deg']:5.1f} {r['true_rotation_from_x_axis_deg']:7.3f} "
            f"{r['fit_rotation_deg']:7.3f} {r['rotation_error_deg']:7.3f} {r['held_out_rms_nm']:7.2f}nm "
            f"{r['held_out_floor_nm']:7.2f}nm "
            f"{r['held_out_pitch_std_raw_pct']:5.2f}% "
            f"{r['held_out_pitch_std_corrected_pct']:5.2f}%"
        )
    print(
        "turn: the lattice's stage angle; true / fit: its angle from the x piezo's direction (deg); "
        "held-out: rms residual of the held-out features (a checkerboard of half the sites); "
        "floor: the same measure through the simulator's own tip path; "
        "raw / corr.: held-out local pitch spread, % of the pitch"
    )


if __name__ == "__main__":
    main()
