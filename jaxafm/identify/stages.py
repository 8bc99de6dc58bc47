"""The stages of step A's fit and what each minimises.

A periodic lattice makes the image loss many-valleyed. The fit stays in the right valley by
fitting the model first to the features' chords, each with its feature's lattice indices (a
smooth problem with one valley: :func:`chord_residuals`), and then to the images, both Gaussian-blurred alike
(:func:`image_residuals`), whose basin is as wide as the blur, sharpening in stages. The stages
are :class:`Stage` records (:func:`plan_stages`) and the solver's settings a :class:`FitPlan`;
:func:`fit_stage` runs one. The chord stages may climb a pyramid of coarsened scans
(:func:`coarse_factor`).

Every residual function takes ``(raw, args)`` with the data in ``args``, so that a compiled
solve serves every scan of the same shapes (:func:`~jaxafm.identify.fit.solve`).
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Sequence
from typing import NamedTuple, Optional, Union

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..config.calibrate import coarsen_fits
from .calibration_scan import CalibrationScan, coarse_pixels
from .chords import background_design
from .fit import check_solver, linearisation, residual_values, solve
from .image_ops import blur, gaussian_kernel
from .quantities import known_misfits
from .scan_model import ScanModel

Array = jax.Array

#: the coarse stages keep at least this many pixels per lattice pitch along the lines
COARSE_PX_PER_PITCH = 8


@dataclasses.dataclass(frozen=True)
class FitPlan:
    """How step A's staged fit runs (:func:`~jaxafm.identify.staged_fit.identify`).

    Attributes:
        solver: one of :data:`~jaxafm.config.names.SOLVERS`.
        blur_px: the image stages' Gaussian blurs (pixels of the stage's scans), widest first.
        coarsen: the most pixels of a line a chord stage averages into one (a power of two),
            1 for none, ``"auto"`` for :func:`coarse_factor`'s choice.
        max_steps: the stages' step limit: one for every stage, or one per stage in order (the
            chord stages, then each blur).
        rtol: each stage's relative tolerance.
        atol: each stage's absolute tolerance.
        hold_out: hold out the odd sites of a checkerboard of the lattice for validation.
        select: climb the model ladder (:func:`~jaxafm.identify.selection.select`) in the last
            chord stage, to the model the data support; else fit the configured model as it is.
        wide_loop: the loop may hold the retrace more than a pitch behind the trace at the line
            reversal: every scan's retrace matchings are tried, one a pitch further back among
            them (:meth:`~jaxafm.identify.calibration_scan.CalibrationScan.feature_matches`),
            a later scan's in the first chord stage over all scans
            (:meth:`~jaxafm.identify.staged_fit._StagedFit._matched`).
        path_tolerance_nm: the tip path's sd (nm, rms over the images) a fit may leave open: a
            path more open than this and than a held-out feature's predicted error is refused
            (:func:`~jaxafm.identify.plausibility.unsettled`); ``None``: a tenth of the scans'
            finest pixel (:data:`~jaxafm.identify.plausibility.PATH_TOLERANCE_PX`).
    """

    solver: str = "jaxafm.geodesic_levenberg_marquardt"
    blur_px: tuple = (2.0, 1.0)
    coarsen: Union[int, str] = 1
    max_steps: Union[int, tuple] = 100
    rtol: float = 1e-5
    atol: float = 1e-8
    hold_out: bool = True
    select: bool = True
    wide_loop: bool = False
    path_tolerance_nm: Optional[float] = None


class StageKind(enum.Enum):
    """What a stage fits: the features' chords, or the blurred images."""

    CHORDS = "chords"
    IMAGES = "images"


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of step A's fit.

    Attributes:
        kind: what it fits.
        label: its name in the log and the metrics (display only).
        first_scan_only: it fits the first scan alone (the first chord stage of several scans).
        blur_px: an image stage's Gaussian sigma (px).
        radius_px: the blur kernel's half width (px), one for every image stage so that their
            compiled solves are one.
    """

    kind: StageKind
    label: str
    first_scan_only: bool = False
    blur_px: float = 0.0
    radius_px: int = 0

    def scans(self, scans: tuple) -> tuple:
        """The scans this stage fits."""
        return scans[:1] if self.first_scan_only else scans

    def kernel(self) -> np.ndarray:
        """An image stage's blur kernel (:func:`~jaxafm.identify.image_ops.gaussian_kernel`)."""
        return gaussian_kernel(self.blur_px, self.radius_px)


