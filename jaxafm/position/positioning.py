"""Positioning on the simulated AFM: the paper's steps A, B and C and the pushing task.

The software drives the instrument with *wanted* positions (nm) in the frame of
the images it took. They pass through step B's landmark map (wanted ->
command), then through step A's inverse model or the nominal calibration
(command -> volts), then the instrument. Step A's model runs beside the
instrument as a twin: every drive goes through both, so the inverse always
knows where the model's plays and creep stand.

Every action is a pure function of equinox Modules and runs in real time from a
:class:`Stand` (instrument and twin state): creep and drift carry on from one to
the next. Step C (:func:`local_scan`) is a ``lax.while_loop`` of line scans, so
all of it runs under ``jit`` and ``vmap``.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from .. import checks
from ..identify.inverse import inverse_and_state
from ..instrument.afm import AFM, AFMState, Raster, raster_images, raster_times
from ..instrument.samples import Particles, Tip
from ..model.scanner import Scanner, ScannerState
from .landmarks import LandmarkMap
from .online import NO_PUSH_FIELD, PushField

Array = jax.Array


class Stand(eqx.Module):
    """Where things stand: the instrument, step A's twin (``None`` without a model), and the
    last wanted position ``wanted`` (2,) nm, from which the next move starts."""

    afm: AFMState
    twin: Optional[ScannerState]
    wanted: Array


class Positioner(eqx.Module):
    """The instrument ``afm`` as the positioning software drives it: through the landmark
    map ``frame`` (step B) if given, then step A's fitted ``model`` if given (its numerical
    inverse, run from the twin's state), else the nominal calibration. Drives beyond
    ``+-afm.u_max`` saturate."""

    afm: AFM
    model: Optional[Scanner] = None
    frame: Optional[LandmarkMap] = None

    def start(self, state: AFMState, twin: Optional[ScannerState] = None) -> Stand:
        """A stand at the instrument's ``state``; the wanted position is where the drive points."""
        if (self.model is None) != (twin is None):
            raise ValueError("a positioner with a model needs the twin's state, and one without a model none")
        return Stand(state, twin, state.u * self.afm.sensitivity)

    def volts(self, wanted: Array, t: Array, stand: Stand) -> tuple:
        """The drive (T, 2) V for ``wanted`` (T, 2) nm at times ``t`` and the twin's next state."""
        command = wanted if self.frame is None else self.frame(wanted)
        if self.model is None:
            return self.afm.nominal_volts(command), stand.twin
        u, _, twin = inverse_and_state(self.model, command, t, stand.twin, stand.afm.u, self.afm.u_max)
        return u, twin

    def drive(self, sample, stand: Stand, wanted: Array, t: Array, key: Array) -> tuple:
        """Follow ``wanted`` (T, 2) nm at times ``t`` (T,) s: true path (T, 2) nm, recorded
        heights (T,) nm, and the next stand."""
        u, twin = self.volts(wanted, t, stand)
        u = jnp.clip(u, -self.afm.u_max, self.afm.u_max)
        path, h, state = self.afm.drive(sample, u, t, stand.afm, key)
        return path, h, Stand(state, twin, wanted[-1])


def goto(
    pos: Positioner,
    sample,
    stand: Stand,
    target: Array,
    key: Array,
    move_time: float = 0.1,
    dwell: float = 0.2,
    samples: int = 64,
    approach: float = 0.0,
    along: Optional[Array] = None,
) -> tuple:
    """Move straight to ``target`` (2,) nm over ``move_time`` s and dwell there ``dwell`` s.

    With ``approach`` a > 0 nm the move first passes through ``target + a e`` and
    ``target - a e`` (a leg of ``move_time`` each), ``e`` = ``along`` (2,) (default (1, 1)), and
    reaches the target moving along ``e``: whatever came before, every hysteresis operator
    narrower than the middle leg's move on its axis (2 a |e_i|) arrives in the same state, so two
    arrivals at one place agree however the tip came there (step B: landmarks and targets reached
    alike, rising on both axes). Returns the true tip position (2,) nm at the end of the dwell,
    the true path and the next stand.
    """
    target = jnp.asarray(target, dtype=float)
    e = jnp.ones(2) if along is None else jnp.asarray(along, dtype=float)
    points = (
        [stand.wanted] + ([target + approach * e, target - approach * e] if approach > 0 else []) + [target]
    )
    n_move = samples // 2
    frac = (jnp.arange(1, n_move + 1) / n_move)[:, None]
    legs = [a + frac * (b - a) for a, b in zip(points[:-1], points[1:])]
    wanted = jnp.concatenate(legs + [jnp.broadcast_to(target, (samples - n_move, 2))])
    dt = jnp.concatenate(
        [
            jnp.full(n_move * len(legs), move_time / n_move),
            jnp.full(samples - n_move, dwell / (samples - n_move)),
        ]
    )
    t = stand.afm.scanner.t + jnp.cumsum(dt)
    path, _, stand = pos.drive(sample, stand, wanted, t, key)
    return path[-1], path, stand


