"""Step A: identify the scanner from one trace/retrace image pair of a calibration lattice.

The paper (section III-A) images a grating of known pitch after the
initialisation cycle ``{u2, u1}``, turns feature points into (voltage, true
position) pairs and fits a polynomial per branch. Here that polynomial is the
baseline (:func:`fit_polynomials`), and the scanner model itself is fitted end
to end: the simulated AFM images the known lattice through the candidate model
along the same drive, and the solver matches the two images, trace and
retrace together (:func:`identify`).

A periodic lattice makes the image loss many-valleyed. The fit stays in the
right valley in three ways: (1) the feature points carry lattice indices, and
trace and retrace columns are matched at the line reversal, where the tip is
continuous, so they cannot slip by a pitch; (2) the model is first fitted to
those points, a smooth problem with one valley; (3) the image fit then starts
from there on Gaussian-blurred images (both blurred alike), whose basin is as
wide as the blur, and sharpens in stages.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Optional, Union

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import checks
from ..config.calibrate import coarsen_fits
from ..config.names import MODEL_EFFECTS
from ..instrument.afm import AFM, Raster, RasterScan, raster_scan
from ..instrument.samples import Lattice, Plane, Tip
from ..model.effects import Bow, Coupling, Creep, Drift, FeedbackLag, RateDependence
from ..model.hysteresis import (
    AbstractHysteresis,
    Deadzone,
    GeneralizedPI,
    PrandtlIshlinskii,
    Preisach,
    softplus_inverse,
)
from ..model.io import check_monotone
from ..model.scanner import Axis, Scanner
from .features import LatticeFeatures, feature_centres, index_lattice, neighbour_distances, pitch_spread
from .fit import FitResult, _solve, check_solver, free_parameters, residual_values

Array = jax.Array
KEY = jax.random.key(0)  # a fitted model's drift has no wander, so its key never matters


class CalibrationScan(eqx.Module):
    """A trace/retrace image pair (lines, pixels) nm of a lattice of ``pitch`` (2,) nm, and
    how it was driven: the nominal calibration ``sensitivity`` (2,) nm/V through ``raster``,
    from rest at ``u0`` (2,) V at ``t0`` s after the drive ``history`` (H, 2) V.
    ``pits``: the lattice has pits, not pillars."""

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
        self.depth_scale = jnp.asarray(float(np.ptp(np.asarray(trace))) or 1.0)

    def coarse(self, factor: int) -> CalibrationScan:
        """This scan with ``factor`` pixels of each line averaged into one: the same lines and
        line rate, ``pixels / factor`` pixels a line, each at the mean of its fine pixels' centres,
        and the over-scan margin whose reversals come nearest the fine scan's (within
        ``factor / 2`` fine pixels). The drive then turns a little off the fine one's, so a fit
        to a coarse scan is a start for the fine scan, not its fit."""
        if factor == 1:
            return self
        r = self.raster
        pixels = r.pixels // factor
        margin = round((r.margin + (factor - 1) / 2) / factor)
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
        )

    @property
    def pitch_px(self) -> tuple:
        return tuple(p / s for p, s in zip(self.pitch, self.raster.pixel_size))

    def volts(self, rc: np.ndarray) -> np.ndarray:
        """The nominal drive (n, 2) V at fractional pixels ``rc`` (n, 2) (row, col)."""
        return self.raster.nominal(rc) / np.asarray(self.sensitivity)

    @property
    def name(self) -> str:
        return f"the {self.raster.angle_deg:g} degree scan"

    def features(self) -> tuple:
        """Pillar (or pit) centres of trace and retrace, indexed in one lattice frame: the
        lattice of their nominal stage positions (so images at any scan angle index alike);
        the retrace's indices matched to the trace's by the nearest feature at the line
        reversal (the first of :meth:`feature_matches`)."""
        trace, retraces = self.feature_matches()
        return trace, retraces[0]

    def feature_matches(self) -> tuple:
        """The trace's features and the retrace's, the latter indexed in each way the line
        reversal allows (:func:`_retrace_matches`): ``(trace, [retrace, ...])``."""
        sign = -1.0 if self.pits else 1.0
        found = []
        for k in ("trace", "retrace"):
            name = f"{self.name}'s {k} image"
            rc = feature_centres(sign * np.asarray(getattr(self, k)), name)
            _check_coverage(rc, self.pitch_px, (self.raster.lines, self.raster.pixels), name)
            ij, angle = index_lattice(self.raster.nominal(rc), self.pitch, name, "nm")
            found.append(LatticeFeatures(rc, ij, angle))
        return found[0], _retrace_matches(*found, self.pitch_px)


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
    nearer side's first. :func:`identify` keeps the one whose feature fit is best."""
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
    return [LatticeFeatures(fr.rc, fr.ij + np.asarray(shift), fr.angle) for shift in shifts]


