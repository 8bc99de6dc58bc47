"""Step B: landmark-based coarse positioning (paper section III-B).

An N x N grid of indents is pressed at wanted positions ``D`` (start ``P``,
step ``S`` pixels of an n x n image, eq. 3: ``P + S (N - 1) < n``), driven by
commands ``I``; the area is re-scanned and the indents found there, ``M``, are
where the tip really went, in the frame of the image. A target ``M_x`` seen in
that image is then reached through the command interpolated from the landmarks:

- ``"pairwise"``: a variant of the paper's eq. 4-5 over the ``m`` nearest landmarks,
  ``f_ij = (M_x - M_xi) / (M_xj - M_xi) (I_xj - I_xi) + I_xi`` per axis, averaged over the
  pairs ``i < j`` that lie apart on that axis: pairs in one column (row) are left out of the x
  (y) average, where eq. 5 would divide by about zero, so the mean is over those pairs, not
  over all ``m (m - 1) / 2`` of eq. 4;
- ``"polynomial"``: a least-squares polynomial surface ``I = p(M)`` of total
  degree ``degree`` per axis (the abstract's curve fit).

Commands are positions (nm) in the frame of the drive map that turns them into
volts: the nominal calibration, or step A's inverse model. For the nominal map
they are the paper's voltages times the sensitivity.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from scipy.optimize import linear_sum_assignment
from skimage import feature

from .. import checks
from ..config.run import check_landmark_grid

Array = jax.Array
METHODS = ("pairwise", "polynomial")


@dataclasses.dataclass(frozen=True)
class LandmarkGrid:
    """An ``n`` x ``n`` indent grid in an ``image_px`` x ``image_px`` image: first indent at pixel
    ``start_px`` (both axes), then every ``step_px`` pixels (paper eq. 3)."""

    n: int
    start_px: float
    step_px: float
    image_px: int

    def __post_init__(self):
        check_landmark_grid(self.n, self.start_px, self.step_px, self.image_px)

    def positions(self, raster) -> np.ndarray:
        """Wanted indent positions ``D`` (n*n, 2) nm in ``raster``'s frame, row by row from the
        lowest y, alternating direction (the order they are pressed in)."""
        k = self.start_px + self.step_px * np.arange(self.n)
        rows = []
        for i, y in enumerate(k):
            xs = k if i % 2 == 0 else k[::-1]
            rows += [(x, y) for x in xs]
        px = np.asarray(rows)
        return np.asarray(raster.origin) + px * np.asarray(raster.pixel_size)


def find_features(
    z: np.ndarray, raster, count: int, pits: bool, min_height: float, min_distance_nm: float, window_nm: float
) -> np.ndarray:
    """Sub-pixel centres (k, 2) nm of up to ``count`` pits (or bumps) of ``z`` (lines, pixels) nm
    deeper (higher) than ``min_height`` nm against the image's median level.

    Maxima come from ``skimage.feature.peak_local_max``; each centre is the
    centroid, within ``window_nm``, of the part of the feature above a quarter of its height.
    """
    z = np.asarray(z, dtype=float)
    s = (-1.0 if pits else 1.0) * (z - np.median(z))
    pixel = np.asarray(raster.pixel_size)
    md = max(1, int(min_distance_nm / pixel.min()))
    peaks = feature.peak_local_max(
        s, min_distance=md, threshold_abs=min_height, num_peaks=count, exclude_border=False
    )
    w = max(1, int(np.ceil(window_nm / pixel.min())))
    centres = []
    for r, c in peaks:
        r0, c0 = max(r - w, 0), max(c - w, 0)
        patch = s[r0 : r + w + 1, c0 : c + w + 1]
        weight = np.clip(patch - s[r, c] / 4, 0, None)
        rr, cc = np.mgrid[r0 : r0 + patch.shape[0], c0 : c0 + patch.shape[1]]
        rc = np.array([(rr * weight).sum(), (cc * weight).sum()]) / weight.sum()
        centres.append(np.asarray(raster.origin) + rc[::-1] * pixel)
    return np.asarray(centres).reshape(-1, 2)


def match_grid(found: np.ndarray, wanted: np.ndarray, spacing: float) -> np.ndarray:
    """The grid slot of each indent ``found`` (k, 2) nm in the re-scan: an index into ``wanted``
    ``D`` (N*N, 2) nm, or -1 for a find that matches no slot. Holes in the grid are allowed.

    One-to-one nearest slots (``scipy.optimize.linear_sum_assignment``), first against ``D``
    moved by the median offset of each find from its nearest slot (the grid's shift, which an
    uncompensated drive makes a large part of the spacing), then twice against ``D`` through the
    affine map the matched pairs give (the scan's scale, skew and offset), keeping pairs closer
    than ``spacing / 3`` nm.
    """
    found, wanted = np.asarray(found, float).reshape(-1, 2), np.asarray(wanted, float)
    slot = np.full(len(found), -1)
    if len(found) == 0:
        return slot
    offsets = found[:, None] - wanted[None]
    nearest = offsets[np.arange(len(found)), np.argmin(np.linalg.norm(offsets, axis=-1), axis=1)]
    predicted = wanted + np.median(nearest, axis=0)
    for _ in range(3):
        d = np.linalg.norm(found[:, None] - predicted[None], axis=-1)
        rows, cols = linear_sum_assignment(d)
        close = d[rows, cols] < spacing / 3
        slot[:] = -1
        slot[rows[close]] = cols[close]
        ok = slot >= 0
        if ok.sum() < 3:
            break
        A = np.column_stack([wanted[slot[ok]], np.ones(ok.sum())])
        affine = np.linalg.lstsq(A, found[ok], rcond=None)[0]
        predicted = np.column_stack([wanted, np.ones(len(wanted))]) @ affine
    return slot


def usable_degree(count: int, degree: int) -> int:
    """The highest polynomial degree up to ``degree`` whose surface ``count`` landmarks
    over-determine (terms ``(d + 1)(d + 2) / 2`` at most ``count - 2``); 0 when not even a plane's."""
    while degree >= 1 and (degree + 1) * (degree + 2) // 2 > count - 2:
        degree -= 1
    return max(degree, 0)


class LandmarkMap(eqx.Module):
    """Commands (nm) for targets seen in the re-scan: ``measured`` ``M`` (K, 2) nm landmark
    positions found in the image, ``commands`` ``I`` (K, 2) nm that put them there.

    ``method``: ``"pairwise"`` (eq. 4-5 over the ``m`` nearest) or ``"polynomial"``
    (of total ``degree``). A pair of landmarks that share a column (row) carries
    no x (y) information and makes eq. 5 divide by about zero; pairs closer than
    ``min_separation`` nm on an axis (default: a quarter of the median distance between
    neighbouring landmarks) are left out of that axis's average.
    """

    measured: Array
    commands: Array
    method: str = eqx.field(static=True, default="polynomial")
    m: int = eqx.field(static=True, default=4)
    degree: int = eqx.field(static=True, default=3)
    min_separation: Array = None
    coefficients: Array = None  # (terms, 2), polynomial only
    centre: Array = None
    scale: Array = None

    def __init__(
        self,
        measured,
        commands,
        method: str = "polynomial",
        m: int = 4,
        degree: int = 3,
        min_separation: float | None = None,
    ):
        measured, commands = jnp.asarray(measured, dtype=float), jnp.asarray(commands, dtype=float)
        if measured.ndim != 2 or measured.shape[1] != 2 or measured.shape != commands.shape:
            raise ValueError(
                f"landmarks need measured and command positions of one shape (K, 2), got "
                f"{measured.shape} and {commands.shape}"
            )
        if method not in METHODS:
            raise ValueError(f"unknown landmark interpolation {method!r}; one of {', '.join(METHODS)}")
        K = measured.shape[0]
        if method == "pairwise" and not 2 <= m <= K:
            raise ValueError(f"pairwise interpolation needs 2 <= m <= {K} landmarks, got m = {m}")
        terms = (degree + 1) * (degree + 2) // 2
        if method == "polynomial" and not (degree >= 1 and K >= terms):
            raise ValueError(
                f"a degree-{degree} surface has {terms} coefficients per axis but there are {K} "
                "landmarks: lower the degree (>= 1) or use a larger grid"
            )
        self.measured, self.commands = measured, commands
        self.method, self.m, self.degree = method, int(m), int(degree)
        self.centre = jnp.mean(measured, axis=0)
        self.scale = jnp.maximum(jnp.ptp(measured, axis=0) / 2, 1e-9)
        spacing = float(np.median(_nearest_distances(np.asarray(measured))))
        self.min_separation = jnp.asarray(
            0.25 * spacing if min_separation is None else min_separation, dtype=float
        )
        if method == "polynomial":
            A = self._terms(measured)
            self.coefficients = jnp.linalg.lstsq(A, commands)[0]

    def _terms(self, p: Array) -> Array:
        x, y = ((p - self.centre) / self.scale).T
        return jnp.stack([x**i * y ** (d - i) for d in range(self.degree + 1) for i in range(d + 1)], axis=-1)

    def __call__(self, targets: Array) -> Array:
        """Commands (..., 2) nm for ``targets`` (..., 2) nm in the re-scan's frame."""
        targets = jnp.asarray(targets, dtype=float)
        flat = targets.reshape(-1, 2)
        if self.method == "polynomial":
            out = self._terms(flat) @ self.coefficients
        else:
            out = jax.vmap(self._pairwise)(flat)
        return out.reshape(targets.shape)

    def _pairwise(self, x: Array) -> Array:
        """Eq. 4-5 for one target ``x`` (2,)."""
        _, idx = lax.top_k(-jnp.sum((self.measured - x) ** 2, axis=-1), self.m)
        M, I = self.measured[idx], self.commands[idx]
        i, j = np.triu_indices(self.m, 1)
        dM = M[j] - M[i]
        ok = jnp.abs(dM) > self.min_separation
        f = (x - M[i]) / jnp.where(ok, dM, 1.0) * (I[j] - I[i]) + I[i]
        n = jnp.sum(ok, axis=0)
        # no informative pair on an axis (m = 2 in one column): the nearest landmark, moved by the offset
        fallback = I[0] + (x - M[0])
        return jnp.where(n > 0, jnp.sum(jnp.where(ok, f, 0.0), axis=0) / jnp.maximum(n, 1), fallback)

    def check_inside(self, targets, name: str = "target") -> None:
        """Raise an error for a target outside the landmarks' bounding box: the map would extrapolate."""
        if not checks.is_concrete(targets):
            return
        t = np.asarray(targets, dtype=float).reshape(-1, 2)
        lo, hi = np.asarray(self.measured).min(0), np.asarray(self.measured).max(0)
        bad = np.any((t < lo) | (t > hi), axis=1)
        if bad.any():
            p = t[np.argmax(bad)]
            raise ValueError(
                f"{name} ({p[0]:.0f}, {p[1]:.0f}) nm lies outside the landmark grid, x {lo[0]:.0f} to "
                f"{hi[0]:.0f} nm, y {lo[1]:.0f} to {hi[1]:.0f} nm: choose a target inside it or press a "
                "larger grid"
            )


def _nearest_distances(p: np.ndarray) -> np.ndarray:
    d = np.hypot(*(p[:, None, :] - p[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1)
