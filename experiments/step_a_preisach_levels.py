"""How many Preisach levels the features of a lattice image hold: step A with a fixed Preisach model.

One case of ``experiments/step_a_independent.py`` (the same draw; by default 100, a 0° + 90°
pair), fitted by step A with the model ladder off (``select: false``) and a Preisach plane of 4,
8 or 16 levels with the effects the ladder keeps on that case with a Preisach class
(``experiments/step_a_floor.py --classes preisach``; on 100 coupling, feedback lag, creep,
drift, the default; on the speed series 111 coupling, rate dependence, creep). Per plane: the held-out features
as ``jaxafm calibrate`` reports them, and the tip path against the generator's truth (rms after
the one rigid motion, px) over every pixel, inside the features' chords' reach on both stage
axes, and in the margins of each stage axis (pixels outside that axis' reach, inside the other's);
beside it, inside the reach and outside it, the path's own standard deviation as the fit predicts
it from its training chords (:func:`jaxafm.identify.identifiability.path_sd`, rms over the
pixels): whether the model knows where its path is uncertain.

Each run is ``LEVELS`` or ``LEVELS:SPREAD``: the plane's levels and the spread of step A's
smoothness prior on its density (:data:`jaxafm.identify.stages.DENSITY_CURVATURE`, mean relay
weights; ``none`` fits without the prior), by default step A's own.

    python experiments/step_a_preisach_levels.py [--seed 100] [--runs 4 8 16 16:0.05 16:none]
    python experiments/step_a_preisach_levels.py --seed 111 --runs 4 8 16 --effects coupling rate_dependence creep

writes experiments/results/step_a_independent/preisach_levels_SEED.json (tables of docs/step_a.md).
"""

from __future__ import annotations

import argparse
import json
import time

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import jax
import numpy as np
import step_a_independent as S

import jaxafm.identify.stages as stages
from jaxafm.identify.fit import clear_caches
from jaxafm.identify.identifiability import path_sd
from jaxafm.jobs.calibrate import identification_metrics, identify_model

#: the effects step A's ladder keeps on case 100 with a Preisach class
EFFECTS = ["coupling", "feedback_lag", "creep", "drift"]


def scored(
    seed: int, levels: int, spread: float | None = stages.DENSITY_CURVATURE, effects: list = EFFECTS
) -> dict:
    """Step A with a fixed ``levels``-level plane and ``effects`` on case ``seed`` and the
    density prior's ``spread`` (None: no prior), scored (module docstring)."""
    stages.DENSITY_CURVATURE = np.inf if spread is None else spread
    jax.clear_caches()  # the spread is a constant of the compiled residuals
    clear_caches()
    spec = next(c for c in S.plan(20, 3) if c["seed"] == seed)
    case, scans, cfg = S.draw_and_read(spec, 64, "fine", model=S.PREISACH)
    model = cfg.models[0].model_copy(update={"levels": levels, "effects": list(effects)})
    solver = cfg.solver.model_copy(update={"select": False})
    began = time.perf_counter()
    ident = identify_model(scans, model, solver, cfg.grating, log=lambda *_: None)
    seconds = time.perf_counter() - began
    pixel = scans[0].raster.pixel_size[0]
    e2, inside = S.path_errors_by_axis_reach(ident.model, scans, case)
    rms = lambda m: float(np.sqrt(np.mean(e2[m]))) / pixel
    sd2 = np.concatenate([s.ravel() for s in path_sd(ident.model, scans, ident.chords)]) ** 2
    both = inside[0] & inside[1]
    return {
        "levels": levels,
        "prior_spread": spread,
        "held_out_px": identification_metrics(ident)["held_out_rms_nm"] / pixel,
        "all_px": rms(np.ones_like(e2, bool)),
        "inside_px": rms(both),
        "x_margins_px": rms(~inside[0] & inside[1]),
        "y_margins_px": rms(inside[0] & ~inside[1]),
        "sd_inside_px": float(np.sqrt(np.mean(sd2[both]))) / pixel,
        "sd_outside_px": float(np.sqrt(np.mean(sd2[~both]))) / pixel,
        "plausible": ident.plausible,
        "seconds": seconds,
    }


def main() -> None:
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--seed", type=int, default=100)
    a.add_argument("--runs", nargs="+", default=["4", "8", "16", "16:0.05", "16:none"])
    a.add_argument("--effects", nargs="+", default=EFFECTS, help="the plane's effects (default: case 100's)")
    args = a.parse_args()
    rows = []
    for run in args.runs:
        levels, _, spread = run.partition(":")
        spread = stages.DENSITY_CURVATURE if not spread else None if spread == "none" else float(spread)
        rows.append(scored(args.seed, int(levels), spread, args.effects))
        r = rows[-1]
        print(
            f"{levels} levels, prior spread {spread}: held-out features {r['held_out_px']:.2f} px; "
            f"tip path {r['all_px']:.2f} px "
            f"(inside {r['inside_px']:.2f}, x margins {r['x_margins_px']:.2f}, y margins "
            f"{r['y_margins_px']:.2f}); its predicted sd {r['sd_inside_px']:.2f} inside, "
            f"{r['sd_outside_px']:.2f} outside; {r['seconds']:.0f} s",
            flush=True,
        )
    out = S.OUT / f"preisach_levels_{args.seed}.json"
    out.write_text(json.dumps({"seed": args.seed, "effects": args.effects, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
