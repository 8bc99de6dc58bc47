"""The simulated AFM: drive voltages through the scanner, the probe over the sample.

An action (a raster scan, a line scan, a move, a press) is a drive ``u(t)`` (V)
run from where the instrument stands (``AFMState``). The scanner turns it into
the true tip path (nm); the probe follows the sample, dilated by the tip
(effect ``tip``), and the z-feedback records that height through a lag
(effect ``feedback_lag``), or through a lag that follows falling steps more
slowly than rising ones (effect ``feedback_asymmetry``). Every action returns the state after it, so actions
chain in real time: creep and drift carry on from one to the next.

Voltages come from wanted positions through ``volts(xy, t)`` (nm and s -> V): by
default the instrument's nominal linear calibration ``u = xy / sensitivity``,
which is what an uncompensated AFM does; a fitted inverse model
(:class:`~jaxafm.identify.inverse.Compensator`) compensates instead.

Everything is a pure function of equinox Modules: ``jit``, ``vmap`` over
instruments or samples, and ``grad`` with respect to scanner parameters work.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import checks
from ..config.names import check_effect_names
from ..model.effects import FeedbackAsymmetry, FeedbackLag
from ..model.scanner import Scanner, ScannerState, default_scanner
from .samples import AbstractSample, Indented, Tip, surface

Array = jax.Array


class AFMState(eqx.Module):
    """Where the instrument stands: the scanner's state, the drive ``u`` (2,) V, and
    the feedback's recorded height ``z`` (1,) nm."""

    scanner: ScannerState
    u: Array
    z: Array


class AFM(eqx.Module):
    """A scanner, a tip and a z-feedback, with the nominal calibration the software assumes.

    ``sensitivity`` (2,) nm/V: the linear calibration turning wanted positions
    into voltages; ``u_max`` V: the drive range, ``|u| <= u_max`` on each axis.
    ``tip`` is the probe's shape (pressing always uses it); ``dilate`` says
    whether images see it (effect ``tip``); ``feedback`` a :class:`FeedbackLag` (effect
    ``feedback_lag``), a :class:`FeedbackAsymmetry` (effect ``feedback_asymmetry``) or ``None``
    for a perfect feedback.
    """

    scanner: Scanner
    tip: Tip
    sensitivity: Array
    feedback: Optional[FeedbackLag | FeedbackAsymmetry] = None
    u_max: float = eqx.field(static=True, default=10.0)
    dilate: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        checks.positive("AFM.sensitivity (nm/V)", self.sensitivity)
        if not self.u_max > 0:
            raise ValueError(f"AFM.u_max is the drive range in V and must be > 0, got {self.u_max}")

    @property
    def effects(self) -> frozenset:
        own = {"tip"} if self.dilate else set()
        if self.feedback is not None:
            own.add(_FEEDBACK[type(self.feedback)])
        return frozenset(own) | self.scanner.effects

    def without(self, *names: str) -> AFM:
        """The same instrument with the named effects switched off."""
        check_effect_names(names, "AFM.without")
        afm = eqx.tree_at(lambda a: a.scanner, self, self.scanner.without(*names))
        if self.feedback is not None and _FEEDBACK[type(self.feedback)] in names:
            afm = eqx.tree_at(lambda a: a.feedback, afm, None, is_leaf=lambda v: v is None)
        if "tip" in names:
            afm = dataclasses.replace(afm, dilate=False)
        return afm

    def nominal_volts(self, xy: Array, t: Optional[Array] = None) -> Array:
        """The uncompensated drive for wanted positions ``xy`` (..., 2) nm: ``xy / sensitivity``,
        the same at any time ``t``."""
        return jnp.asarray(xy, dtype=float) / self.sensitivity

    def initial_state(self, u0=(0.0, 0.0), t0=0.0, history=None) -> AFMState:
        """At rest at the drive ``u0`` (2,) V at time ``t0`` s, after the drive ``history`` (H, 2) V.

        ``history=[[-u_max, -u_max], [u_max, u_max]]`` is the paper's initialisation cycle.
        """
        u0 = jnp.asarray(u0, dtype=float)
        return AFMState(self.scanner.initial_state(u0, t0, history), u0, jnp.zeros(1))

    def drive(self, sample, u: Array, t: Array, state: AFMState, key: Optional[Array] = None) -> tuple:
        """Run the drive ``u`` (T, 2) V at times ``t`` (T,) s from ``state``.

        Returns the true tip path (T, 2) nm, the recorded height (T,) nm and the next state.
        """
        self.check_range(u)
        checks.increasing("times t", t)
        if (
            checks.is_concrete(t)
            and checks.is_concrete(state.scanner.t)
            and np.size(t)
            and t[0] < state.scanner.t
        ):
            raise ValueError(
                f"the drive's times start at {float(t[0])} s, before the state's last sample at "
                f"{float(state.scanner.t)} s: drive forward in time"
            )
        return _drive(self, sample, jnp.asarray(u, dtype=float), jnp.asarray(t, dtype=float), state, key)

    def check_range(self, u: Array) -> None:
        """Raise for a drive ``u`` (..., 2) V that is not finite or leaves ``+-u_max``."""
        if not checks.is_concrete(u):
            return
        checks.finite("the drive u (V)", u)
        peak = float(np.max(np.abs(np.asarray(u)))) if np.size(u) else 0.0
        if peak > self.u_max * (1 + 1e-9):
            raise ValueError(
                f"the drive needs {peak:.3g} V, beyond the scanner's range of +-{self.u_max:g} V "
                f"(about +-{self.u_max * float(np.min(self.sensitivity)):.0f} nm): make the scan smaller, "
                "move its centre inward or reduce the overscan"
            )


