"""Step A on a real lattice carrying artefacts it does not have: scars and dust.

Real AFM images often carry scars (the z feedback losing or regaining the surface for part of a
line) and dust (specks taller than the features). The shipped Nanosurf lattices happen to be
clean, so this experiment adds both to each image of a lattice, identifies it as its
``configs/calibrate_nanosurf_NAME.yaml`` says (``jaxafm calibrate``'s own reading and step A),
and compares the held-out features with the clean run's. It repeats the identification with
the outlier handling of ``jaxafm.identify.chords`` switched off, one part at a time
(:data:`HANDLING_OFF`): scars not looked for; the features' height from the 99.5th percentile
without the check against the mode (the median above half of it, dust included); pixels beyond
both of the lattice's levels (dust) not masked; a feature's chords kept when those left one way
all lie on one side of it. No truth is known: the held-out features, and the clean image's own
result, are the check.

The artefacts, drawn per image (seeded): ``--scars`` scars, each 1 to 3 lines tall, 40 to 120 px
long, 300 to 800 nm up or down, anywhere; dust over ``--dust`` of the image in specks of 3 x 3 px,
1.5 um tall (on a pit lattice: holes 1.5 um deep, what stands out of its features' side).

    python experiments/real_lattice_artefacts.py [--lattices round_pillars square_pits]

writes experiments/results/real_lattice_artefacts/metrics.json (two tables of docs/step_a.md) and
``artefacts.png``, one image of each lattice as step A got it. Where the loss with all handling
on lies (``breakdown``): the model fitted to the images with artefacts and the one fitted to
the clean images (identified here, as the committed run), each scored on the held-out chords of
both: the model fitted to the clean images scored on the chords with artefacts measures what
they do to the measurement, the other model on the clean chords what they do to the fit; and how
far the fit with artefacts itself predicts its held-out features' errors (``predicted_errors``).
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
from jaxafm.identify.held_out import held_out_errors, model_centres, split_chords
from jaxafm.identify.identifiability import point_predictions
from jaxafm.identify.stages import chord_data
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


#: the parts of the outlier handling switched off, one at a time (``none``: all on)
HANDLING_OFF = ("none", "scars", "dust", "dust_mask", "one_side")


@contextmanager
def handling(part: str):
    """``chords`` with one part of its outlier handling off: ``scars`` (none looked for),
    ``dust`` (the height from the 99.5th percentile without the mode check), ``dust_mask``
    (pixels beyond both of the lattice's levels not masked), ``one_side`` (a feature's chords
    kept when those left one way all lie on one side of it), or ``none`` off."""
    saved = chords._scars, chords._upper_mode, chords._beyond, chords._straddling
    if part == "scars":
        chords._scars = lambda image, labels, keep: np.zeros(labels.shape, bool)
    elif part == "dust":
        chords._upper_mode = lambda r, sd, bins=200: 0.0
    elif part == "dust_mask":
        chords._beyond = lambda n: np.zeros(n.shape, bool)
    elif part == "one_side":
        chords._straddling = lambda ends, feature, centres, axis: (ends, feature)
    try:
        yield
    finally:
        chords._scars, chords._upper_mode, chords._beyond, chords._straddling = saved


def dirty_scans(lattice: str, scars: int, dust: float, seed: int) -> tuple:
    """The lattice's config and its scans as ``jaxafm calibrate`` reads them, every image with
    ``scars`` scars and dust over a fraction ``dust`` (drawn from ``seed``)."""
    path = ROOT / "configs" / f"calibrate_nanosurf_{lattice}.yaml"
    cfg = load_config(path, CalibrateConfig)
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
    return cfg, scans


def identify(lattice: str, scars: int, dust: float, off: str, seed: int) -> tuple:
    """The lattice's configured identification on its images with the artefacts, ``off`` part of
    the outlier handling switched off: ``(metrics, scans, identification)``, the last ``None``
    where step A refused (the metrics say why)."""
    cfg, scans = dirty_scans(lattice, scars, dust, seed)
    jax.clear_caches()
    clear_caches()
    with handling(off):
        try:
            ident = identify_model(
                scans, cfg.models[0], cfg.solver, cfg.grating, log=lambda *_: None, measured=True
            )
        except ValueError as e:
            return {"refused": str(e)[:300]}, scans, None
        m = identification_metrics(ident)
        found = chords.find_chords(np.asarray(scans[0].trace), scans[0].pits)
    counts = {"features_found": len(found.centres), "features_with_chords": len(np.unique(found.feature))}
    return {k: m[k] for k in KEPT} | counts, scans, ident


def held_out_part(images: list) -> list:
    """The held-out features' chords of the scans whose :func:`matched_images` are ``images``,
    as step A splits them (``split_chords``)."""
    return split_chords(list(zip(images[::2], images[1::2])), True)[1]


def breakdown(lattice: str, dirty: tuple, args) -> dict:
    """Where the loss lies: the held-out features' rms residual (nm) of the model fitted to the
    images with artefacts and of the one fitted to the clean images, each scored on the held-out
    chords of both (``dirty``: ``(scans, ident)`` with the artefacts, all handling on)."""
    _, clean, ident = identify(lattice, 0, 0.0, "none", args.seed)  # no scar, no speck
    images = {"dirty": matched_images(dirty[0]), "clean": matched_images(clean)}
    held = {name: held_out_part(found) for name, found in images.items()}
    out = {"lattice": lattice}
    for model_name, model in (("dirty", dirty[1].model), ("clean", ident.model)):
        for chords_name, scans in (("dirty", dirty[0]), ("clean", clean)):
            e = held_out_errors(model, scans, held[chords_name])
            out[f"model_{model_name}_chords_{chords_name}_nm"] = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    out |= worst_features(dirty[1].model, clean, held["clean"], images)
    return out | predicted_errors(dirty[1], dirty[0], held["dirty"])


#: the family-wise level at which :func:`predicted_errors` bounds the held-out points' distances
FAMILY_LEVEL = 0.99


def predicted_errors(ident, scans: tuple, held: list, count: int = 4) -> dict:
    """How the fit itself predicts the errors of its held-out features (``held``: their chords on
    ``scans``), as step A's validation does (``point_predictions`` from its training chords): the
    median predicted sd (nm, the root of the covariance's trace) over the held-out points, and
    the ``count`` points furthest out, each with its error and predicted sd (nm) and its squared
    Mahalanobis distance ``d2`` against the bound a ``FAMILY_LEVEL`` ellipse sets for the largest of
    ``n`` points (the chi-square quantile of two degrees of freedom at ``1 - (1 - level) / n``)."""
    got = point_predictions(ident.model, scans, ident.chords, chord_data(held, scans, 1))
    sd = np.sqrt(np.trace(got.covariance, axis1=1, axis2=2))
    d2 = np.einsum("pi,pij,pj->p", got.offsets, np.linalg.inv(got.covariance), got.offsets)
    names = image_names(scans)
    worst = [
        (
            names[int(got.keys[i, 0])],
            [int(v) for v in got.keys[i, 1:]],
            float(np.hypot(*got.offsets[i])),
            float(sd[i]),
            float(d2[i]),
        )
        for i in np.argsort(-d2)[:count]
    ]
    return {
        "predicted_sd_median_nm": float(np.median(sd)),
        "predicted_worst": worst,
        "predicted_bound_d2": float(-2.0 * np.log((1.0 - FAMILY_LEVEL) / len(d2))),
    }


def worst_features(model, clean: tuple, held: list, images: dict, count: int = 4) -> dict:
    """Where ``model`` (fitted to the images with artefacts) misplaces the held-out features of
    the ``clean`` scans (``held``: their chords) most: the ``count`` worst (image, lattice
    indices (i, j), error nm), and per image the training sites (even i + j) that have chords in
    the clean image but none with the artefacts (``images``: each set's
    :func:`matched_images`)."""
    names = image_names(clean)
    keyed = [image for scan in model_centres(model, clean, held) for image in scan]
    errors = []
    for name, (keys, centres) in zip(names, keyed):
        e = centres - np.asarray(model.lattice.sites(np.asarray(keys, dtype=float)))
        errors += [(name, [int(k) for k in key], float(np.hypot(*d))) for key, d in zip(keys, e)]
    lost = {}
    for name, c, d in zip(names, images["clean"], images["dirty"]):
        sites = [{tuple(map(int, ij)) for ij in f.chord_indices() if sum(ij) % 2 == 0} for f in (c, d)]
        lost[name] = sorted(sites[0] - sites[1])
    return {"worst_held_out": sorted(errors, key=lambda r: -r[2])[:count], "training_sites_lost": lost}


def image_names(scans: tuple) -> list:
    """Every image's name in :func:`matched_images`' order: ``scan K trace``, ``scan K retrace``."""
    return [f"scan {k} {image}" for k in range(len(scans)) for image in ("trace", "retrace")]


def matched_images(scans: tuple) -> list:
    """Every image's features as step A matches them: per scan its trace's, then its retrace's."""
    return [f for t, r in (s.feature_matches(False) for s in scans) for f in (t, r[0])]


def figure(shown: dict) -> None:
    """``artefacts.png``: the trace image of each lattice in ``shown`` (name: scan) levelled as
    step A got it, the scars found, the features with chords and those left without."""
    fig, axes = plt.subplots(1, len(shown), figsize=(5 * len(shown), 4.9), squeeze=False)
    for ax, (lattice, scan) in zip(axes[0], shown.items()):
        found = chords.find_chords(np.asarray(scan.trace), scan.pits)
        view = found.image.levelled
        size = np.asarray(scan.raster.size) / 1000.0
        ax.imshow(view, origin="lower", cmap="afmhot", vmin=-0.2, vmax=1.5, extent=(0, size[0], 0, size[1]))
        ys, xs = np.nonzero(found.image.scars)
        px = size / np.array(view.shape[::-1])
        ax.plot(xs * px[0], ys * px[1], ",", color="cyan", alpha=0.6)
        c = found.centres[:, ::-1] * px
        chorded = np.isin(np.arange(len(c)), found.feature)
        ax.plot(c[chorded, 0], c[chorded, 1], "+", color="lime", ms=10, mew=1.5)
        ax.plot(c[~chorded, 0], c[~chorded, 1], "x", color="red", ms=9, mew=2)
        ax.set(title=f"{lattice.replace('_', ' ')}: trace with scars and dust")
        ax.set(xlabel="x (µm)", ylabel="y (µm)")
    fig.suptitle("levelled as step A got it; scars found: cyan; features: + (with chords), x (left without)")
    fig.tight_layout()
    fig.savefig(OUT / "artefacts.png", dpi=110)


def main() -> None:
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("--lattices", nargs="+", default=["round_pillars", "square_pits"])
    a.add_argument("--scars", type=int, default=12)
    a.add_argument("--dust", type=float, default=0.01)
    a.add_argument("--seed", type=int, default=0)
    args = a.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    rows, shown, parts = [], {}, []
    for lattice in args.lattices:
        clean = json.loads(
            (ROOT / f"experiments/results/calibrate_nanosurf_{lattice}/metrics.json").read_text()
        )
        clean_row = {k: clean[f"gpi_{k}"] for k in KEPT}
        rows.append({"lattice": lattice, "images": "clean (the committed run)", **clean_row})
        print(rows[-1], flush=True)
        for off in HANDLING_OFF:
            m, scans, ident = identify(lattice, args.scars, args.dust, off, args.seed)
            rows.append({"lattice": lattice, "images": "scars and dust", "handling_off": off, **m})
            print(rows[-1], flush=True)
            if off == "none" and ident is not None:
                shown[lattice] = scans[0]
                parts.append(breakdown(lattice, (scans, ident), args))
                print(parts[-1], flush=True)
    doc = {
        "command": "python experiments/real_lattice_artefacts.py",
        "args": vars(args),
        "rows": rows,
        "breakdown": parts,
    }
    (OUT / "metrics.json").write_text(json.dumps(doc, indent=1) + "\n")
    figure(shown)
    print(f"wrote {OUT / 'metrics.json'} and artefacts.png")


if __name__ == "__main__":
    main()
