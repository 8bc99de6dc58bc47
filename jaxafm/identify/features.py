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
from scipy.spatial import cKDTree
from skimage import filters, measure


@dataclasses.dataclass(frozen=True)
class LatticeFeatures:
    """Pillar centres of one image: ``rc`` (n, 2) fractional (row, col) pixels, their lattice
    indices ``ij`` (n, 2) (along the lattice's first and second axis) and the lattice's angle
    ``angle`` (rad, anticlockwise) in the frame it was indexed in; ``chords``: the
    :class:`~jaxafm.identify.chords.Chords` the centres are the features of (their
    ``feature`` numbers index ``rc``), where they came from them."""

    rc: np.ndarray
    ij: np.ndarray
    angle: float = 0.0
    chords: object = None

    def chord_indices(self) -> np.ndarray:
        """The lattice indices (n, 2) of each chord's feature."""
        return self.ij[self.chords.feature]


def check_image(z: np.ndarray, name: str) -> np.ndarray:
    """``z`` as a float image, checked: 2-D, at least 8 x 8 pixels, finite and not flat.

    Raises:
        ValueError: naming the image ``name`` and what is wrong with it.
    """
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


def feature_centres(z: np.ndarray, name: str = "image", smooth: bool = False) -> np.ndarray:
    """Centres (n, 2) fractional (row, col) px of the complete pillars (pits: pass ``-z``).

    Thresholded at Otsu's level, labelled, and each region's centre taken as its
    height-weighted centroid (sub-pixel), the heights counted from the background's median,
    or with ``smooth`` from the threshold: a pixel then joins a region with no weight, so the
    centre moves smoothly as a feature moves across the pixels (less pixel locking, as
    comparing two images of one feature needs). Regions touching the border are cut and
    dropped.
    """
    z = check_image(z, name)
    level = filters.threshold_otsu(z)
    mask = z > level
    labels = measure.label(mask)
    if smooth:
        weights = np.where(mask, z - level, 0.0)
    else:
        weights = z - np.median(z[~mask]) if (~mask).any() else z - z.min()
    rc, spanning = [], 0
    for region in measure.regionprops(labels, intensity_image=weights):
        r0, c0, r1, c1 = region.bbox
        spanning += (r0 == 0 and r1 == z.shape[0]) or (c0 == 0 and c1 == z.shape[1])
        if r0 == 0 or c0 == 0 or r1 == z.shape[0] or c1 == z.shape[1]:
            continue
        rc.append(region.centroid_weighted)
    if len(rc) < 9 and spanning >= 3:
        raise ValueError(
            f"{name}: {spanning} features run right across the image: it shows the lines of a 1-D grating "
            "(or pits/pillars joined at this threshold), not a lattice of separate pits or pillars. Step A "
            "identifies both axes from a 2-D lattice; a 1-D grating shows only the axis across its lines "
            "(jaxafm.identify.line_grating.fit_line_grating fits that)"
        )
    if len(rc) < 9:
        raise ValueError(
            f"{name}: found {len(rc)} complete features; the grating must fill the scan with "
            "at least 3 x 3 pillars or pits (pits: pass the negated image)"
        )
    return np.asarray(rc)


def lattice_angle(xy: np.ndarray, pitch, name: str = "image", units: str = "px") -> float:
    """The angle (rad, in (-45, 45] degrees) of a square lattice of points ``xy`` (n, 2) whose
    pitch along its axes is ``pitch`` (2,) (in the units of ``xy``).

    Every vector between nearest neighbours (scaled to unit pitch) lies along a lattice axis
    up to a multiple of 90 degrees; the angle is the circular mean of four times their
    angles, divided by four."""
    q = np.asarray(xy, dtype=float) / np.asarray(pitch, dtype=float)
    dist, idx = cKDTree(q).query(q, k=min(5, len(q)))
    nearest = float(np.median(dist[:, 1]))
    near = (dist[:, 1:] > 0.7) & (dist[:, 1:] < 1.3)
    if not 0.7 < nearest < 1.3 or near.sum() < 4:
        shown = np.median(np.linalg.norm((q[idx[:, 1]] - q) * np.asarray(pitch), axis=1))
        raise ValueError(
            f"{name}: neighbouring features lie {shown:.4g} {units} apart (median), but the stated "
            f"pitch is {' x '.join(f'{p:.4g}' for p in np.broadcast_to(pitch, (2,)))} {units}: no "
            "periodicity at the stated pitch; check the grating pitch and the scan size"
        )
    v = (q[idx[:, 1:]] - q[:, None, :])[near]
    return float(np.angle(np.mean(np.exp(4j * np.arctan2(v[:, 1], v[:, 0])))) / 4)