class ScanModel(eqx.Module):
    """What step A fits: the scanner, the z-feedback lag, and the lattice's unknowns
    (phase, radius, depth, edge width; the pitch is known). ``rotation_free``: the lattice's
    angle on the stage is fitted too (:func:`parameters` says how that fixes a gauge)."""

    scanner: Scanner
    feedback: Optional[FeedbackLag]
    lattice: Lattice
    rotation_free: bool = eqx.field(static=True, default=False)

    def afm(self, scan: CalibrationScan) -> AFM:
        """The simulated AFM with this model as its scanner (tip dilation off)."""
        return AFM(
            self.scanner, Tip(), jnp.asarray(scan.sensitivity), self.feedback, u_max=scan.u_max, dilate=False
        )

    def paths(self, scan: CalibrationScan) -> tuple:
        """The tip's path (lines, pixels, 2) nm over the trace and the retrace pixels, along the
        scan's drive (the heights are not rendered)."""
        afm = eqx.tree_at(lambda a: a.feedback, self.afm(scan), None, is_leaf=lambda v: v is None)
        out = raster_scan(afm, Plane(), self._start(afm, scan), scan.raster, key=KEY)
        return out.path_trace, out.path_retrace

    def _start(self, afm: AFM, scan: CalibrationScan):
        return afm.initial_state(
            scan.u0, scan.t0, None if scan.history is None else jnp.asarray(scan.history)
        )

    def image(self, scan: CalibrationScan) -> RasterScan:
        """:func:`~jaxafm.instrument.afm.raster_scan` of the lattice through this model, along the
        scan's drive."""
        afm = self.afm(scan)
        return raster_scan(afm, self.lattice, self._start(afm, scan), scan.raster, key=KEY)

    def site_errors(self, scan: CalibrationScan, images: Sequence) -> list:
        """Per image of ``scan`` (trace, retrace), where this model puts the tip at each feature
        ``(rc, ij)`` of ``images`` less that feature's lattice site, in pitches (n, 2) along the
        lattice's axes."""
        return [
            self.lattice.coordinates(_interpolate(path, jnp.asarray(rc))) - jnp.asarray(ij)
            for (rc, ij), path in zip(images, self.paths(scan))
        ]


def initial_model(
    scan: CalibrationScan,
    kind: str = "gpi",
    effects: Sequence[str] = MODEL_EFFECTS,
    operators: int = 20,
    deadzones: int = 3,
    levels: int = 20,
    rotation: Optional[float] = 0.0,
) -> ScanModel:
    """The nominal model a fit starts from: the straight calibration line, no other effect yet.

    ``kind``: ``pi`` (``operators`` plays evenly over ``[0, u_max)``), ``gpi`` (plus
    ``deadzones`` dead zones a side, evenly over the imaged half width: beyond it no data
    would hold them) or ``preisach`` (``levels`` levels over ``+-u_max``). ``effects``
    lists the others to fit (names as in docs/conventions.md). ``rotation``: the lattice's
    known angle on the stage (rad), or ``None`` to fit it.
    """
    unknown = [e for e in effects if e not in MODEL_EFFECTS]
    if unknown:
        raise ValueError(
            f"effect {unknown[0]!r} cannot be fitted from grating images; "
            f"choose from {', '.join(MODEL_EFFECTS)}"
        )
    if kind == "gpi" and "asymmetry" not in effects:
        kind = "pi"

    def axis(gain: float, k: int) -> Axis:
        half = gain * scan.u_max
        imaged = scan.raster.size[k] / 2  # dead zones where the image constrains them
        if kind == "preisach":
            h = Preisach.uniform(levels, -scan.u_max, scan.u_max, total=half)
        else:
            h = PrandtlIshlinskii.uniform(operators, scan.u_max, gain, others=1e-3)
            if kind == "gpi":
                steps = (np.arange(deadzones) + 1) / (deadzones + 1) * imaged
                h = GeneralizedPI(h, Deadzone.identity(-steps, steps))
            elif kind != "pi":
                raise ValueError(f"unknown hysteresis model {kind!r}; one of pi, gpi, preisach")
        return Axis(
            h,
            RateDependence(jnp.asarray(5e-3)) if "rate_dependence" in effects else None,
            Creep.logarithmic(CREEP_START, per_decade=1) if "creep" in effects else None,
        )

    has = lambda e, module: module if e in effects else None
    scanner = Scanner(
        axis(scan.sensitivity[0], 0),
        axis(scan.sensitivity[1], 1),
        has("coupling", Coupling(jnp.zeros(()), jnp.zeros(()))),
        has("bow", Bow(jnp.zeros(()), jnp.zeros(()))),
        has("drift", Drift(jnp.zeros(2), jnp.zeros(2), jnp.asarray(1e-3))),
    )
    z = -np.asarray(scan.trace) if scan.pits else np.asarray(scan.trace)
    depth = float(np.percentile(z, 98) - np.percentile(z, 2))
    lattice = Lattice(
        jnp.asarray(scan.pitch),
        jnp.asarray(0.25 * min(scan.pitch)),
        jnp.asarray(-depth if scan.pits else depth),
        jnp.asarray(50.0),
        jnp.asarray(0.0 if rotation is None else rotation),
        jnp.zeros(2),
    )
    return ScanModel(scanner, has("feedback_lag", FeedbackLag(jnp.asarray(5e-4))), lattice, rotation is None)


#: step A's starting creep, fraction per decade: positive, as its fit keeps it (a tenth of the
#: 0.01-0.02 of published data)
CREEP_START = 1e-3


def _field(get: Callable, scale: float, positive: bool = False, shared: bool = False):
    """One fitted field: its getter, the maps raw (order one) -> value -> raw, and whether one
    raw number is shared by all its elements."""
    return (
        get,
        (lambda r: jax.nn.softplus(r) * scale) if positive else (lambda r: r * scale),
        (lambda v: softplus_inverse(v / scale)) if positive else (lambda v: v / scale),
        shared,
    )


