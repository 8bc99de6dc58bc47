"""Feature points of calibration-grating images (scikit-image), the paper's step A input.

A lattice image gives the sub-pixel centres of its pillars (or pits) and
their lattice indices; a 1-D grating image gives, per row, the sub-pixel
centres of its lines. From these come (drive, true position) pairs for the
paper's polynomial fit, the start of the end-to-end fit, and the local pitch
whose spread measures how uniform an image is (before and after compensation).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from skimage import filters, measure


@dataclasses.dataclass(frozen=True)
class LatticeFeatures:
    """Pillar centres of one image: ``rc`` (n, 2) fractional (row, col) pixels and
    their lattice indices ``ij`` (n, 2) (column index along x, row index along y)."""

    rc: np.ndarray
    ij: np.ndarray


def _check_image(z: np.ndarray, name: str) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    if z.ndim != 2 or min(z.shape) < 8:
        raise ValueError(f"{name} must be a 2-D image of at least 8 x 8 pixels, got shape {z.shape}")
    if not np.isfinite(z).all():
        raise ValueError(
            f"{name} has {int((~np.isfinite(z)).sum())} NaN or infinite pixels: "
            "fill or crop them before extracting features"
        )
    if np.ptp(z) == 0:
        raise ValueError(f"{name} is flat: no grating features to find")
    return z


def _indices(coord: np.ndarray, spacing_px: float, axis: str, name: str) -> np.ndarray:
    """Group coordinates into consecutive lattice lines: a new line after a gap over half a pitch."""
    order = np.argsort(coord)
    gaps = np.diff(coord[order]) > 0.5 * spacing_px
    idx = np.empty(len(coord), dtype=int)
    idx[order] = np.concatenate([[0], np.cumsum(gaps)])
    lines = np.array([coord[idx == k].mean() for k in range(idx.max() + 1)])
    if len(lines) < 3:
        raise ValueError(
            f"{name}: only {len(lines)} complete feature line(s) along {axis}; the grating must "
            "fill the scan with at least 3 pitches each way: scan a larger area or use a finer grating"
        )
    step = np.median(np.diff(lines))
    if not 0.7 < step / spacing_px < 1.4:
        raise ValueError(
            f"{name}: features repeat every {step:.1f} px along {axis}, but the stated pitch is "
            f"{spacing_px:.1f} px there (ratio {step / spacing_px:.2f}): no periodicity at the stated pitch; "
            "check the grating pitch and the scan size"
        )
    return idx


def lattice_features(z: np.ndarray, pitch_px: tuple, name: str = "image") -> LatticeFeatures:
    """Centres of the complete pillars (pits: pass ``-z``) of a lattice image.

    Thresholded at Otsu's level, labelled, and each region's centre taken as
    its height-weighted centroid (sub-pixel). Regions touching the border are
    cut and dropped. ``pitch_px`` (x, y) is the stated pitch in nominal pixels;
    a lattice that does not repeat near it raises an error.
    """
    z = _check_image(z, name)
    mask = z > filters.threshold_otsu(z)
    labels = measure.label(mask)
    weights = z - np.median(z[~mask]) if (~mask).any() else z - z.min()
    rc = []
    for region in measure.regionprops(labels, intensity_image=weights):
        r0, c0, r1, c1 = region.bbox
        if r0 == 0 or c0 == 0 or r1 == z.shape[0] or c1 == z.shape[1]:
            continue
        rc.append(region.centroid_weighted)
    if len(rc) < 9:
        raise ValueError(
            f"{name}: found {len(rc)} complete features; the grating must fill the scan with "
            "at least 3 x 3 pillars or pits (pits: pass the negated image)"
        )
    rc = np.asarray(rc)
    ij = np.stack(
        [_indices(rc[:, 1], pitch_px[0], "x", name), _indices(rc[:, 0], pitch_px[1], "y", name)], -1
    )
    return LatticeFeatures(rc, ij)


def local_pitch(f: LatticeFeatures, pixel_size: tuple) -> np.ndarray:
    """Distances (nm, at the nominal pixel size) between x-neighbours in the same lattice row."""
    out = []
    for j in np.unique(f.ij[:, 1]):
        row = f.ij[:, 1] == j
        i, x = f.ij[row, 0], f.rc[row, 1] * pixel_size[0]
        order = np.argsort(i)
        i, x = i[order], x[order]
        neighbours = np.diff(i) == 1
        out.append(np.diff(x)[neighbours])
    return np.concatenate(out)


def edge_crossings(row: np.ndarray, band: float = 0.2) -> tuple:
    """Sub-pixel edges of one grating profile: where ``row`` crosses its mid-level.

    The mid-level is halfway between the row's 10th and 90th percentiles. An
    edge counts only once the profile has gone from below ``level - band * c``
    to above ``level + band * c`` (or back), ``c`` the 10-90 % contrast, so that
    noise on a slope gives one edge, not three; its position is the mean of the
    mid-level crossings (linear interpolation between samples) on that passage.
    Returns ``(positions, rising)``: fractional indices, ascending, and whether
    the profile rises there.
    """
    row = np.asarray(row, dtype=float)
    lo, hi = np.percentile(row, [10, 90])
    level, half = 0.5 * (lo + hi), band * (hi - lo)
    state = np.where(row > level + half, 1, np.where(row < level - half, -1, 0))
    k = np.flatnonzero(state)
    turns = np.flatnonzero(np.diff(state[k]) != 0)
    pos = np.empty(len(turns))
    for i, t in enumerate(turns):
        a, b = k[t], k[t + 1]
        s = row[a : b + 1] - level
        j = np.flatnonzero((s[:-1] > 0) != (s[1:] > 0))
        pos[i] = np.mean(a + j + s[j] / (s[j] - s[j + 1]))
    return pos, state[k[turns + 1]] > 0


def pitch_spread(pitches: np.ndarray) -> dict:
    """Spread of local pitches (nm): mean, std and peak-to-peak, also as % of the mean."""
    p = np.asarray(pitches, dtype=float)
    mean = float(p.mean())
    return {
        "pitch_mean_nm": mean,
        "pitch_std_nm": float(p.std()),
        "pitch_ptp_nm": float(np.ptp(p)),
        "pitch_std_pct": 100 * float(p.std()) / mean,
        "pitch_ptp_pct": 100 * float(np.ptp(p)) / mean,
    }
