"""Step A from one scan angle or two: does a 0 + 90 degree pair identify y's small loops?

The calibration raster reverses its fast axis every line but moves its slow axis one way
only, so from a 0-degree image alone y's small loops are not in the data. A second image at
90 degrees makes y the fast axis. For each set of scan angles this identifies the scanner
(the default simulated AFM, the configured GPI model, the lattice mounted square) and
measures against the true scanner (drift and noise off):

- minor loops: after the initialisation cycle both scanners go to 0 V and sweep triangles of
  +-a V (a = 0.1 ... 3); the travel of the last rising sweep, fitted / true, per axis;
- step A's linearity: the lattice re-imaged (85 % of the area) with the model's analytic
  inverse at scan angles 0 and 90 degrees, max |error| along each raster's fast axis
  (% of the width): x at 0 degrees, y at 90;
- the fitted tip path against the simulator's over the calibration scans, after the rigid
  motion no image sees (``step_a.tip_path_error``), and the held-out residual beside its floor,
  the same measure through the simulator's own tip path (``step_a.held_out_floor``).

    python experiments/step_a_angles.py [--pixels 128] [--max-steps 100]
        [--out experiments/results/step_a_angles]

Writes ``metrics.json`` and ``step_a_angles.png``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jaxafm.config import CalibrationLattice, CalibrationModel, CalibrationSolver, SimulatedCalibration
from jaxafm.identify import step_a
from jaxafm.instrument.afm import Raster
from jaxafm.jobs import calibrate

ROOT = Path(__file__).resolve().parents[1]
AMPLITUDES_V = (0.1, 0.2, 0.5, 1.0, 3.0)
SETS = {"0 deg": [0.0], "0 + 90 deg": [0.0, 90.0]}


def minor_loop_ratios(true, fit, u_max: float) -> np.ndarray:
    """(amplitudes, 2): the fitted scanner's travel over the last rising sweep of a +-a V
    triangle, after the cycle and a move to 0 V, over the true scanner's, per axis."""
    cycle = jnp.array([[-u_max, -u_max], [u_max, u_max]])
    out = []
    for a in AMPLITUDES_V:
        u1 = np.concatenate([np.linspace(u_max, 0, 200), np.linspace(0, -a, 50), np.linspace(-a, a, 100)])
        u, t = jnp.asarray(np.stack([u1, u1], -1)), 1.0 + 1e-3 * jnp.arange(len(u1))
        travel = [np.asarray(m(u, t, history=cycle)) for m in (true, fit)]
        out.append((travel[1][-1] - travel[1][249]) / (travel[0][-1] - travel[0][249]))
    return np.asarray(out)


def linearity(sim, scans, model, angle: float) -> dict:
    """The model's analytic inverse re-imaging 85 % of the calibration area at ``angle``."""
    r = scans[0].raster
    work = Raster(0.85 * r.size[0], r.pixels, r.lines, line_rate=r.line_rate, overscan=0.05, angle_deg=angle)
    volts = step_a.model_compensator(model, scans, sim, "analytic")
    bare, _ = step_a.compensated_scan(sim, work, None)
    try:
        image, _ = step_a.compensated_scan(sim, work, volts)
    except ValueError as e:  # the inverse needs drives beyond those the model was fitted over
        return {
            "compensated_pct": float("nan"),
            "uncompensated_pct": _worst(step_a.position_errors(bare, work)),
            "refused": str(e),
        }
    return {
        "compensated_pct": _worst(step_a.position_errors(image, work)),
        "uncompensated_pct": _worst(step_a.position_errors(bare, work)),
    }