def parameters(model: ScanModel, scan: CalibrationScan) -> tuple:
    """``(raw, rebuild)``: the fitted parameters at order one, and the map back to a model.

    Two gauges, as no image can tell them apart. The hysteresis offsets stay at 0: a
    translation of the whole image is the lattice's phase, so the scanner's zero stays
    where its virgin state put it. With the lattice's rotation fitted, the coupling of y
    from x (``coupling.yx``) stays 0: turning the lattice by ``a`` and adding ``a`` to
    ``coupling.yx`` and ``-a`` to ``coupling.xy`` move every image alike (to first order),
    so the scanner's x axis is defined as the direction its x piezo moves the tip, and
    the fitted rotation is the lattice's from that axis.
    """
    travel = 2 * scan.u_max * float(np.mean(scan.sensitivity))
    pitch = min(scan.pitch)
    fields = [
        _field(lambda m: m.lattice.phase, pitch),
        _field(lambda m: m.lattice.radius, pitch, True),
        _field(lambda m: m.lattice.depth, scan.depth_scale),
        _field(lambda m: m.lattice.edge_width, 50.0, True),
    ]
    s = model.scanner
    if model.rotation_free:
        fields.append(_field(lambda m: m.lattice.angle, 0.01))
    if s.coupling is not None:
        fields.append(_field(lambda m: m.scanner.coupling.xy, 0.01))
        if not model.rotation_free:
            fields.append(_field(lambda m: m.scanner.coupling.yx, 0.01))
    if s.bow is not None:
        fields += [_field(lambda m: m.scanner.bow.bx, 1e-6), _field(lambda m: m.scanner.bow.by, 1e-6)]
    if s.drift is not None:
        fields.append(_field(lambda m: m.scanner.drift.velocity, 0.05))
    if model.feedback is not None:
        fields.append(_field(lambda m: m.feedback.tau, 1e-3, True))
    for a in ("x", "y"):
        axis = getattr(s, a)
        if axis.creep is not None:  # logarithmic creep: one gamma per axis, its lags as configured,
            n = axis.creep.weights.size  # and positive: creep continues the move
            creep = lambda m, a=a: getattr(m.scanner, a).creep.weights
            fields.append(_field(creep, 0.01 / n, positive=True, shared=True))
        if axis.rate_dependence is not None:
            fields.append(_field(lambda m, a=a: getattr(m.scanner, a).rate_dependence.tau, 1e-3, True))
    getters = [f[0] for f in fields]
    hysteresis = [free_parameters(getattr(s, a).hysteresis, 2 * scan.u_max, travel) for a in ("x", "y")]
    raw = (
        [jnp.mean(f[2](f[0](model))) if f[3] else f[2](f[0](model)) for f in fields],
        [h[0] for h in hysteresis],
    )

    def rebuild(raw):
        values = [f[1](r) * jnp.ones_like(f[0](model)) for f, r in zip(fields, raw[0])]
        m = eqx.tree_at(lambda m: [g(m) for g in getters], model, values)
        h = [
            _zero_offset(rb(r), getattr(s, a).hysteresis)
            for (_, rb), r, a in zip(hysteresis, raw[1], ("x", "y"))
        ]
        return eqx.tree_at(lambda m: (m.scanner.x.hysteresis, m.scanner.y.hysteresis), m, tuple(h))

    return raw, rebuild


def _zero_offset(h: AbstractHysteresis, start: AbstractHysteresis) -> AbstractHysteresis:
    """``h`` with the offset of ``start`` (for a generalised PI, its PI operator's)."""
    return eqx.tree_at(lambda g: g.offset, h, start.offset)


def _interpolate(a: Array, rc: Array, xp=jnp) -> Array:
    """Bilinear interpolation of ``a`` (L, P, ...) at fractional pixels ``rc`` (n, 2), with the
    array module ``xp`` (``jax.numpy`` inside the fits, ``numpy`` for a look at a result)."""
    r0 = xp.clip(xp.floor(rc[:, 0]).astype(int), 0, a.shape[0] - 2)
    c0 = xp.clip(xp.floor(rc[:, 1]).astype(int), 0, a.shape[1] - 2)
    fr, fc = (rc[:, 0] - r0)[:, None], (rc[:, 1] - c0)[:, None]
    return (
        (1 - fr) * (1 - fc) * a[r0, c0]
        + (1 - fr) * fc * a[r0, c0 + 1]
        + fr * (1 - fc) * a[r0 + 1, c0]
        + fr * fc * a[r0 + 1, c0 + 1]
    )


def gaussian_kernel(sigma_px: float, radius: int) -> np.ndarray:
    """Taps ``-radius..radius`` of a Gaussian of ``sigma_px`` pixels (a unit impulse for 0)."""
    k = np.arange(-radius, radius + 1)
    return (k == 0).astype(float) if sigma_px <= 0 else np.exp(-0.5 * (k / sigma_px) ** 2)


def blur(z: Array, kernel: Array) -> Array:
    """Separable blur of an image along both axes, renormalised at the borders."""
    r = (kernel.shape[0] - 1) // 2

    def along(a, axis):
        padded = jnp.pad(a, [(r, r) if ax == axis else (0, 0) for ax in range(a.ndim)])
        return sum(
            kernel[i] * jax.lax.slice_in_dim(padded, i, i + a.shape[axis], axis=axis)
            for i in range(kernel.shape[0])
        )

    return along(along(z, 0), 1) / along(along(jnp.ones_like(z), 0), 1)


