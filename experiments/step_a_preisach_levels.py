"""How many Preisach levels the features of a lattice image hold: step A with a fixed Preisach model.

One 0° + 90° case of ``experiments/step_a_independent.py`` (the same draw), fitted by step A with
the model ladder off (``select: false``) and a Preisach plane of 4, 8 or 16 levels with the
effects the ladder keeps on that case with a Preisach class (``experiments/step_a_floor.py
--classes preisach``: coupling, feedback lag, creep, drift). Per plane: the held-out features
as ``jaxafm calibrate`` reports them, and the tip path against the generator's truth (rms after
the one rigid motion, px) over every pixel, inside the features' chords' reach on both stage
axes, and in the margins of each stage axis (pixels outside that axis' reach, inside the other's).

    python experiments/step_a_preisach_levels.py [--seed 100] [--levels 4 8 16]

writes experiments/results/step_a_independent/preisach_levels.json (a table of docs/step_a.md).
"""

from __future__ import annotations

import argparse
import json
import time

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import numpy as np
import step_a_independent as S

from jaxafm.jobs.calibrate import identification_metrics, identify_model

#: the effects step A's ladder keeps on case 100 with a Preisach class
EFFECTS = ["coupling", "feedback_lag", "creep", "drift"]


def scored(seed: int, levels: int) -> dict:
    """Step A with a fixed ``levels``-level plane on case ``seed``, scored (module docstring)."""
    spec = next(c for c in S.plan(20, 3) if c["seed"] == seed)
    case, scans, cfg = S.draw_and_read(spec, 64, "fine", model=S.PREISACH)
    model = cfg.models[0].model_copy(update={"levels": levels, "effects": EFFECTS})
    solver = cfg.solver.model_copy(update={"select": False})
    began = time.perf_counter()
    ident = identify_model(scans, model, solver, cfg.grating, log=lambda *_: None)
    seconds = time.perf_counter() - began
    pixel = scans[0].raster.pixel_size[0]
    e2, inside = S.path_errors_by_axis_reach(ident.model, scans, case)
    rms = lambda m: float(np.sqrt(np.mean(e2[m]))) / pixel
    return {
        "levels": levels,
        "held_out_px": identification_metrics(ident)["held_out_rms_nm"] / pixel,
        "all_px": rms(np.ones_like(e2, bool)),
        "inside_px": rms(inside[0] & inside[1]),
        "x_margins_px": rms(~inside[0] & inside[1]),
        "y_margins_px": rms(inside[0] & ~inside[1]),
        "plausible": ident.plausible,
        "seconds": seconds,
    }


def main() -> None:
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--seed", type=int, default=100)
    a.add_argument("--levels", type=int, nargs="+", default=[4, 8, 16])
    args = a.parse_args()
    rows = []
    for levels in args.levels:
        rows.append(scored(args.seed, levels))
        r = rows[-1]
        print(
            f"{levels} levels: held-out features {r['held_out_px']:.2f} px; tip path {r['all_px']:.2f} px "
            f"(inside {r['inside_px']:.2f}, x margins {r['x_margins_px']:.2f}, y margins "
            f"{r['y_margins_px']:.2f}); {r['seconds']:.0f} s",
            flush=True,
        )
    out = S.OUT / "preisach_levels.json"
    out.write_text(json.dumps({"seed": args.seed, "effects": EFFECTS, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