def press_at(
    pos: Positioner,
    sample,
    stand: Stand,
    target: Array,
    depth: float,
    key: Array,
    dwell: float = 0.2,
    approach: float = 0.0,
) -> tuple:
    """Move to ``target`` (2,) nm (:func:`goto`, with its ``approach``), dwell, and indent
    ``depth`` nm where the tip really is. Returns ``(sample with the indent, stand, true xy)``."""
    xy, _, stand = goto(pos, sample, stand, target, key, dwell=dwell, approach=approach)
    return sample.press(xy, depth), stand, xy


def raster(
    pos: Positioner, sample, stand: Stand, raster: Raster, key: Array, move_time: float = 0.1
) -> tuple:
    """Image ``sample`` along ``raster`` (wanted positions); the images as
    :func:`~jaxafm.instrument.afm.raster_scan` gives them, and the next stand."""
    wanted = jnp.asarray(raster.wanted().reshape(-1, 2))
    k_move, k_scan = jax.random.split(key)
    _, _, stand = goto(pos, sample, stand, wanted[0], k_move, move_time, dwell=0.05)
    t = raster_times(raster, stand.afm.scanner.t)
    path, h, stand = pos.drive(sample, stand, wanted, t, k_scan)
    return raster_images(raster, path, h, t), stand


# ---------------------------------------------------------------------------------------------
# Step C: local-scan fine positioning (paper section III-C)


class LocalScan(eqx.Module):
    """The local scan's settings: ``points`` per line, each line scanned there and back in
    ``line_time`` s per direction (the mean of both cancels the feedback lag), a move of
    ``move_time`` s to each line; the search reaches ``margin`` nm beyond the particle's
    expected place (a search that finds nothing starts again from there with twice the margin,
    up to ``widenings`` times: an error beyond the margin is found rather than given up on, and
    what it finds teaches the moves after it), a line through the estimate ``line_margin`` nm
    beyond the particle's reach
    (short: the move from its end to the centre found crosses the frame's scale error over that
    length); at most ``max_lines`` lines in all. A line is *centred* when its pulse's
    middle lies within ``centre_tolerance`` R, or ``centre_floor`` nm if more, of the line's
    centre, and its height within a factor ``1 + height_tolerance`` of a centred line's, 2R,
    either way (a check that it is the particle sought; the paper checks the pulse's width
    against 2R). The height is the z signal's, which no lateral frame distorts; a width is not:
    a frame's scale error stretches it, and a short line's scale is a small loop's, which a
    model fitted to full-range lines knows least (on ``configs/study.yaml``'s scanner 9, whose
    model sends a 260 nm push 40 % short, centred lines read 0.26 times as wide as the truth
    along x and 1.4 times along y). Two centred lines through the estimate in a row, one along
    each axis, verify the centre. The floor is the frame's repeatability from line to line:
    with step A's model, successive lines along the slow axis measured the same particle
    0.4-1 nm apart (``jaxafm run configs/paper.yaml``).

    ``condition_y``: the first line along y through the estimate (after each search) moves the
    estimate but never confirms it; a second line along y does. A move to the target with an
    approach (:func:`goto`) ends rising on each axis; the first line's trace passes that turning
    point and sets moving again the plays the move left standing, so its middle carries the
    model's error in their weights, while the second line runs below the first one's top, where
    they stand still. Along x the search line, which never confirms, does this."""

    points: int = eqx.field(static=True, default=192)
    line_time: float = eqx.field(static=True, default=0.5)
    move_time: float = eqx.field(static=True, default=0.05)
    margin: float = eqx.field(static=True, default=40.0)
    line_margin: float = eqx.field(static=True, default=40.0)
    widenings: int = eqx.field(static=True, default=0)
    max_lines: int = eqx.field(static=True, default=24)
    height_tolerance: float = eqx.field(static=True, default=0.25)
    centre_tolerance: float = eqx.field(static=True, default=0.1)
    centre_floor: float = eqx.field(static=True, default=1.0)
    condition_y: bool = eqx.field(static=True, default=False)

    def half_length(self, radius: Array, tip: Tip, search: bool = True, widened: Array = 0) -> Array:
        """Half the length of a line, nm: the imaged particle's reach plus the search margin
        (``search``; doubled ``widened`` times), or plus ``line_margin`` (a line through the
        estimate)."""
        return 2 * (radius + tip.radius) + jnp.where(search, self.search_margin(widened), self.line_margin)

    def search_margin(self, widened: Array = 0) -> Array:
        """The search's margin, nm, after ``widened`` searches that found nothing."""
        return self.margin * 2.0**widened


