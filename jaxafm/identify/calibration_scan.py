"""Step A's data: a trace/retrace image pair of a calibration lattice and how it was driven
(:class:`CalibrationScan`), its features indexed in one lattice frame, and the matching of the
retrace's lattice indices to the trace's at the line reversal.

The paper (section III-A) images a grating of known pitch after the initialisation cycle
``{u2, u1}``; its feature points carry lattice indices, and trace and retrace columns are matched
at the line reversal, where the tip is continuous, so that they cannot slip by a pitch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import checks
from ..instrument.afm import Raster
from .chords import find_chords
from .features import LatticeFeatures, index_lattice

Array = jax.Array


class CalibrationScan(eqx.Module):
    """A trace/retrace image pair (lines, pixels) nm of a lattice of ``pitch`` (2,) nm, and
    how it was driven: the nominal calibration ``sensitivity`` (2,) nm/V through ``raster``,
    from rest at ``u0`` (2,) V at ``t0`` s after the drive ``history`` (H, 2) V.
    ``pits``: the lattice has pits, not pillars. ``off_line_sd``: its features' chords are read
    without those off their features' lines (:func:`~jaxafm.identify.chords.find_chords`)."""

    trace: Array
    retrace: Array
    raster: Raster = eqx.field(static=True)
    pitch: tuple = eqx.field(static=True)
    sensitivity: tuple = eqx.field(static=True)
    u_max: float = eqx.field(static=True)
    u0: tuple = eqx.field(static=True)
    t0: float = eqx.field(static=True)
    history: Optional[tuple] = eqx.field(static=True)
    pits: bool = eqx.field(static=True)
    off_line_sd: Optional[float] = eqx.field(static=True)
    depth_scale: Array  # nm, () : an array, so that step A's compiled solves serve every scan

    def __init__(
        self,
        trace,
        retrace,
        raster: Raster,
        pitch,
        sensitivity,
        u_max: float,
        u0=(0.0, 0.0),
        t0: float = 0.0,
        history=None,
        pits: bool = False,
        off_line_sd: Optional[float] = None,
    ):
        shape = (raster.lines, raster.pixels)
        for name, z in (("trace", trace), ("retrace", retrace)):
            if np.shape(z) != shape:
                raise ValueError(f"the {name} image has shape {np.shape(z)}, but the raster gives {shape}")
        self.trace, self.retrace = jnp.asarray(trace, dtype=float), jnp.asarray(retrace, dtype=float)
        self.raster = raster
        self.pitch = tuple(float(p) for p in np.broadcast_to(pitch, (2,)))
        self.sensitivity = tuple(float(v) for v in np.broadcast_to(sensitivity, (2,)))
        checks.positive("the grating pitch (nm)", self.pitch)
        checks.positive("the nominal sensitivity (nm/V)", self.sensitivity)
        checks.positive("u_max (V)", u_max)
        checks.finite("u0 (V)", u0)
        checks.finite("t0 (s)", t0)
        self.u_max, self.u0, self.t0 = float(u_max), tuple(float(v) for v in u0), float(t0)
        self.history = (
            None if history is None else tuple(tuple(float(v) for v in h) for h in np.asarray(history))
        )
        self.pits = bool(pits)
        self.off_line_sd = None if off_line_sd is None else float(off_line_sd)
        self.depth_scale = jnp.asarray(float(np.ptp(np.asarray(trace))) or 1.0)

    def coarse(self, factor: int) -> CalibrationScan:
        """This scan with ``factor`` pixels of each line averaged into one: the same lines and
        line rate, ``pixels / factor`` pixels a line, each at the mean of its fine pixels' centres,
        and the widest over-scan margin whose reversals do not go beyond the fine scan's (they
        come within ``factor`` fine pixels of them; beyond, the drive could leave the range the
        fine scan fits in). The drive then turns a little off the fine one's, so a fit to a
        coarse scan is a start for the fine scan, not its fit."""
        if factor == 1:
            return self
        r = self.raster
        pixels = r.pixels // factor
        margin = int((r.margin + (factor - 1) / 2) // factor)
        raster = dataclasses.replace(r, pixels=pixels, overscan=margin / pixels)
        down = lambda z: np.asarray(z).reshape(r.lines, raster.pixels, factor).mean(axis=-1)
        return CalibrationScan(
            down(self.trace),
            down(self.retrace),
            raster,
            self.pitch,
            self.sensitivity,
            self.u_max,
            self.u0,
            self.t0,
            self.history,
            self.pits,
            self.off_line_sd,
        )

    @property
    def pitch_px(self) -> tuple:
        return tuple(p / s for p, s in zip(self.pitch, self.raster.pixel_size))

    def volts(self, rc: np.ndarray) -> np.ndarray:
        """The nominal drive (n, 2) V at fractional pixels ``rc`` (n, 2) (row, col)."""
        return self.raster.nominal(rc) / np.asarray(self.sensitivity)

    @property
    def name(self) -> str:
        return f"the {self.raster.angle_deg:g} degree scan at {self.raster.line_rate:g} Hz"

    def features(self) -> tuple:
        """Pillar (or pit) centres of trace and retrace, indexed in one lattice frame: the
        lattice of their nominal stage positions (so images at any scan angle index alike);
        the retrace's indices matched to the trace's by the nearest feature at the line
        reversal (the first of :meth:`feature_matches`)."""
        trace, retraces = self.feature_matches()
        return trace, retraces[0]

    def feature_matches(self, wide_loop: bool = False) -> tuple:
        """The trace's features and the retrace's (with their chords,
        :func:`~jaxafm.identify.chords.find_chords`), the latter indexed in each way the line
        reversal allows (:func:`_retrace_matches`): ``(trace, [retrace, ...])``. With
        ``wide_loop``, one more way last: the first's a pitch further back
        (:func:`one_pitch_back`), for a loop that holds the retrace more than a pitch behind.

        Raises:
            ValueError: naming the image, when it shows fewer than 3 x 3 complete features or
                does not fill the image with them.
        """
        found = []
        for k in ("trace", "retrace"):
            name = f"{self.name}'s {k} image"
            chords = find_chords(np.asarray(getattr(self, k)), self.pits, name, self.off_line_sd)
            rc = chords.centres
            if len(rc) < 9 and chords.spanning >= 3:
                raise ValueError(
                    f"{name}: {chords.spanning} features run right across the image: it shows the lines of "
                    "a 1-D grating (or pits/pillars joined into lines), not a lattice of separate pits or "
                    "pillars. Step A identifies both axes from a 2-D lattice; a 1-D grating shows only the "
                    "axis across its lines (jaxafm.identify.line_grating.fit_line_grating fits that)"
                )
            if len(rc) < 9:
                raise ValueError(
                    f"{name}: found {len(rc)} complete {'pits' if self.pits else 'pillars'}; the lattice "
                    "must fill the scan with at least 3 x 3 of them"
                )
            _check_coverage(rc, self.pitch_px, (self.raster.lines, self.raster.pixels), name)
            ij, angle = index_lattice(self.raster.nominal(rc), self.pitch, name, "nm")
            found.append(LatticeFeatures(rc, ij, angle, chords))
        retraces = _retrace_matches(*found, self.pitch_px)
        if wide_loop:
            back = one_pitch_back(found[0], retraces[0], self.pitch_px)
            retraces += [back] if all(np.any(r.ij != back.ij) for r in retraces) else []
        return found[0], retraces


def one_pitch_back(ft: LatticeFeatures, fr: LatticeFeatures, pitch_px: tuple) -> LatticeFeatures:
    """The retrace ``fr`` indexed as if it saw every pillar one pitch further back along the line
    than ``fr``'s indices say: each index plus the trace's step to the next pillar along its
    line (the change of indices most neighbour pairs of ``ft`` agree on). A loop wide enough
    holds the retrace more than a pitch behind the trace at the line reversal (1.5-1.8 pitches
    for configs/study_wide.yaml's five widest at 10 % overscan): the nearest retrace feature
    to a trace feature there is then the next pillar's, and none of
    :func:`_retrace_matches`' ways is right."""
    d = ft.rc[None, :, :] - ft.rc[:, None, :]  # (feature, other, (row, col))
    ahead = (np.abs(d[..., 0]) < 0.5 * pitch_px[1]) & (d[..., 1] > 0.5 * pitch_px[0])
    dist = np.where(ahead, d[..., 1], np.inf)
    has = np.isfinite(dist.min(axis=1))
    steps, counts = np.unique(ft.ij[np.argmin(dist[has], axis=1)] - ft.ij[has], axis=0, return_counts=True)
    return dataclasses.replace(fr, ij=fr.ij + steps[np.argmax(counts)])


def coarse_pixels(rc: np.ndarray, factor: int) -> np.ndarray:
    """Fractional pixels (n, 2) (row, col) of a scan in its :meth:`CalibrationScan.coarse` scan:
    the rows stay, a column ``c`` becomes ``(c + 1/2) / factor - 1/2``."""
    rc = np.asarray(rc, dtype=float)
    return np.c_[rc[:, 0], (rc[:, 1] + 0.5) / factor - 0.5]


def drive_range(scans: tuple) -> np.ndarray:
    """The drive (2, 2) V [min, max] per axis that the calibration scans covered, over-scan included."""
    u = np.concatenate([s.raster.wanted().reshape(-1, 2) / np.asarray(s.sensitivity) for s in scans])
    return np.stack([u.min(axis=0), u.max(axis=0)], axis=-1)


def line_strokes(scans: tuple) -> np.ndarray:
    """Per piezo axis (2,), the largest stroke any scan's line drives it back and forth over, a
    fraction of the axis's drive range over the scans (:func:`drive_range`): 1 along a 0-degree
    scan's fast axis and 0 along its slow axis, which steps but never reverses within an image;
    about a half on both axes at 45 degrees."""
    strokes = [
        np.ptp(s.raster.wanted().reshape(s.raster.lines, -1, 2) / np.asarray(s.sensitivity), axis=1).max(
            axis=0
        )
        for s in scans
    ]
    return np.max(strokes, axis=0) / np.ptp(drive_range(scans), axis=1)


def check_scan_set(scans: Sequence[CalibrationScan]) -> None:
    """Refuse a set of scans that are not of one lattice on one instrument, or repeat a scan.

    Raises:
        ValueError: for no scan, scans that differ in pitch, pits, sensitivity or ``u_max``
            (naming both scans and values), or a scan angle given twice at one line rate.
    """
    if not scans:
        raise ValueError("step A needs at least one calibration scan")
    first = scans[0]
    for s in scans[1:]:
        for what in ("pitch", "pits", "sensitivity", "u_max"):
            if getattr(s, what) != getattr(first, what):
                raise ValueError(
                    f"{s.name} has {what} {getattr(s, what)}, {first.name} {getattr(first, what)}: "
                    "the scans of one calibration must share the lattice and the instrument"
                )
    seen = [(s.raster.angle_deg, s.raster.line_rate) for s in scans]
    if len(set(seen)) != len(seen):
        raise ValueError(
            f"scans (angle deg, line rate Hz) {seen} repeat: give each angle once at each line rate"
        )


def _check_coverage(rc: np.ndarray, pitch_px: tuple, shape: tuple, name: str) -> None:
    """Refuse a lattice that does not fill its image: complete features must come within two
    pitches of every edge (a feature cut by the edge is dropped, so up to about 1.25 pitches
    can lie bare there)."""
    lo, hi = rc.min(axis=0), rc.max(axis=0)
    pitch = np.asarray(pitch_px)[::-1]  # (row, col)
    bare = np.concatenate([lo, np.asarray(shape) - 1 - hi]) / np.tile(pitch, 2)
    if bare.max() > 2:
        raise ValueError(
            f"{name}: the lattice covers only rows {lo[0]:.0f}-{hi[0]:.0f} and columns "
            f"{lo[1]:.0f}-{hi[1]:.0f} of the {shape[0]} x {shape[1]} px image: crop the image to "
            "the lattice (step A fits every pixel to the lattice)"
        )


def _retrace_matches(ft: LatticeFeatures, fr: LatticeFeatures, pitch_px: tuple) -> list:
    """The retrace's features, their indices shifted onto the trace's in the ways the line
    reversal allows, the likelier first. Near the reversal (the images' last columns) the trace
    turns into the retrace and the tip is continuous, so a pillar sits at nearly the same pixel
    in both images, but only nearly: a scan that overscans turns beyond the last column, where
    the hysteresis loop is still open, and the retrace sees a pillar up to about a pitch
    earlier along the line than the trace (0.6-0.95 pitch for 12-18 % loops at 10 % overscan).
    So each trace feature of the last half pitch is paired with its nearest retrace feature of
    the same line on either side; each side gives the shift most of its pairs agree on, the
    nearer side's first. Step A's chord stage keeps the one whose fit is best
    (:func:`~jaxafm.identify.staged_fit.identify`)."""
    turn = ft.rc[:, 1] > ft.rc[:, 1].max() - 0.5 * pitch_px[0]
    d = fr.rc[None, :, :] - ft.rc[turn, None, :]  # (turn features, retrace features, (row, col))
    line = np.abs(d[..., 0]) < 0.5 * pitch_px[1]
    sides = []
    for side in (d[..., 1] <= 0, d[..., 1] > 0):
        dist = np.where(line & side, np.abs(d[..., 1]), np.inf)
        paired = np.isfinite(dist.min(axis=1))
        if paired.any():
            nearest = np.argmin(dist[paired], axis=1)
            shifts, counts = np.unique(ft.ij[turn][paired] - fr.ij[nearest], axis=0, return_counts=True)
            sides.append((float(np.median(dist[paired].min(axis=1))), tuple(shifts[np.argmax(counts)])))
    shifts = list(dict.fromkeys(shift for _, shift in sorted(sides)))
    return [dataclasses.replace(fr, ij=fr.ij + np.asarray(shift)) for shift in shifts]
