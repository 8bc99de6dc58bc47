"""Does the record diagnosis's verdict stay when the record is cropped or decimated?

Records of the independent generator (tests/independent.py, no jaxafm code), the cases of
``experiments/independent_check.py``'s first seed round (the same cases) at the ``--levels`` asked for (every
effect, the nominal's hysteresis class the truth's or not, as there) and ``--controls`` controls.
Each record is diagnosed four times, with the same nominal and candidates: whole (6 s at 1 kHz),
its first 10 % cut off (the record then starts in mid-motion), its last 10 % cut off, and every
second sample kept (500 Hz: a slower sampler; the 200 Hz mode stays below its Nyquist frequency).
A variant *flips* when its verdict (the effect named, or none) differs from the whole record's;
the hysteresis shape found is compared too. Writes rows-K-of-N.json (one row per case, as it
goes), summary.json and stability.png into experiments/results/stability/.

    python experiments/stability.py                              # 7 middle cases + 2 controls, ~80 min on one core
    python experiments/stability.py --shard 1/2 & python experiments/stability.py --shard 2/2
    python experiments/stability.py --nominal pi --shard 1/2     # only the PI-nominal cases
    python experiments/stability.py --summarise                  # only rebuild summary and figure
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
from independent import cases
from independent_check import CANDIDATES, case_record, named_effect

from jaxafm.diagnose import record as D
from jaxafm.instrument.records import Record

OUT = Path(__file__).parent / "results" / "stability"


def variants(record: Record) -> dict:
    """The record whole, cropped by 10 % at either end, and decimated by 2."""
    n = len(record.t)
    cut = {
        "whole": slice(None),
        "start cropped 10 %": slice(n // 10, None),
        "end cropped 10 %": slice(None, n - n // 10),
        "decimated by 2": slice(None, None, 2),
    }
    return {k: Record(record.t[s], record.u[s], record.d[s], record.meta) for k, s in cut.items()}


def _first_round(case: dict, levels: list, controls: int) -> bool:
    """A case of the independent check's first seed round (the same case, nominal class included)."""
    if case["effect"] is None:
        return case["seed"] < 10_000 + controls
    return case["level"] in levels and case["seed"] % 10 == 0


def run_case(case: dict) -> dict:
    spec = D.Nominal(kind=case["nominal_kind"])
    out = []
    for name, record in variants(case_record(case)).items():
        t0 = time.perf_counter()
        res = D.diagnose_record(record, spec, CANDIDATES, log=lambda s: None)
        out.append(
            {
                "variant": name,
                "samples": len(record.t),
                "verdict": res.verdict,
                "shape": res.shape,
                "heldout_gap_before_nm": res.nominal.heldout_gap_nm,
                "heldout_gap_final_nm": res.final.heldout_gap_nm,
                "seconds": time.perf_counter() - t0,
            }
        )
    whole = out[0]
    return case | {
        "variants": out,
        "verdict_flips": [v["variant"] for v in out[1:] if v["verdict"] != whole["verdict"]],
        "shape_flips": [v["variant"] for v in out[1:] if v["shape"] != whole["shape"]],
    }


def right(variant: dict, case: dict) -> bool:
    """As in the independent check (a control is right with no verdict)."""
    return named_effect(case["effect"], variant["verdict"], variant["shape"]) == case["effect"]


def summarise(rows: list) -> dict:
    names = [v["variant"] for v in rows[0]["variants"]][1:] if rows else []
    per_variant = {
        n: {
            "verdict_flips": sum(n in r["verdict_flips"] for r in rows),
            "shape_flips": sum(n in r["shape_flips"] for r in rows),
        }
        for n in names
    }
    return {
        "cases": len(rows),
        "variants_per_case": len(names),
        "cases_with_a_verdict_flip": sum(bool(r["verdict_flips"]) for r in rows),
        "verdict_flips": sum(len(r["verdict_flips"]) for r in rows),
        "shape_flips": sum(len(r["shape_flips"]) for r in rows),
        "per_variant": per_variant,
        "right_whole": sum(right(r["variants"][0], r) for r in rows),
        "right_all_variants": sum(all(right(v, r) for v in r["variants"]) for r in rows),
        "seconds_per_diagnosis_median": float(np.median([v["seconds"] for r in rows for v in r["variants"]])),
    }


def figure(rows: list, path: Path) -> None:
    """One row per case, one column per variant: the verdict and shape, red where it flipped."""
    names = [v["variant"] for v in rows[0]["variants"]]
    fig, ax = plt.subplots(figsize=(3.0 * len(names) + 3, 0.55 * len(rows) + 1.6))
    for i, r in enumerate(rows):
        for j, v in enumerate(r["variants"]):
            flip = v["verdict"] != r["variants"][0]["verdict"]
            color = "#f4a6a6" if flip else ("#cfe8cf" if right(v, r) else "#fbe3b0")
            ax.add_patch(plt.Rectangle((j, i), 1, 1, color=color, ec="w"))
            ax.text(
                j + 0.5,
                i + 0.5,
                f"{v['verdict'] or 'none'}\nshape {v['shape'] or '-'}",
                ha="center",
                va="center",
                fontsize=7,
            )
    ax.set_xlim(0, len(names))
    ax.set_ylim(len(rows), 0)
    ax.set_xticks(np.arange(len(names)) + 0.5, names)
    ax.set_yticks(
        np.arange(len(rows)) + 0.5,
        [
            f"{r['effect'] or 'control'} {r['level']} (truth {r['truth_hysteresis']}, "
            f"nominal {r['nominal_kind']})"
            for r in rows
        ],
        fontsize=8,
    )
    ax.tick_params(length=0)
    s = summarise(rows)
    ax.set_title(
        f"Verdict per record variant (green: right, amber: wrong as on the whole record, red: flipped); "
        f"verdict flips: {s['verdict_flips']} of {s['cases'] * s['variants_per_case']} variants",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", nargs="+", default=["middle"], help="low, middle, high")
    ap.add_argument("--controls", type=int, default=2)
    ap.add_argument(
        "--nominal",
        choices=("pi", "preisach"),
        default=None,
        help="only the cases with this nominal kind (writes rows-KIND-....json beside the others)",
    )
    ap.add_argument("--shard", default="1/1", help="K/N: every N-th case from the K-th")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--summarise", action="store_true", help="only rebuild summary.json and the figure")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    k, n = (int(v) for v in args.shard.split("/"))
    if not args.summarise:
        todo = [c for c in cases() if _first_round(c, args.levels, args.controls)]
        todo = [c for c in todo if args.nominal in (None, c["nominal_kind"])][k - 1 :: n]
        tag = f"-{args.nominal}" if args.nominal else ""
        rows, saved = [], args.out / f"rows{tag}-{k}-of-{n}.json"
        for i, case in enumerate(todo):
            row = run_case(case)
            rows.append(row)
            saved.write_text(json.dumps(rows, indent=1))
            print(
                f"[{i + 1}/{len(todo)}] {case['effect'] or 'control'} {case['level']} "
                f"(truth {case['truth_hysteresis']}, nominal {case['nominal_kind']}): "
                + ", ".join(f"{v['variant']} {v['verdict']}/{v['shape']}" for v in row["variants"])
                + f"; flips {row['verdict_flips'] or 'none'}",
                flush=True,
            )
    rows = [r for f in sorted(args.out.glob("rows-*.json")) for r in json.loads(f.read_text())]
    rows.sort(key=lambda r: (r["effect"] is None, r["effect"] or "", r["seed"]))
    summary = summarise(rows)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    figure(rows, args.out / "stability.png")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
