"""jaxafm's record diagnosis on records from an independent generator (tests/independent.py).

The records do not come from jaxafm's simulator: tests/independent.py writes the physics anew in
NumPy/SciPy (its docstring states every equation): a two-axis piezo actuator, 6 s at 1 kHz,
triangle drives of varying amplitude and frequency, a Prandtl-Ishlinskii or a smooth Preisach
hysteresis, and one effect (asymmetry, rate dependence, creep, drift, coupling, bow, vibration)
at three magnitudes (independent.MAGNITUDES), several seeds each, plus controls with none. In
half of the cases the nominal model's class differs from the truth's (a Preisach truth diagnosed
with a PI nominal, or the reverse); the diagnosis has to find the effect anyway, and not blame
an effect for a control whose only "gap" is the hysteresis class.

A case is right when the verdict is its effect; an asymmetry case also when the diagnosis's
hysteresis-shape finding (``res.shape``) is a richer operator ("gpi" or "preisach": both
hold an asymmetric loop). A control is flagged when it gets any
verdict. Writes, into experiments/results/independent_check/: cases.json (one row per case,
written as it goes), summary.json (confusion matrices, top-1 per level, same-class and
different-class nominal apart, controls flagged, median shrink of correctly named cases) and
confusion.png.

    python experiments/independent_check.py                    # 5 seeds, 20 controls: ~3.7 h on one core
    python experiments/independent_check.py --limit 4          # the first 4 cases, a quick look
    python experiments/independent_check.py --effects creep control --limit 6
    python experiments/independent_check.py --seeds 2 --controls 6 --levels middle control   # ~30 min
    python experiments/independent_check.py --shard 1/2 & python experiments/independent_check.py --shard 2/2
                                                               # two processes, one core each: ~2 h
    python experiments/independent_check.py --nominal pi --shard 1/2   # only the PI-nominal cases
    python experiments/independent_check.py --summarise        # only rebuild summary and figure
    python experiments/independent_check.py --reported     # four described cases, 60 s at 100 Hz (~5 min)
    python experiments/independent_check.py --wandering --shard 1/2   # and --shard 2/2 beside it:
        # drifts that wander (random walk, Ornstein-Uhlenbeck) and creep, half on Preisach truths,
        # symmetric PI nominal (independent.wandering_cases: 108 cases + 20 controls, ~2 h on 2 cores),
        # into experiments/results/independent_check_wandering/
    python experiments/independent_check.py --wandering --truth preisach --effects drift creep \
        --profile-nodes 7 --shard 1/2 --out experiments/results/independent_check_wandering_nodes7
        # and --shard 2/2 beside it: the Preisach truths' cases, the Preisach rung with 7 profile nodes
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import benchutil  # noqa: F401  (puts tests/ on sys.path)
import matplotlib.pyplot as plt
from independent import (
    DRIVE,
    EFFECTS,
    LEVELS,
    MAGNITUDES,
    NOISE_NM,
    REPORTED_CASES,
    REPORTED_DRIVE,
    UNITS,
    WANDERS,
    case_noise,
    case_wanders,
    cases,
    make_case,
    make_drive,
    wander_parameters,
    wandering_cases,
)
from scipy.linalg import cho_factor, cho_solve

from jaxafm.diagnose import plant
from jaxafm.diagnose import record as D
from jaxafm.diagnose.report import above_floor, noise_floor_nm
from jaxafm.instrument.records import Record

OUT = Path(__file__).parent / "results" / "independent_check"
WANDERING_OUT = OUT.parent / "independent_check_wandering"
CANDIDATES = ("asymmetry", "rate_dependence", "creep", "drift", "coupling", "bow", "vibration")
LABELS = (*EFFECTS, "none")
CLASSES = ("same", "different")


def case_record(case: dict) -> Record:
    """The case's record, made by the independent generator."""
    wander = case.get("wander")
    rec = make_case(case["effect"], case["level"], case["seed"], case["truth_hysteresis"], wander=wander)
    return Record(
        t=rec["t"],
        u=rec["u"],
        d=rec["d"],
        meta={
            "source": f"independent generator: {case['effect'] or 'control'}"
            f"{f' ({wander} wander)' if wander else ''} {case['level']} "
            f"seed {case['seed']}, truth {case['truth_hysteresis']}",
            "truth": rec["truth"],
        },
    )