class ScanResult(eqx.Module):
    """What the local scan found: ``centre`` (2,) nm in the wanted frame, ``found`` (verified),
    the ``lines`` scanned, their ``starts``/``ends`` (max_lines, 2) nm and kind ``phases``
    (0 search, 1 along y, 2 along x through the estimate; -1 unused), the scanning ``seconds``."""

    centre: Array
    found: Array
    lines: Array
    starts: Array
    ends: Array
    phases: Array
    seconds: Array


#: the quantile of a line's heights taken as the substrate under a pulse (:func:`pulse`)
SUBSTRATE_QUANTILE = 0.1


def pulse(h: Array, s: Array, min_height: Array) -> tuple:
    """The pulse of a line's heights ``h`` (P,) nm at positions ``s`` (P,) nm nearest the line's
    middle (``s = 0``): present when it rises ``min_height`` above the substrate and lies wholly
    inside the line; its middle at half height (linear interpolation between samples) and its
    height above the substrate. Returns ``(found, middle, height)``.

    A line may cross a neighbour too (particles 200 nm apart: a line through a particle of
    R = 45 nm reaches 155 nm either side). The pulses are the runs of samples rising more than
    ``min_height / 2`` above the substrate; the one with the sample nearest the middle is the
    particle's, and its half height lies inside its run whenever it rises ``min_height``. The
    substrate is the heights' lowest tenth (:data:`SUBSTRATE_QUANTILE`), not their median:
    through a frame that step A's model shrinks, a line is shorter than it was asked to be and
    a particle can cover most of it (on ``configs/study.yaml``'s scanner 9, whose model sends a
    260 nm push 40 % short, a line through the estimate of a particle of R = 50 nm lay two
    thirds to three quarters on it, and its median on the particle's flank, 55-69 nm above the
    substrate)."""
    P = h.shape[0]
    base = jnp.quantile(h, SUBSTRATE_QUANTILE)
    raised = h - base > min_height / 2
    run = jnp.cumsum(raised & ~jnp.concatenate([jnp.zeros(1, bool), raised[:-1]]))
    own = raised & (run == run[jnp.argmin(jnp.where(raised, jnp.abs(s), jnp.inf))])
    peak = jnp.max(jnp.where(own, h, base))
    level = base + (peak - base) / 2
    above = own & (h > level)
    first = jnp.argmax(above)
    last = P - 1 - jnp.argmax(above[::-1])

    def crossing(i0, i1):
        frac = (level - h[i0]) / jnp.where(h[i1] != h[i0], h[i1] - h[i0], 1.0)
        return s[i0] + frac * (s[i1] - s[i0])

    left = crossing(jnp.maximum(first - 1, 0), first)
    right = crossing(jnp.minimum(last + 1, P - 1), last)
    found = (peak - base > min_height) & (first > 0) & (last < P - 1)
    return found, (left + right) / 2, peak - base