@dataclasses.dataclass(frozen=True)
class Identification:
    """What :func:`identify` returns.

    Attributes:
        model: the fitted :class:`ScanModel` (the last accepted stage's).
        stages: one :class:`~jaxafm.identify.fit.FitResult` per stage (feature points, then
            each blur), in order.
        seconds: the whole identification's wall time (s).
        accepted: per stage, whether its result was kept (an image stage that worsens the
            held-out features is not, :func:`_judge`).
        held_out_nm: per stage, the held-out features' rms distance from their lattice sites
            (nm) after it; NaN when no feature is held out.
        validation: the held-out features' summary (:func:`validate`).
        failures: what failed the plausibility checks (:func:`implausible`); empty if none.
    """

    model: ScanModel
    stages: tuple
    seconds: float
    accepted: tuple = ()
    held_out_nm: tuple = ()
    validation: dict = dataclasses.field(default_factory=dict)
    failures: tuple = ()

    @property
    def converged(self) -> bool:
        return all(
            s.converged for s, ok in zip(self.stages, self.accepted or [True] * len(self.stages)) if ok
        )

    @property
    def plausible(self) -> bool:
        return not self.failures


def _point_residuals(raw, args) -> Array:
    """At each training feature point, where the model puts the tip less that feature's lattice
    site, in pitches along the lattice's axes (every scan, trace and retrace), times its weight
    (0 for the padding of :func:`_padded`). Needs only the tip's path."""
    start, scans, points = args
    model = parameters(start, scans[0])[1](raw)
    return jnp.concatenate(
        [
            (e * w[:, None]).ravel()
            for scan, images in zip(scans, points)
            for e, (_, _, w) in zip(model.site_errors(scan, [(rc, ij) for rc, ij, _ in images]), images)
        ]
    )


def _features(points) -> Array:
    """How many features (not padding) the feature stage's data ``points`` hold."""
    return sum(jnp.sum(w) for images in points for _, _, w in images)


def _point_loss(raw, args) -> Array:
    """Half the mean square of :func:`_point_residuals` over the features (not the padding)."""
    return jnp.sum(_point_residuals(raw, args) ** 2) / (4 * _features(args[2]))


def _padded(rc: np.ndarray, ij: np.ndarray) -> tuple:
    """Features ``(rc, ij)`` (n, 2) padded to the next power of two with weight 0, and their
    weights (1 for a feature): every scanner's feature fit then has one of a few shapes, and its
    compiled solve is reused, although the features found differ from scan to scan."""
    n = len(rc)
    pad = (1 << max(n - 1, 0).bit_length()) - n
    zeros = np.zeros((pad, 2))
    return (
        jnp.asarray(np.concatenate([rc, zeros])),
        jnp.asarray(np.concatenate([ij, zeros.astype(np.asarray(ij).dtype)])),
        jnp.asarray(np.r_[np.ones(n), np.zeros(pad)]),
    )


def _image_residuals(raw, args) -> Array:
    """The model's image less the measured one, both blurred by ``kernel``, weighted by the
    training ``masks`` (scan, 2, lines, pixels), trace and retrace, in fractions of the
    measured depth."""
    start, scans, (kernel, masks) = args
    model = parameters(start, scans[0])[1](raw)
    out = []
    for scan, mask in zip(scans, masks):
        image = model.image(scan)
        for w, m, z in zip(mask, (image.trace, image.retrace), (scan.trace, scan.retrace)):
            out.append((w * (blur(m, kernel) - blur(z, kernel)) / scan.depth_scale).ravel())
    return jnp.concatenate(out)


def _image_loss(raw, args) -> Array:
    """Half the mean square of :func:`_image_residuals`."""
    return 0.5 * jnp.mean(_image_residuals(raw, args) ** 2)