def floor_nm(case: dict) -> float:
    """The noise floor of the case's held-out output (the diagnosis's estimate, not the truth's)."""
    data = D.ActuatorRecord.split_off(case_record(case), D.Nominal(kind=case["nominal_kind"]))
    return noise_floor_nm(data.d[data.heldout])


def wander_cov(s: np.ndarray, t: np.ndarray, wander: dict) -> np.ndarray:
    """The covariance (nm^2) of the generator's wander between times ``s`` and ``t`` (s from the
    record's start, where it is 0): a walk ``sigma^2 min(s, t)``; an Ornstein-Uhlenbeck process
    started at 0, ``sigma^2 (exp(-|s - t| / tau) - exp(-(s + t) / tau))``."""
    sigma, ss, tt = wander["sigma"], s[:, None], t[None, :]
    if wander["kind"] == "walk":
        return sigma**2 * np.minimum(ss, tt)
    return sigma**2 * (np.exp(-np.abs(ss - tt) / wander["tau_s"]) - np.exp(-(ss + tt) / wander["tau_s"]))


def attainable_gap_nm(case: dict) -> float:
    """The held-out gap on the blocks a drift is judged on (the diagnosis's split) that an exact
    model of the actuator leaves: the generator's wander (:func:`independent.case_wanders`) and
    noise (:func:`independent.case_noise`) of the case's seed, the wander predicted across the
    held-out blocks from the training ones by its best (kriging) estimate: conditioned on the
    truth's covariance (:func:`wander_cov`) and ``NOISE_NM``, a line's start and rate fitted
    beside it by generalised least squares (flat prior; the drift's straight part then drops
    out of the error). No model predicts a wander across a held-out block better. Dense NumPy
    algebra on the truth; jaxafm only splits the record."""
    t, u = DRIVE
    wander = wander_parameters(case["wander"], case["level"])
    left = case_wanders(t, wander, case["seed"]) + case_noise((t.size, 2), case["seed"])
    data = D.ActuatorRecord.split_off(
        Record(t=t, u=u, d=left, meta={}), D.Nominal(kind=case["nominal_kind"])
    ).blocked
    s, o, h = t - t[0], data.train, data.heldout
    line = np.stack([np.ones_like(s), s], 1)
    chol = cho_factor(wander_cov(s[o], s[o], wander) + NOISE_NM**2 * np.eye(o.sum()))
    ko, across = cho_solve(chol, line[o]), wander_cov(s[h], s[o], wander)
    errors = []
    for r in left.T:
        coef = np.linalg.solve(line[o].T @ ko, ko.T @ r[o])
        errors.append(r[h] - line[h] @ coef - across @ cho_solve(chol, r[o] - line[o] @ coef))
    return float(np.sqrt(np.mean(np.square(errors))))


def relay_roughness_nm(case: dict) -> float:
    """What a Preisach truth's relays add to the held-out gap its effect is judged on, beyond any
    model of its density: the rms (nm, both axes) of the case's record less the same case with
    the density continuous over the plane (``independent.make_case``'s ``relays=None``: the same
    density, noise and draws), over the held-out samples of the split the diagnosis judges the
    effect on (alternating blocks for a drift, the later part otherwise). The generator places
    one relay at a random point of each of its 100 x 100 cells, so the output jumps as each one
    switches: noise-like, and heavier-tailed than white noise. 0 for a PI truth (a continuous
    output) and for a control."""
    if case["effect"] is None or case["truth_hysteresis"] != "preisach":
        return 0.0
    grid, continuous = (
        make_case(
            case["effect"], case["level"], case["seed"], "preisach", wander=case.get("wander"), relays=n
        )["d"]
        for n in (100, None)
    )
    t, u = DRIVE
    data = D.ActuatorRecord.split_off(Record(t=t, u=u, d=grid, meta={}), D.Nominal(kind=case["nominal_kind"]))
    held = (data.blocked if case["effect"] == "drift" else data).heldout
    return float(np.sqrt(np.mean(np.square((grid - continuous)[held]))))