def plan_stages(scans: int, blur_px: Sequence[float]) -> tuple:
    """Step A's stages for ``scans`` scans: the chords (of the first scan, then of all
    when there are several), then the images at each blur of ``blur_px``, widest first.

    Raises:
        ValueError: for a blur outside 0 to 64 px.
    """
    for b in blur_px:
        if not 0 <= b <= 64:
            raise ValueError(f"blur_px: each blur is a Gaussian sigma of 0 to 64 px, got {b}")
    several = scans > 1
    plan = [Stage(StageKind.CHORDS, "chords" + (", first scan" if several else ""), several)]
    if several:
        plan.append(Stage(StageKind.CHORDS, "chords, all scans"))
    radius = int(np.ceil(3 * max(blur_px, default=0)))
    plan += [Stage(StageKind.IMAGES, f"images, blur {b:g} px", blur_px=b, radius_px=radius) for b in blur_px]
    return tuple(plan)


def stage_steps(max_steps: Union[int, Sequence[int]], stages: Sequence[Stage]) -> list:
    """Each of ``stages``' step limit: ``max_steps`` for all, or its entries one per stage.

    Raises:
        ValueError: for a list of another length than the stages.
    """
    if isinstance(max_steps, (int, np.integer)):
        return [max_steps] * len(stages)
    limits = list(max_steps)
    if len(limits) != len(stages):
        raise ValueError(
            f"max_steps (a config's solver.max_steps) = {limits} gives {len(limits)} step limits for "
            f"{len(stages)} stages ({'; '.join(s.label for s in stages)}): give one number for every stage "
            "or one per stage"
        )
    return limits


def coarse_factor(scans: Sequence[CalibrationScan], coarsen: Union[int, str] = "auto") -> int:
    """The most pixels of a line step A's chord stages average into one (its pyramid's top).

    ``"auto"``: the largest power of two that divides every scan's pixels per line and leaves
    :data:`COARSE_PX_PER_PITCH` pixels per pitch; a given number must fit the scans
    (:func:`~jaxafm.config.calibrate.coarsen_fits`).

    Raises:
        ValueError: for a given number that does not fit the scans, with what would.
    """
    pixels = [scan.raster.pixels for scan in scans]
    per_pitch = min(min(scan.pitch) / scan.raster.pixel_size[0] for scan in scans)  # along a line
    if coarsen == "auto":
        factor = 1
        while all(p % (2 * factor) == 0 for p in pixels) and per_pitch / (2 * factor) >= COARSE_PX_PER_PITCH:
            factor *= 2
        return factor
    if not coarsen_fits(coarsen, pixels, per_pitch):
        raise ValueError(
            f"coarsen (a config's solver.coarsen) = {coarsen!r} must be a power of two (1: no coarse "
            f"stages) that divides the scans' pixels per line {pixels} and leaves 2 px per pitch "
            f"({per_pitch:.3g} px per pitch at full resolution); 'auto' would take {coarse_factor(scans)}"
        )
    return int(coarsen)


# ---------------------------------------------------------------------------------------------
# What the stages minimise


def chord_residuals(raw, args) -> Array:
    """Per training chord, how far (in pitches) its midpoint lies off its feature's line of
    midpoints through the lattice site
    (:meth:`~jaxafm.identify.scan_model.ScanModel.chord_offsets`), the chord's ends placed where
    the model's tip was when it crossed them (the edge delay earlier), times its weight (0 for
    the padding of :func:`pad_chords`): where the model places the features. Needs only the
    tip's path. ``args = (start model, scans, chords)``, ``chords`` as :func:`chord_data` gives
    them."""
    start, scans, chords = args
    model = start.free_parameters(scans[0])[1](raw)
    return _chord_terms(model, scans, chords, [model.paths(scan) for scan in scans])[0]


def chord_fit_residuals(raw, args) -> Array:
    """What the chord stages minimise: :func:`chord_residuals`, then, where the model says so
    (:attr:`~jaxafm.identify.scan_model.ScanModel.chord_lengths`), each chord's length against
    its features' common length (:func:`width_misfits`), scan by scan."""
    start, scans, chords = args
    model = start.free_parameters(scans[0])[1](raw)
    return jnp.concatenate(_chord_terms(model, scans, chords, [model.paths(scan) for scan in scans]))