#: The effect name of each kind of z-feedback.
_FEEDBACK = {FeedbackLag: "feedback_lag", FeedbackAsymmetry: "feedback_asymmetry"}


@eqx.filter_jit
def _drive(afm: AFM, sample, u: Array, t: Array, state: AFMState, key) -> tuple:
    """``AFM.drive`` after its checks, compiled once per instrument structure and drive length."""
    path, scanner_state = afm.scanner.run(u, t, state.scanner, key)
    h = render(sample, afm.tip if afm.dilate else None, path)
    if afm.feedback is not None:
        h, z = afm.feedback.run(h, t, state.z, state.scanner.t)
    else:
        z = h[-1:]
    return path, h, AFMState(scanner_state, u[-1], z)


def render(sample, tip: Optional[Tip], path: Array, batch: int = 2048) -> Array:
    """The height (T,) nm the probe follows along ``path`` (T, 2) nm, in chunks of ``batch``
    consecutive points so that memory stays bounded on long paths over samples with many
    features; each chunk is imaged whole, so a sample can leave out what cannot reach it
    (:meth:`~jaxafm.instrument.samples.Indented.imaged`)."""
    height = surface(sample, tip)
    n = path.shape[0]
    if n <= batch:
        return height(path)
    chunks = -(-n // batch)
    padded = jnp.pad(path, ((0, chunks * batch - n), (0, 0)), mode="edge")
    return lax.map(height, padded.reshape(chunks, batch, 2)).reshape(-1)[:n]


def default_afm(
    tip_radius: float = 10.0, tip_half_angle_deg: float = 20.0, feedback_tau: float = 1e-3, **scanner_options
) -> AFM:
    """The default instrument: ``default_scanner(**scanner_options)``, a 10 nm tip of 20 degrees,
    a 1 ms feedback lag (0: a z signal without lag), and the nominal calibration
    ``travel / (2 u_range)`` nm/V.

    Raises:
        ValueError: naming the argument: a tip radius or lag that is not finite and >= 0, a half
            angle outside (0, 90) degrees, or a bad scanner option (:func:`default_scanner`).
    """
    checks.positive("default_afm: tip_radius (nm)", tip_radius)
    checks.nonnegative("default_afm: feedback_tau (s)", feedback_tau)
    if not 0 < tip_half_angle_deg < 90:
        raise ValueError(
            f"default_afm: tip_half_angle_deg must be in (0, 90) degrees, got {tip_half_angle_deg}"
        )
    scanner = default_scanner(**scanner_options)
    u_range = scanner_options.get("u_range", 10.0)
    travel = scanner_options.get("travel", 10_000.0)
    return AFM(
        scanner,
        Tip(jnp.asarray(tip_radius), jnp.asarray(np.deg2rad(tip_half_angle_deg))),
        jnp.full(2, travel / (2 * u_range)),
        FeedbackLag(jnp.asarray(feedback_tau)) if feedback_tau > 0 else None,
        u_max=u_range,
    )


def _check_action(afm, sample, state) -> None:
    """Refuse an action's arguments that are not an instrument, a sample and a state, naming the
    argument and what it must be.

    Raises:
        TypeError: ``afm`` not an :class:`AFM`, ``sample`` not a sample
            (:class:`~jaxafm.instrument.samples.AbstractSample`), ``state`` not an :class:`AFMState`.
    """
    for name, value, kind, what in (
        ("afm", afm, AFM, "an AFM (e.g. default_afm())"),
        ("sample", sample, AbstractSample, "a sample (e.g. Plane(), Lattice(...), Indented.empty(...))"),
        ("state", state, AFMState, "an AFMState (afm.initial_state(), or the state an action returned)"),
    ):
        if not isinstance(value, kind):
            raise TypeError(f"{name} must be {what}, got {type(value).__name__} {value!r:.60}")


def _times(state: AFMState, n: int, dt: float) -> Array:
    return state.scanner.t + dt * jnp.arange(1, n + 1)


def move(
    afm: AFM,
    sample,
    state: AFMState,
    u_target: Array,
    duration: float = 0.1,
    samples: int = 32,
    key: Optional[Array] = None,
) -> tuple:
    """Ramp the drive straight to ``u_target`` (2,) V over ``duration`` s; returns ``(path, state)``."""
    _check_action(afm, sample, state)
    checks.finite("move: u_target (V)", u_target)
    if not duration > 0 or samples < 1:
        raise ValueError(f"a move needs duration > 0 s and samples >= 1, got {duration} s, {samples}")
    frac = jnp.arange(1, samples + 1)[:, None] / samples
    u = state.u + frac * (jnp.asarray(u_target, dtype=float) - state.u)
    path, _, state = afm.drive(sample, u, _times(state, samples, duration / samples), state, key)
    return path, state


#: each leg of the initialisation cycle (:func:`run_cycle`), s
SETTLE_S = 0.5


def run_cycle(afm: AFM, sample, state: AFMState, cycle: np.ndarray, key: Optional[Array] = None) -> AFMState:
    """The initialisation cycle from ``state``: a move to each drive of ``cycle`` (H, 2) V in
    turn (e.g. ``-u_max`` then ``+u_max`` on both axes: the wiping-out property leaves every
    play in a known state), each held :data:`SETTLE_S` s; returns the state after it."""
    for target in cycle:
        _, state = move(afm, sample, state, target, SETTLE_S, key=key)
    return state


def press(
    afm: AFM,
    sample: Indented,
    state: AFMState,
    depth: float,
    hold: float = 0.2,
    samples: int = 32,
    key: Optional[Array] = None,
) -> tuple:
    """Hold the drive for ``hold`` s and press the tip ``depth`` nm into the sample where it is.

    Returns ``(sample with the indent, state, xy)``; ``xy`` (2,) nm is where the
    tip really was, at the end of the hold.
    """
    if not isinstance(sample, Indented):
        raise TypeError(
            "press needs a sample that can take indents: wrap it as Indented.empty(sample, afm.tip)"
        )
    checks.positive("press depth (nm)", depth)
    path, state = move(afm, sample, state, state.u, hold, samples, key)
    return sample.press(path[-1], depth), state, path[-1]


def line_scan(
    afm: AFM,
    sample,
    state: AFMState,
    start: Array,
    end: Array,
    points: int,
    speed: float,
    volts: Optional[Callable] = None,
    key: Optional[Array] = None,
    move_time: float = 0.1,
) -> tuple:
    """Scan from ``start`` to ``end`` (2,) nm (wanted positions) in ``points`` samples at ``speed`` nm/s.

    The tip first moves to the start over ``move_time`` s. Returns the recorded
    heights (points,) nm, the true path (points, 2) nm and the next state.
    """
    _check_action(afm, sample, state)
    if points < 2:
        raise ValueError(f"a line scan needs points >= 2, got {points}")
    checks.positive("line scan speed (nm/s)", speed)
    checks.finite("line scan start (nm)", start)
    checks.finite("line scan end (nm)", end)
    volts = afm.nominal_volts if volts is None else volts
    start, end = jnp.asarray(start, dtype=float), jnp.asarray(end, dtype=float)
    wanted = start + jnp.linspace(0.0, 1.0, points)[:, None] * (end - start)
    length = jnp.linalg.norm(end - start)
    dt = jnp.maximum(length, 1e-9) / speed / (points - 1)
    t = state.scanner.t + move_time + dt * jnp.arange(1, points + 1)
    u = volts(wanted, t)
    afm.check_range(u)
    k_move, k_scan = (None, None) if key is None else jax.random.split(key)
    _, state = move(afm, sample, state, u[0], move_time, key=k_move)
    path, h, state = afm.drive(sample, u, t, state, k_scan)
    return h, path, state


@dataclasses.dataclass(frozen=True)
class Raster:
    """A raster scan: ``size`` (width, height) nm centred on ``centre`` (nm), ``pixels`` per
    line, ``lines``, ``line_rate`` Hz (trace + retrace of one line per period),
    ``overscan``, the fraction of the width added at each end of a line, and the scan
    angle ``angle_deg``.

    In the scan's own frame the fast axis is its x: each line is a trace (x rising),
    then a retrace, at the line's y; the slow axis steps from bottom to top
    (``direction="up"``) or top to bottom. Images are stored with row 0 at the lowest
    scan-frame y. The scan frame is the stage frame turned anticlockwise by
    ``angle_deg`` about ``centre``, as an AFM's scan rotation turns it: at 0 degrees the
    fast axis is the scanner's x, at 90 degrees its y (the lines then step towards -x).
    """

    size: tuple
    pixels: int
    lines: int
    line_rate: float = 1.0
    centre: tuple = (0.0, 0.0)
    overscan: float = 0.1
    direction: str = "up"
    angle_deg: float = 0.0

    def __post_init__(self):
        size = tuple(float(s) for s in np.broadcast_to(np.asarray(self.size, dtype=float), (2,)))
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "centre", tuple(float(c) for c in self.centre))
        if not all(np.isfinite([self.pixels, self.lines])):
            raise ValueError(
                f"Raster pixels and lines must be whole numbers, got {self.pixels} and {self.lines}"
            )
        if not all(np.isfinite(size)) or min(size) <= 0:
            raise ValueError(f"Raster.size must be > 0 nm on both axes, got {self.size}")
        if self.pixels != int(self.pixels) or self.lines != int(self.lines):
            raise ValueError(
                f"Raster pixels and lines must be whole numbers, got {self.pixels} and {self.lines}"
            )
        object.__setattr__(self, "pixels", int(self.pixels))
        object.__setattr__(self, "lines", int(self.lines))
        if len(self.centre) != 2 or not all(np.isfinite(self.centre)):
            raise ValueError(f"Raster.centre must be finite (x, y) nm, got {self.centre}")
        if self.pixels < 2 or self.lines < 1:
            raise ValueError(f"Raster needs pixels >= 2 and lines >= 1, got {self.pixels} and {self.lines}")
        if not 0 < self.line_rate < np.inf:
            raise ValueError(f"Raster.line_rate must be > 0 Hz, got {self.line_rate}")
        if not 0 <= self.overscan <= 1:
            raise ValueError(f"Raster.overscan is a fraction of the width, 0 to 1, got {self.overscan}")
        if self.direction not in ("up", "down"):
            raise ValueError(f"Raster.direction must be 'up' or 'down', got {self.direction!r}")
        if not np.isfinite(self.angle_deg):
            raise ValueError(f"Raster.angle_deg must be a finite angle in degrees, got {self.angle_deg}")
        object.__setattr__(self, "angle_deg", float(self.angle_deg))

    @property
    def rotation(self) -> np.ndarray:
        """The (2, 2) matrix turning scan-frame vectors into stage-frame ones."""
        a = np.deg2rad(self.angle_deg)
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    def nominal(self, rc: np.ndarray) -> np.ndarray:
        """Nominal stage positions (n, 2) nm of fractional pixels ``rc`` (n, 2) (row, col)
        of this raster's images."""
        rc = np.asarray(rc, dtype=float).reshape(-1, 2)
        scan = np.asarray(self.origin) + rc[:, ::-1] * np.asarray(self.pixel_size)
        return self._to_stage(scan)

    def _to_stage(self, scan: np.ndarray) -> np.ndarray:
        c = np.asarray(self.centre)
        return c + (scan - c) @ self.rotation.T

    @property
    def pixel_size(self) -> tuple:
        return (self.size[0] / self.pixels, self.size[1] / self.lines)

    @property
    def margin(self) -> int:
        """Over-scan samples at each end of a line."""
        return int(round(self.overscan * self.pixels))

    @property
    def origin(self) -> tuple:
        """Nominal position of pixel [0, 0]'s centre in the scan frame, nm (the stage's at 0 degrees)."""
        return tuple(c - s / 2 + p / 2 for c, s, p in zip(self.centre, self.size, self.pixel_size))

    @property
    def sample_time(self) -> float:
        return 1.0 / (2 * self.line_rate * (self.pixels + 2 * self.margin))

    def wanted(self) -> np.ndarray:
        """Wanted stage positions (lines, 2, n, 2) nm: per line, trace then retrace samples."""
        m, dx, dy = self.margin, *self.pixel_size
        x = self.origin[0] + dx * np.arange(-m, self.pixels + m)
        y = self.origin[1] + dy * np.arange(self.lines)
        if self.direction == "down":
            y = y[::-1]
        xs = np.stack([x, x[::-1]])  # (2, n)
        out = np.empty((self.lines, 2, x.size, 2))
        out[..., 0] = xs
        out[..., 1] = y[:, None, None]
        return out if self.angle_deg == 0 else self._to_stage(out)