def with_roughness(rows: list, path: Path) -> list:
    """``rows`` with each case's :func:`relay_roughness_nm`, read from ``path`` (a JSON map by
    case) where it was computed before; the rest computed (about 3 s a Preisach case) and
    added there as they come."""
    known = json.loads(path.read_text()) if path.exists() else {}
    key = lambda r: f"{r['effect']}-{r.get('wander')}-{r['level']}-{r['seed']}-{r['truth_hysteresis']}"
    for r in rows:
        if key(r) not in known:
            known[key(r)] = relay_roughness_nm(r)
            path.write_text(json.dumps(known, indent=1))
    return [r | {"relay_roughness_nm": known[key(r)]} for r in rows]


def diagnose(case: dict, candidates: tuple):
    """Run the diagnosis; returns (result, the candidates it accepted)."""
    record = case_record(case)
    spec = D.Nominal(kind=case["nominal_kind"])
    try:
        return D.diagnose_record(record, spec, candidates, log=lambda s: None), candidates
    except ValueError as err:
        if "vibration" not in candidates or "vibration" not in str(err):
            raise
        # 'vibration' is not (yet) a candidate jaxafm knows: drop it for now
        print(f"  diagnose_record rejected 'vibration' ({err}); running without it", flush=True)
        kept = tuple(c for c in candidates if c != "vibration")
        return D.diagnose_record(record, spec, kept, log=lambda s: None), kept


def named_effect(effect, verdict, shape):
    """The effect a diagnosis named: its verdict, or "asymmetry" for an asymmetry case whose shape
    found is a richer operator ("gpi" or "preisach": both hold an asymmetric loop)."""
    if effect == "asymmetry" and shape in ("gpi", "preisach"):
        return "asymmetry"
    return verdict


def run_case(case: dict, candidates: tuple) -> tuple:
    start = time.perf_counter()
    res, used = diagnose(case, candidates)
    rows = {r.effect: r for r in res.candidates}
    effect, verdict, shape = case["effect"], res.verdict, getattr(res, "shape", None)
    named = named_effect(effect, verdict, shape)
    correct = named == effect
    shrink_of = lambda e: rows[e].shrink_pct if e in rows else None
    row = case | {
        "class": "same" if case["truth_hysteresis"] == case["nominal_kind"] else "different",
        "verdict": verdict,
        "shape": shape,
        "named": named,
        "correct": bool(correct) if effect else None,
        "flagged": verdict is not None if effect is None else None,
        "seconds": time.perf_counter() - start,
        "heldout_gap_before_nm": res.nominal.heldout_gap_nm,
        "heldout_gap_final_nm": res.final.heldout_gap_nm,
        "noise_floor_nm": floor_nm(case),
        "verdict_shrink_pct": shrink_of(verdict) if verdict else 0.0,
        "total_shrink_pct": res.verdict_json()["total_shrink_pct"],
        "shapes": [[r.effect, r.shrink_pct, r.delta_bic, bool(r.significant)] for r in res.shapes],
        "truth_shrink_pct": shrink_of(effect) if effect else None,
        "truth_fitted": rows[effect].fit.shown().get("fitted") if effect in rows else None,
        "candidates_used": list(used),
        "skipped": {k: str(v) for k, v in res.skipped.items()},
        "ranking": [[r.effect, r.shrink_pct, r.delta_bic, bool(r.significant)] for r in res.candidates],
    }
    return row, used


