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
pixels): whether the model knows where its path is uncertain. And what a ladder could score the
plane by from its training features alone (:func:`scores`): the information criterion it uses,
and the features' centres with each of them, or half of them, left out of the fit. A plane step A
refuses (its error, e.g. scans it cannot align through it) is recorded with the reason.

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
from jaxafm.identify.held_out import fitted_parameters, held_out_errors
from jaxafm.identify.identifiability import path_sd
from jaxafm.identify.selection import aicc
from jaxafm.identify.stages import chord_linearisation, feature_groups, feature_keys
from jaxafm.identify.uncertainty import leave_group_out
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
    } | scores(ident, scans)


def scores(ident, scans) -> dict:
    """What the ladder could choose the plane by, from its training chords alone: the
    information criterion it uses (:func:`~jaxafm.identify.selection.aicc`), and the rms (px)
    of the training chords' residuals and of their features' centres (each feature's chords'
    mean residual along the lines and across them), as fitted and with each feature left out of
    the fit and with each half of them left out (:func:`left_out_residuals`)."""
    chords, model = ident.chords, ident.model.as_float64()
    train = [[_unpadded(c) for c in images] for images in chords]
    k = fitted_parameters(model, scans, chords)
    pitch_px = min(scans[0].pitch) / scans[0].raster.pixel_size[0]
    fitted, left = left_out_residuals(model, scans, chords)
    half = left_out_residuals(model, scans, chords, halves=True)[1]
    groups = feature_groups(chords)
    along = np.concatenate([np.asarray(c.along) for images in chords for c in images])[groups >= 0]
    _, centre = np.unique(np.stack([groups[groups >= 0], along], -1), axis=0, return_inverse=True)
    rms = lambda e: float(np.sqrt(np.mean(e**2))) * pitch_px
    centres = lambda e: rms(np.bincount(centre.ravel(), e) / np.bincount(centre.ravel()))
    return {
        "aicc": aicc(held_out_errors(model, scans, train), k)[0],
        "fitted_parameters": k,
        "chords_fitted_px": rms(fitted),
        "chords_left_out_px": rms(left),
        "centres_fitted_px": centres(fitted),
        "centres_left_out_px": centres(left),
        "centres_half_out_px": centres(half),
    }


def left_out_residuals(model, scans: tuple, chords: tuple, halves: bool = False) -> tuple:
    """``(fitted, left_out)``: each training chord's residual (pitches, (n,), the padding
    dropped) as fitted, and as a fit without its feature would leave it: leave-one-feature-out
    cross-validation of the chord stage's data ``chords``, in one step from the fit on all of
    them. For least squares linearised at the fit, with the precision ``A = J^T J + P``
    (:func:`~jaxafm.identify.held_out.fitted_parameters`' weak prior and the density's
    smoothness prior ``P``), leaving out the rows ``B`` of one feature turns their residuals
    ``r_B`` into ``(I - J_B A^-1 J_B^T)^-1 r_B`` (the block form of the PRESS identity, Allen
    1974; :func:`~jaxafm.identify.uncertainty.leave_group_out`). A feature's chords go out
    together: they share its shape's irregularity. With ``halves``, the features go out in two
    halves instead, those of even and of odd first lattice index (of the training checkerboard,
    two square lattices of twice the pitch, each between the other's sites)."""
    r, J, smooth = chord_linearisation(model, scans, chords)
    groups = feature_groups(chords)
    real = groups >= 0
    if halves:
        groups = np.where(real, np.nan_to_num(feature_keys(chords)[:, 0]) % 2, -1)
    r, J, groups = r[real], J[real], groups[real]
    weak = np.mean(r**2) * np.eye(J.shape[1])
    out = np.empty_like(r)
    for g, e in leave_group_out(J, r, groups, smooth + weak).items():
        out[groups == g] = e
    return r, out


def _unpadded(c) -> tuple:
    """One image's padded chords (:class:`~jaxafm.identify.stages.PaddedChords`) as
    ``(ends, ij, along)`` without the padding."""
    real = np.asarray(c.weight) > 0
    return np.asarray(c.ends)[real], np.asarray(c.ij)[real], np.asarray(c.along)[real]


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
        try:
            rows.append(scored(args.seed, int(levels), spread, args.effects))
        except ValueError as refused:  # step A's own refusal (e.g. scans it cannot align)
            rows.append({"levels": int(levels), "prior_spread": spread, "refused": str(refused)})
            print(f"{levels} levels, prior spread {spread}: refused: {refused}", flush=True)
            continue
        r = rows[-1]
        print(
            f"{levels} levels, prior spread {spread}: held-out features {r['held_out_px']:.2f} px; "
            f"tip path {r['all_px']:.2f} px "
            f"(inside {r['inside_px']:.2f}, x margins {r['x_margins_px']:.2f}, y margins "
            f"{r['y_margins_px']:.2f}); its predicted sd {r['sd_inside_px']:.2f} inside, "
            f"{r['sd_outside_px']:.2f} outside; AICc {r['aicc']:.1f} ({r['fitted_parameters']:.1f} parameters); "
            f"training chords {r['chords_fitted_px']:.3f} px fitted, {r['chords_left_out_px']:.3f} px "
            f"with their feature left out; feature centres {r['centres_fitted_px']:.3f} px fitted, "
            f"{r['centres_left_out_px']:.3f} px left out, {r['centres_half_out_px']:.3f} px a half left out; "
            f"{r['seconds']:.0f} s",
            flush=True,
        )
    out = S.OUT / f"preisach_levels_{args.seed}.json"
    out.write_text(json.dumps({"seed": args.seed, "effects": args.effects, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