def _worst(errors: dict) -> float:
    return max(errors["linearity_error_trace_pct"], errors["linearity_error_retrace_pct"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pixels", type=int, default=128)
    ap.add_argument("--max-steps", type=int, default=100)
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "step_a_angles")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    grating = CalibrationLattice(pitch_nm=1000, rotation_deg=0.0)
    spec = CalibrationModel(name="gpi", kind="gpi", operators=16, deadzones=3)
    # step A's default solver and image stages, on the configured model as it is (no ladder)
    solver = CalibrationSolver(max_steps=args.max_steps, select=False)
    results = {}
    for name, angles in SETS.items():
        scans, sim = calibrate.calibration_scans(
            SimulatedCalibration(pixels=args.pixels, angles_deg=angles), grating
        )
        print(f"{name}: identifying from {len(scans)} scan(s) of {args.pixels}^2 px ...", flush=True)
        start = time.perf_counter()
        ident = calibrate.identify_model(scans, spec, solver, grating)
        fit_s = time.perf_counter() - start
        true = sim.afm.scanner.without("drift", "noise")
        ratios = minor_loop_ratios(true, ident.model.scanner, sim.afm.u_max)
        results[name] = {
            "fit_s": fit_s,
            "minor_loop_ratio_x": ratios[:, 0].tolist(),
            "minor_loop_ratio_y": ratios[:, 1].tolist(),
            "minor_loop_max_error_pct": (100 * np.abs(ratios - 1).max(axis=0)).tolist(),
            "linearity_x_at_0deg": linearity(sim, scans, ident.model, 0.0),
            "linearity_y_at_90deg": linearity(sim, scans, ident.model, 90.0),
            "held_out_floor_nm": step_a.held_out_floor(sim, scans),
            "tip_path_rms_nm": step_a.tip_path_error(sim, ident.model, scans).tolist(),
        } | calibrate.identification_metrics(ident)
        r = results[name]
        print(
            f"  {fit_s:.0f} s; minor loops max |fit/true - 1|: x {r['minor_loop_max_error_pct'][0]:.2f} %, "
            f"y {r['minor_loop_max_error_pct'][1]:.2f} %; "
            f"linearity x {r['linearity_x_at_0deg']['compensated_pct']:.3f} %"
            f" (uncompensated {r['linearity_x_at_0deg']['uncompensated_pct']:.2f} %), y "
            f"{r['linearity_y_at_90deg']['compensated_pct']:.3f} % "
            f"(uncompensated {r['linearity_y_at_90deg']['uncompensated_pct']:.2f} %); held-out "
            f"{r.get('held_out_rms_nm', float('nan')):.2f} nm (the true tip path's {r['held_out_floor_nm']:.2f} nm); "
            f"tip path off the truth x {r['tip_path_rms_nm'][0]:.2f}, y {r['tip_path_rms_nm'][1]:.2f} nm rms; "
            f"plausible {r['plausible']}",
            flush=True,
        )
    (args.out / "metrics.json").write_text(json.dumps(results, indent=1))
    print(f"\n{'amplitude':>10s}" + "".join(f" {n + ' ' + a:>16s}" for n in SETS for a in ("x", "y")))
    for i, a in enumerate(AMPLITUDES_V):
        cells = [results[n][f"minor_loop_ratio_{ax}"][i] for n in SETS for ax in ("x", "y")]
        print(f"{'+-' + format(a, 'g') + ' V':>10s}" + "".join(f" {c:16.4f}" for c in cells))
    fig, ax = plt.subplots(figsize=(6.5, 4.2), constrained_layout=True)
    for (name, r), c in zip(results.items(), ("C3", "C0")):
        for axis, style in (("x", "--"), ("y", "-")):
            ax.plot(
                AMPLITUDES_V,
                r[f"minor_loop_ratio_{axis}"],
                style,
                color=c,
                marker="o",
                label=f"{name}: {axis}",
            )
    ax.axhspan(0.99, 1.01, color="0.9", label="within 1 %")
    ax.set(
        xscale="log",
        xlabel="triangle amplitude a (V): sweeps of +-a after the initialisation cycle",
        ylabel="fitted / true travel",
        title="Step A's small loops, identified from one scan angle or two",
    )
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.savefig(args.out / "step_a_angles.png", dpi=120)


if __name__ == "__main__":
    main()