def _median(values: list):
    """The median of the values that are not ``None``; ``None`` for none."""
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else None


def _scores(rows: list) -> dict:
    labels = list(LABELS)
    name = lambda v: v or "none"
    matrix = {lv: np.zeros((len(labels), len(labels)), int) for lv in (*LEVELS, "control")}
    for r in rows:
        matrix[r["level"]][labels.index(name(r["effect"])), labels.index(name(r["named"]))] += 1
    out = {"cases": len(rows), "confusion": {k: v.tolist() for k, v in matrix.items()}}
    withheld = [r for r in rows if r["effect"] is not None]
    for lv in LEVELS:
        sel = [r for r in withheld if r["level"] == lv]
        if sel:
            out[f"top1_{lv}_pct"] = float(100 * np.mean([r["correct"] for r in sel]))
            out[f"cases_{lv}"] = len(sel)
    out["top1_all_pct"] = float(100 * np.mean([r["correct"] for r in withheld])) if withheld else None
    per_effect = {}
    for e in EFFECTS:
        sel = [r for r in withheld if r["effect"] == e]
        if sel:
            per_effect[e] = {lv: [bool(r["correct"]) for r in sel if r["level"] == lv] for lv in LEVELS}
    out["correct_by_effect_and_level"] = per_effect
    ctrl = [r for r in rows if r["effect"] is None]
    out["controls"] = len(ctrl)
    out["controls_flagged"] = int(sum(r["flagged"] for r in ctrl))
    out["controls_flagged_as"] = sorted({r["verdict"] for r in ctrl if r["flagged"]})
    right = [r for r in withheld if r["correct"]]

    def median(key):  # over the correctly named cases that have the value
        return _median([r[key] for r in right])

    out["median_shrink_correct_pct"] = median("truth_shrink_pct")
    out["median_shrink_ceiling_correct_pct"] = median("shrink_ceiling_pct")
    out["median_shrink_and_ceiling_by_level_pct"] = {
        lv: [
            float(np.median(v)) if v else None
            for v in (
                [r[key] for r in right if r["level"] == lv and r[key] is not None]
                for key in ("truth_shrink_pct", "shrink_ceiling_pct")
            )
        ]
        for lv in LEVELS
    }
    out["median_total_shrink_correct_pct"] = median("total_shrink_pct")
    out["median_shrink_above_floor_correct_pct"] = median("shrink_above_floor_pct")
    out["median_total_shrink_above_floor_correct_pct"] = median("total_shrink_above_floor_pct")
    out["median_shrink_above_floor_ceiling_correct_pct"] = median("shrink_above_floor_ceiling_pct")
    out["median_shrink_above_generator_floor_correct_pct"] = median("shrink_above_generator_floor_pct")
    out["median_shrink_above_generator_floor_ceiling_correct_pct"] = median(
        "shrink_above_generator_floor_ceiling_pct"
    )
    out["median_shrink_above_generator_floor_by_truth_pct"] = {
        truth: _median(
            [r["shrink_above_generator_floor_pct"] for r in right if r["truth_hysteresis"] == truth]
        )
        for truth in ("pi", "preisach")
    }
    preisach = [r for r in withheld if r["truth_hysteresis"] == "preisach"]
    out["median_relay_roughness_nm"] = _median([r.get("relay_roughness_nm") for r in preisach])
    out["median_shrink_by_effect_pct"] = {  # correctly named: own, total, own above the floor
        e: [
            float(np.median(v)) if v else None
            for v in (
                [r[key] for r in right if r["effect"] == e and r[key] is not None]
                for key in ("truth_shrink_pct", "total_shrink_pct", "shrink_above_floor_pct")
            )
        ]
        for e in EFFECTS
    }
    out["median_noise_floor_nm"] = float(np.median([r["noise_floor_nm"] for r in rows])) if rows else None
    out["shape_findings"] = {
        str(s): int(sum(str(r["shape"]) == s for r in rows)) for s in sorted({str(r["shape"]) for r in rows})
    }
    out["seconds_per_case_median"] = float(np.median([r["seconds"] for r in rows])) if rows else None
    return out


