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
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import checks
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
from ..model.scanner import Axis, Scanner
from .features import LatticeFeatures, lattice_features
from .fit import FitResult, _solve, check_solver, free_parameters

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
    depth_scale: float = eqx.field(static=True)

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
        self.depth_scale = float(np.ptp(np.asarray(trace))) or 1.0

    @property
    def pitch_px(self) -> tuple:
        return tuple(p / s for p, s in zip(self.pitch, self.raster.pixel_size))

    def volts(self, rc: np.ndarray) -> np.ndarray:
        """The nominal drive (n, 2) V at fractional pixels ``rc`` (n, 2) (row, col)."""
        rc = np.asarray(rc, dtype=float)
        xy = np.asarray(self.raster.origin) + rc[:, ::-1] * np.asarray(self.raster.pixel_size)
        return xy / np.asarray(self.sensitivity)

    def features(self) -> tuple:
        """Pillar (or pit) centres of trace and retrace, indexed in one lattice frame."""
        sign = -1.0 if self.pits else 1.0
        ft = lattice_features(sign * np.asarray(self.trace), self.pitch_px, "trace image")
        fr = lattice_features(sign * np.asarray(self.retrace), self.pitch_px, "retrace image")
        return ft, _match_indices(ft, fr)


def _match_indices(ft: LatticeFeatures, fr: LatticeFeatures) -> LatticeFeatures:
    """Shift the retrace's indices onto the trace's: x columns matched at the right edge, where
    the trace turns into the retrace and the tip is continuous; y rows by position (same lines)."""

    def line_means(f, axis, col):
        return {k: f.rc[f.ij[:, axis] == k, col].mean() for k in np.unique(f.ij[:, axis])}

    tx, rx = line_means(ft, 0, 1), line_means(fr, 0, 1)
    right = max(tx)
    shift_x = right - min(rx, key=lambda k: abs(rx[k] - tx[right]))
    ty, ry = line_means(ft, 1, 0), line_means(fr, 1, 0)
    shift_y = min(ty) - min(ry, key=lambda k: abs(ry[k] - ty[min(ty)]))
    return LatticeFeatures(fr.rc, fr.ij + np.array([shift_x, shift_y]))


class ScanModel(eqx.Module):
    """What step A fits: the scanner, the z-feedback lag, and the lattice's unknowns
    (phase, radius, depth, edge width; the pitch is known)."""

    scanner: Scanner
    feedback: Optional[FeedbackLag]
    lattice: Lattice

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


def initial_model(
    scan: CalibrationScan,
    kind: str = "gpi",
    effects: Sequence[str] = MODEL_EFFECTS,
    operators: int = 20,
    deadzones: int = 3,
    levels: int = 20,
) -> ScanModel:
    """The nominal model a fit starts from: the straight calibration line, no other effect yet.

    ``kind``: ``pi`` (``operators`` plays evenly over ``[0, u_max)``), ``gpi`` (plus
    ``deadzones`` dead zones a side, evenly over the imaged half width: beyond it no data
    would hold them) or ``preisach`` (``levels`` levels over ``+-u_max``). ``effects``
    lists the others to fit (names as in docs/conventions.md).
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
            Creep.logarithmic(0.0, per_decade=1) if "creep" in effects else None,
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
        jnp.zeros(()),
        jnp.zeros(2),
    )
    return ScanModel(scanner, has("feedback_lag", FeedbackLag(jnp.asarray(5e-4))), lattice)


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

    The hysteresis offsets stay at 0: a translation of the whole image is the
    lattice's phase, so the scanner's zero stays where its virgin state put it.
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
    if s.coupling is not None:
        fields += [
            _field(lambda m: m.scanner.coupling.xy, 0.01),
            _field(lambda m: m.scanner.coupling.yx, 0.01),
        ]
    if s.bow is not None:
        fields += [_field(lambda m: m.scanner.bow.bx, 1e-6), _field(lambda m: m.scanner.bow.by, 1e-6)]
    if s.drift is not None:
        fields.append(_field(lambda m: m.scanner.drift.velocity, 0.05))
    if model.feedback is not None:
        fields.append(_field(lambda m: m.feedback.tau, 1e-3, True))
    for a in ("x", "y"):
        axis = getattr(s, a)
        if axis.creep is not None:  # logarithmic creep: one gamma per axis, its lags as configured
            n = axis.creep.weights.size
            fields.append(_field(lambda m, a=a: getattr(m.scanner, a).creep.weights, 0.01 / n, shared=True))
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


def _interpolate(a: Array, rc: Array) -> Array:
    """Bilinear interpolation of ``a`` (L, P, ...) at fractional pixels ``rc`` (n, 2)."""
    r0 = jnp.clip(jnp.floor(rc[:, 0]).astype(int), 0, a.shape[0] - 2)
    c0 = jnp.clip(jnp.floor(rc[:, 1]).astype(int), 0, a.shape[1] - 2)
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
        model: the fitted :class:`ScanModel`.
        stages: one :class:`~jaxafm.identify.fit.FitResult` per stage (feature points, then
            each blur), in order.
        seconds: the whole identification's wall time (s).
    """

    model: ScanModel
    stages: tuple
    seconds: float

    @property
    def converged(self) -> bool:
        return all(s.converged for s in self.stages)


