"""The single-image diagnosis on real 2-D lattice images: three lattices, trace and retrace.

    python experiments/real_lattice.py [--out experiments/results/real_lattice]

The shipped Nanosurf easyScan 2 images (jaxafm/data/real/README.md: square pits, round pits and
round pillars of one 10 um lattice, 50 um x 50 um, 256 x 256 px, forward and backward frames)
each diagnosed from the hysteresis-only scanner with ``kind: lattice`` (the rows' tilt taken as
the lattice's turn; coupling, bow and creep as candidates), as ``jaxafm diagnose
configs/diagnose_real_lattice.yaml`` does for one of them. Prints and writes a table
(``metrics.json``) of the verdict, the turn, the gaps and the fitted skew beyond the turn, and
``real_lattice.png``: each frame with its residual before and after the verdict.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import jaxafm
from jaxafm.diagnose.core import Rules
from jaxafm.diagnose.image import diagnose_image
from jaxafm.instrument.images import read_image

REAL = Path(jaxafm.__file__).parent / "data" / "real"
IMAGES = ("square_pits", "round_pits", "round_pillars")
PITCH_NM = 10_000.0
CANDIDATES = ("coupling", "bow", "creep")


def row(res) -> dict:
    """One frame's line of the table."""
    top = res.top
    return {
        "verdict": res.verdict,
        "turn_deg": float(np.degrees(np.arctan(res.data.row_tilt))),
        "chords_train": res.data.describe()["train_samples"],
        "chords_heldout": res.data.describe()["heldout_samples"],
        "nominal_heldout_gap_nm": res.nominal.heldout_gap_nm,
        "verdict_heldout_gap_nm": top.heldout_gap_after_nm if top else res.nominal.heldout_gap_nm,
        "verdict_shrink_pct": top.shrink_pct if top else 0.0,
        "skew_beyond_turn": res.candidates[[c.effect for c in res.candidates].index("coupling")].fit.fitted[
            "skew"
        ],
        "shape_slope": res.nominal.fitted["shape"],
        "candidates": {c.effect: [c.shrink_pct, c.delta_bic, bool(c.significant)] for c in res.candidates},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("experiments/results/real_lattice"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    table, shown = {}, []
    for name in IMAGES:
        for direction in ("trace", "retrace"):
            image = read_image(REAL / f"lattice_{name}_nanosurf.nid", direction=direction)
            res = diagnose_image(image, CANDIDATES, 0.6, Rules(), kind="lattice", pitch_nm=PITCH_NM)
            table[f"{name} {direction}"] = r = row(res)
            shown.append((f"{name} {direction}", image, res))
            print(
                f"{name:14s} {direction:8s} verdict {r['verdict']}: turn {r['turn_deg']:.2f} deg, held-out gap "
                f"{r['nominal_heldout_gap_nm']:.0f} -> {r['verdict_heldout_gap_nm']:.0f} nm "
                f"({r['verdict_shrink_pct']:.1f} %), skew beyond the turn {r['skew_beyond_turn']:.4f}, "
                f"chords {r['chords_train']} + {r['chords_heldout']}"
            )
    (args.out / "metrics.json").write_text(json.dumps(table, indent=1))
    fig, axes = plt.subplots(3, 6, figsize=(24, 12.5))
    for k, (label, image, res) in enumerate(shown):
        a = axes[0, k]
        lo, hi = np.percentile(image.z, (1, 99))  # a few clipped spikes would set the scale
        a.imshow(
            image.z, origin="lower", extent=np.array(image.extent) / 1e3, cmap="afmhot", vmin=lo, vmax=hi
        )
        a.set(title=label, xlabel="x [µm]", ylabel="y [µm]")
        e, top = res.data.edges, res.top
        lim = 3 * res.nominal.heldout_gap_nm
        for a, fit, what in (
            (axes[1, k], res.nominal, "nominal"),
            (axes[2, k], top.fit if top else None, "verdict"),
        ):
            if fit is None:
                a.set_axis_off()
                continue
            a.scatter(e.x_nm / 1e3, e.y_nm / 1e3, c=fit.residual, s=4, cmap="coolwarm", vmin=-lim, vmax=lim)
            gap = fit.heldout_gap_nm
            a.axhline(res.data.first_heldout_row * image.pixel_size[1] / 1e3, color="k", ls="--", lw=0.8)
            a.set(
                xlim=axes[0, k].get_xlim(),
                ylim=axes[0, k].get_ylim(),
                xlabel="x [µm]",
                title=f"{what}"
                + (f" + {top.effect}" if what == "verdict" else "")
                + f": held-out {gap:.0f} nm",
            )
    fig.suptitle(
        "Real 2-D lattices (Nanosurf easyScan 2, 10 µm pitch): chord-midpoint residuals [nm, colour "
        "+-3x the nominal gap], held out above the dashed line",
        fontsize=13,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(args.out / "real_lattice.png", dpi=70)
    print(f"wrote {args.out}/metrics.json and real_lattice.png")


if __name__ == "__main__":
    main()