def with_floor(row: dict) -> dict:
    """``row`` with its gaps above the noise floor: the named effect's shrink (against the model
    it was added to) and the total (nominal -> final), both on ``above_floor`` gaps, and the
    named effect's :func:`ceiling`; the same shrink and ceiling above the generator's floor,
    ``NOISE_NM`` and the row's ``relay_roughness_nm`` (:func:`with_roughness`) in quadrature,
    which the report's estimate from the held-out output takes only in part. Rows of a
    run before these keys existed get their floor and final gap from the stored record and
    shrinks."""
    row = dict(row)
    if "noise_floor_nm" not in row:  # not setdefault: its default would regenerate every record
        row["noise_floor_nm"] = floor_nm(row)
    row.setdefault("heldout_gap_final_nm", row["heldout_gap_before_nm"] * (1 - row["total_shrink_pct"] / 100))
    floor, final = row["noise_floor_nm"], row["heldout_gap_final_nm"]
    if row["effect"] == "drift" and row.get("wander") and "attainable_gap_nm" not in row:
        row["attainable_gap_nm"] = attainable_gap_nm(row)
    best = row.get("attainable_gap_nm", NOISE_NM)

    rough = row.get("relay_roughness_nm", 0.0)
    row["generator_floor_nm"] = float(np.hypot(NOISE_NM, rough))

    def shrink(before, after=final, floor=floor):  # None where nothing of the gap before is above the floor
        excess = above_floor(before, floor)
        return 100 * (1 - above_floor(after, floor) / excess) if excess > 0 else None

    row["total_shrink_above_floor_pct"] = shrink(row["heldout_gap_before_nm"])
    own = row["truth_shrink_pct"]
    base = None if own is None else final / (1 - own / 100)  # the gap of the model the effect was added to
    row["shrink_above_floor_pct"] = None if base is None else shrink(base)
    row["shrink_ceiling_pct"] = None if base is None else ceiling(base, best)
    row["shrink_above_floor_ceiling_pct"] = None if base is None else shrink(base, best)
    generator = row["generator_floor_nm"]
    row["shrink_above_generator_floor_pct"] = None if base is None else shrink(base, final, generator)
    row["shrink_above_generator_floor_ceiling_pct"] = (
        None if base is None else shrink(base, float(np.hypot(best, rough)), generator)
    )
    return row


def ceiling(gap_nm: float, best_nm: float = NOISE_NM) -> float:
    """The most any model could shrink a held-out gap of ``gap_nm`` (%): to ``best_nm``, the
    generator's own white noise (``NOISE_NM`` rms, which no model of the actuator predicts), or
    for a wandering drift its :func:`attainable_gap_nm`."""
    return 100 * (1 - best_nm / gap_nm)


def summarise(rows: list) -> dict:
    """Scores over all cases, then for the same-class and the different-class nominal apart."""
    rows = [with_floor(r) for r in rows]
    out = {"labels": list(LABELS), "all": _scores(rows)}
    for c in CLASSES:
        out[c] = _scores([r for r in rows if r["class"] == c])
    return out