def _chord_terms(model: ScanModel, scans: tuple, chords: tuple, paths: list) -> tuple:
    """``(offsets, widths)``: :func:`chord_residuals` of ``model`` with the tip's ``paths`` (per
    scan, trace and retrace) given, and :func:`width_misfits` per scan (empty unless the model
    fits the chords' lengths)."""
    out, widths = [], [jnp.zeros(0)]
    for scan, images, path in zip(scans, chords, paths):
        shift = model.edge_delay / scan.raster.sample_time  # columns of this scan
        placed = []
        for trace, (ends, ij, along, w), forward in zip(path, images, (1.0, -1.0)):
            tips = model.chord_ends(trace, ends, forward * shift)
            out.append(w * model.chord_offsets(tips, ij, along) / min(scan.pitch))
            placed.append((tips, ij, along, w))
        if model.chord_lengths:
            widths.append(_scan_width_misfits(model, scan, placed))
    return jnp.concatenate(out), jnp.concatenate(widths)


def _scan_width_misfits(model: ScanModel, scan: CalibrationScan, placed: list) -> Array:
    """:func:`width_misfits` of one scan's chords, trace and retrace together: per image the
    tip positions at the chords' ends (n, 2, 2) nm and the chords' ``(ij, along, w)``."""
    parts = [(*model.chord_spans(tips, ij), along, w) for tips, ij, along, w in placed]
    lengths, offsets, along, w = (jnp.concatenate(v) for v in zip(*parts))
    return width_misfits(lengths, offsets, along, w, min(scan.pitch))


#: the nodes of a feature's chord-length profile over the chord's distance from the feature's
#: centre, 0 to half a pitch (:func:`width_misfits`)
WIDTH_NODES = 17


def width_misfits(lengths: Array, offsets: Array, along: Array, w: Array, pitch: float) -> Array:
    """How far (n,) each chord's length lies from its features' common length at its distance
    from their centres, in pitches: every feature of a lattice has one shape, so chords the same
    distance from their features' centres, running the same way, are one length, whatever the
    shape. The common length is a profile linear between :data:`WIDTH_NODES` nodes over half a
    pitch, one for the chords along the lines and one for those along the columns, fitted to
    the weighted chords and projected out (Frisch-Waugh-Lovell). A chord's midpoint alone leaves
    the path free to run fast or slow across its feature; its length holds the path's local
    scale. Times half the chords' weights: a length is the difference of two edges, a midpoint
    their mean, so its noise is twice the midpoint's.

    Arguments:
        lengths: the chords' lengths (n,) nm.
        offsets: their distances (n,) nm from their features' centres.
        along: whether each runs along the lines (n,).
        w: their weights (n,).
        pitch: the lattice's pitch, nm.
    """
    nodes = jnp.linspace(0.0, 0.5, WIDTH_NODES)
    hat = jnp.clip(1.0 - jnp.abs(jnp.minimum(offsets / pitch, 0.5)[:, None] - nodes) / nodes[1], 0.0, 1.0)
    along = jnp.asarray(along, dtype=hat.dtype)[:, None]
    z = jnp.concatenate([hat * along, hat * (1.0 - along)], axis=1)
    zw = z * w[:, None]
    gram = zw.T @ z + 1e-9 * jnp.eye(z.shape[1])
    fitted = z @ jnp.linalg.solve(gram, zw.T @ (lengths / pitch))
    return 0.5 * w * (lengths / pitch - fitted)