def _indices(coord: np.ndarray, axis: str, name: str, unit: float, units: str) -> np.ndarray:
    """Group coordinates (in pitches) into consecutive lattice lines: a new line after a gap of
    over half a pitch. ``unit`` converts a pitch into ``units`` for the messages."""
    order = np.argsort(coord)
    gaps = np.diff(coord[order]) > 0.5
    idx = np.empty(len(coord), dtype=int)
    idx[order] = np.concatenate([[0], np.cumsum(gaps)])
    lines = np.array([coord[idx == k].mean() for k in range(idx.max() + 1)])
    if len(lines) < 3:
        raise ValueError(
            f"{name}: only {len(lines)} complete feature line(s) along {axis}; the grating must "
            "fill the scan with at least 3 pitches each way: scan a larger area or use a finer grating"
        )
    step = float(np.median(np.diff(lines)))
    if not 0.7 < step < 1.4:
        raise ValueError(
            f"{name}: features repeat every {step * unit:.4g} {units} along {axis}, but the stated pitch "
            f"is {unit:.4g} {units} (ratio {step:.2f}): no periodicity at the stated pitch; "
            "check the grating pitch and the scan size"
        )
    return idx


def index_lattice(xy: np.ndarray, pitch, name: str = "image", units: str = "px") -> tuple:
    """Lattice indices ``ij`` (n, 2) of points ``xy`` (n, 2) on a lattice of ``pitch`` (2,)
    (both in ``units``), turned by :func:`lattice_angle`; returns ``(ij, angle)``."""
    pitch = np.asarray(pitch, dtype=float)
    angle = lattice_angle(xy, pitch, name, units)
    c, s = np.cos(angle), np.sin(angle)
    q = np.asarray(xy, dtype=float) / pitch
    along = np.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1]], -1)
    ij = np.stack([_indices(along[:, k], ax, name, pitch[k], units) for k, ax in enumerate(("x", "y"))], -1)
    return ij, angle


def lattice_features(z: np.ndarray, pitch_px: tuple, name: str = "image") -> LatticeFeatures:
    """Centres of the complete pillars (pits: pass ``-z``) of a lattice image
    (:func:`feature_centres`), indexed in the image's pixel frame (:func:`index_lattice`).
    ``pitch_px`` (x, y) is the stated pitch in nominal pixels; a lattice that does not repeat
    near it raises an error."""
    rc = feature_centres(z, name)
    ij, angle = index_lattice(rc[:, ::-1], pitch_px, name)
    return LatticeFeatures(rc, ij, angle)


def local_pitch(f: LatticeFeatures, pixel_size: tuple) -> np.ndarray:
    """Distances (nm, at the nominal pixel size) between first-axis neighbours in the same
    lattice row."""
    return neighbour_distances(f.rc[:, ::-1] * np.asarray(pixel_size), f.ij)


def neighbour_distances(xy: np.ndarray, ij: np.ndarray, step: int = 1) -> np.ndarray:
    """Distances, per pitch, between points ``xy`` (n, 2) whose lattice indices ``ij`` (n, 2)
    lie ``step`` apart along the first axis in the same row (each such pair once)."""
    out = []
    for j in np.unique(ij[:, 1]):
        row = np.flatnonzero(ij[:, 1] == j)
        row = row[np.argsort(ij[row, 0])]
        i, p = ij[row, 0], xy[row]
        a, b = np.nonzero(i[None, :] - i[:, None] == step)
        out.append(np.linalg.norm(p[b] - p[a], axis=1) / step)
    return np.concatenate(out) if out else np.zeros(0)


def edge_crossings(row: np.ndarray, band: float = 0.2, levels=None) -> tuple:
    """Sub-pixel edges of one grating profile: where ``row`` crosses its mid-level.

    The mid-level is halfway between the row's 10th and 90th percentiles. An
    edge counts only once the profile has gone from below ``level - band * c``
    to above ``level + band * c`` (or back), ``c`` the 10-90 % contrast, so that
    noise on a slope gives one edge, not three; its position is the mean of the
    mid-level crossings (linear interpolation between samples) on that passage.
    ``levels``: ``(lo, hi)`` to use instead of the percentiles (e.g. the depth of a
    lattice's pit rows). Returns ``(positions, rising)``: fractional indices,
    ascending, and whether the profile rises there.
    """
    row = np.asarray(row, dtype=float)
    lo, hi = np.percentile(row, [10, 90]) if levels is None else levels
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
