"""Chords of a calibration lattice's features: the image levelled, the features found, and where
every scan line (and every pixel column) enters and leaves each feature, to a fraction of a pixel.

Step A's chord stage fits these crossings instead of whole images or feature centroids: they do
not depend on the height background a real image carries (a plane tilt, a bow, the z feedback's
line-to-line offsets), and a lattice of a few features gives hundreds of them.

**Levelling** (:func:`level`). The height is modelled as ``z = s f + B + o_l + e``: the features
``f`` (0 on the surface, 1 on a pillar's top or a pit's floor) of height ``s``, a background ``B``
(a 2-D polynomial in Legendre form, :func:`background_design`), an offset ``o_l`` per scan line,
and noise. ``B`` and ``o_l`` are fitted to the surface pixels only, which are found again after
each fit (below half the feature height, and within five robust standard deviations of the
surface), so the features never bend the background. The height ``s`` is the features' level:
the median of the pixels above half the 99.5th percentile, unless dust taller than the features
owns that percentile (:func:`_feature_level`). What is left, divided by ``s``, is the
levelled image ``n``: about 0 on the surface and 1 on the features. Pixels that stand above (or
below) all four of their neighbours by more than eight robust standard deviations of the surface
and a quarter of the feature height (spikes), pixels more than half the feature height beyond
both the surface and the feature level (dust, a hole: no part of the lattice lies there), pixels
at the image's extreme value where a few share it (an amplifier's clipping), and scars (runs
along a line, at most three lines tall, that stand as far out of the lines around them:
:func:`_scars`) are outliers; a scar's pixels are mended from the lines around them before the
features are found (:meth:`LevelledImage.mended`).

**Features and chords** (:func:`find_chords`). A feature is a connected region where ``n > 1/2``
that touches no image edge and is not much smaller than the others (a spike is; the others'
typical size is taken over the regions that are not specks of dust, :data:`SPECK`). A chord is a run
of one scan line (or one pixel column) through a feature: its two ends are where ``n`` crosses
1/2, interpolated linearly between the two pixels on either side. A chord shorter than half the
feature's longest one grazes its rim, where the crossing is ill-defined, and is dropped, as is a
chord with an outlier at either end. A feature's chords one way fix its centre across them where
they lie on both sides of it (a lattice's features are point-symmetric: chords at mirrored lines
balance); where outliers took all of them on one side, those left may run along a wall, and the
feature keeps none that way. A feature without chords along the lines or along the columns keeps
none: its chords do not fix its centre. On request (``off_line_sd``), a chord whose midpoint lies
off the line its feature's other midpoints lie on is dropped too (:func:`_on_line`: a line by a
turned square's corner meets a third side).
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Optional

import numpy as np
from scipy import ndimage
from skimage import filters

#: a feature at most this fraction of the median feature's area is a spike or a fragment
MIN_FEATURE_AREA = 0.3
#: a region at most this fraction of the largest one's area is a speck (dust, a spike), not one
#: of the lattice's features, and is left out of the typical feature's area
SPECK = 0.1
#: a scar is at most this many lines tall, and is found against this many lines each side of it
SCAR_LINES = 3
#: a scar runs along its line for at least this many pixels (a spike is shorter)
SCAR_RUN = 8
#: a chord shorter than this fraction of its feature's longest chord (same direction) grazes the rim
MIN_CHORD = 0.5
#: the least robust sd (px) of the midpoints about their lines: an image without noise scatters them
#: by the edges' interpolation alone, and no chord is an outlier for lying a few hundredths off
OFF_LINE_FLOOR_PX = 0.05
#: the fewest chords one way across a feature whose midpoints :func:`_on_line` judges
OFF_LINE_CHORDS = 4
#: a pixel further than this (in feature heights) beyond the surface and the feature level is not
#: the lattice's (:func:`_beyond`)
BEYOND = 0.5
#: the background's polynomial order, Legendre in x and y (0: offset, 1: plane, 2: plus a bow)
BACKGROUND_ORDER = 2


@dataclasses.dataclass(frozen=True)
class LevelledImage:
    """An image levelled for its features (:func:`level`).

    Attributes:
        levelled: ``(z - background) / height`` (lines, pixels): 0 on the surface, 1 on the features.
        background: the fitted background and line offsets (lines, pixels) nm.
        height: the features' height above (pillars) or depth below (pits) the surface, nm.
        surface: the pixels the background was fitted to (lines, pixels).
        outliers: spikes, scars and clipped pixels (lines, pixels).
        noise_nm: the surface's robust standard deviation, nm.
        scars: the scars among the outliers (lines, pixels; :func:`_scars`), None where not
            looked for.
    """

    levelled: np.ndarray
    background: np.ndarray
    height: float
    surface: np.ndarray
    outliers: np.ndarray
    noise_nm: float
    scars: Optional[np.ndarray] = None

    def mended(self) -> np.ndarray:
        """``levelled`` with each scar's pixels replaced by the median of the lines around them
        that are not scars (:func:`_column_median`): what the lines show there."""
        if self.scars is None or not self.scars.any():
            return self.levelled
        return np.where(self.scars, _column_median(self.levelled, self.scars), self.levelled)


@dataclasses.dataclass(frozen=True)
class Chords:
    """The features and chords of one image (:func:`find_chords`).

    Attributes:
        ends: where each chord enters and leaves its feature, (n, 2, 2) fractional pixels
            (row, col), in the order the scan met them (along a line: left then right; along a
            column: bottom then top).
        feature: each chord's feature, an index into ``centres`` (n,).
        along_lines: whether a chord runs along a scan line (else along a pixel column) (n,).
        centres: each feature's centroid (features, 2) fractional pixels (row, col).
        image: the levelled image the chords were found in.
        spanning: how many regions run right across the image (a 1-D grating's lines do).
    """

    ends: np.ndarray
    feature: np.ndarray
    along_lines: np.ndarray
    centres: np.ndarray
    image: LevelledImage
    spanning: int = 0


def background_design(shape: tuple, order: int = BACKGROUND_ORDER) -> np.ndarray:
    """The background's columns (lines * pixels, k): the products ``P_a(x) P_b(y)`` of Legendre
    polynomials with ``a + b <= order``, x and y from -1 to 1 across the image."""
    lines, pixels = shape
    x = np.polynomial.legendre.legvander(np.linspace(-1, 1, pixels), order)  # (pixels, order + 1)
    y = np.polynomial.legendre.legvander(np.linspace(-1, 1, lines), order)
    cols = [np.outer(y[:, b], x[:, a]).ravel() for a in range(order + 1) for b in range(order + 1 - a)]
    return np.stack(cols, axis=-1)


def _robust_sd(v: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(v - np.median(v)))) if v.size else 0.0


def level(z: np.ndarray, pits: bool, name: str = "image", order: int = BACKGROUND_ORDER) -> LevelledImage:
    """Level ``z`` (lines, pixels) nm for its features (the module's equation).

    Raises:
        ValueError: naming the image, when no feature level stands out of the surface.
    """
    s = -np.asarray(z, dtype=float) if pits else np.asarray(z, dtype=float)
    lines, pixels = s.shape
    clipped = _clipped(s)
    if np.ptp(s[~clipped]) == 0:
        but = f" but {clipped.sum()} at its extreme value" if clipped.any() else ""
        raise ValueError(
            f"{name}: every pixel{but} has the height {np.asarray(z)[~clipped].flat[0]:.6g} nm: the image "
            "holds no features (an empty or saturated channel?)"
        )
    design = background_design(s.shape, order)
    surface = ~clipped
    offsets = np.zeros(lines)
    for i in range(10):
        w = surface.ravel()
        coef = np.linalg.lstsq(design[w], (s - offsets[:, None]).ravel()[w], rcond=None)[0]
        r = s - (design @ coef).reshape(s.shape)
        if i:  # line offsets once the features are out of the surface
            offsets = np.array(
                [np.median(r[k][surface[k]]) if surface[k].sum() > pixels // 4 else 0.0 for k in range(lines)]
            )
            offsets -= np.median(offsets)
        r = r - offsets[:, None]
        r -= np.median(r[surface])
        sd = _robust_sd(r[surface])
        height = _feature_level(r[~clipped], sd)
        new = (r < 0.5 * height) & (np.abs(r) < max(5 * sd, 0.02 * height)) & ~clipped
        if np.array_equal(new, surface) or new.sum() <= design.shape[1]:  # converged, or no surface left
            break
        surface = new
    rounding = 1e-6 * np.ptp(s)  # features of round-off on a noiseless plane
    if not height > max(10 * sd, rounding):
        if height > rounding and (lines := _spanning(r)) >= 3:  # round-off's streaks are no grating
            raise ValueError(
                f"{name}: {lines} features run right across the image: it shows the lines of a 1-D "
                "grating, not a lattice of separate pits or pillars. Step A identifies both axes from a "
                "2-D lattice; a 1-D grating shows only the axis across its lines "
                "(jaxafm.identify.line_grating.fit_line_grating fits that)"
            )
        raise ValueError(
            f"{name}: no feature level stands out of the surface after levelling (features "
            f"{height:.3g} nm, surface noise {sd:.3g} nm): is it a lattice of "
            f"{'pits' if pits else 'pillars'}? (grating.pits)"
        )
    spikes = _spikes(r, _outlier_step(sd, height))
    background = (s - r) * (-1.0 if pits else 1.0)
    return LevelledImage(r / height, background, height, surface, spikes | clipped | _beyond(r / height), sd)


def _beyond(n: np.ndarray) -> np.ndarray:
    """Pixels of the levelled image ``n`` further than :data:`BEYOND` beyond both of the lattice's
    levels (0 and 1): dust on the surface, a speck on a pillar, a hole in a pit's floor."""
    return (n > 1 + BEYOND) | (n < -BEYOND)


def _outlier_step(sd: float, height: float) -> float:
    """How far (nm) a spike or a scar stands out of what is around it."""
    return max(8 * sd, 0.25 * height)


def _feature_level(r: np.ndarray, sd: float) -> float:
    """The features' level in the levelled heights ``r`` (nm, surface at 0): the median of the
    pixels above half the 99.5th percentile. Where tall outliers (dust on the surface, 0.5 % of
    the image or more) own that percentile, the level found is not within a quarter of the main
    mode of the heights above the surface (:func:`_upper_mode`), and the pixels above 1.5 times
    that mode are left out of the percentile."""
    level = lambda v: float(np.median(v[v > 0.5 * np.percentile(v, 99.5)])) if v.size else 0.0
    height, mode = level(r), _upper_mode(r, sd)
    if mode > 0 and not 0.75 * mode < height < 1.25 * mode:
        height = level(r[r < 1.5 * mode])
    return height


def _upper_mode(r: np.ndarray, sd: float, bins: int = 200) -> float:
    """The most common height (nm) of the pixels above the surface (by five of its standard
    deviations, and 1 % of the 99.5th percentile: not its round-off when it has no noise): a
    histogram of ``bins`` bins, smoothed over five; 0 with too few pixels."""
    v = r[r > max(5 * sd, 0.01 * np.percentile(r, 99.5))]
    if v.size < 5 * bins:
        return 0.0
    hist, edges = np.histogram(v, bins=bins)
    smooth = np.convolve(hist, np.ones(5) / 5, mode="same")
    return float(0.5 * (edges[:-1] + edges[1:])[np.argmax(smooth)])


def _spanning(r: np.ndarray) -> int:
    """How many regions above the image's Otsu level run right across it, top to bottom or side
    to side (the lines of a 1-D grating do)."""
    labels, _ = ndimage.label(r > filters.threshold_otsu(r))
    across = np.union1d(np.intersect1d(labels[0], labels[-1]), np.intersect1d(labels[:, 0], labels[:, -1]))
    return len(np.setdiff1d(across, [0]))


def _spikes(r: np.ndarray, step: float) -> np.ndarray:
    """Pixels above (or below) all four neighbours by more than ``step``: a feature's edge pixel
    has a neighbour on its own level, a spike none."""
    p = np.pad(r, 1, mode="edge")
    near = np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])
    return np.all(r - near > step, axis=0) | np.all(near - r > step, axis=0)


