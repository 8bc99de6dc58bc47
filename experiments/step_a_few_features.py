"""Step A as a new user would run it on a small real lattice: a 3 x 3 pit lattice at four line
rates, trace and retrace TIFF files, a config that gives only the files and the lattice.

The images come from the independent generator (tests/independent_lattice.py, NumPy and SciPy,
sharing no code with jaxafm): a Preisach scanner with drive lag, creep, coupling, bow and drift;
square pits of a 10 um pitch in a 30 um image (117 nm a pixel at 256 px) with sloped walls under
a broadened tip; a plane, a bow, line offsets, spikes, clipped pixels and noise. Each image is
written as float32 TIFF (heights in nm) with a ``data`` section a user would write for it; the
configuration is that section and the lattice's pitch, nothing else, so every solver setting is
``jaxafm calibrate``'s default for measured images. Step A runs as ``jaxafm calibrate`` runs it
(reading, identification, plausibility checks); the result is scored against the generator's
truth: the tip path at every pixel of every scan after the one rigid motion no image can see,
inside and outside the features' reach, and per axis.

    python experiments/step_a_few_features.py [--seed 7] [--pixels 256] [--rates 0.5 1 2 4]
    python experiments/step_a_few_features.py --blur-px 2 1   # with the simulated AFM's image stages
    python experiments/step_a_few_features.py --known y --sd-pct 2   # the y gain stated, as a user may know it
    python experiments/step_a_few_features.py --known y --lag        # and the model's rate dependence too
    python experiments/step_a_few_features.py --known y --model preisach  # step A's Preisach class
    python experiments/step_a_few_features.py --known y --chord-lengths   # the chords' lengths fitted too

With ``--known`` the config also states the generator's true gain of those axes (``models[].known``,
as step A's quantities define a gain: the ascending branch's mean slope over the drive the scans
cover, computed from the generator's own relays) with an sd of ``--sd-pct`` % of it.

writes experiments/results/step_a_few_features/seed<seed>[_blur..][_known_..][_lag][_preisach][_lengths].json
(with its log) and the fitted scanner beside it (``..._model.json``, :func:`jaxafm.model.io.save_model`).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import independent_lattice as G
import numpy as np
import step_a_independent as S

from jaxafm.config import CalibrateConfig
from jaxafm.config.calibrate import CALIBRATION_EFFECTS
from jaxafm.identify.calibration_scan import drive_range
from jaxafm.identify.identifiability import path_sd
from jaxafm.jobs.calibrate import identification_metrics, identify_model, read_calibration
from jaxafm.model.io import save_model

OUT = Path(__file__).parent / "results" / "step_a_few_features"


def user_config(
    given: dict,
    blur_px: list | None = None,
    known: dict | None = None,
    lag: bool = False,
    kind: str = "gpi",
    lengths: bool = False,
) -> CalibrateConfig:
    """What a user writes for the files: the ``data`` section and the lattice's pitch and kind
    (and ``solver.blur_px`` and a model's ``known`` quantities when given; with ``lag``, the
    model's default effects with ``rate_dependence`` in place of ``feedback_lag``: at one angle
    step A fits only one of the two, the edges showing their sum; ``kind``: step A's model class,
    the Preisach class as step_a_independent.py fits it; ``lengths``: ``solver.chord_lengths``)."""
    solver = ({} if blur_px is None else {"blur_px": blur_px}) | ({"chord_lengths": True} if lengths else {})
    grating = {k: given["grating"][k] for k in ("pitch_nm", "pits")}
    model = (S.PREISACH if kind == "preisach" else {"name": "gpi"}) | ({"known": known} if known else {})
    lagged = [e for e in CALIBRATION_EFFECTS if e != "feedback_lag"] + ["rate_dependence"]
    if kind == "preisach":  # a Preisach plane has no dead zones
        lagged.remove("asymmetry")
    models = [model | ({"effects": lagged} if lag else {})]
    return CalibrateConfig(data=given["data"], grating=grating, solver=solver, models=models, compensate=None)


def true_gains(case, scans) -> dict:
    """The generator's gain of each axis (nm/V) as step A's quantities define it
    (:func:`jaxafm.identify.quantities.quantities`): the ascending branch's mean slope over the
    drive range the scans cover (:func:`~jaxafm.identify.calibration_scan.drive_range`), after a
    sweep down over it; from the generator's own axis, ``p = k u + S sum w R``."""
    drive = drive_range(scans)
    out = {}
    for k, a in enumerate("xy"):
        axis = case["scanner"].axes[k]
        lo, hi = drive[k]
        u = np.concatenate(
            [np.linspace(0, hi, 201), np.linspace(hi, lo, 401)[1:], np.linspace(lo, hi, 401)[1:]]
        )
        p = axis.reversible_nm_per_v * u + axis.hysteretic_nm * G.preisach(u, axis.relays)
        out[f"{a}_gain_nm_per_v"] = float((p[-1] - p[600]) / (hi - lo))
    return out