def reported(out: Path) -> None:
    """The four cases of ``independent.REPORTED_CASES`` on their drive, every candidate, from a
    symmetric PI nominal: each case's verdict and candidates into ``out / reported.json``."""
    drive = make_drive(*REPORTED_DRIVE)
    rows = []
    for name, spec in REPORTED_CASES.items():
        c = make_case(**spec, drive=drive)
        record = Record(t=c["t"], u=c["u"], d=c["d"], meta={"source": f"independent generator: {name}"})
        start = time.perf_counter()
        res = D.diagnose_record(record, D.Nominal(kind="pi"), CANDIDATES, log=lambda s: None)
        rows.append(
            {
                "case": name,
                "truth": c["truth"],
                "verdict": res.verdict,
                "shape": res.shape,
                "right": res.verdict == spec["effect"],
                "nominal_heldout_gap_nm": res.nominal.heldout_gap_nm,
                "candidates": [c.to_json() for c in res.candidates],
                "seconds": time.perf_counter() - start,
            }
        )
        top = res.top
        where = f", on {top.judged_on}" if top and top.judged_on else ""
        gaps = f" ({top.heldout_gap_before_nm:.1f} -> {top.heldout_gap_after_nm:.1f} nm, {top.shrink_pct:.1f} %{where})"
        print(f"{name}: {res.text}{gaps if top else ''}", flush=True)
    (out / "reported.json").write_text(json.dumps(rows, indent=1))


def by_wander(rows: list) -> dict:
    """Per drift wander kind (and creep), the cases named right per level, as ``[right, cases]``."""
    out = {}
    for r in rows:
        if r["effect"] is None:
            continue
        key = f"drift ({r['wander']} wander)" if r.get("wander") else r["effect"]
        right = out.setdefault(key, {lv: [0, 0] for lv in LEVELS})[r["level"]]
        right[0] += bool(r["correct"])
        right[1] += 1
    return out