def refit_edges(model: ScanModel, scans: tuple, chords: tuple, steps: int = 8) -> ScanModel:
    """``model`` with its chord nuisances (``edge_delay`` when it has a feedback lag, and
    ``chord_slope``) refitted to the training ``chords`` (:func:`chord_data`), the scanner held:
    an image stage moves the scanner and the feedback lag but cannot see these two (the model
    images the lattice itself), so its held-out features are placed with the edges it implies.
    Gauss-Newton on :func:`chord_residuals`' terms, the delay projected onto >= 0 as step A
    keeps it (:class:`ScanModel`); ``steps`` iterations of a problem linear in the slopes and
    nearly linear in the delay."""
    free_delay = model.feedback is not None
    paths = [model.paths(scan) for scan in scans]

    def residuals(p):
        m = eqx.tree_at(lambda m: (m.edge_delay, m.chord_slope), model, (p[0], p[1:]))
        return _chord_terms(m, scans, chords, paths)[0]

    p = jnp.concatenate([jnp.reshape(model.edge_delay, 1), model.chord_slope])
    keep = jnp.asarray([1.0 if free_delay else 0.0, 1.0, 1.0])
    jac = jax.jit(jax.jacfwd(residuals))
    res = jax.jit(residuals)
    for _ in range(steps):
        J = jac(p) * keep
        r = res(p)
        H = J.T @ J + 1e-12 * jnp.trace(J.T @ J) * jnp.eye(3) + jnp.diag(1.0 - keep)
        p = p - jnp.linalg.solve(H, J.T @ r)
        p = p.at[0].max(0.0)
    return eqx.tree_at(lambda m: (m.edge_delay, m.chord_slope), model, (p[0], p[1:]))


def count_chords(chords) -> Array:
    """How many chords (not padding) a chord stage's data hold."""
    return sum(jnp.sum(w) for images in chords for *_, w in images)


def chord_loss(raw, args) -> Array:
    """Half the sum of squares of :func:`chord_fit_residuals` over the chords' count (not the padding)."""
    return 0.5 * jnp.sum(chord_fit_residuals(raw, args) ** 2) / count_chords(args[2])


class PaddedChords(NamedTuple):
    """One image's chords as a chord stage takes them (:func:`pad_chords`): their ends (m, 2, 2)
    px (row, column), their features' lattice indices (m, 2), whether each runs along the lines
    (m,), and each one's weight (m,): 1 for a chord, 0 for the padding."""

    ends: Array
    ij: Array
    along: Array
    weight: Array


def pad_chords(ends: np.ndarray, ij: np.ndarray, along: np.ndarray, size: int) -> PaddedChords:
    """Chords ``(ends, ij, along)`` ((n, 2, 2), (n, 2), (n,)) padded to ``size`` (or the next
    power of two above n, if more) with weight 0 (a dummy chord across the first pixel): the
    chord fits of every scan of one raster then have one shape (:func:`chord_capacity`), and
    their compiled solves are reused."""
    n = len(ends)
    pad = (size if n <= size else 1 << (n - 1).bit_length()) - n
    dummy = np.broadcast_to(np.array([[0.0, 0.0], [0.0, 1.0]]), (pad, 2, 2))
    return PaddedChords(
        jnp.asarray(np.concatenate([np.asarray(ends, float).reshape(-1, 2, 2), dummy])),
        jnp.asarray(np.concatenate([np.asarray(ij, float).reshape(-1, 2), np.zeros((pad, 2))])),
        jnp.asarray(np.concatenate([np.asarray(along, bool), np.ones(pad, bool)])),
        jnp.asarray(np.r_[np.ones(n), np.zeros(pad)]),
    )


def chord_capacity(scan: CalibrationScan) -> int:
    """The most chords an image of ``scan`` can hold: each line crosses at most one feature per
    pitch of its width and one more, each pixel column one per pitch of the height and one more."""
    r = scan.raster
    per_line = int(np.ceil(r.size[0] / min(scan.pitch))) + 1
    per_column = int(np.ceil(r.size[1] / min(scan.pitch))) + 1
    return r.lines * per_line + r.pixels * per_column


