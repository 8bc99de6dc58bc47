"""What step A fits (:class:`ScanModel`: the scanner, the z-feedback's lag and the lattice's
unknowns), the nominal model a fit starts from (:func:`nominal_scan_model`, after the
:class:`ScanModelSpec`), and its parameters at order one (:meth:`ScanModel.free_parameters`,
each module's own ``free_parameters`` with step A's scales).

The model is the simulated AFM itself (:func:`~jaxafm.instrument.afm.raster_scan`) with the
candidate scanner: it images the known lattice along the scan's drive, so a fitted model and the
truth simulator are one code path with different parameters.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import lsq_linear

from ..config.names import MODEL_EFFECTS
from ..instrument.afm import AFM, RasterScan, raster_scan
from ..instrument.samples import Lattice, Plane, Tip
from ..model.effects import Bow, Coupling, Creep, Drift, FeedbackLag, RateDependence
from ..model.hysteresis import AbstractHysteresis, Deadzone, GeneralizedPI, PrandtlIshlinskii, Preisach
from ..model.scanner import Axis, Scanner
from .calibration_scan import CalibrationScan
from .image_ops import interpolate, sample_at

Array = jax.Array
KEY = jax.random.key(0)  # a fitted model's drift has no wander, so its key never matters

#: step A's starting creep, fraction per decade: positive, as its fit keeps it (a tenth of the
#: 0.01-0.02 of published data)
CREEP_START = 1e-3
#: step A's creep bank with a fitted onset (``ScanModelSpec.creep_onset``,
#: :meth:`~jaxafm.model.effects.Creep.with_onset`): lags from 10 ms to 1000 s, 2 a decade (a
#: pixel's time at 64-512 px and 0.5-4 Hz is 0.2-16 ms), and the onset it starts from, the 0.1 s
#: the log law is often written from (``log10(t / 0.1 s)``)
CREEP_ONSET_TAUS_S = (0.01, 1000.0)
CREEP_ONSET_START_S = 0.1
#: the hold step A's rate dependence steps its lag through (:func:`~jaxafm.model.effects.hold_weights`):
#: a raster's drive is a ramp between its samples, one a pixel, so the linear hold, whose
#: ``tau`` is the delay of a ramp at any sample time
LAG_HOLD = "linear"

# The order-one scales of step A's parameters (what a raw value of 1 stands for). Phase and
# radius are in pitches and the depth in the image's height range (the scan's ``depth_scale``);
# the hysteresis weights in travel / drive span; the creep rate spread over the bank's lags.
EDGE_SCALE_NM = 50.0
ANGLE_SCALE_RAD = 0.01
COUPLING_SCALE = 0.01
BOW_SCALE_PER_NM = 1e-6
DRIFT_SCALE_NM_S = 0.05
LAG_SCALE_S = 1e-3
CREEP_SCALE = 0.01
SLOPE_SCALE = 0.01
#: the least edge delay a richer model's fit starts from (a tenth of LAG_SCALE_S): above the
#: bound 0, where the fit can move it either way
DELAY_RESTART_S = 1e-4


@dataclasses.dataclass(frozen=True)
class ScanModelSpec:
    """Which scanner model step A fits (:func:`nominal_scan_model`).

    Attributes:
        kind: ``pi`` (``operators`` plays evenly over ``[0, u_max)``), ``gpi`` (plus
            ``deadzones`` dead zones a side, evenly over the imaged half width, or inside
            ``deadzone_reach`` (the features' chords' reach, :func:`feature_reach`), beyond which
            no data would hold them; a ``gpi`` without
            ``asymmetry`` among the effects is a ``pi``) or
            ``preisach`` (``levels`` levels over ``+-u_max``).
        effects: the other effects to fit (names as in docs/conventions.md; those of
            :data:`~jaxafm.config.names.MODEL_EFFECTS`).
        operators: plays per axis.
        deadzones: dead zones a side.
        levels: Preisach levels.
        rotation: the lattice's known angle on the stage (rad), or ``None`` to fit it.
        deadzone_reach: per stage axis ``(below, above)`` nm, where to lay the dead zones out
            instead of the imaged half width (step A's model ladder sets it,
            :func:`~jaxafm.identify.selection.supported_dead_zones`).
        creep_onset: creep follows ``d0 (1 + gamma log10(1 + t / t0))`` with its onset ``t0``
            fitted too (:meth:`~jaxafm.model.effects.Creep.with_onset`); otherwise a log law
            of fixed shape from 0.1 s.
        known: what the user knows of the scanner beforehand, ``(key, value, sd)`` per
            quantity (keys of :data:`~jaxafm.config.names.KNOWABLE`): step A's Gaussian
            prior on it (:attr:`ScanModel.known`).
        chord_lengths: the chord stages fit each chord's length too (:attr:`ScanModel.chord_lengths`).
    """

    kind: str = "gpi"
    effects: tuple = MODEL_EFFECTS
    operators: int = 20
    deadzones: int = 3
    levels: int = 20
    rotation: Optional[float] = 0.0
    deadzone_reach: Optional[tuple] = None
    creep_onset: bool = False
    known: tuple = ()
    chord_lengths: bool = False


class ScanModel(eqx.Module):
    """What step A fits: the scanner, the z-feedback lag, and the lattice's unknowns
    (phase, radius, depth, edge width; the pitch is known). ``rotation_free``: the lattice's
    angle on the stage is fitted too (:meth:`free_parameters` says how that fixes a gauge).

    ``chord_slope`` (2,): how the midpoints of a feature's chords lie, for chords along the
    scan lines and along the pixel columns (:meth:`chord_offsets`). The chords of a centrally
    symmetric feature that run one way have their midpoints on a line through its centre: for
    a round feature the line across the chords (slope 0), for a square one the line along the
    sides they cross (the slope the tangent of the sides' tilt from that perpendicular).

    ``edge_delay`` (s): how late an edge the tip crosses shows in the image, at half its height:
    the z signal's lag and latency (a first-order feedback lag of time constant tau delays a
    sharp edge's half-height crossing by tau ln 2, a latency by itself). The chords see it; the
    image stages render the lag itself (``feedback``). Fitted with the effect ``feedback_lag``,
    kept >= 0: a z signal cannot show an edge before the tip reaches it. At one line rate it
    trades against the loop's width (both set trace and retrace edges apart by a constant where
    the tip's speed is); unbounded, a fit settles on a wider loop and a negative delay
    (docs/step_a.md).

    ``known``: the keys of the quantities the user states beforehand (of
    :func:`~jaxafm.identify.quantities.quantities`, e.g. ``("y_gain_nm_per_v",)``), with their
    values ``known_value`` (k,) and sds ``known_sd`` (k,) in the keys' units: every stage fits
    them under a Gaussian prior of that mean and sd (:func:`~jaxafm.identify.stages.prior_rows`),
    and what the scans determine counts it.
    ``known_scale``: the stage's residual spread in units of the spread its priors are weighed
    against (:func:`~jaxafm.identify.stages.weigh_known`), so that a stated sd counts against
    the residuals as they scatter.

    ``chord_lengths``: the chord stages fit each chord's length against its features' common
    length as well as its midpoint (:func:`~jaxafm.identify.stages.width_misfits`)."""

    scanner: Scanner
    feedback: Optional[FeedbackLag]
    lattice: Lattice
    chord_slope: Array = eqx.field(default_factory=lambda: jnp.zeros(2))
    edge_delay: Array = eqx.field(default_factory=lambda: jnp.zeros(()))
    rotation_free: bool = eqx.field(static=True, default=False)
    known: tuple = eqx.field(static=True, default=())
    known_value: Array = eqx.field(default_factory=lambda: jnp.zeros(0))
    known_sd: Array = eqx.field(default_factory=lambda: jnp.ones(0))
    known_scale: Array = eqx.field(default_factory=lambda: jnp.ones(()))
    chord_lengths: bool = eqx.field(static=True, default=False)

    def chord_ends(self, path: Array, ends: Array, shift, xp=jnp) -> Array:
        """Where the tip was (n, 2, 2) nm when it crossed the chords' ``ends`` (n, 2, 2)
        fractional pixels (row, col) of an image whose tip positions are ``path`` (lines,
        pixels, 2): ``shift`` columns earlier in time than where the image shows them (the edge
        delay; columns run backwards in time in a retrace). ``xp``: the array module
        (:func:`~jaxafm.identify.image_ops.interpolate`)."""
        rc = xp.asarray(ends).reshape(-1, 2) - xp.asarray([0.0, 1.0]) * shift
        return interpolate(xp.asarray(path), rc, xp).reshape(-1, 2, 2)

    def chord_offsets(self, tips: Array, ij: Array, along_lines: Array) -> Array:
        """How far (n,) nm each chord's midpoint lies off the line its feature's midpoints
        should lie on (class docstring): with ``d`` the chord's direction and ``p`` its
        perpendicular, ``d . (m - c) - s p . (m - c)``, ``m`` its midpoint (of the tip positions
        ``tips`` (n, 2, 2) nm at its ends), ``c`` the lattice site ``ij`` (n, 2), ``s`` the
        ``chord_slope`` of its direction. 0 on a perfect model."""
        m = tips.mean(axis=1) - self.lattice.sites(ij)
        d = tips[:, 1] - tips[:, 0]
        d = d / jnp.linalg.norm(d, axis=1, keepdims=True)
        p = jnp.stack([-d[:, 1], d[:, 0]], axis=-1)
        s = jnp.where(along_lines, self.chord_slope[0], self.chord_slope[1])
        return jnp.sum(d * m, axis=1) - s * jnp.sum(p * m, axis=1)

    def chord_spans(self, tips: Array, ij: Array) -> tuple:
        """Each chord's length (n,) nm between the tip positions ``tips`` (n, 2, 2) nm at its
        ends, and how far (n,) nm its midpoint lies from the line through its feature's lattice
        site ``ij`` (n, 2) along it: where across its feature the chord runs."""
        d = tips[:, 1] - tips[:, 0]
        length = jnp.linalg.norm(d, axis=1)
        p = jnp.stack([-d[:, 1], d[:, 0]], axis=-1) / length[:, None]
        return length, jnp.abs(jnp.sum(p * (tips.mean(axis=1) - self.lattice.sites(ij)), axis=1))

    def lag_from_edges(self) -> ScanModel:
        """This model with its feedback lag set to what its edge delay implies,
        ``tau = max(edge_delay, DELAY_RESTART_S) / ln 2`` (a first-order lag delays a sharp
        edge's half-height crossing by ``tau ln 2``). The chord stages fit the delay and leave
        the lag at its start; an image stage that renders the lag from there sees every edge
        the difference late, trace one way and retrace the other, while the scanner the chords
        fitted holds its loop narrower by as much (the two trade at one line rate). On
        configs/study.yaml's scanners 6, 9 and 13 chord delays of 11-13 ms against a 0.5 ms start
        put the images 2-3 px off and the image stages wandered to tip paths 200 nm off;
        started from the implied lag they walk to 1-3 nm. Without a feedback lag, unchanged."""
        if self.feedback is None:
            return self
        tau = jnp.maximum(self.edge_delay, DELAY_RESTART_S) / jnp.log(2.0)
        return eqx.tree_at(lambda m: m.feedback.tau, self, tau.astype(self.feedback.tau.dtype))

    def afm(self, scan: CalibrationScan) -> AFM:
        """The simulated AFM with this model as its scanner (tip dilation off)."""
        return AFM(
            self.scanner, Tip(), jnp.asarray(scan.sensitivity), self.feedback, u_max=scan.u_max, dilate=False
        )

    def paths(self, scan: CalibrationScan) -> tuple:
        """The tip's path (lines, pixels, 2) nm over the trace and the retrace pixels, along the
        scan's drive (the heights are not rendered)."""
        afm = eqx.tree_at(lambda a: a.feedback, self.afm(scan), None, is_leaf=lambda v: v is None)
        out = raster_scan(afm, Plane(), self.start(afm, scan), scan.raster, key=KEY)
        return out.path_trace, out.path_retrace

    def start(self, afm: AFM, scan: CalibrationScan):
        """Where ``afm`` (this model's) stands before the scan: at rest at ``scan.u0`` at
        ``scan.t0`` after its drive history."""
        return afm.initial_state(
            scan.u0, scan.t0, None if scan.history is None else jnp.asarray(scan.history)
        )

    def image(self, scan: CalibrationScan) -> RasterScan:
        """:func:`~jaxafm.instrument.afm.raster_scan` of the lattice through this model, along the
        scan's drive."""
        afm = self.afm(scan)
        return raster_scan(afm, self.lattice, self.start(afm, scan), scan.raster, key=KEY)

    def site_errors(self, scan: CalibrationScan, images: Sequence) -> list:
        """Per image of ``scan`` (trace, retrace), where this model puts the tip at each feature
        ``(rc, ij)`` of ``images`` less that feature's lattice site, in pitches (n, 2) along the
        lattice's axes."""
        return [
            self.lattice.coordinates(interpolate(path, jnp.asarray(rc))) - jnp.asarray(ij)
            for (rc, ij), path in zip(images, self.paths(scan))
        ]

    def as_float64(self) -> ScanModel:
        """This model with every floating-point leaf a float64 array (none weakly typed), so that
        the stages' compiled functions see the same argument types from every model."""
        return jax.tree.map(lambda x: jnp.array(x, dtype=float) if eqx.is_inexact_array(x) else x, self)

    def roughness(self, scan: CalibrationScan) -> Array:
        """The second differences of each Preisach axis' density
        (:meth:`~jaxafm.model.hysteresis.Preisach.roughness`) in units of the mean relay weight
        of :meth:`free_parameters`' scale; empty for plays."""
        parts = [
            h.roughness(_travel(scan))
            for h in (self.scanner.x.hysteresis, self.scanner.y.hysteresis)
            if isinstance(h, Preisach)
        ]
        return jnp.concatenate(parts) if parts else jnp.zeros(0)

    def free_parameters(self, scan: CalibrationScan) -> tuple:
        """``(raw, rebuild)``: the fitted parameters at order one, and the map back to a model.

        Each module's own ``free_parameters`` with step A's scales (the module's constants; the
        lattice's in the scan's pitch and depth, the hysteresis weights in the travel over the
        drive span). Two gauges, as no image can tell them apart. The hysteresis offsets stay
        at 0: a translation of the whole image is the lattice's phase, so the scanner's zero
        stays where its virgin state put it. With the lattice's rotation fitted, the coupling
        of y from x (``coupling.yx``) stays 0: turning the lattice by ``a`` and adding ``a`` to
        ``coupling.yx`` and ``-a`` to ``coupling.xy`` move every image alike (to first order),
        so the scanner's x axis is defined as the direction its x piezo moves the tip, and
        the fitted rotation is the lattice's from that axis.

        Returns:
            ``raw``, a pair (the lattice's and the effects' raw parameters in a list, the two
            hysteresis operators' in another), and ``rebuild(raw) -> ScanModel``.
        """
        s = self.scanner
        angle = ANGLE_SCALE_RAD if self.rotation_free else None
        lattice = self.lattice.free_parameters(min(scan.pitch), scan.depth_scale, EDGE_SCALE_NM, angle)
        parts = [
            (lambda m: m.lattice, lattice),
            (lambda m: m.chord_slope, _scaled(self.chord_slope, SLOPE_SCALE)),
        ]
        if s.coupling is not None:
            coupling = s.coupling.free_parameters(COUPLING_SCALE, hold_yx=self.rotation_free)
            parts.append((lambda m: m.scanner.coupling, coupling))
        if s.bow is not None:
            parts.append((lambda m: m.scanner.bow, s.bow.free_parameters(BOW_SCALE_PER_NM)))
        if s.drift is not None:
            parts.append((lambda m: m.scanner.drift, s.drift.free_parameters(DRIFT_SCALE_NM_S)))
        if self.feedback is not None:
            parts.append((lambda m: m.feedback, self.feedback.free_parameters(LAG_SCALE_S)))
            parts.append((lambda m: m.edge_delay, _nonnegative(self.edge_delay, LAG_SCALE_S)))
        for a in ("x", "y"):
            axis = getattr(s, a)
            if axis.creep is not None:  # one rate per axis, its lags as configured, >= 0
                creep = axis.creep.free_parameters(CREEP_SCALE / axis.creep.weights.size, rate=True)
                parts.append((lambda m, a=a: getattr(m.scanner, a).creep, creep))
            if axis.rate_dependence is not None:
                lag = axis.rate_dependence.free_parameters(LAG_SCALE_S)
                parts.append((lambda m, a=a: getattr(m.scanner, a).rate_dependence, lag))
        hysteresis = [
            getattr(s, a).hysteresis.free_parameters(2 * scan.u_max, _travel(scan)) for a in ("x", "y")
        ]
        raw = ([r for _, (r, _) in parts], [r for r, _ in hysteresis])

        def rebuild(raw):
            modules = [rb(r) for (_, (_, rb)), r in zip(parts, raw[0])]
            m = eqx.tree_at(lambda m: [where(m) for where, _ in parts], self, modules)
            h = [
                _zero_offset(rb(r), getattr(s, a).hysteresis)
                for (_, rb), r, a in zip(hysteresis, raw[1], ("x", "y"))
            ]
            return eqx.tree_at(lambda m: (m.scanner.x.hysteresis, m.scanner.y.hysteresis), m, tuple(h))

        return raw, rebuild


def _travel(scan: CalibrationScan) -> float:
    """The travel (nm) over the drive span ``+-u_max`` at the mean sensitivity: the scale of step
    A's hysteresis weights."""
    return 2 * scan.u_max * float(np.mean(scan.sensitivity))


def _scaled(value: Array, scale: float) -> tuple:
    """A free array at order one: ``(value / scale, raw -> raw * scale)``."""
    return value / scale, lambda raw: raw * scale


def _nonnegative(value: Array, scale: float) -> tuple:
    """A free value >= 0 at order one: ``(value / scale, raw -> max(raw, 0) scale)``. Where the
    data want it below 0 the raw value goes there and the value stays at 0 (the bound active,
    its gradient 0); above 0, and at 0 itself, it is fitted as a free value is."""
    return value / scale, lambda raw: jnp.where(raw >= 0.0, raw, 0.0) * scale


def _zero_offset(h: AbstractHysteresis, start: AbstractHysteresis) -> AbstractHysteresis:
    """``h`` with the offset of ``start`` (for a generalised PI, its PI operator's)."""
    return eqx.tree_at(lambda g: g.offset, h, start.offset)


def nominal_scan_model(
    scan: CalibrationScan, spec: ScanModelSpec = ScanModelSpec(), scans: Optional[tuple] = None
) -> ScanModel:
    """The nominal model a fit starts from: the straight calibration line, no other effect yet
    (each effect of ``spec`` present where it changes nothing, or nearly: creep at
    :data:`CREEP_START`, lags of 5 ms and 0.5 ms); the lattice's depth from the image, its radius
    a quarter pitch, its angle ``spec.rotation`` (0 when fitted). The plays are laid out over
    the drive the lines of ``scans`` (the whole set; default ``scan`` alone) sweep
    (:func:`play_span`).

    Raises:
        ValueError: for an effect that cannot be fitted from images or an unknown kind.
    """
    effects = spec.effects
    unknown = [e for e in effects if e not in MODEL_EFFECTS]
    if unknown:
        raise ValueError(
            f"effect {unknown[0]!r} cannot be fitted from grating images; "
            f"choose from {', '.join(MODEL_EFFECTS)}"
        )
    has = lambda e, module: module if e in effects else None
    scanner = Scanner(
        _nominal_axis(scan, spec, 0, scans or (scan,)),
        _nominal_axis(scan, spec, 1, scans or (scan,)),
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
        jnp.asarray(0.0 if spec.rotation is None else spec.rotation),
        jnp.zeros(2),
    )
    feedback = has("feedback_lag", FeedbackLag(jnp.asarray(5e-4)))
    known = np.asarray([v for _, *v in spec.known], dtype=float).reshape(-1, 2)
    return ScanModel(
        scanner,
        feedback,
        lattice,
        rotation_free=spec.rotation is None,
        known=tuple(k for k, *_ in spec.known),
        known_value=jnp.asarray(known[:, 0]),
        known_sd=jnp.asarray(known[:, 1]),
        chord_lengths=spec.chord_lengths,
    )


#: the widest play, as a fraction of the drive a line sweeps on its axis
PLAY_SPAN = 0.45


def play_span(scans: tuple, k: int) -> float:
    """The thresholds' span (V) of step A's plays on axis ``k``, from the set's ``scans``.

    ``u_max`` when the drive's ``history`` before the images is known (the initialisation cycle
    of a simulated calibration): the cycle turns every play out to ``u_max``, and what the wide
    plays remember of it shapes every later move. Otherwise (measured images, whose history is
    unknown) :data:`PLAY_SPAN` of the least drive a line sweeps on that axis in the scans whose
    lines sweep it (their fast axis is ``k`` or turned towards it), so that every play turns
    inside a line, the widest near its far end, and none only in the over-scan, where no feature
    shows what it does (a play that barely turns there sets the loop by where the line reverses,
    which no image pins); ``u_max`` when no scan's lines sweep the axis, whose drive then turns
    only between scans."""
    if scans[0].history is not None:
        return scans[0].u_max
    sweeps = [
        float(np.min(np.ptp(scan.raster.wanted()[:, 0, :, k] / scan.sensitivity[k], axis=1)))
        for scan in scans
    ]
    swept = [v for v, scan in zip(sweeps, scans) if v > 0.1 * scan.u_max]
    return PLAY_SPAN * min(swept) if swept else scans[0].u_max


def feature_reach(scans: tuple) -> tuple:
    """How far (nm, ``(below, above)`` per stage axis, below < 0 < above) the features' chords
    reach from the stage's centre, at their nominal positions over the ``scans``: where step A's
    dead zones may sit (:func:`_nominal_axis` lays them out evenly inside it). A dead zone beyond
    the last chord end has no data to hold its weight, and the fitted slope there, free, sends
    the tip through the image's margins anywhere; half the imaged width on an axis whose
    features do not straddle the centre."""
    ends = np.concatenate(
        [scan.raster.nominal(scan.features()[0].chords.ends.reshape(-1, 2)) for scan in scans]
    )
    reach = []
    for k in (0, 1):
        below, above = float(ends[:, k].min()), float(ends[:, k].max())
        half = scans[0].raster.size[k] / 2
        reach.append((below, above) if below < 0 < above else (-half, half))
    return tuple(reach)


def _nominal_axis(scan: CalibrationScan, spec: ScanModelSpec, k: int, scans: tuple) -> Axis:
    """Axis ``k`` of :func:`nominal_scan_model`: the nominal line through ``spec.kind``'s operator."""
    kind = "pi" if spec.kind == "gpi" and "asymmetry" not in spec.effects else spec.kind
    gain = scan.sensitivity[k]
    if kind == "preisach":
        h = Preisach.uniform(spec.levels, -scan.u_max, scan.u_max, total=gain * scan.u_max)
    else:
        h = PrandtlIshlinskii.uniform(spec.operators, play_span(scans, k), gain, others=1e-3)
        if kind == "gpi":
            half = scan.raster.size[k] / 2
            below, above = spec.deadzone_reach[k] if spec.deadzone_reach else (-half, half)
            steps = (np.arange(spec.deadzones) + 1) / (spec.deadzones + 1)
            h = GeneralizedPI(h, Deadzone.identity(steps * below, steps * above))
        elif kind != "pi":
            raise ValueError(f"unknown hysteresis model {kind!r}; one of pi, gpi, preisach")
    return Axis(
        h,
        RateDependence(jnp.asarray(5e-3), hold=LAG_HOLD) if "rate_dependence" in spec.effects else None,
        _nominal_creep(spec) if "creep" in spec.effects else None,
    )


def _nominal_creep(spec: ScanModelSpec) -> Creep:
    """Step A's starting creep: :data:`CREEP_START` a decade on lags from 0.1 s to 1000 s, one a
    decade, or with ``spec.creep_onset`` the regularised log law from 10 ms, its onset fitted."""
    if spec.creep_onset:
        return Creep.logarithmic(CREEP_START, *CREEP_ONSET_TAUS_S).with_onset(CREEP_ONSET_START_S)
    return Creep.logarithmic(CREEP_START, per_decade=1)


def transplant(fitted: ScanModel, into: ScanModel) -> ScanModel:
    """``into`` (a richer model's start) with what ``fitted`` already knows: the lattice, the
    chord slopes, every effect both have, and the hysteresis where ``into``'s is of the same
    shape, or a PI operator on a grid that holds ``fitted``'s thresholds (the plays doubled:
    the new plays start at ``into``'s small weight), or a generalised PI around ``fitted``'s PI
    operator (its dead zones at identity). An edge delay at its bound 0 restarts at
    :data:`DELAY_RESTART_S`, where the richer model's fit can still move it."""
    out = eqx.tree_at(lambda m: (m.lattice, m.chord_slope), into, (fitted.lattice, fitted.chord_slope))
    for name in ("coupling", "bow", "drift"):
        if getattr(fitted.scanner, name) is not None and getattr(into.scanner, name) is not None:
            out = eqx.tree_at(lambda m: getattr(m.scanner, name), out, getattr(fitted.scanner, name))
    if fitted.feedback is not None and into.feedback is not None:
        delay = jnp.maximum(fitted.edge_delay, DELAY_RESTART_S)
        out = eqx.tree_at(lambda m: (m.feedback, m.edge_delay), out, (fitted.feedback, delay))
    for a in ("x", "y"):
        old, new = getattr(fitted.scanner, a), getattr(into.scanner, a)
        for name in ("creep", "rate_dependence"):
            if getattr(old, name) is not None and getattr(new, name) is not None:
                out = eqx.tree_at(lambda m: getattr(getattr(m.scanner, a), name), out, getattr(old, name))
        h = _grown(old.hysteresis, new.hysteresis)
        out = eqx.tree_at(lambda m: getattr(m.scanner, a).hysteresis, out, h)
    return out


def _grown(old: AbstractHysteresis, new: AbstractHysteresis) -> AbstractHysteresis:
    """``new``'s operator carrying ``old``'s fitted weights where their shapes allow
    (:func:`transplant`), else ``new`` as it is."""
    if isinstance(new, GeneralizedPI):
        pi = _grown(old.pi if isinstance(old, GeneralizedPI) else old, new.pi)
        dz = (
            old.deadzone
            if isinstance(old, GeneralizedPI)
            and old.deadzone.upper_weights.shape == new.deadzone.upper_weights.shape
            else new.deadzone
        )
        return GeneralizedPI(pi, dz)
    if type(old) is not type(new):
        return new
    if jax.tree.structure(old) == jax.tree.structure(new) and all(
        np.shape(a) == np.shape(b) for a, b in zip(jax.tree.leaves(old), jax.tree.leaves(new))
    ):
        return old
    if isinstance(new, PrandtlIshlinskii):
        r_old, r_new = np.asarray(old.thresholds), np.asarray(new.thresholds)
        at = np.searchsorted(r_new, r_old)
        if np.all(at < len(r_new)) and np.allclose(r_new[np.minimum(at, len(r_new) - 1)], r_old):
            weights = jnp.asarray(new.weights).at[at].set(old.weights)
            return PrandtlIshlinskii(new.thresholds, weights, old.offset)
    return new


def start_lattice(model: ScanModel, scan: CalibrationScan, features: tuple) -> ScanModel:
    """``model`` with its lattice placed on the scan's features: the angle from the trace's
    features (if fitted), the phase from them through the model, the radius from the pillars'
    (or pits') area, ``sqrt(area / pi)``."""
    ft = features[0]
    if model.rotation_free:
        model = eqx.tree_at(lambda m: m.lattice.angle, model, jnp.asarray(ft.angle))
    lattice = model.lattice
    from_phase = np.asarray(lattice.sites(ft.ij)) - np.asarray(lattice.phase)
    phase = np.mean(sample_at(model.paths(scan)[0], ft.rc) - from_phase, axis=0)
    z = -np.asarray(scan.trace) if scan.pits else np.asarray(scan.trace)
    area = (z > 0.5 * (z.max() + z.min())).mean() * np.prod(scan.pitch)
    radius = float(np.sqrt(area / np.pi))
    return eqx.tree_at(
        lambda m: (m.lattice.phase, m.lattice.radius), model, (jnp.asarray(phase), jnp.asarray(radius))
    )


def start_loop(model: ScanModel, scan: CalibrationScan, trace, retrace) -> ScanModel:
    """``model`` with the plays of the stage axis nearest ``scan``'s fast axis started as a
    uniform loop scaled to the scan's matched features: the first play's weight ``a``, a common
    weight ``c`` of the others (an even density, the least a start should assume of the loop's
    shape: a sparse least-squares fit of every weight puts the loop on a few plays, whose small
    loops no full-range raster sees and a positioning move then gets wrong) and a phase ``p``,
    ``a, c >= 0``, fitted so that every trace and retrace feature centre of one lattice index lies
    at one place along that axis: ``x0 + A (a, c) - p = s`` in least squares
    (``scipy.optimize.lsq_linear``), ``s`` the sites' offsets from the lattice's phase, ``x0`` the
    model's positions at the centres with no play weighing and ``A`` what each of ``a`` and ``c``
    adds per unit, exact: a play operator's output is linear in its weights. A start for the chord stage
    on a wide loop, whose branches at the line reversal lie far from the nominal model's narrow
    loop (:func:`nominal_scan_model`); its dead zones, creep and coupling stay as they are."""
    angle = np.deg2rad(scan.raster.angle_deg)
    k = 0 if abs(np.cos(angle)) >= abs(np.sin(angle)) else 1
    h = getattr(model.scanner, "xy"[k]).hysteresis
    if not isinstance(h, (PrandtlIshlinskii, GeneralizedPI)):
        return model

    def where(m):
        h = getattr(m.scanner, "xy"[k]).hysteresis
        return h.pi.weights if isinstance(h, GeneralizedPI) else h.weights

    def at_features(w) -> np.ndarray:
        path = eqx.tree_at(where, model, w).paths(scan)
        return np.concatenate([sample_at(p, f.rc)[:, k] for p, f in zip(path, (trace, retrace))])

    w0 = jnp.asarray(where(model))
    first, others = jnp.eye(w0.size, dtype=w0.dtype)[0], jnp.ones(w0.size, dtype=w0.dtype).at[0].set(0.0)
    x0 = at_features(jnp.zeros_like(w0))  # the rest of the model: no play weighs
    A = np.stack([at_features(d) - x0 for d in (first, others)], axis=1)
    ij = np.concatenate([trace.ij, retrace.ij])
    s = np.asarray(model.lattice.sites(ij))[:, k] - float(model.lattice.phase[k])
    fit = lsq_linear(np.c_[A, -np.ones(len(s))], s - x0, bounds=([0.0, 0.0, -np.inf], np.inf))
    a, c = fit.x[:2]
    return eqx.tree_at(where, model, a * first + c * others)
