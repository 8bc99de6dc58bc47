"""Step A on a real lattice carrying artefacts it does not have: scars and dust.

Real AFM images often carry scars (the z feedback losing or regaining the surface for part of a
line) and dust (specks taller than the features). The shipped Nanosurf lattices happen to be
clean, so this experiment adds both to each image of a lattice, identifies it as its
``configs/calibrate_nanosurf_NAME.yaml`` says (``jaxafm calibrate``'s own reading and step A),
and compares the held-out features with the clean run's. It repeats the identification with
the outlier handling of ``jaxafm.identify.chords`` switched off, one part at a time: scars not
looked for, and the features' height from the 99.5th percentile without the check against the
mode (the median above half of it, dust included). No truth is known:
the held-out features, and the clean image's own result, are the check.

The artefacts, drawn per image (seeded): ``--scars`` scars, each 1 to 3 lines tall, 40 to 120 px
long, 300 to 800 nm up or down, anywhere; dust over ``--dust`` of the image in specks of 3 x 3 px,
1.5 um tall (on a pit lattice: holes 1.5 um deep, what stands out of its features' side).

    python experiments/real_lattice_artefacts.py [--lattices round_pillars square_pits]

writes experiments/results/real_lattice_artefacts/metrics.json (a table of docs/step_a.md) and
``artefacts.png``, one image of each lattice as step A got it.
"""

from __future__ import annotations

import argparse
import json
from contextlib import contextmanager
from pathlib import Path

import equinox as eqx
import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from jaxafm.config import CalibrateConfig
from jaxafm.config.common import load_config
from jaxafm.identify import chords
from jaxafm.identify.fit import clear_caches
from jaxafm.jobs.calibrate import identification_metrics, identify_model, read_calibration

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "real_lattice_artefacts"
#: what the table keeps of each identification (``identification_metrics``' keys)
KEPT = ("held_out_rms_nm", "held_out_raw_rms_nm", "held_out_pitch_std_corrected_pct", "plausible")


def with_artefacts(z: np.ndarray, pits: bool, scars: int, dust: float, rng) -> np.ndarray:
    """``z`` (lines, pixels) nm with ``scars`` scars and specks of dust over a fraction ``dust``."""
    z = z.copy()
    lines, pixels = z.shape
    for _ in range(scars):
        tall, long = rng.integers(1, 4), rng.integers(40, 121)
        i, j = rng.integers(0, lines - tall), rng.integers(0, pixels - long)
        z[i : i + tall, j : j + long] += rng.choice([-1, 1]) * rng.uniform(300, 800)
    for _ in range(int(dust * z.size / 9)):
        i, j = rng.integers(1, lines - 1), rng.integers(1, pixels - 1)
        z[i - 1 : i + 2, j - 1 : j + 2] += -1500.0 if pits else 1500.0
    return z


@contextmanager
def handling(part: str):
    """``chords`` with one part of its outlier handling off: ``scars`` (none looked for),
    ``dust`` (the height from the 99.5th percentile without the mode check), or ``none`` off."""
    saved = chords._scars, chords._upper_mode
    if part == "scars":
        chords._scars = lambda image, labels, keep: np.zeros(labels.shape, bool)
    elif part == "dust":
        chords._upper_mode = lambda r, sd, bins=200: 0.0
    try:
        yield
    finally:
        chords._scars, chords._upper_mode = saved


def identify(lattice: str, scars: int, dust: float, off: str, seed: int) -> dict:
    """The lattice's configured identification on its images with the artefacts, ``off`` part of
    the outlier handling switched off."""
    path = ROOT / "configs" / f"calibrate_nanosurf_{lattice}.yaml"
    cfg = load_config(path, CalibrateConfig)
    jax.clear_caches()
    clear_caches()
    scans = read_calibration(cfg.data, cfg.grating, path, log=lambda *_: None)
    rng = np.random.default_rng(seed)
    scans = tuple(
        eqx.tree_at(
            lambda s: (s.trace, s.retrace),
            s,
            tuple(with_artefacts(np.asarray(z), s.pits, scars, dust, rng) for z in (s.trace, s.retrace)),
        )
        for s in scans
    )
    with handling(off):
        try:
            ident = identify_model(scans, cfg.models[0], cfg.solver, cfg.grating, log=lambda *_: None)
        except ValueError as e:
            return {"refused": str(e)[:300]}, scans
        m = identification_metrics(ident)
        found = chords.find_chords(np.asarray(scans[0].trace), scans[0].pits)
    return {k: m[k] for k in KEPT} | {"features_found": len(found.centres)}, scans


def main() -> None:
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("--lattices", nargs="+", default=["round_pillars", "square_pits"])
    a.add_argument("--scars", type=int, default=12)
    a.add_argument("--dust", type=float, default=0.01)
    a.add_argument("--seed", type=int, default=0)
    args = a.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    rows, shown = [], {}
    for lattice in args.lattices:
        clean = json.loads(
            (ROOT / f"experiments/results/calibrate_nanosurf_{lattice}/metrics.json").read_text()
        )
        clean_row = {k: clean[f"gpi_{k}"] for k in KEPT}
        rows.append({"lattice": lattice, "images": "clean (the committed run)", **clean_row})
        print(rows[-1], flush=True)
        for off in ("none", "scars", "dust"):
            m, scans = identify(lattice, args.scars, args.dust, off, args.seed)
            rows.append({"lattice": lattice, "images": "scars and dust", "handling_off": off, **m})
            print(rows[-1], flush=True)
            shown[lattice] = scans[0]
    doc = {"command": "python experiments/real_lattice_artefacts.py", "args": vars(args), "rows": rows}
    (OUT / "metrics.json").write_text(json.dumps(doc, indent=1) + "\n")
    fig, axes = plt.subplots(1, len(shown), figsize=(5 * len(shown), 4.6), squeeze=False)
    for ax, (lattice, scan) in zip(axes[0], shown.items()):
        found = chords.find_chords(np.asarray(scan.trace), scan.pits)
        view = found.image.levelled
        size = np.asarray(scan.raster.size) / 1000.0
        ax.imshow(view, origin="lower", cmap="afmhot", vmin=-0.2, vmax=1.5, extent=(0, size[0], 0, size[1]))
        ys, xs = np.nonzero(found.image.scars)
        px = size / np.array(view.shape[::-1])
        ax.plot(xs * px[0], ys * px[1], ",", color="cyan", alpha=0.6)
        c = found.centres[:, ::-1] * px
        ax.plot(c[:, 0], c[:, 1], "+", color="lime", ms=10, mew=1.5)
        ax.set(title=f"{lattice}: trace with scars and dust\n(levelled; scars found: cyan; features: +)")
        ax.set(xlabel="x (µm)", ylabel="y (µm)")
    fig.tight_layout()
    fig.savefig(OUT / "artefacts.png", dpi=110)
    print(f"wrote {OUT / 'metrics.json'} and artefacts.png")


if __name__ == "__main__":
    main()