def search_spacing(radius: Array, tip: Tip) -> Array:
    """The local search's line spacing, nm: 3/4 of the band ``2 sqrt(R^2 + 2 R r)`` of lines
    whose heights rise more than R (the detection threshold) over a particle of radius R imaged
    by a tip of radius r: a line at ``d`` from the centre peaks at ``R - r + sqrt((R + r)^2 - d^2)``."""
    return 1.5 * jnp.sqrt(radius**2 + 2 * radius * tip.radius)


def _offset(k: Array) -> Array:
    """Search order of line offsets, in units of the search's line spacing: 0, +1, -1, +2, -2, ..."""
    m = (k + 1) // 2
    return jnp.where(k % 2 == 1, m, -m)


#: samples of the move to each line's start
LINE_MOVE_SAMPLES = 16


def local_scan(
    pos: Positioner,
    sample,
    stand: Stand,
    guess: Array,
    radius: Array,
    key: Array,
    spec: LocalScan = LocalScan(),
) -> tuple:
    """Find the centre of a particle of ``radius`` nm expected near ``guess`` (2,) nm (paper III-C).

    The search: x lines through the guess, shifted in y by ``search_spacing``
    (three quarters of the band of lines that show the particle) until the
    heights show the particle; the estimate moves to the middle of that pulse.
    Then lines through the estimate, along y and x in turn, each moving the
    estimate to its pulse's middle. The middle of a chord of a round particle is
    its centre's coordinate along the line, whatever the chord; so a line whose
    middle lies within ``spec.centre_tolerance`` R (at least ``spec.centre_floor``
    nm) of where it was aimed confirms
    the estimate on its axis, in any frame a scale error stretches. Two such
    lines through the estimate in a row, one per axis, whose pulses rise within a factor
    ``1 + spec.height_tolerance`` of a centred line's 2R, verify the centre; a search line
    never confirms (its middle carries the frame's error over the search margin's
    length, so a centred one still left the tip 0.1 R off). A line that
    loses the particle restarts the search from the estimate. A search whose lines, out to
    the margin, show nothing starts again with twice the margin, up to ``spec.widenings``
    times; then, or after ``spec.max_lines`` lines, ``found`` is false. Returns ``(ScanResult, stand)``.
    """
    radius = jnp.asarray(radius, dtype=float)
    if checks.is_concrete(radius):
        checks.positive("particle radius R (nm)", radius)
    line = _Line(pos, sample, spec, radius, search_spacing(radius, pos.afm.tip))
    guess = jnp.asarray(guess, dtype=float)
    t0 = stand.afm.scanner.t
    empty = jnp.zeros((spec.max_lines, 2))
    start = _Search(
        stand,
        key,
        0,
        0,
        0,
        guess,
        guess,
        0,
        False,
        False,
        False,
        0,
        empty,
        empty,
        jnp.full(spec.max_lines, -1),
    )
    end = lax.while_loop(lambda c: ~c.done, line.next, start)
    result = ScanResult(
        end.estimate, end.verified, end.lines, end.starts, end.ends, end.phases, end.stand.afm.scanner.t - t0
    )
    return result, end.stand


class _Search(NamedTuple):
    """The local scan's state from line to line: where things stand, the key, the ``phase`` (0
    search, 1 along y, 2 along x through the estimate), the search line ``k`` from ``origin``,
    the searches ``widened`` (:attr:`LocalScan.widenings`), the ``estimate``, the ``lines``
    scanned, whether it is ``done`` (and ``verified``), whether the last line confirmed the
    estimate (``confirmed``), the lines along y since the last search line (``y_lines``), and
    each line's ``starts``, ``ends``, ``phases``."""

    stand: Stand
    key: Array
    phase: Array
    k: Array
    widened: Array
    origin: Array
    estimate: Array
    lines: Array
    done: Array
    verified: Array
    confirmed: Array
    y_lines: Array
    starts: Array
    ends: Array
    phases: Array