def figure(summary: dict, path: Path) -> None:
    labels = summary["labels"]
    classes = [c for c in CLASSES if summary[c]["cases"]]  # a selection may hold one class only
    fig, axes = plt.subplots(len(classes), 3, figsize=(19, 12.5 if len(classes) == 2 else 7.5), squeeze=False)
    for row, cls in zip(axes, classes):
        s = summary[cls]
        for ax, lv in zip(row, LEVELS):
            m = np.array(s["confusion"][lv]) + np.array(s["confusion"]["control"])
            ax.imshow(m, cmap="Blues", vmin=0, vmax=max(m.max(), 1))
            for i in range(len(labels)):
                for j in range(len(labels)):
                    if m[i, j]:
                        dark = m[i, j] > 0.6 * m.max()
                        ax.text(j, i, m[i, j], ha="center", va="center", color="w" if dark else "k")
            ax.set_xticks(range(len(labels)), labels, rotation=40, ha="right")
            ax.set_yticks(range(len(labels)), labels)
            acc = s.get(f"top1_{lv}_pct")
            acc_s = "-" if acc is None else f"{acc:.0f} %"
            ax.set(
                xlabel="verdict (asymmetry cases: also the shape finding)",
                ylabel="effect in the record (truth)",
                title=f"{cls} class nominal, {lv} magnitude + controls\n"
                f"top-1 {acc_s}; controls flagged {s['controls_flagged']}/{s['controls']}",
            )
    fig.suptitle("jaxafm record diagnosis on the independent generator's records", fontsize=14)
    fig.tight_layout(rect=None if len(classes) == 2 else (0, 0, 1, 0.94))  # room for the suptitle
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=None, help="seeds per effect and level (5; --wandering 12)")
    ap.add_argument("--controls", type=int, default=20)
    ap.add_argument("--limit", type=int, default=None, help="run only the first LIMIT cases")
    ap.add_argument(
        "--effects", nargs="+", default=None, help="run only these effects ('control' for the controls)"
    )
    ap.add_argument(
        "--levels", nargs="+", default=None, help="run only these levels (low, middle, high, control)"
    )
    ap.add_argument(
        "--nominal",
        choices=("pi", "preisach"),
        default=None,
        help="run only the cases with this nominal kind (writes cases-KIND-....json beside the others)",
    )
    ap.add_argument(
        "--truth",
        choices=("pi", "preisach"),
        default=None,
        help="run only the cases whose truth has this hysteresis class",
    )
    ap.add_argument(
        "--profile-nodes",
        type=int,
        default=None,
        help="the diagnosis's factorised Preisach rung with this many profile nodes "
        "(jaxafm.diagnose.plant.PROFILE_NODES; give a --out of its own)",
    )
    ap.add_argument(
        "--shard",
        default="1/1",
        help="K/N: run every N-th case from the K-th (writes cases[-SELECTION]-K-of-N.json)",
    )
    ap.add_argument(
        "--wandering",
        action="store_true",
        help="the cases of drifts that wander and of creep (independent.wandering_cases; "
        "--seeds default 12) into experiments/results/independent_check_wandering/",
    )
    ap.add_argument(
        "--reported",
        action="store_true",
        help="only the four cases of independent.REPORTED_CASES (reported.json in the --wandering folder)",
    )
    ap.add_argument("--out", type=Path, default=None, help="the results' folder")
    ap.add_argument(
        "--summarise",
        action="store_true",
        help="only rebuild summary.json and the figure from the cases*.json files",
    )
    args = ap.parse_args()
    args.out = args.out or (WANDERING_OUT if args.wandering or args.reported else OUT)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.reported:
        return reported(args.out)
    k, n = (int(v) for v in args.shard.split("/"))
    # the selection in the file's name, so that shards of different selections never overwrite each other
    tag = "".join(
        f"-{v}" for v in [args.nominal, args.truth, *(args.levels or []), *(args.effects or [])] if v
    )
    saved = args.out / (f"cases{tag}.json" if n == 1 else f"cases{tag}-{k}-of-{n}.json")
    if not args.summarise:
        rows = []  # this run's (the summary below merges every cases*.json in the folder)
        todo = (
            wandering_cases(args.seeds or 12, args.controls)
            if args.wandering
            else cases(args.seeds or 5, args.controls)
        )
        if args.effects:
            todo = [c for c in todo if (c["effect"] or "control") in args.effects]
        if args.levels:
            todo = [c for c in todo if c["level"] in args.levels]
        if args.nominal:
            todo = [c for c in todo if c["nominal_kind"] == args.nominal]
        if args.truth:
            todo = [c for c in todo if c["truth_hysteresis"] == args.truth]
        if args.profile_nodes:
            plant.PROFILE_NODES = args.profile_nodes
        todo = todo[: args.limit][k - 1 :: n]
        candidates = CANDIDATES
        for i, case in enumerate(todo):
            row, candidates = run_case(case, candidates)
            rows.append(row)
            if row["effect"] is None:
                mark = "flagged" if row["flagged"] else "ok"
            else:
                mark = "right" if row["correct"] else "wrong"
            wander = f" ({case['wander']} wander)" if case.get("wander") else ""
            print(
                f"[{i + 1}/{len(todo)}] {case['effect'] or 'control'}{wander} {case['level']} seed {case['seed']} "
                f"(truth {case['truth_hysteresis']}, nominal {case['nominal_kind']}): verdict {row['verdict']}, "
                f"shape {row['shape']} -> {mark} "
                f"(gap {row['heldout_gap_before_nm']:.1f} nm, shrink {row['verdict_shrink_pct']:.1f} %, "
                f"{row['seconds']:.0f} s)",
                flush=True,
            )
            saved.write_text(json.dumps(rows, indent=1))
    rows = [r for f in sorted(args.out.glob("cases*.json")) for r in json.loads(f.read_text())]
    rows = with_roughness(rows, args.out / "roughness.json")
    summary = summarise(rows) | {"magnitudes": MAGNITUDES, "units": UNITS, "candidates": list(CANDIDATES)}
    if any(r.get("wander") for r in rows):
        summary["wanders"] = WANDERS | {"by_wander": by_wander(rows)}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    figure(summary, args.out / "confusion.png")
    print(
        json.dumps(
            {
                k: {kk: vv for kk, vv in v.items() if kk != "confusion"}
                for k, v in summary.items()
                if k in ("all", *CLASSES)
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
