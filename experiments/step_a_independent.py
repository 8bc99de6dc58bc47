"""Step A on lattice images jaxafm did not make: the independent generator (tests/independent_lattice.py).

Each case draws a scanner (a Preisach loop, drive lag, log creep, coupling, drift) and a lattice
(rounded square or round pits or pillars, sloped walls, tip broadening) and images it at 0 and 90
degrees (and, for a speed series, at several line rates), with a plane and a bow, line offsets,
spikes, clipped pixels and noise. The images go through ``jaxafm calibrate``'s own reading
(files written as a user would give them) and step A; the result is scored against the
generator's truth:

- the tip path: the fitted model's tip at every pixel of every scan against the true one, after
  the one rigid motion (a turn and a shift) that no image can see, rms in pixels;
- the held-out features' residual (pixels) and the relative errors of the distances between them
  (%), as ``jaxafm calibrate`` reports them;
- with a speed series, the fitted rate-dependence lag against the generator's drive lag;
- how well the fit knows its own errors: the held-out features and the true tip path inside the
  ellipses it predicts (:func:`path_coverage`; the features' as ``jaxafm calibrate`` reports them);
- the deliberately unidentifiable cases (one scan at one speed; a 3 x 3 lattice): refused, or
  reduced with the reason.

    python experiments/step_a_independent.py [--cases 20] [--speeds 4] [--shard 1/2] [--resume]
    python experiments/step_a_independent.py --seeds 102 105  # those cases again, in place
    python experiments/step_a_independent.py --model preisach  # step A with the Preisach class
    python experiments/step_a_independent.py --creep-onset --seeds 102 105  # creep's onset fitted too
    python experiments/step_a_independent.py --chord-lengths --seeds 102 105  # solver.chord_lengths
    python experiments/step_a_independent.py --off-line-chords 5 --seeds 101 107  # grating.off_line_chords_sd

writes experiments/results/step_a_independent/ (step_a_independent_preisach/ with --model
preisach; the folder's name ending _creep_onset with --creep-onset, _lengths with
--chord-lengths, _off_line with --off-line-chords): cases-K-of-N.json per shard, after each
case (with --resume the cases already in one are skipped); then summary.json and summary.png,
what the docs table shows (--summarise: those alone).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import benchutil  # noqa: F401  (puts tests/ on sys.path)
import independent_lattice as G
import jax
import numpy as np

from jaxafm.config import CalibrateConfig
from jaxafm.identify.fit import clear_caches
from jaxafm.identify.identifiability import LEVELS, ellipse_quantile, feature_spread, path_covariance
from jaxafm.identify.scan_model import feature_reach
from jaxafm.jobs.calibrate import identification_metrics, identify_model, read_calibration

OUT = Path(__file__).parent / "results" / "step_a_independent"
MODEL = {"name": "gpi", "kind": "gpi", "operators": 16, "deadzones": 3}
#: the other model class step A can fit: a Preisach plane (its branches may differ in shape, so no
#: asymmetry effect)
PREISACH = {"name": "preisach", "kind": "preisach", "levels": 16}
#: the effects step A may fit: the generator has no z lag, so the drive's lag is the scanner's own
EFFECTS = ["asymmetry", "creep", "coupling", "bow", "drift"]
#: the study of each model class (``--model``): step A's richest model and where the results go
CLASSES = {"gpi": (MODEL, OUT), "preisach": (PREISACH, OUT.parent / "step_a_independent_preisach")}


def _key(row: dict, name: str) -> str:
    """The key of step A's metric ``name`` in a case's ``row``: prefixed with the model class the
    case was fitted with (``gpi_``, ``preisach_``)."""
    return f"{row.get('model_class', 'gpi')}_{name}"


def plan(cases: int, speeds: int) -> list:
    """The cases: the two unidentifiable kinds, then ``cases`` drawn ones at 0 and 90 degrees and
    one line rate (every third a speed series of ``speeds`` rates at 0 degrees)."""
    out = [
        {"seed": 900 + k, "rates": (1.0,), "angles": (0.0,), "unidentifiable": why}
        for k, why in enumerate(G.UNIDENTIFIABLE)
    ]
    for k in range(cases):
        series = k % 3 == 2
        rates = tuple(G.LINE_RATES_HZ[:speeds]) if series else (1.0,)
        angles = (0.0,) if series else (0.0, 90.0)
        out.append({"seed": 100 + k, "rates": rates, "angles": angles, "unidentifiable": None})
    return out


def draw_and_read(
    spec: dict,
    pixels: int,
    kind: str,
    magnitudes: dict | None = None,
    model: dict = MODEL,
    grating: dict | None = None,
) -> tuple:
    """``(case, scans)``: the generator's case for ``spec`` (its scanner's ``magnitudes`` as
    :func:`independent_lattice.draw_case` takes them), written as a user would give it and read
    back through ``jaxafm calibrate``'s own reading (``grating``'s settings over the case's own);
    and the step A configuration for it, with ``model`` (:data:`MODEL` or :data:`PREISACH`) as
    its richest model."""
    case = G.draw_case(
        spec["seed"],
        kind,
        line_rates_hz=spec["rates"],
        angles_deg=spec["angles"],
        pixels=pixels,
        unidentifiable=spec["unidentifiable"],
        magnitudes=magnitudes,
    )
    series = len(spec["rates"]) > 1
    with tempfile.TemporaryDirectory() as folder:
        files = G.write_case(case, folder)
        given = json.loads(Path(files["data"]).read_text())
        # the one-speed case asks for the rate dependence one speed cannot fix
        lag = series or spec["unidentifiable"] == "one_speed"
        effects = EFFECTS + (["rate_dependence"] if lag else ["feedback_lag"])
        if model["kind"] == "preisach":
            effects.remove("asymmetry")
        cfg = CalibrateConfig(
            data=given["data"],
            grating=given["grating"] | (grating or {}),
            models=[model | {"effects": effects}],
            solver={"blur_px": [], "coarsen": "auto", "max_steps": 200},
            compensate=None,
        )
        scans = read_calibration(cfg.data, cfg.grating, Path(folder) / "c.yaml", log=lambda *_: None)
    return case, scans, cfg


def run_case(
    spec: dict,
    pixels: int,
    kind: str,
    model: dict = MODEL,
    solver: dict | None = None,
    grating: dict | None = None,
) -> dict:
    """Draw, write, read and identify one case with ``model`` as step A's richest model (and
    ``solver``'s and ``grating``'s settings over the case's own); score it against the truth. The
    compiled functions of earlier cases are dropped first: kept, they fill the memory of a long run."""
    jax.clear_caches()
    clear_caches()
    case, scans, cfg = draw_and_read(spec, pixels, kind, model=model, grating=grating)
    settings = cfg.solver.model_copy(update=solver or {})
    began = time.perf_counter()
    said = []
    try:
        ident = identify_model(scans, cfg.models[0], settings, cfg.grating, log=said.append)
    except ValueError as e:
        refused = {"model_class": model["name"], "refused": str(e)}
        return _row(spec, case, refused, time.perf_counter() - began, said)
    m = {"model_class": model["name"]} | {
        f"{model['name']}_{k}": v for k, v in identification_metrics(ident).items()
    }
    m["tip_path_rms_px"] = path_error(ident.model, scans, case)
    m["tip_path_per_scan_rms_px"] = _path_error_per_scan(ident.model, scans, case)
    m["tip_path_inside_reach_rms_px"], m["tip_path_outside_reach_rms_px"], m["inside_reach_share"] = (
        path_error_by_reach(ident.model, scans, case)
    )
    m |= path_coverage(ident, scans, case)
    truth = case["truth"]["scanner"]
    m["true_rate_lag_s"] = truth["rate_tau_s"]
    m["true_creep_per_decade"] = truth["creep_per_decade"]
    m["true_drift_nm_per_s"] = truth["drift_nm_per_s"]
    m["true_loop_pct"] = [a["loop_pct"] for a in truth["axes"]]
    return _row(spec, case, m, time.perf_counter() - began, said)


def _row(spec, case, m, seconds, said) -> dict:
    pixel = case["scans"][0].meta["size_nm"][0] / case["scans"][0].meta["pixels"]
    return {
        "seed": spec["seed"],
        "rates_hz": list(spec["rates"]),
        "angles_deg": list(spec["angles"]),
        "unidentifiable": case["truth"]["unidentifiable"],
        "feature": case["meta"]["feature"],
        "pixel_nm": pixel,
        "seconds": seconds,
        "log": said,
        **m,
    }


def _paths(model, scans, case) -> tuple:
    """The fitted and the true tip paths (N, 2) nm over every pixel of every scan, trace then
    retrace of each, and each pixel's nominal stage position (N, 2) nm."""
    fitted, true, nominal = [], [], []
    for scan, s in zip(scans, case["scans"]):
        rows, cols = np.asarray(s.truth["tip_trace_nm"]).shape[:2]
        rc = np.stack(np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij"), -1).reshape(-1, 2)
        for k, p in zip(("trace", "retrace"), model.paths(scan)):
            fitted.append(np.asarray(p).reshape(-1, 2))
            true.append(np.asarray(s.truth[f"tip_{k}_nm"]).reshape(-1, 2))
            nominal.append(np.asarray(scan.raster.nominal(rc.astype(float))))
    return np.concatenate(fitted), np.concatenate(true), np.concatenate(nominal)


def path_error(model, scans, case) -> float:
    """rms (px) of the fitted tip path against the true one over every pixel of every scan, after
    the best rigid motion of the fitted frame onto the true one."""
    fitted, true, _ = _paths(model, scans, case)
    return float(np.sqrt(np.mean(_rigid_errors(fitted, true)))) / scans[0].raster.pixel_size[0]


def path_error_by_reach(model, scans, case) -> tuple:
    """:func:`path_error` (px) over the pixels inside the features' chords' reach on both stage
    axes (:func:`~jaxafm.identify.scan_model.feature_reach`: where the data hold the path) and
    over those outside it (the image's margins, where the model extrapolates; None when there
    are none), and the share of pixels inside."""
    e, inside_axes = path_errors_by_axis_reach(model, scans, case)
    inside = inside_axes[0] & inside_axes[1]
    rms = lambda m: float(np.sqrt(np.mean(e[m]))) / scans[0].raster.pixel_size[0] if m.any() else None
    return rms(inside), rms(~inside), float(inside.mean())


def path_errors_by_axis_reach(model, scans, case) -> tuple:
    """The squared tip-path errors (N,) nm^2 of every pixel of every scan after the rigid motion
    (:func:`path_error`'s), and per stage axis whether each pixel lies inside the features'
    chords' reach on it (2 masks (N,))."""
    fitted, true, nominal = _paths(model, scans, case)
    return _rigid_errors(fitted, true), _inside_reach(scans, nominal)


def _inside_reach(scans, nominal: np.ndarray) -> list:
    """Per stage axis, whether each pixel at its nominal position (N, 2) nm lies inside the
    features' chords' reach on that axis (2 masks (N,))."""
    reach = feature_reach(scans)
    return [(nominal[:, k] >= reach[k][0]) & (nominal[:, k] <= reach[k][1]) for k in (0, 1)]


def _path_error_per_scan(model, scans, case) -> list:
    """:func:`path_error` of each scan alone, each after its own rigid motion: small where each
    scan's path is right but the scans' paths sit apart (a lattice offset between them that the
    fit took up as drift, say)."""
    out = []
    for scan, s in zip(scans, case["scans"]):
        a = np.concatenate([np.asarray(p).reshape(-1, 2) for p in model.paths(scan)])
        b = np.concatenate([np.asarray(s.truth[f"tip_{k}_nm"]).reshape(-1, 2) for k in ("trace", "retrace")])
        out.append(float(np.sqrt(np.mean(_rigid_errors(a, b)))) / scan.raster.pixel_size[0])
    return out


def _rigid_errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared lengths (N,) nm^2 of ``a - b`` after the rigid motion of ``a`` that fits ``b`` best."""
    return np.sum(_rigid(a, b)[0] ** 2, axis=1)


def _rigid(a: np.ndarray, b: np.ndarray) -> tuple:
    """``(e, r)``: the errors (N, 2) nm of ``a`` against ``b`` after the rigid motion of ``a``
    that fits ``b`` best (Kabsch), and its turn ``r`` (2, 2), ``a`` turned is ``a @ r``."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ma).T @ (b - mb))
    r = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return (a - ma) @ r + mb - b, r


def path_coverage(ident, scans, case) -> dict:
    """How well step A knows its own tip path: the true path's errors (:func:`path_error`'s)
    inside the 50 % and 90 % ellipses the fit predicts at each pixel, % of the pixels, and the
    rms error it predicts (px): from the parameters' covariance alone
    (:func:`jaxafm.identify.identifiability.path_covariance`), and with the spread of a feature
    the fit did not see added on both axes (``_with_spread``;
    :func:`jaxafm.identify.identifiability.feature_spread`: chord noise, feature irregularity
    and what of the model's error the features show); the latter's 90 % coverage also inside
    the features' reach on both stage axes and outside it (:func:`path_error_by_reach`'s split)."""
    fitted, true, nominal = _paths(ident.model, scans, case)
    e, r = _rigid(fitted, true)
    cov = np.concatenate([c.reshape(-1, 2, 2) for c in path_covariance(ident.model, scans, ident.chords)])
    cov = r.T @ cov @ r  # into the truth's frame, as the errors
    spread = np.trace(feature_spread(ident.model, scans, ident.chords)) / 2 * np.eye(2)
    pixel = scans[0].raster.pixel_size[0]
    out = {}
    for name, c in (("", cov), ("_with_spread", cov + spread)):
        inside = np.einsum("ni,nij,nj->n", e, np.linalg.pinv(c), e)[:, None] <= [
            ellipse_quantile(L) for L in LEVELS
        ]
        out |= {
            f"tip_path_coverage_{round(100 * L)}{name}_pct": 100 * float(np.mean(i))
            for L, i in zip(LEVELS, inside.T)
        }
        out[f"tip_path_predicted_rms{name}_px"] = (
            float(np.sqrt(np.mean(np.trace(c, axis1=1, axis2=2)))) / pixel
        )
    within = np.all(_inside_reach(scans, nominal), axis=0)
    held = inside[:, LEVELS.index(0.9)]
    for name, where in (("inside", within), ("outside", ~within)):
        out[f"tip_path_coverage_90_with_spread_{name}_reach_pct"] = (
            100 * float(np.mean(held[where])) if where.any() else None
        )
    return out


def _stat(rows: list, value, how) -> float | None:
    """``how`` (np.median, np.max) of ``value(row)`` over ``rows``; None for none."""
    return float(how([value(r) for r in rows])) if rows else None


def summarise(out: Path = OUT) -> dict:
    """The shards' cases in ``out`` in one summary: the drawn cases' scores (median and worst),
    the speed series' fitted lags against the truth, and what became of the unidentifiable cases."""
    rows = [r for p in sorted(out.glob("cases-*.json")) for r in json.loads(p.read_text())]
    drawn = [r for r in rows if r["unidentifiable"] is None]
    saved = [r for r in drawn if "refused" not in r and r.get(_key(r, "plausible"))]
    s = {"cases": len(drawn), "saved": len(saved)}
    scores = {
        "tip_path_rms_px": lambda r: r["tip_path_rms_px"],
        "tip_path_worst_scan_rms_px": lambda r: max(r["tip_path_per_scan_rms_px"]),
        "held_out_rms_px": lambda r: r[_key(r, "held_out_rms_nm")] / r["pixel_nm"],
        "held_out_raw_rms_px": lambda r: r[_key(r, "held_out_raw_rms_nm")] / r["pixel_nm"],
        "held_out_distance_error_rms_pct": lambda r: r[_key(r, "held_out_distance_error_rms_corrected_pct")],
        "held_out_distance_error_max_pct": lambda r: r[_key(r, "held_out_distance_error_max_corrected_pct")],
        "held_out_distance_error_max_raw_pct": lambda r: r[_key(r, "held_out_distance_error_max_raw_pct")],
    }
    for key, value in scores.items():
        s |= {f"{key}_median": _stat(saved, value, np.median), f"{key}_max": _stat(saved, value, np.max)}
    covered = [r for r in saved if "tip_path_coverage_90_pct" in r]
    s["coverage_cases"] = len(covered)
    for level in (90, 50):
        for key in (f"tip_path_coverage_{level}_pct", f"tip_path_coverage_{level}_with_spread_pct"):
            s[f"{key}_median"] = _stat(covered, lambda r: r[key], np.median)
        key = f"held_out_coverage_{level}_pct"
        s[f"{key}_median"] = _stat(covered, lambda r: r[_key(r, key)], np.median)
    series = [r for r in drawn if len(r["rates_hz"]) > 1]
    s["speed_series"] = len(series)
    s["rate_lag_relative_error_pct"] = [
        100 * (r[_key(r, "x_rate_lag_s")] / r["true_rate_lag_s"] - 1)
        if r.get(_key(r, "x_rate_lag_s"))
        else None
        for r in series
    ]
    s["unidentifiable"] = [
        {"case": r["unidentifiable"], "outcome": _outcome(r), "ladder": r.get(_key(r, "model_ladder"))}
        for r in rows
        if r["unidentifiable"] is not None
    ]
    (out / "summary.json").write_text(json.dumps(s, indent=1))
    _figure(drawn, out)
    return s


def _figure(drawn: list, out: Path) -> None:
    """summary.png: per drawn case, the tip path's and the held-out features' rms error (px)
    against the goals, and the largest held-out distance error raw and corrected (%)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted((r for r in drawn if "refused" not in r), key=lambda r: r["seed"])
    saved = [bool(r.get(_key(r, "plausible"))) for r in rows]
    labels = [
        f"{r['seed']}\n{'speeds' if len(r['rates_hz']) > 1 else '0+90°'}" + ("" if ok else "\nrefused")
        for r, ok in zip(rows, saved)
    ]
    x = np.arange(len(rows))
    fig, (a, b) = plt.subplots(2, 1, figsize=(max(6, 0.55 * len(rows)), 6.5), sharex=True)
    a.bar(x - 0.2, [r["tip_path_rms_px"] for r in rows], 0.4, label="tip path, every pixel")
    a.bar(
        x + 0.2, [r[_key(r, "held_out_rms_nm")] / r["pixel_nm"] for r in rows], 0.4, label="held-out features"
    )
    a.axhline(0.1, color="C0", ls="--", lw=1, label="goal, tip path (0.1 px)")
    a.axhline(0.15, color="C1", ls="--", lw=1, label="goal, held-out (0.15 px)")
    a.set_ylabel("rms error (px)")
    a.legend(fontsize=8)
    b.bar(
        x - 0.2,
        [r[_key(r, "held_out_distance_error_max_raw_pct")] for r in rows],
        0.4,
        label="raw image",
        color="0.6",
    )
    b.bar(
        x + 0.2,
        [r[_key(r, "held_out_distance_error_max_corrected_pct")] for r in rows],
        0.4,
        label="corrected",
    )
    b.axhline(0.2, color="k", ls="--", lw=1, label="goal (0.2 %)")
    b.set_yscale("log")
    b.set_ylim(bottom=0.1)
    b.set_ylabel("largest held-out distance error (%)")
    b.set_xticks(x, labels, fontsize=7)
    b.set_xlabel("case (seed, scans; hatched: the fit step A refused or judged not plausible)")
    b.legend(fontsize=8)
    for bars in a.containers + b.containers:  # a fit step A did not save: hatched, faded
        for bar, ok in zip(bars, saved):
            bar.set(alpha=1 if ok else 0.4, hatch=None if ok else "//")
    richest = (
        {"gpi": "generalised PI", "preisach": "Preisach"}[rows[0].get("model_class", "gpi")] if rows else ""
    )
    fig.suptitle(
        f"Step A on the independent generator's lattices\n(chords only, model ladder up to the {richest} class)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(out / "summary.png", dpi=120)
    plt.close(fig)


def _outcome(r: dict) -> str:
    """What became of an unidentifiable case, in words: refused (why), failed its checks (which),
    or saved, with the rungs the ladder did not try (why) and the model it kept."""
    if "refused" in r:
        return f"refused: {r['refused']}"
    if r.get(_key(r, "failures")):
        return "not plausible: " + "; ".join(r[_key(r, "failures")])
    skipped = [rung for rung in r.get(_key(r, "model_ladder"), []) if ": not tried" in rung]
    kept = f"{r[_key(r, 'model_kind')]}, {_size(r)} + {', '.join(r[_key(r, 'model_effects')])}"
    return "saved, reduced: " + "; ".join(skipped + [f"kept {kept}"]) if skipped else f"saved ({kept})"


def _size(r: dict) -> str:
    """The kept model's plays (PI, generalised PI) or levels (Preisach), in words."""
    what = "levels" if r[_key(r, "model_kind")] == "preisach" else "plays"
    return f"{r[_key(r, 'model_operators')]} {what}"


def _line(r: dict) -> str:
    """One case's result in a line."""
    head = f"seed {r['seed']} {r['feature']} {r['angles_deg']} deg {r['rates_hz']} Hz: "
    if "refused" in r:
        return head + f"refused: {r['refused']}"
    return head + (
        f"model {r[_key(r, 'model_kind')]} {_size(r)} {r[_key(r, 'model_effects')]}; "
        f"tip path {r['tip_path_rms_px']:.3f} px "
        f"(per scan {np.round(r['tip_path_per_scan_rms_px'], 3).tolist()}), "
        f"held-out {r[_key(r, 'held_out_rms_nm')] / r['pixel_nm']:.3f} px, "
        f"distances {r[_key(r, 'held_out_distance_error_max_corrected_pct')]:.3f} % max; "
        f"failures {r[_key(r, 'failures')]}; {r['seconds']:.0f} s"
    )


def rerun(
    seeds: list,
    cases: list,
    pixels: int,
    kind: str,
    model: dict = MODEL,
    out: Path = OUT,
    solver: dict | None = None,
    grating: dict | None = None,
) -> None:
    """Run the cases of ``seeds`` again, each row replacing the one of its seed in the
    cases-*.json of ``out`` that holds it (after each case)."""
    held = {r["seed"]: path for path in out.glob("cases-*.json") for r in json.loads(path.read_text())}
    for spec in (c for c in cases if c["seed"] in seeds):
        row = run_case(spec, pixels, kind, model, solver, grating)
        print(_line(row), flush=True)
        path = held.get(spec["seed"], out / "cases-rerun.json")
        rows = json.loads(path.read_text()) if path.exists() else []
        rows = [r for r in rows if r["seed"] != spec["seed"]] + [row]
        path.write_text(json.dumps(sorted(rows, key=lambda r: r["seed"]), indent=1, default=float))


def main() -> None:
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--cases", type=int, default=20)
    a.add_argument("--speeds", type=int, default=3)
    a.add_argument("--pixels", type=int, default=128)
    a.add_argument("--kind", default="fine", choices=list(G.KINDS))
    a.add_argument("--shard", default="1/1")
    a.add_argument("--summarise", action="store_true")
    a.add_argument("--resume", action="store_true", help="skip the cases a cases-*.json already holds")
    a.add_argument(
        "--seeds", type=int, nargs="+", help="run these cases again, each in the file that holds it"
    )
    a.add_argument(
        "--model",
        choices=sorted(CLASSES),
        default="gpi",
        help="step A's model class (its own results folder)",
    )
    a.add_argument(
        "--creep-onset",
        action="store_true",
        help="fit creep's onset too (the model's creep_onset; its own results folder)",
    )
    a.add_argument(
        "--chord-lengths",
        action="store_true",
        help="fit the chords' lengths too (solver.chord_lengths; its own results folder)",
    )
    a.add_argument(
        "--off-line-chords",
        type=float,
        metavar="SD",
        help="leave out chords off their features' lines (grating.off_line_chords_sd; its own results folder)",
    )
    args = a.parse_args()
    model, folder = CLASSES[args.model]
    if args.creep_onset:
        model, folder = model | {"creep_onset": True}, folder.with_name(folder.name + "_creep_onset")
    solver = {"chord_lengths": True} if args.chord_lengths else {}
    if args.chord_lengths:
        folder = folder.with_name(folder.name + "_lengths")
    grating = {} if args.off_line_chords is None else {"off_line_chords_sd": args.off_line_chords}
    if grating:
        folder = folder.with_name(folder.name + "_off_line")
    folder.mkdir(parents=True, exist_ok=True)
    if args.seeds:
        rerun(
            args.seeds, plan(args.cases, args.speeds), args.pixels, args.kind, model, folder, solver, grating
        )
    elif not args.summarise:
        k, n = (int(v) for v in args.shard.split("/"))
        done = {r["seed"] for p in folder.glob("cases-*.json") for r in json.loads(p.read_text())}
        todo = [
            c for c in plan(args.cases, args.speeds)[k - 1 :: n] if not (args.resume and c["seed"] in done)
        ]
        out = folder / f"cases-{k}-of-{n}.json"
        rows = json.loads(out.read_text()) if args.resume and out.exists() else []
        for spec in todo:
            rows.append(run_case(spec, args.pixels, args.kind, model, solver, grating))
            print(_line(rows[-1]), flush=True)
            out.write_text(json.dumps(rows, indent=1, default=float))
    print(json.dumps(summarise(folder), indent=1))


if __name__ == "__main__":
    main()