class RasterScan(eqx.Module):
    """What a raster scan records, as images: per pixel the height, where the tip really
    was and when, for the trace and the retrace.

    Attributes:
        trace: the recorded heights (lines, pixels) nm of the trace, left to right, row 0 at
            the lowest y.
        retrace: the same for the retrace, also left to right.
        path_trace: the true tip positions (lines, pixels, 2) nm of the trace's pixels.
        path_retrace: the same for the retrace.
        t_trace: the times (lines, pixels) s of the trace's pixels.
        t_retrace: the same for the retrace.
        state: the instrument's state after the scan (``None`` from :func:`raster_images`,
            which only arranges samples).
    """

    trace: Array
    retrace: Array
    path_trace: Array
    path_retrace: Array
    t_trace: Array
    t_retrace: Array
    state: Optional[AFMState] = None


def raster_scan(
    afm: AFM,
    sample,
    state: AFMState,
    raster: Raster,
    volts: Optional[Callable] = None,
    key: Optional[Array] = None,
    move_time: float = 0.1,
) -> RasterScan:
    """Image ``sample`` with ``raster`` from ``state``: trace and retrace height images (nm).

    The tip first moves to the raster's first point over ``move_time`` s.

    Arguments:
        afm: the instrument.
        sample: the sample (an :class:`~jaxafm.instrument.samples.AbstractSample`).
        state: where the instrument stands.
        raster: the scan's geometry and timing.
        volts: ``volts(xy, t)`` (nm, s -> V), the drive for wanted positions; the nominal
            calibration by default.
        key: a PRNG key, needed when the scanner has drift or noise.
        move_time: the move's duration (s).

    Returns:
        A :class:`RasterScan`: the images, the tip's true path and times per pixel, and the
        instrument's state after the scan.
    """
    _check_action(afm, sample, state)
    volts = afm.nominal_volts if volts is None else volts
    wanted = raster.wanted().reshape(-1, 2)
    t = raster_times(raster, state.scanner.t + move_time)
    u = volts(jnp.asarray(wanted), t)
    afm.check_range(u)
    k_move, k_scan = (None, None) if key is None else jax.random.split(key)
    _, state = move(afm, sample, state, u[0], move_time, key=k_move)
    path, h, state = afm.drive(sample, u, t, state, k_scan)
    return dataclasses.replace(raster_images(raster, path, h, t), state=state)