def identify(
    scans,
    model: Optional[ScanModel] = None,
    *,
    kind: str = "gpi",
    effects: Sequence[str] = MODEL_EFFECTS,
    operators: int = 20,
    deadzones: int = 3,
    levels: int = 20,
    rotation: Optional[float] = 0.0,
    hold_out: bool = True,
    solver: str = "jaxafm.geodesic_levenberg_marquardt",
    blur_px: Sequence[float] = (2.0, 1.0),
    coarsen: Union[int, str] = 1,
    max_steps: Union[int, Sequence[int]] = 100,
    rtol: float = 1e-5,
    atol: float = 1e-8,
    log: Callable = print,
) -> Identification:
    """Fit the scanner end to end: to the feature points, then to the images at each blur.

    Several scans (e.g. at scan angles 0 and 90 degrees, so that both axes reverse in the
    data) are fitted together; the first one's feature fit fixes how the others' lattice
    indices line up with its own (:func:`_align`). Half the features are held out
    (``hold_out``) as a checkerboard, those whose lattice indices sum to an odd number, so
    that every lattice row and column keeps features for both axes; the fit never sees them
    or the image around them (:func:`_split_masks`). An image stage is kept only if it does not worsen the held-out
    features' residual (nm, :func:`held_out_rms`) beyond its uncertainty (:func:`_judge`), so
    no stage leaves the feature fit's valley unnoticed: a slip by a pitch shows there first.
    The held-out image residual is reported beside it. The stages climb a pyramid along the
    scans' lines (:meth:`CalibrationScan.coarse`): the last stage fits the whole scans, the
    one before it every two pixels of a line averaged, the one before that four, up to
    ``coarsen``; a step costs about as much less. The result is the full-resolution fit.
    Never returns a silently bad fit: each stage's convergence, acceptance and loss are in
    the result, a stage whose loss is not finite raises, and the fitted model is checked
    (:func:`implausible`).

    Arguments:
        scans: a :class:`CalibrationScan` or several, of one lattice and one instrument.
        model: the start; by default :func:`initial_model` with ``kind``, ``effects``,
            ``operators``, ``deadzones``, ``levels`` and ``rotation``.
        rotation: the lattice's known angle on the stage (rad), or ``None`` to fit it.
        hold_out: hold out the odd sites of a checkerboard of the lattice for validation.
        solver: one of :data:`~jaxafm.identify.fit.SOLVERS`.
        blur_px: the image stages' Gaussian blurs (pixels of the stage's scans), widest first.
        coarsen: the most pixels of a line a stage averages into one (a power of two), 1 for
            none (the default), ``"auto"`` for :func:`coarse_factor`'s choice.
        max_steps: the stages' step limit: one for every stage, or one per stage in order (the
            feature stages, then each blur).
        rtol: each stage's relative tolerance.
        atol: each stage's absolute tolerance.
        log: where each stage's one-line summary goes.

    Returns:
        An :class:`Identification`.
    """
    scans = (scans,) if isinstance(scans, CalibrationScan) else tuple(scans)
    _check_set(scans)
    for b in blur_px:
        if not 0 <= b <= 64:
            raise ValueError(f"blur_px: each blur is a Gaussian sigma of 0 to 64 px, got {b}")
    factor = coarse_factor(scans, coarsen)
    start = time.perf_counter()
    trace, retraces = scans[0].feature_matches()
    found = [(trace, retraces[0])] + [scan.features() for scan in scans[1:]]
    if model is None:
        model = initial_model(scans[0], kind, effects, operators, deadzones, levels, rotation)
    model = _start_lattice(_float64(model), scans[0], found[0])  # float64 leaves: one compilation each
    train, test = _split(found, hold_out)  # the first stage may change the first scan's retrace
    plan = [("feature points" + (", first scan" if len(scans) > 1 else ""), scans[:1], None)]
    if len(scans) > 1:
        plan.append(("feature points, all scans", scans, None))
    radius = int(np.ceil(3 * max(blur_px, default=0)))
    plan += [(f"images, blur {b:g} px", scans, gaussian_kernel(b, radius)) for b in blur_px]
    limits = stage_steps(max_steps, [name for name, *_ in plan])
    for limit in limits:
        check_solver(solver, limit, rtol, atol)
    stages, accepted, held_nm, masks = [], [], [], None
    for i, (name, fitted, data) in enumerate(plan):
        if i == 1 and len(scans) > 1:
            train, test = _align(model, scans, found, train, test)
        image = name.startswith("images")
        k = 1 if image else factor  # the feature points on the coarse scans, the images whole
        level = tuple(scan.coarse(k) for scan in fitted)
        name += f", {level[0].raster.pixels} px a line" if k > 1 else ""
        if image:
            masks = masks or _split_masks(model, level, hold_out)
            data = (jnp.asarray(data), masks[0])
        log(f"  stage {i + 1}/{len(plan)} {name} ...")
        t0 = time.perf_counter()
        matched = ""
        if image:
            fit, steps, ok, loss = _fit_stage(name, model, level, data, solver, limits[i], rtol, atol)
        elif i == 0:
            (fit, steps, ok, loss), found, (train, test), matched = _first_features(
                name, model, level, found, retraces, hold_out, k, solver, limits[i], rtol, atol
            )
        else:
            data = _feature_data(train, k)
            fit, steps, ok, loss = _fit_stage(name, model, level, data, solver, limits[i], rtol, atol)
        message = (
            f"{solver}: converged in {steps} steps, loss {loss:.3e}"
            if ok
            else f"{solver}: did NOT converge in {steps} steps (max_steps={limits[i]}); last loss {loss:.3e}"
        ) + matched
        error = held_out_rms(fit, fitted, test[: len(fitted)])
        comparable = [e for e, (_, f, _) in zip(held_nm, plan) if len(f) == len(scans)]
        keep, verdict = _judge(comparable, error, test) if image else (True, "")
        if not np.isnan(error):
            message += f", held-out features {error:.2f} nm" + verdict
        if image and masks[1] is not None:
            message += f", held-out image {_held_out_image(fit, level, data[0], masks[1]):.3f} % of depth"
        model = fit if keep else model
        stages.append(FitResult(fit, solver, ok, steps, loss, time.perf_counter() - t0, message))
        accepted.append(keep)
        held_nm.append(error)
        log(f"  stage {i + 1}/{len(plan)} {name}: {message}, {stages[-1].seconds:.1f} s")
    return Identification(
        model,
        tuple(stages),
        time.perf_counter() - start,
        tuple(accepted),
        tuple(held_nm),
        validate(model, scans, test),
        tuple(implausible(model, scans)),
    )


def _split(found: list, hold_out: bool) -> tuple:
    """Per scan, per image, the features fitted and those held out: ``(train, test)``, each
    ``[[(rc, ij), ...], ...]``; held out are the odd sites of the lattice's checkerboard."""
    held = [[(f.ij.sum(axis=1) % 2 == 1) & hold_out for f in images] for images in found]
    train = [[(f.rc[~h], f.ij[~h]) for f, h in zip(images, hs)] for images, hs in zip(found, held)]
    test = [[(f.rc[h], f.ij[h]) for f, h in zip(images, hs)] for images, hs in zip(found, held)]
    return train, test


def _feature_data(train: list, factor: int) -> tuple:
    """The feature stage's data: per scan, per image, the fitted features on the scans
    coarsened by ``factor``, padded (:func:`_padded`)."""
    return tuple(tuple(_padded(_coarse_rc(rc, factor), ij) for rc, ij in images) for images in train)


