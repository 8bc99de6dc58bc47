"""The stages of the paper's ablation and their survey of the workspace (paper section IV).

A stage drives the instrument with or without step A's model and step B's landmark map. Its
survey presses the landmark grid (B) and images the workspace; in the images it finds the
particles a user would pick as targets (:func:`find_targets`) and the indents
(:func:`find_landmarks`), from which step B's maps are built (:func:`landmark_maps`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from skimage import registration

from ..instrument.afm import Raster, RasterScan
from ..instrument.samples import Indented, Particles
from .landmarks import LandmarkGrid, LandmarkMap, find_features, match_grid, usable_degree
from .positioning import Positioner, Stand, press_at, raster


@dataclasses.dataclass(frozen=True)
class Stage:
    """A stage of the ablation: whether it drives through step A's model (``with_a``) and
    through step B's landmark map (``with_b``). A+B goes on to step C and the push."""

    name: str
    with_a: bool
    with_b: bool

    @property
    def key(self) -> str:
        """The stage's name as a metrics key (:func:`stage_key`)."""
        return stage_key(self.name)


#: the stages that survey the workspace, in order
STAGES = (
    Stage("open_loop", False, False),
    Stage("A", True, False),
    Stage("B", False, True),
    Stage("A+B", True, True),
)


def stage_key(label: str) -> str:
    """A stage label as a metrics key: ``"A+B (polynomial)"`` -> ``"AB_polynomial"``."""
    return label.replace("+", "").replace(" (", "_").replace(")", "")


def particle_field(
    corner: np.ndarray, per_side: int, spacing: float, radius_nm: Sequence[float], seed: int
) -> Particles:
    """``per_side`` x ``per_side`` particles ``spacing`` nm apart, the first half a spacing from
    ``corner`` (2,) nm on both axes, each jittered by up to 1/8 of the spacing, radii uniform in
    ``radius_nm`` [min, max] (one ``numpy`` generator seeded with ``seed`` draws both)."""
    rng = np.random.default_rng(seed)
    k = (np.arange(per_side) + 0.5) * spacing
    sites = corner + np.stack(np.meshgrid(k, k), -1).reshape(-1, 2)
    centres = sites + rng.uniform(-spacing / 8, spacing / 8, sites.shape)
    radii = rng.uniform(*radius_nm, len(centres))
    return Particles(jnp.asarray(centres), jnp.asarray(radii))


@dataclasses.dataclass(frozen=True)
class Survey:
    """A stage's survey: the workspace ``images``, the ``sample`` with the indents pressed into
    it, where things ``stand`` after it, and the ``seconds`` it took (pressing and imaging)."""

    images: RasterScan
    sample: Indented
    stand: Stand
    seconds: float


def survey(
    pos: Positioner,
    stand: Stand,
    sample: Indented,
    work: Raster,
    key: jax.Array,
    landmarks: Optional[np.ndarray] = None,
    depth: float = 50.0,
    approach: float = 0.0,
) -> Survey:
    """Press an indent ``depth`` nm deep at each of the ``landmarks`` (k, 2) nm, if given (step B;
    each reached with ``approach``, :func:`~jaxafm.position.positioning.goto`), then image the
    workspace along ``work``."""
    k_press, k_scan = jax.random.split(key)
    t0 = float(stand.afm.scanner.t)
    for j, d in enumerate(() if landmarks is None else landmarks):
        sample, stand, _ = press_at(
            pos, sample, stand, jnp.asarray(d), depth, jax.random.fold_in(k_press, j), approach=approach
        )
    images, stand = raster(pos, sample, stand, work, k_scan)
    return Survey(images, sample, stand, float(stand.afm.scanner.t) - t0)