def raster_times(raster: Raster, after) -> Array:
    """Times (T,) s of every sample of ``raster.wanted()``, the first one sample time after ``after`` s."""
    n = raster.lines * 2 * (raster.pixels + 2 * raster.margin)
    return after + raster.sample_time * jnp.arange(1, n + 1)


def raster_images(raster: Raster, path: Array, h: Array, t: Array) -> RasterScan:
    """A raster's samples arranged as images, without the over-scan.

    Arguments:
        raster: the scan's geometry.
        path: the true tip path (T, 2) nm of every sample of ``raster.wanted()``.
        h: the recorded heights (T,) nm.
        t: the times (T,) s.

    Returns:
        A :class:`RasterScan` with ``state=None``.
    """
    L, P, m = raster.lines, raster.pixels, raster.margin
    n = P + 2 * m
    out = {}
    for i, name in enumerate(("trace", "retrace")):
        pick = lambda a: a.reshape((L, 2, n) + a.shape[1:])[:, i, m : m + P]
        flip = (lambda a: a[:, ::-1]) if i == 1 else (lambda a: a)
        rows = (lambda a: a[::-1]) if raster.direction == "down" else (lambda a: a)
        out[name] = rows(flip(pick(h)))
        out[f"path_{name}"] = rows(flip(pick(path)))
        out[f"t_{name}"] = rows(flip(pick(t)))
    return RasterScan(**out)