class _Line(NamedTuple):
    """One local scan's lines: the positioner, the sample, the settings, the particle's
    ``radius`` and the search's line ``spacing`` (nm)."""

    pos: Positioner
    sample: object
    spec: LocalScan
    radius: Array
    spacing: Array

    def scan(self, stand: Stand, centre: Array, along: Array, half: Array, key: Array) -> tuple:
        """Move to the start of the line ``half`` nm either side of ``centre`` along ``along``,
        scan it there and back: heights (2, points), the line's start and end, the next stand."""
        spec = self.spec
        P = spec.points
        unit = jnp.linspace(-1.0, 1.0, P)
        frac_move = jnp.arange(1, LINE_MOVE_SAMPLES + 1) / LINE_MOVE_SAMPLES
        start, end = centre - half * along, centre + half * along
        there = start + (unit[:, None] + 1) / 2 * (end - start)
        wanted = jnp.concatenate(
            [stand.wanted + frac_move[:, None] * (start - stand.wanted), there, there[::-1]]
        )
        dt = jnp.concatenate(
            [
                jnp.full(LINE_MOVE_SAMPLES, spec.move_time / LINE_MOVE_SAMPLES),
                jnp.full(2 * P, spec.line_time / (P - 1)),
            ]
        )
        t = stand.afm.scanner.t + jnp.cumsum(dt)
        _, h, stand = self.pos.drive(self.sample, stand, wanted, t, key)
        n = LINE_MOVE_SAMPLES
        return jnp.stack([h[n : n + P], h[n + P :][::-1]]), start, end, stand

    def next(self, c: _Search) -> _Search:
        """The next line: scanned where the phase puts it, its pulse judged, the estimate moved."""
        spec, radius = self.spec, self.radius
        ex, ey = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0])
        key, sub = jax.random.split(c.key)
        centre = jnp.where(c.phase == 0, c.origin + _offset(c.k) * self.spacing * ey, c.estimate)
        along = jnp.where(c.phase == 1, ey, ex)
        L = spec.half_length(radius, self.pos.afm.tip, search=c.phase == 0, widened=c.widened)
        h, start, end, stand = self.scan(c.stand, centre, along, L, sub)
        unit = jnp.linspace(-1.0, 1.0, spec.points)
        f1, mid1, z1 = pulse(h[0], unit * L, radius)
        f2, mid2, z2 = pulse(h[1], unit * L, radius)
        seen, mid, height = f1 & f2, (mid1 + mid2) / 2, (z1 + z2) / 2
        centred = (
            seen
            & (jnp.abs(mid) <= jnp.maximum(spec.centre_tolerance * radius, spec.centre_floor))
            & (jnp.abs(jnp.log(height / (2 * radius))) <= jnp.log1p(spec.height_tolerance))
        )
        # a search line never confirms; with condition_y, neither does the first line along y
        confirms = centred & (c.phase > 0) & ~(spec.condition_y & (c.phase == 1) & (c.y_lines == 0))
        verified = confirms & c.confirmed
        # seen: on to a line along the other axis (after the search: along y); lost: search from the estimate
        n_search = 2 * jnp.ceil(spec.search_margin(c.widened) / self.spacing) + 1
        exhausted = (c.phase == 0) & ~seen & (c.k + 1 >= n_search)
        widen = exhausted & (c.widened < spec.widenings)  # again from the origin, twice as far
        n = c.lines + 1
        return _Search(
            stand,
            key,
            jnp.where(seen, jnp.where(c.phase == 1, 2, 1), 0),
            jnp.where(seen | (c.phase > 0) | widen, 0, c.k + 1),
            c.widened + widen,
            jnp.where(seen | (c.phase == 0), c.origin, c.estimate),
            jnp.where(seen, centre + mid * along, c.estimate),
            n,
            verified | (exhausted & ~widen) | (n >= spec.max_lines),
            verified,
            confirms,
            jnp.where(c.phase == 0, 0, c.y_lines + (c.phase == 1)),
            c.starts.at[c.lines].set(start),
            c.ends.at[c.lines].set(end),
            c.phases.at[c.lines].set(c.phase),
        )


# ---------------------------------------------------------------------------------------------
# The pushing task