def _first_features(
    name, model, level, found, retraces, hold_out, factor, solver, limit, rtol, atol
) -> tuple:
    """The first scan's feature stage, fitted once for each way of matching its retrace's
    indices to its trace's (:func:`_retrace_matches`); the best fit (lowest loss) says which
    is right: a retrace indexed a pitch off asks the hysteresis loop for a branch separation
    a pitch off near the reversal, where the loop closes, which no scanner model fits (on
    scanner 3 of configs/study.yaml its loss is 150 times the right match's). Returns
    the fit ``(model, steps, converged, loss)``, the features and their split with the chosen
    retrace, and a note for the stage's message (empty with one match)."""
    tried = []
    for retrace in retraces:
        features = [(found[0][0], retrace)] + list(found[1:])
        split = _split(features, hold_out)
        data = _feature_data(split[0][:1], factor)
        tried.append((_fit_stage(name, model, level, data, solver, limit, rtol, atol), features, split))
    losses = [t[0][3] for t in tried]
    best = int(np.argmin(losses))
    note = (
        f"; retrace indices matched the {'nearer' if best == 0 else 'other'} way at the line reversal "
        f"(loss {losses[best]:.3e}; {', '.join(f'{v:.3e}' for j, v in enumerate(losses) if j != best)} the other way)"
        if len(tried) > 1
        else ""
    )
    return (*tried[best], note)


def stage_steps(max_steps: Union[int, Sequence[int]], stages: Sequence[str]) -> list:
    """Each of ``stages``' step limit: ``max_steps`` for all, or its entries one per stage."""
    if isinstance(max_steps, (int, np.integer)):
        return [max_steps] * len(stages)
    limits = list(max_steps)
    if len(limits) != len(stages):
        raise ValueError(
            f"max_steps (a config's solver.max_steps) = {limits} gives {len(limits)} step limits for "
            f"{len(stages)} stages ({'; '.join(stages)}): give one number for every stage or one per stage"
        )
    return limits


#: the coarse stages keep at least this many pixels per lattice pitch along the lines
COARSE_PX_PER_PITCH = 8


def coarse_factor(scans: Sequence[CalibrationScan], coarsen: Union[int, str] = "auto") -> int:
    """The most pixels of a line :func:`identify`'s stages average into one (its pyramid's top).

    ``"auto"``: the largest power of two that divides every scan's pixels per line and leaves
    :data:`COARSE_PX_PER_PITCH` pixels per pitch; a given number must fit the scans
    (:func:`~jaxafm.config.calibrate.coarsen_fits`).
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


def _coarse_rc(rc: np.ndarray, factor: int) -> np.ndarray:
    """Fractional pixels (n, 2) (row, col) of a scan in its :meth:`CalibrationScan.coarse` scan."""
    rc = np.asarray(rc, dtype=float)
    return np.c_[rc[:, 0], (rc[:, 1] + 0.5) / factor - 0.5]


def _float64(model: ScanModel) -> ScanModel:
    """``model`` with every floating-point leaf a float64 array (none weakly typed), so that the
    stages' compiled functions see the same argument types from every model."""
    return jax.tree.map(lambda x: jnp.array(x, dtype=float) if eqx.is_inexact_array(x) else x, model)


def _fit_stage(name: str, model: ScanModel, scans: tuple, data, solver: str, max_steps, rtol, atol) -> tuple:
    """One stage: the feature points (``data``: per scan, per image ``(rc, ij, weight)``,
    :func:`_padded`) or the images (``data``: ``(kernel, masks)``) of ``scans``, fitted from
    ``model``; returns ``(fit, steps, converged, mean square residual)``, or raises when the loss
    is not finite."""
    image = name.startswith("images")
    residuals, loss_fn = (_image_residuals, _image_loss) if image else (_point_residuals, _point_loss)
    model = _float64(model)
    args = (model, tuple(scans), data)
    raw0, rebuild = parameters(model, scans[0])
    # the path at fixed pixels is smooth in the parameters, a finite difference is as good there
    # as the exact second derivative (the same tip path after the stage, to 0.01 nm, at 256²) and
    # compiles nothing more; the images are not (3.6 against 3.3 nm after the image stage)
    curvature = "jvp" if image else "difference"
    raw, steps, ok = _solve(solver, residuals, loss_fn, raw0, max_steps, rtol, atol, args, curvature)
    r = residual_values(residuals, raw, args)
    loss = float(np.mean(r**2) if image else np.sum(r**2) / (2 * _features(data)))
    if not np.isfinite(loss):
        raise RuntimeError(
            f"step A stage '{name}' diverged with {solver} (loss {loss}); try another solver or a smaller model"
        )
    return rebuild(raw), steps, ok, loss


def _check_set(scans: tuple) -> None:
    """Refuse a set of scans that are not of one lattice on one instrument, or repeat an angle."""
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
    angles = [s.raster.angle_deg for s in scans]
    if len(set(angles)) != len(angles):
        raise ValueError(f"scan angles {angles} repeat: give each scan angle once")


def _start_lattice(model: ScanModel, scan: CalibrationScan, features: tuple) -> ScanModel:
    """Angle from the trace's features (if fitted), phase from them through the starting model,
    radius from the pillars' area."""
    ft = features[0]
    if model.rotation_free:
        model = eqx.tree_at(lambda m: m.lattice.angle, model, jnp.asarray(ft.angle))
    lattice = model.lattice
    from_phase = np.asarray(lattice.sites(ft.ij)) - np.asarray(lattice.phase)
    phase = np.mean(_at(model.paths(scan)[0], ft.rc) - from_phase, axis=0)
    z = -np.asarray(scan.trace) if scan.pits else np.asarray(scan.trace)
    area = (z > 0.5 * (z.max() + z.min())).mean() * np.prod(scan.pitch)
    radius = float(np.sqrt(area / np.pi))
    return eqx.tree_at(
        lambda m: (m.lattice.phase, m.lattice.radius), model, (jnp.asarray(phase), jnp.asarray(radius))
    )