def _trace_and_retrace(images: RasterScan, work: Raster, find, tolerance: float) -> np.ndarray:
    """Features found in both the trace and the retrace image, at the mean of the two: the feedback
    lag and the hysteresis left in the drive shift them in opposite directions. The retrace's finds
    are first moved by the shift that registers the whole retrace image onto the trace
    (``skimage.registration.phase_cross_correlation``), then paired with the trace's as mutual
    nearest neighbours within ``tolerance`` nm."""
    ft, fr = find(images.trace), find(images.retrace)
    if len(ft) == 0 or len(fr) == 0:
        return np.zeros((0, 2))
    rows_cols = registration.phase_cross_correlation(
        np.asarray(images.trace), np.asarray(images.retrace), upsample_factor=4
    )[0]
    shift = rows_cols[::-1] * np.asarray(work.pixel_size)  # (x, y) nm that carries the retrace onto the trace
    d = np.linalg.norm(ft[:, None] - (fr + shift)[None], axis=-1)
    j, i = np.argmin(d, axis=1), np.argmin(d, axis=0)
    ok = (i[j] == np.arange(len(ft))) & (d[np.arange(len(ft)), j] < tolerance)  # mutual nearest neighbours
    return (ft[ok] + fr[j[ok]]) / 2


def find_targets(
    images: RasterScan, work: Raster, particles: Particles, radius_nm: Sequence[float], spacing: float
) -> tuple:
    """The particles (radii in ``radius_nm`` [min, max], ``spacing`` nm apart) found in the
    workspace images, (K, 2) nm, and the index of the true particle each one is (from the true
    tip path over its pixel); unmatched finds are dropped."""
    found = _trace_and_retrace(
        images,
        work,
        lambda z: find_features(
            z,
            work,
            len(particles.radii) + 16,
            pits=False,
            min_height=radius_nm[0],
            min_distance_nm=spacing / 3,
            window_nm=radius_nm[1] + 20.0,
        ),
        spacing / 2,
    )
    px = np.asarray(work.pixel_size)
    col_row = np.clip(np.round((found - np.asarray(work.origin)) / px).astype(int), 0, work.pixels - 1)
    true_xy = np.asarray(images.path_trace)[col_row[:, 1], col_row[:, 0]]
    d = np.linalg.norm(true_xy[:, None] - np.asarray(particles.centres)[None], axis=-1)
    which = np.argmin(d, axis=1)
    ok = d[np.arange(len(found)), which] < spacing / 3
    return found[ok], which[ok]


def find_landmarks(
    images: RasterScan, work: Raster, grid: LandmarkGrid, D: np.ndarray, depth: float
) -> tuple:
    """The indents found in the workspace image, ``M`` (k, 2) nm, and the wanted positions
    ``D`` (k, 2) nm they were pressed at (:func:`~jaxafm.position.landmarks.match_grid`); k <= N*N,
    with the grid's holes left out."""
    spacing = grid.step_px * min(work.pixel_size)
    found = _trace_and_retrace(
        images,
        work,
        lambda z: find_features(
            z,
            work,
            grid.n**2,
            pits=True,
            min_height=depth / 4,
            min_distance_nm=spacing / 2,
            window_nm=max(2.5 * min(work.pixel_size), 30.0),
        ),
        spacing / 2,
    )
    slot = match_grid(found, D, spacing)
    return found[slot >= 0], D[slot[slot >= 0]]


def landmark_maps(M: np.ndarray, D: np.ndarray, methods: Sequence[str], m: int, degree: int) -> dict:
    """Step B's maps ``{method: LandmarkMap}`` on the landmarks found, ``M`` seen where ``D`` was
    pressed, for each of ``methods``: the polynomial at the highest degree up to ``degree`` that
    they over-determine, the pairwise map over the ``m`` nearest (at most as many as were found).
    Empty when fewer than 3 were found. Where the found landmarks do not cover a target, the
    polynomial extrapolates (the nearest usable map)."""
    if len(M) < 3:
        return {}
    degree = max(usable_degree(len(M), degree), 1)  # 3 or 4 landmarks: a plane through them
    return {method: LandmarkMap(M, D, method, min(m, len(M)), degree) for method in methods}