class Push(eqx.Module):
    """The pushing task's settings: start ``gap`` nm behind the contact, reached through a
    ``lead_in`` nm along the push (:func:`push`; 0: straight from where the tip is), push at
    ``speed`` nm/s in ``samples`` steps; then up to ``corrections`` checks
    (:func:`push_and_check`), each a local scan at the goal and, when the particle lies more than
    ``correct_beyond`` R from it, a corrective push. A push whose predicted success
    (:mod:`~jaxafm.position.push_odds`) is below ``min_odds`` is withheld (0: every push is made).
    The particle model: the tip touches a particle of radius R when their centres come within
    ``R + tip radius``; from then on the particle moves with the tip (rigidly), and it stays where
    it is when the tip retracts."""

    gap: float = eqx.field(static=True, default=20.0)
    lead_in: float = eqx.field(static=True, default=0.0)
    speed: float = eqx.field(static=True, default=200.0)
    samples: int = eqx.field(static=True, default=512)
    corrections: int = eqx.field(static=True, default=1)
    correct_beyond: float = eqx.field(static=True, default=0.25)
    min_odds: float = eqx.field(static=True, default=0.0)


class PushResult(eqx.Module):
    """What a push did (:func:`push`): the particle's true final centre ``final`` (2,) nm,
    whether the tip touched it (``contact``), and the tip's true ``path`` (samples, 2) nm."""

    final: Array
    contact: Array
    path: Array


def push(
    pos: Positioner,
    sample,
    stand: Stand,
    centre: Array,
    particle: Array,
    radius: Array,
    direction: Array,
    distance: Array,
    key: Array,
    spec: Push = Push(),
) -> tuple:
    """Push the particle whose centre the software sees at ``centre`` (2,) nm (truly at
    ``particle``) by ``distance`` nm along the unit ``direction`` (2,): approach behind it
    (lifted), lower, push so that it ends at ``centre + distance * direction``, retract.

    With ``spec.lead_in`` L > 0 nm the tip reaches the push's start through ``start + L d`` and
    ``start - L d`` (:func:`goto`'s approach along ``d``), so the push goes on along the way the
    tip came, far from its last reversal, where a model's error in the loop's first part after
    a turn (the small operators a short move sets) matters least; without, the tip backs
    ``R + tip radius + gap`` from the particle and the push starts right at that reversal.

    Returns ``(PushResult, stand)``: what the push did, and the next stand.
    """
    rho = radius + pos.afm.tip.radius
    direction = direction / jnp.linalg.norm(direction)
    start = centre - (rho + spec.gap) * direction
    end = centre + (distance - rho) * direction
    k_to, k_push = jax.random.split(key)
    _, _, stand = goto(pos, sample, stand, start, k_to, dwell=0.1, approach=spec.lead_in, along=direction)
    frac = jnp.arange(1, spec.samples + 1) / spec.samples
    wanted = start + frac[:, None] * (end - start)
    length = spec.gap + distance
    t = stand.afm.scanner.t + length / spec.speed / spec.samples * jnp.arange(1, spec.samples + 1)
    path, _, stand = pos.drive(sample, stand, wanted, t, k_push)
    touching = jnp.linalg.norm(path - particle, axis=-1) <= rho
    contact = jnp.argmax(touching)
    moved = touching.any()
    final = jnp.where(moved, particle + path[-1] - path[contact], particle)
    return PushResult(final, moved, path), stand


def moved(sample: Particles, particle: Array, final: Array) -> Particles:
    """``sample`` with the particle truly at ``particle`` (2,) nm (the nearest there) moved to ``final``."""
    i = jnp.argmin(jnp.sum((sample.centres - particle) ** 2, axis=-1))
    return Particles(sample.centres.at[i].set(final), sample.radii, sample.substrate)


class PushCheck(eqx.Module):
    """What the push and its checks did (:func:`push_and_check`): the ``first`` push, the
    particle's true centre after the corrective pushes ``final`` (2,) nm, the number of
    corrective pushes made (``corrections``); what the software knows of the first push: its
    ``command`` (2,) nm (the tip's travel it asked for, in the wanted frame) and the particle's
    move that the first check saw, ``seen_moved`` (2,) nm (NaN where it found nothing or made
    no check); ``withheld``: no push was made, its predicted success being below
    :attr:`Push.min_odds` (then nothing moved and ``first`` is the particle left in place)."""

    first: PushResult
    final: Array
    corrections: Array
    command: Array
    seen_moved: Array
    withheld: Array = False