def _align(model: ScanModel, scans: tuple, found: list, train: list, test: list) -> tuple:
    """Shift each later scan's lattice indices onto the first scan's. Through ``model`` (fitted
    to the first scan's features) the later scan's trace features land near whole lattice
    coordinates: its rising fast axis follows the branch that the first scan's slow axis
    traced, while its retrace follows a branch no earlier image showed (its retrace indices
    follow the trace's, :func:`_retrace_matches`). The shift is the nearest whole number of
    their median; unless four in five trace features round to that same shift, the scans are
    unmatchable (an error naming the scan)."""
    train, test = list(train), list(test)
    for k in range(1, len(scans)):
        trace = found[k][0]
        d = np.asarray(model.site_errors(scans[k], [(trace.rc, trace.ij)])[0])
        shift = np.round(np.median(d, axis=0))
        agree = float(np.mean(np.all(np.round(d) == shift, axis=1)))
        if agree < 0.8:
            raise ValueError(
                f"{scans[k].name}: only {100 * agree:.0f} % of its trace features lie nearest the same "
                f"lattice sites through the model fitted to {scans[0].name}: the scans do not image one "
                "lattice with one scanner (check the scan angles, sizes and centres), or that fit is too "
                "loose (raise solver.max_steps)"
            )

        def move(part):
            return [(rc, ij + shift.astype(int)) for rc, ij in part]

        train[k], test[k] = move(train[k]), move(test[k])
    return train, test


def _split_masks(model: ScanModel, scans: tuple, hold_out: bool) -> tuple:
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


def _held_out_image(model: ScanModel, scans: tuple, kernel: Array, held: tuple) -> float:
    """The rms of the blurred image residual over the held-out pixels, % of the depth: the
    stage's compiled residuals (:func:`_image_residuals`) with the held-out masks in place of the
    training ones, so nothing is compiled again."""
    model = _float64(model)
    raw = parameters(model, scans[0])[0]
    r = residual_values(_image_residuals, raw, (model, scans, (kernel, held)))
    return 100 * float(np.sqrt(np.sum(r**2) / sum(float(jnp.sum(h)) for h in held)))


def _judge(before: list, after: float, test: list) -> tuple:
    """``(keep, words)``: an image stage is kept unless it raises the held-out feature residual
    (nm) beyond the best so far over all scans (``before``) by more than that residual's own
    uncertainty, 3 / sqrt(2 n) of
    it for n held-out features (the standard error of an rms is about rms / sqrt(2 n)): a
    stage that left the feature fit's valley misplaces the features by a large part of a
    pitch, far beyond that."""
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
            out.append(_at(path, rc) - _at(path, nearest))
    return np.concatenate(out) if out else np.zeros((0, 2))


def _at(path: Array, rc: np.ndarray) -> np.ndarray:
    """The path (nm) at fractional pixels ``rc``, in NumPy (nothing to compile)."""
    return _interpolate(np.asarray(path), np.asarray(rc, dtype=float), np)


def held_out_rms(model: ScanModel, scans: tuple, test: list) -> float:
    """The rms length (nm) of :func:`held_out_errors`; NaN when no feature is held out."""
    e = held_out_errors(model, scans, test)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else float("nan")


def validate(model: ScanModel, scans: tuple, test: list) -> dict:
    """The held-out features: how many, their rms residual (nm, :func:`held_out_rms`), and the
    spread of the local pitch between held-out features two sites apart along a row (the
    nearest in a checkerboard) raw (at their nominal positions) and corrected (where the model
    puts the tip at them), % of the mean."""
    raw, corrected = [], []
    for scan, images in zip(scans, test):
        for (rc, ij), path in zip(images, model.paths(scan)):
            if len(rc):
                raw.append(neighbour_distances(scan.raster.nominal(rc), ij, step=2))
                xy = _at(path, rc)
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


def implausible(model: ScanModel, scans: tuple) -> list:
    """What makes a fitted model unusable, in words (empty: plausible): per scan, the tip's
    travel along the fast axis over the image outside 0.5 to 2 times the image's width; a
    hysteresis branch that falls (:func:`~jaxafm.model.io.check_monotone`); creep of the
    wrong sign (it must continue the move); a loop wider than the travel."""
    failures = []
    for scan in scans:
        path = np.asarray(model.paths(scan)[0]).reshape(-1, 2)
        travel = float(np.ptp(path @ scan.raster.rotation[:, 0]))
        ratio = travel / scan.raster.size[0]
        if not 0.5 < ratio < 2:
            failures.append(
                f"{scan.name}: the tip travels {travel / 1e3:.4g} µm along the fast axis over a "
                f"{scan.raster.size[0] / 1e3:.4g} µm image ({ratio:.2f} times its width)"
            )
    try:
        check_monotone(model.scanner)
    except ValueError as e:
        failures.append(f"a hysteresis branch falls: {e}")
    for a in ("x", "y"):
        creep = getattr(model.scanner, a).creep
        fall = None if creep is None else creep_fall(creep)
        if fall is not None and fall > CREEP_FALL:
            failures.append(
                f"{a} creep runs against the move: after a step its response falls back by "
                f"{100 * fall:.2g} % of the step (allowed {100 * CREEP_FALL:g} %)"
            )
    failures += _loop_widths(model.scanner, scans)
    return failures