def _scars(image: LevelledImage, labels: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Pixels of scars (the z feedback losing or regaining the surface for part of a line): at
    most :data:`SCAR_LINES` lines tall, they stand out of the median of the lines around them
    (:func:`_column_median`) by more than a spike does, for a run of at least :data:`SCAR_RUN`
    pixels along the line; two such runs of one line at most ``2 SCAR_RUN`` pixels apart are
    one scar (crossing a wall, where it may not stand out), and from there a scar reaches along
    its line as far as it stands out by a quarter of that, across gaps of up to four pixels.
    Found twice: the second time against the medians without the scars found the first time
    (a scar's own lines may bend the median beside it, on a wall). A feature's wall is never
    one: across a wall a column's heights are monotone, and the middle one of a monotone run is
    its median. Looked for only where the features ``keep`` (of ``labels``) are taller than that
    median's window: in a lattice of shorter ones a scar cannot be told from a row of features."""
    boxes = ndimage.find_objects(labels)
    tall = np.median([boxes[k - 1][0].stop - boxes[k - 1][0].start for k in keep]) if len(keep) else 0
    scars = np.zeros(labels.shape, bool)
    if tall <= 2 * SCAR_LINES + 1:
        return scars
    r = image.levelled * image.height
    for _ in range(2):
        off = np.abs(r - _column_median(r, scars)) / _outlier_step(image.noise_nm, image.height)
        core = ndimage.binary_opening(off > 1, structure=np.ones((1, SCAR_RUN), bool)) | scars
        core = ndimage.binary_closing(core, structure=np.ones((1, 2 * SCAR_RUN + 1), bool), border_value=0)
        reach = ndimage.binary_closing(off > 0.25, structure=np.ones((1, 5), bool), border_value=0) | core
        scars = ndimage.binary_propagation(core, structure=np.ones((1, 3), bool), mask=reach)
        if not scars.any():
            break
    return scars


def _column_median(r: np.ndarray, left_out: np.ndarray) -> np.ndarray:
    """The median of each pixel's column over the lines around it, :data:`SCAR_LINES` each side
    and its own (beyond the image's first and last line: those lines again), the ``left_out``
    pixels left out (where all are: the pixel's own value)."""
    k = SCAR_LINES
    padded = np.pad(np.where(left_out, np.nan, r), ((k, k), (0, 0)), mode="edge")  # as the first line
    window = np.stack([padded[i : i + r.shape[0]] for i in range(2 * k + 1)])
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN window: its own value below
        median = np.nanmedian(window, axis=0)
    return np.where(np.isnan(median), r, median)


def _clipped(s: np.ndarray) -> np.ndarray:
    """Pixels at the image's highest or lowest value where a few (2 to 1 % of the image) share it:
    an amplifier's clipping; a plateau that many pixels share is the image's own level."""
    out = np.zeros(s.shape, bool)
    for v in (s.max(), s.min()):
        at = s == v
        if 1 < at.sum() <= 0.01 * s.size:
            out |= at
    return out


def find_chords(
    z: np.ndarray, pits: bool, name: str = "image", off_line_sd: Optional[float] = None
) -> Chords:
    """The features and chords of the lattice image ``z`` (lines, pixels) nm (the module's rules);
    an image of no complete feature gives none. With ``off_line_sd``, a chord whose midpoint lies
    further than that many robust sds off its feature's line of midpoints is dropped too
    (:func:`_on_line`: it meets a third side, as a turned square's top or bottom).

    Raises:
        ValueError: naming the image, when no feature level stands out of it (:func:`level`).
    """
    image = level(z, pits, name)
    labels, count, keep = _features(image.levelled)
    scars = _scars(image, labels, keep)
    image = dataclasses.replace(image, outliers=image.outliers | scars, scars=scars)
    n = image.mended()  # a scar is neither a feature nor a gap in one
    if scars.any():
        labels, count, keep = _features(n)
    spanning = _spanning(n)
    centres = np.array(ndimage.center_of_mass(n > 0.5, labels, keep)).reshape(-1, 2)
    index = np.full(count + 1, -1)
    index[keep] = np.arange(len(keep))
    runs = [
        _runs(n, labels, image.outliers, index, along_lines, off_line_sd) for along_lines in (True, False)
    ]
    runs = [_straddling(*run, centres, axis) for axis, run in enumerate(runs)]
    both = np.intersect1d(runs[0][1], runs[1][1])  # the features whose chords fix both coordinates
    runs = [(e[np.isin(f, both)], f[np.isin(f, both)]) for e, f in runs]
    ends = np.concatenate([r[0] for r in runs])
    feature = np.concatenate([r[1] for r in runs])
    along = np.concatenate([np.full(len(r[1]), k == 0) for k, r in enumerate(runs)])
    return Chords(ends, feature, along, centres, image, spanning)


def _features(n: np.ndarray) -> tuple:
    """``(labels, count, keep)``: the regions where the levelled image ``n > 1/2`` and the
    labels of those that are features (the module's rules)."""
    labels, count = ndimage.label(n > 0.5)
    ids = np.arange(1, count + 1)
    area = ndimage.sum_labels(np.ones_like(n), labels, ids)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    inside = ~np.isin(ids, edge)
    lattice = inside & (area > SPECK * area.max(initial=0.0, where=inside))  # not dust or spikes
    typical = np.median(area[lattice]) if lattice.any() else 0.0
    return labels, count, ids[inside & (area > MIN_FEATURE_AREA * typical)]


def _straddling(ends: np.ndarray, feature: np.ndarray, centres: np.ndarray, axis: int) -> tuple:
    """``(ends, feature)`` of the chords (along the lines: ``axis`` 0, their rows; along the
    columns: 1) of the features that have chords on both sides of their ``centres``."""
    side = np.sign(ends[:, 0, axis] - centres[feature, axis])
    below, above = np.zeros((2, len(centres)), bool)
    below[feature[side <= 0]] = True  # a chord through the centre balances itself
    above[feature[side >= 0]] = True
    keep = (below & above)[feature]
    return ends[keep], feature[keep]


def _runs(n, labels, outliers, index, along_lines: bool, off_line_sd: Optional[float] = None) -> tuple:
    """The chords along the lines (rows) or the pixel columns: ends (m, 2, 2) (row, col) and
    features (m,), those grazing a rim or ending at an outlier dropped, and with ``off_line_sd``
    those off their features' lines (:func:`_on_line`)."""
    if not along_lines:
        n, labels, outliers = n.T, labels.T, outliers.T
    ends, feature = [], []
    for k, row in enumerate(n):
        above = row > 0.5
        starts = np.flatnonzero(~above[:-1] & above[1:]) + 1
        stops = np.flatnonzero(above[:-1] & ~above[1:])
        for a in starts:
            b = stops[stops >= a]
            if not len(b):
                break
            b = b[0]
            f = index[labels[k, a]]
            if f < 0 or outliers[k, a - 1 : a + 1].any() or outliers[k, b : b + 2].any():
                continue
            left = a - 1 + (0.5 - row[a - 1]) / (row[a] - row[a - 1])
            right = b + (row[b] - 0.5) / (row[b] - row[b + 1])
            ends.append([[k, left], [k, right]])
            feature.append(f)
    ends = np.asarray(ends, dtype=float).reshape(-1, 2, 2)
    feature = np.asarray(feature, dtype=int)
    length = ends[:, 1, 1] - ends[:, 0, 1]
    longest = np.zeros(index.max() + 1)
    np.maximum.at(longest, feature, length)
    keep = length > MIN_CHORD * longest[feature]
    if off_line_sd is not None:
        keep[keep] = _on_line(ends[keep], feature[keep], off_line_sd)
    ends, feature = ends[keep], feature[keep]
    return (ends if along_lines else ends[..., ::-1]), feature


def _on_line(ends: np.ndarray, feature: np.ndarray, sds: float) -> np.ndarray:
    """Which chords (m,) of one way (``ends`` (m, 2, 2) (line, position along it)) have their
    midpoints within ``sds`` robust sds of their feature's line of midpoints.

    The chords of a point-symmetric feature that cross the same two sides have their midpoints on
    one line (``ScanModel.chord_offsets``), and so have a feature's chords under any path that is
    affine across the feature. Where a line meets a third side (the top or bottom of a square
    turned a few degrees off the lines, by its corner), its chord is cut short there and its
    midpoint lies off that line by up to half the cut. Per feature of :data:`OFF_LINE_CHORDS`
    chords or more, the line is the Theil-Sen fit of the midpoints against the chords' lines (the
    median of the pairwise slopes: the outliers do not tilt it); the sd is 1.4826 times the
    median absolute residual over every feature's chords, at least :data:`OFF_LINE_FLOOR_PX`.
    """
    line, mid = ends[:, 0, 0], ends[:, :, 1].mean(axis=1)
    residual = np.full(len(feature), np.nan)  # NaN: too few chords to judge, kept
    for f in np.unique(feature):
        k = np.flatnonzero(feature == f)
        if len(k) < OFF_LINE_CHORDS:
            continue
        i, j = np.triu_indices(len(k), 1)
        apart = line[k][j] != line[k][i]
        slope = (
            np.median((mid[k][j] - mid[k][i])[apart] / (line[k][j] - line[k][i])[apart])
            if apart.any()
            else 0.0
        )
        residual[k] = mid[k] - slope * line[k]
        residual[k] -= np.median(residual[k])
    judged = np.isfinite(residual)
    if not judged.any():
        return np.ones(len(feature), bool)
    sd = max(1.4826 * float(np.median(np.abs(residual[judged]))), OFF_LINE_FLOOR_PX)
    return ~(np.abs(residual) > sds * sd)