def push_and_check(
    pos: Positioner,
    sample: Particles,
    stand: Stand,
    centre: Array,
    particle: Array,
    radius: Array,
    direction: Array,
    distance: Array,
    key: Array,
    spec: Push = Push(),
    local: LocalScan = LocalScan(),
    approach: float = 0.0,
    home: Array = None,
    learnt: PushField = NO_PUSH_FIELD,
    odds: Array = 1.0,
) -> tuple:
    """The push (:func:`push`), then up to ``spec.corrections`` rounds of: a move that arrives
    at the goal ``centre + distance * direction`` as the tip arrived at the particle, a local
    scan there (paper III-C applied again) and, when the particle it finds lies more than
    ``spec.correct_beyond`` R from the goal, a push from there by what remains. Arriving alike:
    with ``approach`` > 0 the goal is reached by :func:`goto` with that approach; without, the
    tip first goes back to ``home`` (2,) nm, where it came to the particle from (default: where
    the push started from). Straight after the push the frame carries the push's own travel
    error, and a scan there finds the particle at the goal however short it fell; arriving
    alike gives the check the frame the particle was seen in. Every push is commanded through
    ``learnt`` (:meth:`~jaxafm.position.online.PushField.command`: what the checked pushes before
    taught of this scanner's pushes; the default commands what is wanted). With ``odds``, the
    push's predicted success, below ``spec.min_odds`` nothing is done: the tip stays where it
    is and the particle where it was. Returns ``(PushCheck, stand)``: what the pushes did, and
    the next stand."""
    direction = direction / jnp.linalg.norm(direction)
    goal = centre + distance * direction
    home = stand.wanted if home is None else home
    particle0, stand0 = particle, stand
    keys = jax.random.split(key, 1 + 3 * spec.corrections)
    command = learnt.command(distance * direction)
    first, stand = _push_by(pos, sample, stand, centre, particle, radius, command, keys[0], spec)
    final, made, seen_moved = first.final, jnp.asarray(0), jnp.full(2, jnp.nan)
    for i in range(spec.corrections):
        sample = moved(sample, particle, final)
        particle = final
        _, _, stand = goto(
            pos, sample, stand, goal if approach > 0 else home, keys[1 + 3 * i], approach=approach
        )
        seen, stand = local_scan(pos, sample, stand, goal, radius, keys[2 + 3 * i], local)
        if i == 0:
            seen_moved = jnp.where(seen.found, seen.centre - centre, jnp.nan)
        rest = goal - seen.centre
        again = seen.found & (jnp.linalg.norm(rest) > spec.correct_beyond * radius)
        rest = jnp.where(again, learnt.command(rest), 0.0)  # no push: its results are not kept
        pushed, after = _push_by(
            pos, sample, stand, seen.centre, particle, radius, rest, keys[3 + 3 * i], spec
        )
        final = jnp.where(again, pushed.final, final)
        stand = jax.tree_util.tree_map(lambda a, b: jnp.where(again, a, b), after, stand)
        made = made + again
    checked = PushCheck(first, final, made, command, seen_moved, jnp.asarray(False))
    if spec.min_odds <= 0:
        return checked, stand
    withheld = jnp.asarray(odds) < spec.min_odds
    untouched = PushCheck(
        PushResult(particle0, jnp.asarray(False), jnp.zeros_like(first.path)),
        particle0,
        jnp.asarray(0),
        command,
        jnp.full(2, jnp.nan),
        jnp.asarray(True),
    )
    pick = lambda a, b: jnp.where(withheld, a, b)
    return jax.tree_util.tree_map(pick, (untouched, stand0), (checked, stand))


def _push_by(pos, sample, stand, centre, particle, radius, command, key, spec) -> tuple:
    """:func:`push` of the particle seen at ``centre`` by the vector ``command`` (2,) nm."""
    far = jnp.linalg.norm(command)
    unit = command / jnp.where(far > 0, far, 1.0)
    return push(pos, sample, stand, centre, particle, radius, unit, far, key, spec)