def feature_keys(chords: tuple, rows: Optional[int] = None) -> np.ndarray:
    """Per row of :func:`chord_fit_residuals` over the data ``chords``, its feature's lattice
    indices (n, 2); NaN for the padding. Its midpoints' rows (:func:`chord_residuals`) come
    first, then, where it has ``rows`` (default: as many as midpoints) for them, its lengths',
    chord for chord in the same order."""
    keys = np.concatenate(
        [
            np.where(np.asarray(w)[:, None] > 0, np.asarray(ij), np.nan)
            for images in chords
            for _, ij, _, w in images
        ]
    )
    return np.tile(keys, ((rows or len(keys)) // len(keys), 1))


def feature_groups(chords: tuple, rows: Optional[int] = None) -> np.ndarray:
    """Per row of :func:`chord_fit_residuals` over the data ``chords`` (``rows`` of them,
    :func:`feature_keys`), its feature's number: one number per lattice site, whichever image or
    scan shows it; -1 for the padding."""
    keys = feature_keys(chords, rows)
    real = ~np.isnan(keys[:, 0])
    out = np.full(len(keys), -1)
    out[real] = np.unique(keys[real], axis=0, return_inverse=True)[1].ravel()
    return out


def coarse_ends(ends: np.ndarray, factor: int) -> np.ndarray:
    """Chord ends (n, 2, 2) in the pixels of the scan coarsened by ``factor``."""
    return coarse_pixels(np.asarray(ends).reshape(-1, 2), factor).reshape(-1, 2, 2)


def chord_data(part: list, scans: tuple, factor: int) -> tuple:
    """A chord stage's data: per scan, per image, the chords ``(ends, ij, along)`` of ``part``
    (:func:`~jaxafm.identify.held_out.split_chords`) on the ``scans`` coarsened by ``factor``
    (:func:`~jaxafm.identify.calibration_scan.coarse_pixels`), padded to the scan's
    :func:`chord_capacity` (:func:`pad_chords`)."""
    return tuple(
        tuple(
            pad_chords(coarse_ends(ends, factor), ij, along, chord_capacity(scan))
            for ends, ij, along in images
        )
        for images, scan in zip(part, scans)
    )


def image_residuals(raw, args) -> Array:
    """The model's image less the measured one, both blurred by ``kernel``, its height
    background projected out (:func:`level_out`: the model images the lattice alone, the
    measured image carries a plane and a bow, which no scanner parameter may be bent to
    explain), weighted by the training ``masks`` (scan, 2, lines, pixels), trace and
    retrace, in fractions of the measured depth. ``args = (start model, scans, (kernel, masks))``."""
    start, scans, (kernel, masks) = args
    model = start.free_parameters(scans[0])[1](raw)
    out = []
    for scan, mask in zip(scans, masks):
        image = model.image(scan)
        for w, m, z in zip(mask, (image.trace, image.retrace), (scan.trace, scan.retrace)):
            d = level_out(blur(m, kernel) - blur(z, kernel), w)
            out.append((w * d / scan.depth_scale).ravel())
    return jnp.concatenate(out)


def level_out(d: Array, w: Array) -> Array:
    """``d`` (lines, pixels) less its weighted least-squares fit by the Legendre polynomials of
    :func:`~jaxafm.identify.chords.background_design` (a plane and a bow), weights ``w``.

    No offset per line: a line's mean height carries where it crosses the features (a line
    over a row of pits sits lower than one between rows), which is the position information the
    fit is after. :func:`~jaxafm.identify.projection.project_out` for one group, in JAX, so that
    the image residuals stay differentiable."""
    p = jnp.asarray(background_design(d.shape)).reshape(*d.shape, -1)
    a = jnp.einsum("lpk,lp,lpj->kj", p, w, p)
    coef = jnp.linalg.solve(
        a + 1e-12 * jnp.trace(a) * jnp.eye(a.shape[0]), jnp.einsum("lpk,lp,lp->k", p, w, d)
    )
    return d - p @ coef


def image_loss(raw, args) -> Array:
    """Half the mean square of :func:`image_residuals`."""
    return 0.5 * jnp.mean(image_residuals(raw, args) ** 2)


#: step A's smoothness prior on a Preisach density: the spread of its second differences
#: (:meth:`~jaxafm.model.hysteresis.Preisach.roughness`), in mean relay weights. The rms
#: second difference below the diagonal of a 16-level density fitted to a real piezo stack's
#: record (``piezo_sine_1hz.dat``, unregularised) is 0.46: a prior that real shapes pass.
DENSITY_CURVATURE = 0.5
#: the spread of one stage's residuals the prior is weighed against: a chord's midpoint, in
#: pitches, and an image pixel, in fractions of the depth
CHORD_NOISE = 0.01
IMAGE_NOISE = 0.05


def prior_rows(raw, args, noise: float) -> Array:
    """Step A's priors as least-squares rows weighed against a residual spread ``noise``: a
    Preisach density's roughness (:meth:`ScanModel.roughness`) in spreads of
    :data:`DENSITY_CURVATURE`, and each quantity the user stated (:attr:`ScanModel.known`) in its
    stated sd (:func:`~jaxafm.identify.quantities.known_misfits`), each times ``noise``: the rows
    that add ``sum (roughness / DENSITY_CURVATURE)^2 + sum ((q - value) / sd)^2`` to
    ``sum (r / noise)^2``; the stated quantities' rows times ``known_scale`` too, the residuals'
    own spread against ``noise`` (:func:`weigh_known`). Empty for plays with nothing stated."""
    start, scans, _ = args
    model = start.free_parameters(scans[0])[1](raw)
    rough = model.roughness(scans[0]) / DENSITY_CURVATURE
    return noise * jnp.concatenate([rough, model.known_scale * known_misfits(model, scans)])


def weigh_known(model: ScanModel, residuals: np.ndarray, count: float, noise: float) -> ScanModel:
    """``model`` with its stated quantities' rows (:func:`prior_rows`) weighed against the
    spread of its stage's ``residuals`` (rms over their ``count``, the padding left out) instead
    of ``noise``: ``known_scale`` = that spread / ``noise``, so that a stated sd counts as a
    Gaussian prior's against residuals that scatter as these do. Unchanged when nothing is
    stated."""
    if not model.known:
        return model
    spread = np.sqrt(np.sum(np.asarray(residuals) ** 2) / count)
    return eqx.tree_at(lambda m: m.known_scale, model, jnp.asarray(spread / noise, dtype=float))


def has_priors(model: ScanModel, scans: tuple) -> bool:
    """Whether :func:`prior_rows` has any row for ``model``: a Preisach density, or a stated quantity."""
    return bool(model.roughness(scans[0]).size or known_misfits(model, scans).size)


def prior_chord_residuals(raw, args) -> Array:
    """:func:`chord_fit_residuals` and the priors' rows weighed against a chord's spread."""
    return jnp.concatenate([chord_fit_residuals(raw, args), prior_rows(raw, args, CHORD_NOISE)])


def prior_chord_loss(raw, args) -> Array:
    """Half the sum of squares of :func:`prior_chord_residuals` over the chords' count."""
    return 0.5 * jnp.sum(prior_chord_residuals(raw, args) ** 2) / count_chords(args[2])


def chord_linearisation(model: ScanModel, scans: tuple, chords: tuple) -> tuple:
    """``(r, J, P)`` at ``model``: :func:`chord_fit_residuals` over the data ``chords`` (n,), their
    Jacobian (n, k) in the model's raw parameters (:meth:`ScanModel.free_parameters`, raveled),
    and the precision (k, k) of step A's priors in the same units (``J_p^T J_p`` of
    :func:`prior_chord_residuals`' prior rows: a Preisach density's smoothness, the quantities
    the user stated, weighed against the chords' own spread, :func:`weigh_known`; zero for
    plays with nothing stated)."""
    model = model.as_float64()
    raw = model.free_parameters(scans[0])[0]
    args = (model, scans, chords)
    if model.known:
        r = residual_values(chord_fit_residuals, raw, args)
        model = weigh_known(model, r, float(count_chords(chords)), CHORD_NOISE)
        args = (model, scans, chords)
    prior = prior_rows(raw, args, CHORD_NOISE).size
    r, J = linearisation(prior_chord_residuals if prior else chord_fit_residuals, raw, args)
    n = r.size - prior
    return r[:n], J[:n], J[n:].T @ J[n:]


def prior_image_residuals(raw, args) -> Array:
    """:func:`image_residuals` and the priors' rows weighed against a pixel's spread."""
    return jnp.concatenate([image_residuals(raw, args), prior_rows(raw, args, IMAGE_NOISE)])


def prior_image_loss(raw, args) -> Array:
    """Half the sum of squares of :func:`prior_image_residuals` over the image residuals' count."""
    r = image_residuals(raw, args)
    return 0.5 * (jnp.sum(r**2) + jnp.sum(prior_rows(raw, args, IMAGE_NOISE) ** 2)) / r.size


# ---------------------------------------------------------------------------------------------
# One stage


@dataclasses.dataclass(frozen=True)
class StageFit:
    """What :func:`fit_stage` returns: the fitted ``model``, the solver's ``steps``, whether it
    ``converged``, and the mean square residual ``loss`` (features: of the site errors in
    pitches; images: in fractions of the depth); ``passes``: the solves the steps were taken
    in (more than one where stated quantities were weighed anew, :data:`KNOWN_PASSES`)."""

    model: ScanModel
    steps: int
    converged: bool
    loss: float
    passes: int = 1


def fit_stage(stage: Stage, model: ScanModel, scans: tuple, data, plan: FitPlan, max_steps: int) -> StageFit:
    """One stage fitted from ``model`` with ``plan``'s solver: the chords (``data``: per scan,
    per image ``(ends, ij, along, weight)``, :func:`chord_data`) or the images (``data``:
    ``(kernel, masks)``) of ``scans``.

    Raises:
        RuntimeError: when the loss is not finite, naming the stage and the solver.
    """
    images = stage.kind is StageKind.IMAGES
    residuals, loss_fn = (image_residuals, image_loss) if images else (chord_fit_residuals, chord_loss)
    model = model.as_float64()
    args = (model, tuple(scans), data)
    raw0, rebuild = model.free_parameters(scans[0])
    fitted, fitted_loss = residuals, loss_fn
    if has_priors(model, scans):  # a Preisach density's smoothness, quantities the user stated
        fitted, fitted_loss = (
            (prior_image_residuals, prior_image_loss) if images else (prior_chord_residuals, prior_chord_loss)
        )
    # the path at fixed pixels is smooth in the parameters, a finite difference is as good there
    # as the exact second derivative (the same tip path after the stage, to 0.01 nm, at 256²) and
    # compiles nothing more; the images are not (3.6 against 3.3 nm after the image stage)
    curvature = "jvp" if images else "difference"
    stated = bool(known_misfits(model, scans).size)  # rows only for quantities this model has
    steps, passes, raw, scale = 0, 0, raw0, None
    for _ in range(KNOWN_PASSES if stated else 1):
        if stated:  # stated quantities, weighed against the residuals where the solve starts
            weighed = _weighed_at(model, raw, args, residuals, images)
            if scale is not None and abs(float(weighed.known_scale) / scale - 1) <= KNOWN_SCALE_RTOL:
                break
            scale, args = float(weighed.known_scale), (weighed, tuple(scans), data)
        raw, taken, ok = solve(
            plan.solver, fitted, fitted_loss, raw, max_steps, plan.rtol, plan.atol, args, curvature
        )
        steps, passes = steps + taken, passes + 1
    r = residual_values(residuals, raw, args)
    loss = float(np.mean(r**2) if images else np.sum(r**2) / float(count_chords(data)))
    if not np.isfinite(loss):
        raise RuntimeError(
            f"step A stage '{stage.label}' diverged with {plan.solver} (loss {loss}); try another solver "
            "or a smaller model"
        )
    return StageFit(rebuild(raw), steps, ok, loss, passes)


#: a stage with stated quantities is solved again from its solution, the quantities' rows weighed
#: against the residuals' spread there, until that spread moves by at most KNOWN_SCALE_RTOL of
#: itself, at most KNOWN_PASSES times in all (:func:`weigh_known`)
KNOWN_PASSES = 3
KNOWN_SCALE_RTOL = 0.05


def _weighed_at(model: ScanModel, raw, args: tuple, residuals, images: bool) -> ScanModel:
    """``model`` with its stated quantities weighed (:func:`weigh_known`) against its stage's
    ``residuals`` at ``raw``."""
    r = residual_values(residuals, raw, args)
    count = r.size if images else float(count_chords(args[2]))
    return weigh_known(model, r, count, IMAGE_NOISE if images else CHORD_NOISE)


def check_plan(plan: FitPlan, stages: Sequence[Stage]) -> list:
    """The stages' step limits (:func:`stage_steps`), each checked with the plan's solver and
    tolerances (:func:`~jaxafm.identify.fit.check_solver`), after the plan's path tolerance
    (positive, or ``None``)."""
    limits = stage_steps(plan.max_steps, stages)
    tolerance = plan.path_tolerance_nm
    if tolerance is not None and not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(
            f"path_tolerance_nm (a config's solver.path_tolerance_nm) = {tolerance}: give a positive "
            "number of nm, or leave it out for a tenth of the scans' finest pixel"
        )
    for limit in limits:
        check_solver(plan.solver, limit, plan.rtol, plan.atol)
    return limits