def _point_residuals(raw, args) -> Array:
    """At each feature point, where the model puts the tip less that feature's lattice site
    ``phase + index * pitch``, in pitches (trace and retrace). Needs only the tip's path."""
    start, scan, features = args
    model = parameters(start, scan)[1](raw)
    paths = model.paths(scan)
    pitch = jnp.asarray(scan.pitch)
    return jnp.concatenate(
        [
            ((_interpolate(path, rc) - (model.lattice.phase + ij * pitch)) / pitch).ravel()
            for (rc, ij), path in zip(features, paths)
        ]
    )


def _image_residuals(raw, args) -> Array:
    """The model's image less the measured one, both blurred by ``kernel``, trace and retrace,
    in fractions of the measured depth."""
    start, scan, kernel = args
    out = parameters(start, scan)[1](raw).image(scan)
    return jnp.concatenate(
        [
            ((blur(m, kernel) - blur(z, kernel)) / scan.depth_scale).ravel()
            for m, z in ((out.trace, scan.trace), (out.retrace, scan.retrace))
        ]
    )


def _mean_square(residuals: Callable) -> Callable:
    return lambda raw, args: 0.5 * jnp.mean(residuals(raw, args) ** 2)


_POINT_LOSS, _IMAGE_LOSS = _mean_square(_point_residuals), _mean_square(_image_residuals)


def identify(
    scan: CalibrationScan,
    model: Optional[ScanModel] = None,
    *,
    kind: str = "gpi",
    effects: Sequence[str] = MODEL_EFFECTS,
    operators: int = 20,
    deadzones: int = 3,
    levels: int = 20,
    solver: str = "optimistix.levenberg_marquardt",
    blur_px: Sequence[float] = (2.0, 1.0),
    max_steps: int = 100,
    rtol: float = 1e-5,
    atol: float = 1e-8,
    log: Callable = print,
) -> Identification:
    """Fit the scanner end to end: to the feature points, then to the images at each blur.

    Never returns a silently bad fit: each stage's convergence and last loss
    are in the result, and a stage whose loss is not finite raises.

    Arguments:
        scan: the measured trace/retrace pair and how it was driven.
        model: the start; by default :func:`initial_model` with ``kind``, ``effects``,
            ``operators``, ``deadzones`` and ``levels``.
        solver: one of :data:`~jaxafm.identify.fit.SOLVERS`.
        blur_px: the image stages' Gaussian blurs (pixels), widest first.
        max_steps: each stage's step limit.
        rtol: each stage's relative tolerance.
        atol: each stage's absolute tolerance.
        log: where each stage's one-line summary goes.

    Returns:
        An :class:`Identification`: the fitted model and one fit result per stage.
    """
    check_solver(solver, max_steps, rtol, atol)
    for b in blur_px:
        if not 0 <= b <= 64:
            raise ValueError(f"blur_px: each blur is a Gaussian sigma of 0 to 64 px, got {b}")
    start = time.perf_counter()
    features = scan.features()
    model = initial_model(scan, kind, effects, operators, deadzones, levels) if model is None else model
    model = _start_lattice(model, scan, features)
    points = tuple((jnp.asarray(f.rc), jnp.asarray(f.ij)) for f in features)
    plan = [("feature points", _point_residuals, _POINT_LOSS, points)]
    radius = int(np.ceil(3 * max(blur_px, default=0)))
    plan += [
        (f"images, blur {b:g} px", _image_residuals, _IMAGE_LOSS, jnp.asarray(gaussian_kernel(b, radius)))
        for b in blur_px
    ]
    stages = []
    for i, (name, residuals, loss_fn, data) in enumerate(plan):
        model = jax.tree.map(lambda x: jnp.array(x, dtype=float) if eqx.is_inexact_array(x) else x, model)
        args = (model, scan, data)
        raw0, rebuild = parameters(model, scan)
        t0 = time.perf_counter()
        raw, steps, ok = _solve(solver, residuals, loss_fn, raw0, max_steps, rtol, atol, args)
        loss = float(2 * jax.jit(loss_fn)(raw, args))  # the mean square residual
        if not np.isfinite(loss):
            raise RuntimeError(
                f"step A stage '{name}' diverged with {solver} (loss {loss}); "
                "try another solver or a smaller model"
            )
        message = (
            f"{solver}: converged in {steps} steps, loss {loss:.3e}"
            if ok
            else f"{solver}: did NOT converge in {steps} steps (max_steps={max_steps}); last loss {loss:.3e}"
        )
        model = rebuild(raw)
        stages.append(FitResult(model, solver, ok, steps, loss, time.perf_counter() - t0, message))
        log(f"  stage {i + 1}/{len(plan)} {name}: {message}, {stages[-1].seconds:.1f} s")
    return Identification(model, tuple(stages), time.perf_counter() - start)


def _start_lattice(model: ScanModel, scan: CalibrationScan, features: tuple) -> ScanModel:
    """Phase from the feature points through the starting model; radius from the pillars' area."""
    ft = features[0]
    path = np.asarray(model.paths(scan)[0])
    phase = np.mean(
        np.asarray(_interpolate(jnp.asarray(path), jnp.asarray(ft.rc))) - ft.ij * np.asarray(scan.pitch),
        axis=0,
    )
    z = -np.asarray(scan.trace) if scan.pits else np.asarray(scan.trace)
    area = (z > 0.5 * (z.max() + z.min())).mean() * np.prod(scan.pitch)
    radius = float(np.sqrt(area / np.pi))
    return eqx.tree_at(
        lambda m: (m.lattice.phase, m.lattice.radius), model, (jnp.asarray(phase), jnp.asarray(radius))
    )


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