def axis_errors_px(model, scans, case) -> list:
    """rms (px) of the tip path's error along x and along y over every pixel of every scan, after
    the rigid motion (:func:`step_a_independent._rigid`)."""
    fitted, true, _ = S._paths(model, scans, case)
    e = S._rigid(fitted, true)[0] / scans[0].raster.pixel_size[0]
    return [float(v) for v in np.sqrt(np.mean(e**2, axis=0))]


def error_breakdown(model, scans, case) -> dict:
    """Where the tip path's error lies (px, after the one rigid motion of
    :func:`axis_errors_px`): per scan (its line rate) and direction, the rms and the mean error
    along x and y; the rms along x in eight bands of the nominal x position and of the nominal y
    position, along y in those of y, and the mean along x in those of y (the outer bands the
    image's margins); and each scan's rms after its own rigid motion (small where each scan's
    path is right but the scans sit apart)."""
    fitted, true, nominal = S._paths(model, scans, case)
    e = S._rigid(fitted, true)[0] / scans[0].raster.pixel_size[0]
    sizes = [
        np.asarray(c.truth[f"tip_{d}_nm"])[..., 0].size for c in case["scans"] for d in ("trace", "retrace")
    ]
    parts = np.split(np.arange(len(e)), np.cumsum(sizes)[:-1])  # trace, retrace of each scan in turn
    rows = []
    for k, idx in enumerate(parts):
        scan = scans[k // 2]
        spread, mean = np.sqrt(np.mean(e[idx] ** 2, axis=0)), np.mean(e[idx], axis=0)
        rows.append(
            {
                "line_rate_hz": scan.raster.line_rate,
                "direction": ("trace", "retrace")[k % 2],
                "rms_xy_px": [float(v) for v in spread],
                "mean_xy_px": [float(v) for v in mean],
            }
        )
    bands = [np.array_split(np.argsort(nominal[:, k], kind="stable"), 8) for k in (0, 1)]
    rms = lambda b, k: [float(np.sqrt(np.mean(e[i, k] ** 2))) for i in b]
    return {
        "error_by_scan": rows,
        "x_error_by_x_band_px": rms(bands[0], 0),
        "x_error_by_y_band_px": rms(bands[1], 0),
        "y_error_by_y_band_px": rms(bands[1], 1),
        "mean_x_error_by_y_band_px": [float(np.mean(e[i, 0])) for i in bands[1]],
        "tip_path_per_scan_own_rigid_px": S._path_error_per_scan(model, scans, case),
    }


def true_loops_nm(case) -> list:
    """Per scan, how far (nm) the generator's retrace lies behind its trace along the fast axis
    (x, at 0 degrees) in the middle column, on average over the lines: the truth of step A's
    ``loop_scan<k>_nm``."""
    out = []
    for s in case["scans"]:
        trace, retrace = (np.asarray(s.truth[f"tip_{d}_nm"]) for d in ("trace", "retrace"))
        mid = trace.shape[1] // 2
        out.append(float(np.mean(retrace[:, mid, 0] - trace[:, mid, 0])))
    return out


def predicted_sd_by_reach(ident, scans, case) -> dict:
    """The tip path's standard deviation as the fit predicts it from its parameters' covariance
    (:func:`~jaxafm.identify.identifiability.path_sd`), rms (px) over the pixels inside the
    features' reach and outside it (the pixels in :func:`step_a_independent._paths`' order)."""
    sd = np.concatenate([v.reshape(-1) for v in path_sd(ident.model, scans, ident.chords)])
    within = np.all(S._inside_reach(scans, S._paths(ident.model, scans, case)[2]), axis=0)
    rms = lambda m: float(np.sqrt(np.mean(sd[m] ** 2))) / scans[0].raster.pixel_size[0] if m.any() else None
    return {"path_sd_inside_reach_px": rms(within), "path_sd_outside_reach_px": rms(~within)}


def _size(spec) -> str:
    """A kept model's size as its class counts it: plays, or a Preisach plane's levels."""
    return f"{spec.levels} levels" if spec.kind == "preisach" else f"{spec.operators} plays"


def run(
    seed: int,
    pixels: int,
    rates: tuple,
    blur_px: list | None = None,
    known: tuple = (),
    sd_pct: float = 2.0,
    lag: bool = False,
    kind: str = "gpi",
    lengths: bool = False,
    log=print,
) -> tuple:
    """Draw, write and identify the case, the true gains of the ``known`` axes stated with an sd
    of ``sd_pct`` % (:func:`true_gains`), with ``lag`` the model's rate dependence too, with a
    model of class ``kind``, with ``lengths`` the chords' lengths fitted too; score it: the
    scores and the fitted scanner."""
    case = G.draw_case(
        seed,
        "coarse",
        feature="square_pits",
        line_rates_hz=rates,
        angles_deg=(0.0,),
        pixels=pixels,
        few_features=True,
    )
    with tempfile.TemporaryDirectory() as folder:
        files = G.write_case(case, folder, fmt="tiff")
        given = json.loads(Path(files["data"]).read_text())
        plain = user_config(given)
        scans = read_calibration(plain.data, plain.grating, Path(folder) / "c.yaml", log=lambda *_: None)
        gains = true_gains(case, scans)
        stated = {
            f"{a}_gain_nm_per_v": [gains[f"{a}_gain_nm_per_v"], sd_pct / 100 * gains[f"{a}_gain_nm_per_v"]]
            for a in known
        }
        cfg = user_config(given, blur_px, stated, lag, kind, lengths)
    began = time.perf_counter()
    ident = identify_model(scans, cfg.models[0], cfg.solver, cfg.grating, log, measured=True)
    out = {
        "seed": seed,
        "rates_hz": list(rates),
        "pixels": pixels,
        "pixel_nm": scans[0].raster.pixel_size[0],
        "seconds": time.perf_counter() - began,
        "image_blurs_px": list(cfg.solver.image_blurs(True)),
        "true_gains_nm_per_v": gains,
        "known": stated,
        "kept": f"{ident.spec.kind} {_size(ident.spec)} + " + ", ".join(ident.spec.effects),
        "plausible": ident.plausible,
        "failures": list(ident.failures),
        "metrics": identification_metrics(ident),
        "tip_path_rms_px": S.path_error(ident.model, scans, case),
        "tip_path_xy_rms_px": axis_errors_px(ident.model, scans, case),
        "truth": case["truth"]["scanner"],
        "true_loops_nm": true_loops_nm(case),
    }
    out |= S.path_coverage(ident, scans, case) | predicted_sd_by_reach(ident, scans, case)
    out |= error_breakdown(ident.model, scans, case)
    inside, outside, share = S.path_error_by_reach(ident.model, scans, case)
    out |= {"tip_path_inside_reach_rms_px": inside, "tip_path_outside_reach_rms_px": outside}
    out["inside_reach_share"] = share
    return out, ident.model.scanner


def main() -> None:
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--seed", type=int, default=7)
    a.add_argument("--pixels", type=int, default=256)
    a.add_argument("--rates", type=float, nargs="+", default=[0.5, 1.0, 2.0, 4.0])
    a.add_argument("--blur-px", type=float, nargs="*", help="solver.blur_px (default: unset)")
    a.add_argument(
        "--known", nargs="*", choices=["x", "y"], default=[], help="axes whose true gain is stated"
    )
    a.add_argument("--sd-pct", type=float, default=2.0, help="the stated gains' sd, %% of each")
    a.add_argument("--lag", action="store_true", help="rate_dependence in place of feedback_lag in the model")
    a.add_argument("--model", choices=["gpi", "preisach"], default="gpi", help="step A's model class")
    a.add_argument(
        "--chord-lengths", action="store_true", help="solver.chord_lengths: fit the chords' lengths too"
    )
    args = a.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    said = []

    def log(line):
        said.append(line)
        print(line, flush=True)

    row, scanner = run(
        args.seed,
        args.pixels,
        tuple(args.rates),
        args.blur_px,
        tuple(args.known),
        args.sd_pct,
        args.lag,
        args.model,
        args.chord_lengths,
        log,
    )
    row["log"] = said
    blurs = "" if args.blur_px is None else "_blur" + "_".join(f"{b:g}" for b in args.blur_px)
    known = f"_known_{''.join(args.known)}_{args.sd_pct:g}pct" if args.known else ""
    lag = "_lag" if args.lag else ""
    kind = "_preisach" if args.model == "preisach" else ""
    lengths = "_lengths" if args.chord_lengths else ""
    name = f"seed{args.seed}{blurs}{known}{lag}{kind}{lengths}"
    (OUT / f"{name}.json").write_text(json.dumps(row, indent=1, default=float))
    save_model(scanner, OUT / f"{name}_model.json")
    keys = ("plausible", "failures", "kept", "tip_path_rms_px", "tip_path_xy_rms_px", "seconds")
    print(json.dumps({k: row[k] for k in keys}, indent=1, default=float))


if __name__ == "__main__":
    main()
