"""Step A's held-out validation: half the lattice's sites, a checkerboard, are never fitted.

The features at the odd sites (lattice indices summing to an odd number), their chords and the
image around them are held out (:func:`split_chords`, :func:`split_masks`), so that every lattice
row and column keeps features for both axes. A fitted model is scored by how far it misplaces
the held-out features (:func:`held_out_errors`, :func:`held_out_rms`): each feature's centre is
where its chords' midpoints put it, the chords placed where the model's tip was when it crossed
them (:func:`chord_centres`), less its lattice site. An image stage that worsens that beyond its
uncertainty is not kept (:func:`judge_stage`; with no site held out, the training features
judge). The same centres at the images' nominal pixel positions, on the lattice that fits the
training features best, are the raw image's score (:func:`raw_errors`); :func:`validate` puts
both side by side for the metrics.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .features import neighbour_distances, pitch_spread
from .fit import residual_values
from .image_ops import interpolate
from .scan_model import ScanModel
from .stages import chord_linearisation, image_residuals

Array = jax.Array


def split_chords(found: list, hold_out: bool) -> tuple:
    """Per scan, per image, the chords fitted and those held out: ``(train, test)``, each
    ``[[(ends, ij, along_lines), ...], ...]`` (chord ends (n, 2, 2) fractional pixels, their
    features' lattice indices, their direction); held out are the chords of the odd sites of the
    lattice's checkerboard (none without ``hold_out``)."""
    train, test = [], []
    for images in found:
        train.append([])
        test.append([])
        for f in images:
            ij = f.chord_indices()
            held = (ij.sum(axis=1) % 2 == 1) & hold_out
            for part, keep in ((train, ~held), (test, held)):
                part[-1].append((f.chords.ends[keep], ij[keep], f.chords.along_lines[keep]))
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


TRAINING_SLACK_PX = 0.25
"""How far (pixels) an image stage may raise the training features' residual beyond its own
uncertainty and still be kept. The chord stage fitted those features, down to or below what a
perfect model scores from the images (the true tip path of the simulated AFM places the features
to 0.11, 0.05 and 0.02 px rms at 64, 128 and 256 px over 8 um, :func:`path_floor`, while the
chord fit reaches 0.015 px at 256 px), so a stage that brings the tip path closer may raise them by a
few hundredths of a pixel (the 256² step A bench: 0.47 -> 0.98 nm while the tip path goes from
36.3 to 2.8 nm). A stage that left the chord fit's valley misplaces them by a large part of a
pitch, tens of pixels."""


def judge_stage(
    before: list, after: float, features: list, which: str = "held-out", pixel_nm: float = 0.0
) -> tuple:
    """``(keep, words)``: an image stage is kept unless it raises the feature residual (nm) of
    ``features`` (:func:`split_chords`'s ``test``, or its ``train`` when no site is held out;
    ``which`` names them) beyond the best so far over all scans (``before``) by more than that
    residual's own uncertainty, 3 / sqrt(2 n) of it for n features (the standard error of an rms is
    about rms / sqrt(2 n)): a stage that left the chord fit's valley misplaces the features by a
    large part of a pitch, far beyond that. The training features, which the chord stage fitted,
    allow :data:`TRAINING_SLACK_PX` of the images' ``pixel_nm`` more."""
    n = sum(len(np.unique(ij, axis=0)) for images in features for _, ij, _ in images)
    best = min(before, default=np.inf)
    slack = TRAINING_SLACK_PX * pixel_nm if which == "training" else 0.0
    if not n or after <= best * (1 + 3 / np.sqrt(2 * n)) + slack or not np.isfinite(best):
        return True, ""
    return False, f"; REJECTED: the {which} features got worse ({best:.2f} -> {after:.2f} nm)"


def holds_features(part: list) -> bool:
    """Whether :func:`split_chords`'s ``part`` holds any chord."""
    return any(len(ij) for images in part for _, ij, _ in images)


def chord_centres(tips: np.ndarray, ij: np.ndarray, along: np.ndarray, slope) -> tuple:
    """Each feature's centre (nm) from its chords' ends at ``tips`` (n, 2, 2) nm: the point ``c``
    that best satisfies ``a . (m - c) = 0`` over the feature's chords (``m`` a chord's midpoint,
    ``a = d - s p`` as in :meth:`~jaxafm.identify.scan_model.ScanModel.chord_offsets`), in the
    least-squares sense. Returns ``(indices (m, 2), centres (m, 2))``, one row per feature."""
    tips = np.asarray(tips, dtype=float)
    mid = tips.mean(axis=1)
    d = tips[:, 1] - tips[:, 0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = d - np.where(along, slope[0], slope[1])[:, None] * np.stack([-d[:, 1], d[:, 0]], axis=-1)
    keys, which = np.unique(np.asarray(ij), axis=0, return_inverse=True)
    centres = np.empty((len(keys), 2))
    for k in range(len(keys)):
        rows = which.ravel() == k
        centres[k] = np.linalg.lstsq(a[rows], np.sum(a[rows] * mid[rows], axis=1), rcond=None)[0]
    return keys, centres


def model_centres(model: ScanModel, scans: tuple, part: list) -> list:
    """Per scan, per image, the features of ``part`` (:func:`split_chords`) placed by the model:
    :func:`chord_centres` of their chords where its tip crossed them, ``(indices, centres)``."""
    slope = np.asarray(model.chord_slope)
    return [
        [chord_centres(*image, slope) for image in images] for images in placed_chords(model, scans, part)
    ]


def placed_chords(model, scans: tuple, part: list) -> list:
    """Per scan, per image of ``part`` (:func:`split_chords`) that holds chords, ``(tips, ij,
    along)``: the chords' ends (n, 2, 2) nm where ``model``'s tip was when it crossed them (the
    edge delay earlier, :meth:`~jaxafm.identify.scan_model.ScanModel.chord_ends`), or at the
    images' nominal pixel positions when ``model`` is None (the instrument's own calibration:
    what the raw images say), with their features' lattice indices and directions."""
    out = []
    for scan, images in zip(scans, part):
        out.append([])
        if model is None:
            paths, shift = [None, None], 0.0
        else:
            paths, shift = model.paths(scan), float(model.edge_delay) / scan.raster.sample_time
        for path, (ends, ij, along), forward in zip(paths, images, (1.0, -1.0)):
            if not len(ends):
                continue
            if model is None:
                tips = scan.raster.nominal(np.asarray(ends).reshape(-1, 2)).reshape(-1, 2, 2)
            else:
                tips = model.chord_ends(path, ends, forward * shift, np)  # NumPy: nothing to compile
            out[-1].append((np.asarray(tips), ij, along))
    return out


#: the fewest chords one way across a feature that give it a width (:func:`feature_widths`)
MIN_WIDTH_CHORDS = 3


def feature_widths(placed: list) -> tuple:
    """Per chord direction (along the lines, across them), every feature's width (nm) in every
    image of ``placed`` (:func:`placed_chords`): the median length of its chords that run that
    way, where it has :data:`MIN_WIDTH_CHORDS` or more. The features of a lattice are one shape,
    so their widths agree to the edges' noise where the tip path is right; the chord fit places
    only the chords' midpoints, so the widths are a check it has not trained on: a path that
    runs too fast or too slow across a feature shows as a feature too wide or too narrow."""
    out = ([], [])
    for images in placed:
        for tips, ij, along in images:
            length = np.linalg.norm(tips[:, 1] - tips[:, 0], axis=1)
            for way, sel in enumerate((np.asarray(along, bool), ~np.asarray(along, bool))):
                if not sel.any():
                    continue
                keys, which = np.unique(np.asarray(ij)[sel], axis=0, return_inverse=True)
                for k in range(len(keys)):
                    chords = length[sel][which.ravel() == k]
                    if len(chords) >= MIN_WIDTH_CHORDS:
                        out[way].append(float(np.median(chords)))
    return tuple(np.asarray(w) for w in out)


def fitted_parameters(model: ScanModel, scans: tuple, chords: tuple) -> float:
    """How many parameters the chord stage's data ``chords`` fix in ``model``: the trace of the
    hat matrix ``J (J^T J + P)^-1 J^T`` of its residuals, with a weak prior ``P`` (one order-one
    unit of each raw parameter, its natural scale, as unlikely as one standard deviation of the
    residuals), so that a direction the data do not fix does not count; a Preisach density's
    smoothness prior (:func:`~jaxafm.identify.stages.chord_linearisation`) joins ``P``, so a
    fine plane counts the shapes the data fix, not its relays."""
    return hat_trace(*chord_linearisation(model, scans, chords))


def hat_trace(r: np.ndarray, J: np.ndarray, smooth: np.ndarray) -> float:
    """:func:`fitted_parameters` from the chord stage's linearisation ``(r, J, smooth)``
    (:func:`~jaxafm.identify.stages.chord_linearisation`)."""
    H = J.T @ J + smooth + np.mean(r[np.any(J != 0, axis=1)] ** 2) * np.eye(J.shape[1])
    return float(np.trace(np.linalg.solve(H, J.T @ J)))


def held_out_errors(model: ScanModel, scans: tuple, test: list) -> np.ndarray:
    """How far (nm, (n, 2)) the model misplaces each held-out feature (per image it shows in):
    its centre where the model puts the tip at its chords (:func:`model_centres`) less its
    lattice site. A perfect model scores the chords' noise and the features' own irregularity."""
    out = [
        c - np.asarray(model.lattice.sites(jnp.asarray(keys, dtype=float)))
        for images in model_centres(model, scans, test)
        for keys, c in images
    ]
    return np.concatenate(out) if out else np.zeros((0, 2))


def held_out_rms(model: ScanModel, scans: tuple, test: list) -> float:
    """The rms length (nm) of :func:`held_out_errors`; NaN when no feature is held out."""
    e = held_out_errors(model, scans, test)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else float("nan")


def path_floor(scans: tuple, paths: list, slope=(0.0, 0.0)) -> float:
    """What :func:`held_out_rms` would be for a model whose tip path is ``paths`` (per scan, its
    trace's and its retrace's (lines, pixels, 2) nm), the true one where it is known: every
    feature of every image placed from its chords where that tip crossed them
    (:func:`chord_centres`, the chords' midpoint ``slope``), less its lattice site after the one
    rigid motion per image (:func:`fit_sites`), rms nm. With the true path, what is left is the
    chords' noise, the features' irregularity and the pixels' quantisation of the edges: the
    floor no model can place the features below from these images."""
    errors = []
    for scan, (trace_path, retrace_path) in zip(scans, paths):
        trace, retraces = scan.feature_matches()
        for path, found in ((trace_path, trace), (retrace_path, retraces[0])):
            tips = interpolate(jnp.asarray(path), jnp.asarray(found.chords.ends).reshape(-1, 2))
            tips = np.asarray(tips).reshape(-1, 2, 2)
            keys, centres = chord_centres(tips, found.chord_indices(), found.chords.along_lines, slope)
            ideal = keys * np.asarray(scan.pitch)
            errors.append(centres - fit_sites(ideal, centres)(ideal))
    return _rms(np.concatenate(errors))


def nominal_centres(scans: tuple, part: list, slope) -> list:
    """:func:`model_centres` at the images' nominal pixel positions (the instrument's own
    calibration, no delay): what the raw images say."""
    return [[chord_centres(*image, slope) for image in images] for images in placed_chords(None, scans, part)]


def raw_errors(scans: tuple, train: list, test: list, slope) -> np.ndarray:
    """How far (nm, (n, 2)) the raw images misplace each held-out feature: its nominal centre
    (:func:`nominal_centres`) less its site on the lattice of known pitch that fits the training
    features' nominal centres best (a rotation and a translation, :func:`fit_sites`)."""
    pitch = np.asarray(scans[0].pitch)
    flat = lambda cs: [np.concatenate(v) for v in zip(*[kc for images in cs for kc in images])]
    keys, centres = flat(nominal_centres(scans, train, slope))
    sites = fit_sites(keys * pitch, centres)
    out = [c - sites(k * pitch) for images in nominal_centres(scans, test, slope) for k, c in images]
    return np.concatenate(out) if out else np.zeros((0, 2))


def fit_sites(ideal: np.ndarray, measured: np.ndarray):
    """The rotation and translation that carry points ``ideal`` (n, 2) nearest to ``measured``
    (least squares, Kabsch): ``sites(ideal) -> positions``."""
    mi, mm = ideal.mean(axis=0), measured.mean(axis=0)
    u, _, vt = np.linalg.svd((ideal - mi).T @ (measured - mm))
    r = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return lambda points: (np.asarray(points) - mi) @ r + mm


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def _spread(images: list) -> float:
    """The spread (% of the mean) of the distance between features two sites apart along a row
    (the nearest in a checkerboard) over ``images`` of ``(indices, centres)``."""
    d = [neighbour_distances(c, k, step=2) for scans in images for k, c in scans]
    d = np.concatenate(d) if d else np.zeros(0)
    return pitch_spread(d)["pitch_std_pct"] if len(d) > 1 else float("nan")


def _distance_errors(images: list, pitch: np.ndarray) -> np.ndarray:
    """Relative errors (%) of the distances between every two features of one image."""
    out = []
    for scans in images:
        for k, c in scans:
            a, b = np.triu_indices(len(k), 1)
            true = np.linalg.norm((k[a] - k[b]) * pitch, axis=1)
            out.append(100 * (np.linalg.norm(c[a] - c[b], axis=1) - true) / true)
    return np.concatenate(out) if out else np.zeros(0)


#: the chord directions of :func:`feature_widths`, as the metrics name them
WIDTH_WAYS = ("along", "across")


def width_metrics(raw: list, corrected: list) -> dict:
    """The mean (nm) and the spread (% of the mean) of the features' widths
    (:func:`feature_widths`) along the lines and across them, from the same chords placed ``raw``
    and ``corrected`` (:func:`placed_chords`), and how many widths each direction has."""
    out = {}
    for name, placed in (("raw", raw), ("corrected", corrected)):
        for way, w in zip(WIDTH_WAYS, feature_widths(placed)):
            out[f"feature_widths_{way}"] = len(w)
            out[f"feature_width_{way}_{name}_nm"] = float(np.mean(w)) if len(w) else float("nan")
            out[f"feature_width_spread_{way}_{name}_pct"] = (
                100 * float(np.std(w) / np.mean(w)) if len(w) > 1 else float("nan")
            )
    return out


def validate(model: ScanModel, scans: tuple, train: list, test: list) -> dict:
    """The held-out features, raw and corrected, as flat metrics: how many; their rms residual
    (nm, :func:`held_out_errors`, :func:`raw_errors`); the spread of the local pitch between
    held-out features two sites apart along a row, % of the mean; and the relative errors of the
    distances between held-out features (%, max and rms: the published calibrations' measure);
    and over every feature, trained on or held out, the spread of its width along the lines and
    across them, % of the mean, raw and corrected (:func:`feature_widths`), with how many widths
    each direction has."""
    n = sum(len({tuple(k) for k in ij}) for images in test for _, ij, _ in images)
    if not n:
        return {"held_out_features": 0}
    slope = np.asarray(model.chord_slope)
    pitch = np.asarray(scans[0].pitch)
    corrected, raw = model_centres(model, scans, test), nominal_centres(scans, test, slope)
    out = {
        "held_out_features": n,
        "held_out_rms_nm": _rms(held_out_errors(model, scans, test)),
        "held_out_raw_rms_nm": _rms(raw_errors(scans, train, test, slope)),
    }
    every = [
        [tuple(np.concatenate(pair) for pair in zip(a, b)) for a, b in zip(trained, held)]
        for trained, held in zip(train, test)
    ]
    out |= width_metrics(placed_chords(None, scans, every), placed_chords(model, scans, every))
    for name, images in (("raw", raw), ("corrected", corrected)):
        e = _distance_errors(images, pitch)
        out |= {
            f"held_out_pitch_std_{name}_pct": _spread(images),
            f"held_out_distance_error_max_{name}_pct": float(np.abs(e).max()) if len(e) else float("nan"),
            f"held_out_distance_error_rms_{name}_pct": float(np.sqrt(np.mean(e**2)))
            if len(e)
            else float("nan"),
        }
    return out