#: how far (a fraction of the step) a fitted creep's step response may fall back or below the
#: step before the model counts as creeping against the move: 0.1 %, 3 nm after a 3 µm move,
#: under the calibration image's feature precision and 1/40 of the creep of 0.01 per decade
#: over the four decades of the bank
CREEP_FALL = 1e-3


def creep_fall(creep) -> float:
    """How far (a fraction of the step) the step response ``sum_k g_k (1 - exp(-t / tau_k))`` of
    ``creep`` falls below its running maximum or below zero, for t from tau_min / 10 to
    10 tau_max: 0 for creep that continues the move (every weight non-negative)."""
    taus, g = np.asarray(creep.taus), np.asarray(creep.weights)
    t = np.geomspace(taus.min() / 10, taus.max() * 10, 400)
    r = np.concatenate([[0.0], (g * (1 - np.exp(-t[:, None] / taus))).sum(axis=1)])
    return float(np.max(np.maximum.accumulate(r) - r))


@eqx.filter_jit
def _swept(h: AbstractHysteresis, u: Array, history: Array) -> Array:
    """``h(u, history)``, compiled once for both axes' operators (op by op it compiles each step)."""
    return h(u, history)


def _loop_widths(scanner: Scanner, scans: tuple) -> list:
    """A loop over the drive the scans used that is wider than its own travel, per axis."""
    u = np.concatenate([s.raster.wanted().reshape(-1, 2) / np.asarray(s.sensitivity) for s in scans])
    out = []
    for k, a in enumerate("xy"):
        lo, hi = u[:, k].min(), u[:, k].max()
        sweep = np.concatenate([np.linspace(lo, hi, 200), np.linspace(hi, lo, 200)])
        d = np.asarray(_swept(getattr(scanner, a).hysteresis, jnp.asarray(sweep), jnp.asarray([hi, lo])))
        up, down = d[:200], d[200:][::-1]
        travel, width = float(np.ptp(d)), float(np.max(np.abs(down - up)))
        if width > travel:
            out.append(f"the {a} loop is {width:.4g} nm wide over a travel of {travel:.4g} nm")
    return out


# ---------------------------------------------------------------------------------------------
# The paper's baseline: a polynomial per branch from the feature points


@dataclasses.dataclass(frozen=True)
class BranchPolynomials:
    """Position (nm) against drive (V) per branch, fitted to feature points (paper, section III-A):
    ``x_up`` (trace, rising drive), ``x_down`` (retrace), ``y`` (slow axis; one branch).
    Coefficients highest power first (``numpy.polyval``); ``u_range`` (2, 2) V is the
    drive each axis was fitted over."""

    x_up: np.ndarray
    x_down: np.ndarray
    y: np.ndarray
    u_range: np.ndarray

    def branch(self, name: str, u: np.ndarray) -> np.ndarray:
        """Position (nm) on branch ``name`` (``x_up``, ``x_down``, ``y``) at drive ``u`` (V).
        Outside the fitted drive range the polynomial continues along its end tangent:
        a polynomial of degree 5 extrapolated further runs off within a volt."""
        coef = getattr(self, name)
        lo, hi = self.u_range[0 if name.startswith("x") else 1]
        u = np.asarray(u, dtype=float)
        end = np.clip(u, lo, hi)
        return np.polyval(coef, end) + np.polyval(np.polyder(coef), end) * (u - end)

    def position(self, u: np.ndarray, rising: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        x = np.where(rising, self.branch("x_up", u[..., 0]), self.branch("x_down", u[..., 0]))
        return np.stack([x, self.branch("y", u[..., 1])], axis=-1)


def fit_polynomials(
    scan: CalibrationScan, features: Optional[tuple] = None, degree: int = 5
) -> BranchPolynomials:
    """Least-squares polynomials of ``degree`` from the feature points of trace and retrace.

    True positions are ``index * pitch`` plus one offset shared by both branches,
    chosen so that the features' mean true position equals their mean nominal one.
    """
    ft, fr = scan.features() if features is None else features
    pitch = np.asarray(scan.pitch)
    ut, ur = scan.volts(ft.rc), scan.volts(fr.rc)
    nominal = np.concatenate([ut, ur]) * np.asarray(scan.sensitivity)
    sites = np.concatenate([ft.ij, fr.ij]) * pitch
    offset = nominal.mean(axis=0) - sites.mean(axis=0)
    xt, xr = ft.ij * pitch + offset, fr.ij * pitch + offset
    for name, n in (
        ("trace x", len(np.unique(ft.ij[:, 0]))),
        ("retrace x", len(np.unique(fr.ij[:, 0]))),
        ("y", len(np.unique(ft.ij[:, 1]))),
    ):
        if n <= degree:
            raise ValueError(
                f"a degree-{degree} polynomial needs more than {degree} distinct {name} feature "
                f"lines, found {n}: lower the degree or use a finer grating"
            )
    u_all = np.concatenate([ut, ur])
    return BranchPolynomials(
        np.polyfit(ut[:, 0], xt[:, 0], degree),
        np.polyfit(ur[:, 0], xr[:, 0], degree),
        np.polyfit(
            np.concatenate([ut[:, 1], ur[:, 1]]), np.concatenate([xt[:, 1], xr[:, 1]]), min(degree, 3)
        ),
        np.stack([u_all.min(axis=0), u_all.max(axis=0)], axis=-1),
    )
