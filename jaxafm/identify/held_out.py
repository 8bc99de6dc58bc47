"""Step A's held-out validation: half the lattice's sites, a checkerboard, are never fitted.

The features at the odd sites (lattice indices summing to an odd number) and the image around
them are held out (:func:`split_features`, :func:`split_masks`), so that every lattice row and
column keeps features for both axes. A fitted model is scored by how far it misplaces the
held-out features (:func:`held_out_errors`, :func:`held_out_rms`), and a stage that worsens that
beyond its uncertainty is not kept (:func:`judge_stage`); :func:`validate` summarises the
held-out features for the metrics.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .features import feature_centres, neighbour_distances, pitch_spread
from .fit import residual_values
from .image_ops import sample_at
from .scan_model import ScanModel
from .stages import image_residuals

Array = jax.Array


def split_features(found: list, hold_out: bool) -> tuple:
    """Per scan, per image, the features fitted and those held out: ``(train, test)``, each
    ``[[(rc, ij), ...], ...]``; held out are the odd sites of the lattice's checkerboard
    (none without ``hold_out``)."""
    held = [[(f.ij.sum(axis=1) % 2 == 1) & hold_out for f in images] for images in found]
    train = [[(f.rc[~h], f.ij[~h]) for f, h in zip(images, hs)] for images, hs in zip(found, held)]
    test = [[(f.rc[h], f.ij[h]) for f, h in zip(images, hs)] for images, hs in zip(found, held)]
    return train, test


def split_masks(model: ScanModel, scans: tuple, hold_out: bool) -> tuple:
    """``(train, held)``: per scan, (2, lines, pixels) weights of the image residuals, split
    like the features, as a checkerboard of lattice sites: a pixel where ``model`` puts the
    tip within 0.35 pitch (along both lattice axes) of a site whose indices sum to an even
    number trains, of an odd one it is held out; the 0.3 pitch between them is a guard band
    against the blur's reach. Without ``hold_out`` every pixel trains and ``held`` is ``None``."""
    train, held = [], []
    for scan in scans:
        if not hold_out:
            train.append(jnp.ones((2, scan.raster.lines, scan.raster.pixels)))
            continue
        q = np.stack([np.asarray(model.lattice.coordinates(p)) for p in model.paths(scan)])
        site = np.round(q)
        near = np.all(np.abs(q - site) < 0.35, axis=-1)
        odd = site.sum(axis=-1) % 2 == 1
        train.append(jnp.asarray(near & ~odd, dtype=float))
        held.append(jnp.asarray(near & odd, dtype=float))
    return tuple(train), (tuple(held) if hold_out else None)


def held_out_image(model: ScanModel, scans: tuple, kernel: Array, held: tuple) -> float:
    """The rms of the blurred image residual over the held-out pixels, % of the depth: an image
    stage's compiled residuals (:func:`~jaxafm.identify.stages.image_residuals`) with the
    held-out masks in place of the training ones, so nothing is compiled again."""
    model = model.as_float64()
    raw = model.free_parameters(scans[0])[0]
    r = residual_values(image_residuals, raw, (model, scans, (kernel, held)))
    return 100 * float(np.sqrt(np.sum(r**2) / sum(float(jnp.sum(h)) for h in held)))


def judge_stage(before: list, after: float, test: list) -> tuple:
    """``(keep, words)``: an image stage is kept unless it raises the held-out feature residual
    (nm) beyond the best so far over all scans (``before``) by more than that residual's own
    uncertainty, 3 / sqrt(2 n) of it for n held-out features (the standard error of an rms is
    about rms / sqrt(2 n)): a stage that left the feature fit's valley misplaces the features
    by a large part of a pitch, far beyond that."""
    n = sum(len(rc) for images in test for rc, _ in images)
    best = min(before, default=np.inf)
    if not n or after <= best * (1 + 3 / np.sqrt(2 * n)) or not np.isfinite(best):
        return True, ""
    return False, f"; REJECTED: the held-out features got worse ({best:.2f} -> {after:.2f} nm)"


def held_out_errors(model: ScanModel, scans: tuple, test: list) -> np.ndarray:
    """How far (nm, (n, 2)) the model misplaces each held-out feature: where the model puts the
    tip at the feature's centre in the measured image, less where it puts it at the same
    feature's centre in the model's own image, both centres found alike
    (:func:`~jaxafm.identify.features.feature_centres`, ``smooth``). A perfect model scores the image
    noise only: the sub-pixel bias of a centroid (a few % of a pixel) is the same in both
    images and cancels, which a distance to the lattice site would not. Infinite where the
    model's image shows no features."""
    sign = -1.0 if scans[0].pits else 1.0
    out = []
    for scan, images in zip(scans, test):
        if not any(len(rc) for rc, _ in images):
            continue
        image = model.image(scan)  # its tip path is paths()'s: the heights do not move the tip
        for (rc, _), path, z, measured in zip(
            images,
            (image.path_trace, image.path_retrace),
            (image.trace, image.retrace),
            (scan.trace, scan.retrace),
        ):
            if not len(rc):
                continue
            mine = feature_centres(sign * np.asarray(measured), scan.name, smooth=True)
            rc = mine[np.argmin(np.linalg.norm(rc[:, None] - mine[None], axis=-1), axis=1)]
            try:
                own = feature_centres(sign * np.asarray(z), f"the model's image of {scan.name}", smooth=True)
            except ValueError:  # a model whose image shows no lattice misplaces every feature
                out.append(np.full((len(rc), 2), np.inf))
                continue
            nearest = own[np.argmin(np.linalg.norm(rc[:, None] - own[None], axis=-1), axis=1)]
            out.append(sample_at(path, rc) - sample_at(path, nearest))
    return np.concatenate(out) if out else np.zeros((0, 2))


def held_out_rms(model: ScanModel, scans: tuple, test: list) -> float:
    """The rms length (nm) of :func:`held_out_errors`; NaN when no feature is held out."""
    e = held_out_errors(model, scans, test)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else float("nan")


def validate(model: ScanModel, scans: tuple, test: list) -> dict:
    """The held-out features, as flat metrics: how many, their rms residual (nm,
    :func:`held_out_rms`), and the spread of the local pitch between held-out features two sites
    apart along a row (the nearest in a checkerboard) raw (at their nominal positions) and
    corrected (where the model puts the tip at them), % of the mean."""
    raw, corrected = [], []
    for scan, images in zip(scans, test):
        for (rc, ij), path in zip(images, model.paths(scan)):
            if len(rc):
                raw.append(neighbour_distances(scan.raster.nominal(rc), ij, step=2))
                xy = sample_at(path, rc)
                corrected.append(neighbour_distances(xy, ij, step=2))
    n = sum(len(rc) for images in test for rc, _ in images)
    if not n:
        return {"held_out_features": 0}
    out = {"held_out_features": n, "held_out_rms_nm": held_out_rms(model, scans, test)}
    for name, d in (("raw", raw), ("corrected", corrected)):
        d = np.concatenate(d)
        if len(d) > 1:
            out[f"held_out_pitch_std_{name}_pct"] = pitch_spread(d)["pitch_std_pct"]
    return out
