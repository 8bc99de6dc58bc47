"""Monte-Carlo positioning trials (the library of ``jaxafm study``).

A trial is one particle at a place inside a landmark cell, on a scanner drawn for the study, in
one stage's survey of that scanner (:class:`StageSurvey`: the positioner with the stage's model
and landmark map, where things stand after the survey, and the survey image's true paths).
A trial's target is where its particle appears in that survey image (the wanted position at
which the mean of the true trace and retrace paths passes over the particle's centre: a
particle finder without error, :func:`image_position`); the trial then goes there (open loop,
A, B, A+B), and for A+B+C runs the local scan from there, moves to the centre it found and pushes.
With :class:`Learning`, a scanner's A+B trials run in rounds, each aimed by what the local scans
of the rounds before it found (:func:`learning_trials`).

Trials run in jitted, vmapped batches (:func:`run_chunk`) sharded over every JAX device of
every process (:mod:`~jaxafm.study.processes`; one mesh axis ``trials``). Each trial's random
key is ``fold_in(seed, trial)``, so the results depend neither on the batch size nor on the
device count.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import NamedTuple, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from ..instrument.afm import Raster
from ..instrument.samples import Particles
from ..position import online, push_odds
from ..position.positioning import LocalScan, Positioner, Push, Stand
from ..position.survey import stage_key
from ..position.trials import TrialResults, trials
from .processes import gather, replicate, shard

#: :func:`nearest_pixel` searches every STRIDE-th pixel of each STRIDE-th line, then the window
#: of +-STRIDE pixels around the best one.
STRIDE = 8


def nearest_pixel(path: jax.Array, point: jax.Array) -> tuple:
    """The pixel ``(i, j)`` of ``path`` (rows, cols, 2) nm that lies nearest to ``point`` (2,) nm.

    Coarse to fine: the nearest of every :data:`STRIDE`-th pixel and line, then the nearest in
    the (2 STRIDE + 1)^2 window around it (clipped to the image): 1/STRIDE^2 of the work of
    searching every pixel. The same pixel as that search on a raster whose pixels are nearly
    square and nearly evenly spaced (a scanner's distortion of a few %): on an even square raster
    of pitch p the nearest pixel lies within p / sqrt(2) of the point and the nearest coarse one
    within STRIDE p / sqrt(2), so the two are at most (STRIDE + 1) p / sqrt(2) < STRIDE p apart,
    inside the window. A raster too small for the window is searched whole."""
    rows, cols = path.shape[:2]
    w = 2 * STRIDE + 1
    dist = lambda p: jnp.sum((p - point) ** 2, -1)
    if rows < w or cols < w:
        return jnp.divmod(jnp.argmin(dist(path)), cols)
    coarse = path[::STRIDE, ::STRIDE]
    ic, jc = jnp.divmod(jnp.argmin(dist(coarse)), coarse.shape[1])
    i0 = jnp.clip(ic * STRIDE - STRIDE, 0, rows - w)
    j0 = jnp.clip(jc * STRIDE - STRIDE, 0, cols - w)
    di, dj = jnp.divmod(jnp.argmin(dist(jax.lax.dynamic_slice(path, (i0, j0, 0), (w, w, 2)))), w)
    return i0 + di, j0 + dj


@jax.jit
def image_position(mean_path: jax.Array, origin: jax.Array, pixel: jax.Array, centre: jax.Array) -> tuple:
    """Where a particle at ``centre`` (2,) nm appears in a survey image: the wanted position
    (2,) nm at which ``mean_path`` (rows, cols, 2) nm, the mean of the true trace and retrace
    paths, passes over it (the nearest pixel, :func:`nearest_pixel`, then one Newton step on the
    local Jacobian), and whether it does so inside the image (else the particle is not in it)."""
    rows, cols = mean_path.shape[:2]
    i0, j0 = nearest_pixel(mean_path, centre)
    i, j = jnp.clip(i0, 1, rows - 2), jnp.clip(j0, 1, cols - 2)
    J = (
        jnp.stack([mean_path[i, j + 1] - mean_path[i, j - 1], mean_path[i + 1, j] - mean_path[i - 1, j]], -1)
        / 2
    )
    step = jnp.linalg.solve(J, centre - mean_path[i, j])
    pix = jnp.stack([j, i]) + step
    inside = jnp.all((pix >= 0) & (pix <= jnp.array([cols - 1, rows - 1])))
    return origin + pix * pixel, inside


class Unsurveyed(enum.Enum):
    """Why a scanner's stage has no survey (its trials fail)."""

    REFUSED = "step A refused its model"
    TOO_FEW = "too few landmarks"


class StageSurvey(eqx.Module):
    """One stage's survey of one scanner, from which its trials go on: the ``positioner`` (with
    the stage's model and landmark map), where things ``stand`` after the survey, and the mean of
    the true trace and retrace paths of its image, ``mean_path`` (rows, cols, 2) nm."""

    positioner: Positioner
    stand: Stand
    mean_path: jax.Array


@dataclasses.dataclass(frozen=True)
class Learning:
    """Step C's finds teach the A+B moves that follow them on a scanner (:func:`learning_trials`).

    Attributes:
        round_trials: trials run together: each round is aimed with what the finds of the rounds
            before it taught (the first with nothing).
        prior_nm: the prior's standard deviation of each coefficient of the offset field
            (:func:`~jaxafm.position.online.learn_field`), nm.
        noise_nm: the scatter of one find about the field, nm.
        pushes: the checked first pushes teach the pushes after them
            (:func:`~jaxafm.position.online.learn_push`, with the same prior and scatter).
        min_push_odds: a push whose predicted success from the scanner's earlier rounds is below
            it is withheld (0: every push is made; the gate itself is ``TrialSettings.push``'s
            ``min_odds``).
        push_tolerance_radii: the push succeeds within this many R of its goal (the odds' tolerance).
    """

    round_trials: int
    prior_nm: float
    noise_nm: float
    pushes: bool = False
    min_push_odds: float = 0.0
    push_tolerance_radii: float = 1.0


@dataclasses.dataclass(frozen=True)
class TrialSettings:
    """What every trial of a study shares.

    Attributes:
        seed: the study's seed; trial ``i`` of the stage at ``j`` draws from
            ``fold_in(fold_in(fold_in(key(seed), 0), i), j)``.
        work: the workspace raster (its origin and pixel size place a particle in a survey image).
        approach: the approach (nm) of every move through a landmark map
            (:func:`~jaxafm.position.positioning.goto`).
        local: step C's settings, for the trials of A+B; ``None``: no step C.
        push: the push's settings, after step C; ``None``: no push.
        learning: how step C's finds teach the A+B moves; ``None``: they do not.
    """

    seed: int
    work: Raster
    approach: float
    local: Optional[LocalScan] = None
    push: Optional[Push] = None
    learning: Optional[Learning] = None


#: A vmapped local scan runs as many lines as its slowest trial, and most end within 3-4 lines:
#: every trial first runs with at most this many, then those still searching run again, alone.
FIRST_PASS_LINES = 6


def stage_trials(
    survey: StageSurvey,
    x: dict,
    stage: int,
    mesh: Mesh,
    settings: TrialSettings,
    local=None,
    field=None,
    push_field: online.PushField = online.NO_PUSH_FIELD,
    odds=None,
) -> dict:
    """:func:`~jaxafm.position.trials.trials` for the trials ``x`` (NumPy columns ``trial``,
    ``centre``, ``radius``, ``direction``, ``distance``) on one stage's ``survey``, split over the
    mesh. Each trial aims at its particle's place in the survey image (``target``) plus the
    learnt offset ``field`` there (an :class:`~jaxafm.position.online.OffsetField`; ``None``: no
    offset); every push is commanded through ``push_field``, and withheld where its predicted
    success ``odds`` (K,) is below ``settings.push.min_odds`` (``None``: made). With ``local``, in two passes
    (:data:`FIRST_PASS_LINES`); each trial's key is ``fold_in(fold_in(root, trial), stage)``, so
    the second pass gives what one pass with every line would. Returns the trials' NumPy columns
    (:func:`_columns`), ``target``, the ``offset`` aimed by and ``outside_grid``."""
    copies = replicate(survey, mesh)
    pos, stand, mean_path = copies.positioner, copies.stand, copies.mean_path
    work = settings.work
    target, seen = jax.vmap(image_position, (None, None, None, 0))(
        mean_path, jnp.asarray(work.origin), jnp.asarray(work.pixel_size), jnp.asarray(x["centre"])
    )
    target = np.asarray(target)
    offset = np.zeros_like(target) if field is None else field(target)
    x = x | {"target": target + offset} | ({} if odds is None else {"odds": np.asarray(odds, float)})
    frame = survey.positioner.frame
    box = (np.asarray(frame.measured).min(0), np.asarray(frame.measured).max(0)) if frame else None
    root = jax.random.fold_in(jax.random.key(settings.seed), 0)

    def call(idx, spec, size):
        a = shard({k: v[idx] for k, v in x.items()}, mesh, size)
        seen = jax.vmap(lambda c, R: Particles(c[None], R[None]))(
            a["centre"], a["radius"]
        )  # a particle per trial
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.fold_in(root, i), stage))(a["trial"])
        r = trials(
            pos,
            seen,
            stand,
            a["target"],
            a["centre"],
            a["radius"],
            a["direction"],
            a["distance"],
            keys,
            spec,
            settings.push if spec else None,
            settings.approach if pos.frame is not None else 0.0,
            push_field,
            a.get("odds"),
        )
        return _columns(gather(r, len(idx)))

    every = np.arange(len(x["trial"]))
    first = -(-every.size // mesh.size) * mesh.size
    outside = (
        np.zeros(len(every), bool) if box is None else np.any((target < box[0]) | (target > box[1]), axis=1)
    )
    about = {"outside_grid": outside, "target": target, "offset": offset}
    if local is None or local.max_lines <= FIRST_PASS_LINES:
        return _unseen(call(every, local, first), np.asarray(seen)) | about
    r = call(every, dataclasses.replace(local, max_lines=FIRST_PASS_LINES), first)
    again = np.flatnonzero(~r["c_found"] & (r["c_lines"] >= FIRST_PASS_LINES))
    size = -(-max(first // 16, 1) // mesh.size) * mesh.size  # one more shape to compile per batch size
    for start in range(0, again.size, size):
        idx = again[start : start + size]
        r2 = call(idx, local, size)
        for k in r:
            r[k][idx] = r2[k]
    return _unseen(r, np.asarray(seen)) | about


def learning_trials(
    survey: StageSurvey, x: dict, stage: int, mesh: Mesh, settings: TrialSettings, earlier: Observed
) -> dict:
    """:func:`stage_trials` with step C for the trials ``x``, run in order in rounds of
    ``settings.learning.round_trials``: each round aims at its targets plus the offset field
    that step C's verified finds on the scanner so far support (a
    :class:`~jaxafm.position.online.Tracker` without drift, updated after each round: the trials
    of a study all start where its survey left the instrument, at one time), each find observing
    ``centre found - target`` at its target (the particle's place in the survey image) in the
    local scan's frame; with ``settings.learning.pushes``, it
    commands its pushes through the :class:`~jaxafm.position.online.PushField` that the checked
    first pushes so far support (:func:`~jaxafm.position.online.learn_push`, :func:`observed`).
    ``earlier``: what was observed before these trials. Returns the columns, with
    ``learnt_from`` (the finds each trial's offset was learnt from), ``push_learnt_from``
    (the pushes its push was learnt from; 0 without learning pushes) and ``predicted_sd`` (nm):
    the spread per axis of the trial's find about where it was aimed that the tracker predicted,
    its variance factor times the field's sd at the target and one find's scatter
    (``learning.noise_nm``) in quadrature."""
    learn, work = settings.learning, settings.work
    tracker = online.Tracker.start(work.centre, max(work.size) / 2, learn.prior_nm, learn.noise_nm)
    tracker = tracker.observe(earlier.targets, earlier.offsets)
    seen = [earlier]
    rounds = []
    for a in range(0, len(x["trial"]), learn.round_trials):
        so_far = Observed(*(np.concatenate(v) for v in zip(*seen)))
        push_field = online.NO_PUSH_FIELD
        if learn.pushes:
            push_field = online.learn_push(so_far.commands, so_far.moved, learn.prior_nm, learn.noise_nm)
        rows = {k: v[a : a + learn.round_trials] for k, v in x.items()}
        odds = None
        if learn.min_push_odds > 0:
            odds = _round_odds(so_far.pushes, rows, learn.push_tolerance_radii, push_field)
        field = tracker.field()
        r = stage_trials(survey, rows, stage, mesh, settings, settings.local, field, push_field, odds)
        r["predicted_sd"] = tracker.factor * np.hypot(field.sd(r["target"]), learn.noise_nm)
        pushes = None
        if "push_first" in r:
            made = ~r["push_withheld"] & np.isfinite(r["error_nm"])  # unseen: no target, no push
            push = rows["distance"][:, None] * rows["direction"]
            pushes = push_rows(push, first_push_miss(r), r["push_contact"], made, r["push_command"])
        seen.append(
            observed(
                r["target"],
                r["c_centre"],
                r["c_found"],
                r.get("push_command"),
                r.get("push_seen_moved"),
                pushes,
            )
        )
        tracker = tracker.observe(seen[-1].targets, seen[-1].offsets)
        learnt = {"learnt_from": len(so_far.targets), "push_learnt_from": len(so_far.commands) * learn.pushes}
        rounds.append(r | {k: np.full(len(r["target"]), n) for k, n in learnt.items()})
    return {k: np.concatenate([r[k] for r in rounds]) for k in rounds[0]}


def _round_odds(
    pushes: np.ndarray,
    rows: dict,
    tolerance_radii: float,
    push_field: online.PushField = online.NO_PUSH_FIELD,
) -> np.ndarray:
    """Each of a round's pushes' predicted success from the scanner's earlier first pushes
    ``pushes`` (:class:`Observed`), :func:`~jaxafm.position.push_odds.odds_from_earlier`, each
    commanded through the round's ``push_field``; 1 (no odds: the push is made) while fewer than
    :data:`~jaxafm.position.push_odds.MIN_PUSHES` touching pushes came before, or for a push in a
    direction they never spanned."""
    k = len(rows["distance"])
    wanted = rows["distance"][:, None] * rows["direction"]
    command = np.asarray(jax.vmap(push_field.command)(jnp.asarray(wanted)))
    round_pushes = push_rows(wanted, np.full((k, 2), np.nan), 0, 0, command)
    every = np.concatenate([pushes, round_pushes])
    tolerance = tolerance_radii * np.concatenate([np.ones(len(pushes)), rows["radius"]])
    odds = push_odds.odds_from_earlier(
        every[:, :2], every[:, 2:4], every[:, 4] == 1, every[:, 5] == 1, tolerance, every[:, 6:8]
    )
    return np.where(np.isfinite(odds[-k:]), odds[-k:], 1.0)


def _columns(r: TrialResults) -> dict:
    """The study's columns of the trials' results: ``error_nm`` and the true ``tip`` (2,) nm;
    step C's ``c_error_nm``, ``c_found``, ``c_lines``, ``c_seconds``, ``c_centre`` (2,) nm (the
    centre it found, in the wanted frame), ``c_tip`` (2,) nm (the true tip after the move
    there); the push's ``push_final``, ``push_first`` (the
    particle's true centre after the first push), ``push_goal``, ``push_corrections``,
    ``push_contact``, ``push_command`` and ``push_seen_moved`` (what the software asked of the
    first push and saw it do, :class:`~jaxafm.position.positioning.PushCheck`)."""
    columns = {"error_nm": r.error_nm, "tip": r.tip}
    if r.step_c is not None:
        scan = r.step_c.scan
        columns |= {
            "c_error_nm": r.step_c.error_nm,
            "c_found": scan.found,
            "c_lines": scan.lines,
            "c_seconds": scan.seconds,
            "c_centre": scan.centre,
            "c_tip": r.step_c.tip,
        }
    if r.push is not None:
        columns |= {
            "push_final": r.push.final,
            "push_first": r.push.first.final,
            "push_goal": r.push_goal,
            "push_corrections": r.push.corrections,
            "push_contact": r.push.first.contact,
            "push_command": r.push.command,
            "push_seen_moved": r.push.seen_moved,
            "push_withheld": r.push.withheld,
        }
    return columns


def _unseen(r: dict, seen: np.ndarray) -> dict:
    """Trials whose particle lies outside the survey image have no target: their errors are NaN
    and nothing of theirs counts as found or pushed."""
    for k, v in r.items():
        if v.dtype == bool:
            v[~seen] = False
        elif (
            k.endswith("error_nm")
            or k.startswith("push_final")
            or k in ("tip", "c_centre", "c_tip", "push_seen_moved")
        ):
            v[~seen] = np.nan
    return r


class Observed(NamedTuple):
    """What a scanner's trials observed, for :func:`learning_trials`: step C's verified finds,
    their ``targets`` and ``offsets`` (``centre found - target``), the checked first pushes, their
    ``commands`` and the particle's moves the checks saw (``moved``), each (k, 2) nm; and every
    first push tried, ``pushes`` (k, 8): its wanted vector (2, nm), its miss (2, nm, against the
    truth, as a reference outside the frame measures it; NaN where none was made), whether it
    touched its particle and whether it was made (1 or 0: not withheld, and aimed at a particle
    the survey saw), and what it commanded (2, nm)."""

    targets: np.ndarray
    offsets: np.ndarray
    commands: np.ndarray
    moved: np.ndarray
    pushes: np.ndarray


#: no observation: the ``earlier`` of a scanner's first trials
NOTHING_OBSERVED = Observed(*(np.zeros((0, 2)),) * 4, np.zeros((0, 8)))

#: a checked push teaches only when its particle moved at least this share of the command along
#: it: one whose tip missed the particle left it where it was, which is no shortfall of the drive
MOVED_AT_LEAST = 0.5


def observed(target, centre, found, command=None, moved=None, pushes=None) -> Observed:
    """What one round's trials observed: step C's verified finds (``found``; ``target``,
    ``centre`` found); with ``command`` and ``moved``, the first pushes whose check found the
    particle moved by at least :data:`MOVED_AT_LEAST` of the command along it; and the first
    pushes tried, ``pushes`` (k, 8) (:class:`Observed`; ``None``: none)."""
    found = np.asarray(found, bool)
    if command is None:
        command = moved = np.zeros((0, 2))
    along = np.sum(np.nan_to_num(moved) * command, -1) / np.maximum(np.sum(command**2, -1), 1e-12)
    pushed = np.isfinite(moved).all(-1) & (along >= MOVED_AT_LEAST)
    pushes = np.zeros((0, 8)) if pushes is None else pushes
    return Observed(target[found], centre[found] - target[found], command[pushed], moved[pushed], pushes)


def push_rows(push, miss, contact, made, command=None) -> np.ndarray:
    """The first pushes tried, as :class:`Observed` keeps them (k, 8): their wanted vectors
    ``push`` and misses ``miss`` (k, 2) nm, ``contact`` and ``made`` (k,) bool (not withheld, and
    aimed at a particle the survey saw; either may be one value for all), and their ``command``
    (k, 2) nm (``None``: each commanded as wanted)."""
    k = len(push)
    flags = [np.broadcast_to(np.asarray(v, float), (k,)) for v in (contact, made)]
    command = push if command is None else command
    return np.column_stack([push, miss, *flags, command]).astype(float)


def push_vectors(draws: dict) -> np.ndarray:
    """The trials' pushes (k, 2) nm, their distance along their unit direction, from a study's
    draws (``push_distance_nm``, ``push_dx``, ``push_dy``)."""
    return draws["push_distance_nm"][:, None] * np.stack([draws["push_dx"], draws["push_dy"]], -1)


def push_commands(r: dict) -> np.ndarray:
    """The trials' first-push commands (k, 2) nm, what each asked of the tip (equal to
    :func:`push_vectors` unless the pushes learn), from a study's columns (``push_command_x_nm``,
    ``push_command_y_nm``)."""
    return np.stack([r["push_command_x_nm"], r["push_command_y_nm"]], -1)


def first_push_miss(r: dict) -> np.ndarray:
    """The first push's true miss (k, 2) nm, its particle's centre after it less its goal, from
    trials' columns ``r`` (:func:`_columns`); NaN where the push was withheld."""
    return np.where(r["push_withheld"][:, None], np.nan, r["push_first"] - r["push_goal"])


def with_chunk_observed(earlier: Observed, columns, push=None) -> Observed:
    """``earlier`` observations and, after them, those of a chunk's written ``columns``
    (:func:`run_chunk`'s ``AB_target``, ``ABC_centre``, ``ABC_found``, and ``push_command``,
    ``push_seen_moved``, ``push_first_along_nm``, ``push_first_across_nm``, ``push_contact``,
    ``push_withheld`` where the push ran, its trials' ``push`` vectors (k, 2) nm,
    :func:`push_vectors`; :func:`observed`)."""
    xy = lambda name: np.stack([columns[f"{name}_x_nm"], columns[f"{name}_y_nm"]], -1)
    pushed = "push_command_x_nm" in columns
    pushes = None
    if pushed:
        miss = push_odds.from_components(
            columns["push_first_along_nm"], columns["push_first_across_nm"], push
        )
        made = ~columns["push_withheld"] & columns["AB_seen"]
        pushes = push_rows(push, miss, columns["push_contact"], made, push_commands(columns))
    new = observed(
        xy("AB_target"),
        xy("ABC_centre"),
        columns["ABC_found"],
        xy("push_command") if pushed else None,
        xy("push_seen_moved") if pushed else None,
        pushes,
    )
    return Observed(*(np.concatenate([e, n]) for e, n in zip(earlier, new)))


def run_chunk(
    surveys: dict, draws: dict, mesh: Mesh, settings: TrialSettings, earlier: Observed = NOTHING_OBSERVED
) -> dict:
    """The results of the trials in ``draws`` (one scanner's; NumPy columns ``trial``, ``x_nm``,
    ``y_nm``, ``radius_nm``, ``push_dx``, ``push_dy``, ``push_distance_nm``) on each stage's
    survey (``surveys``: stage name -> :class:`StageSurvey`, or :class:`Unsurveyed` where its
    trials fail), columns keyed by stage, run as one batch split over the ``mesh``'s devices
    (the surveys replicated on them); with ``settings.learning``, A+B with step C in rounds that
    learn from what the trials before them observed (:func:`learning_trials`; ``earlier``: what
    the scanner's trials before these observed, :func:`observed`)."""
    x = {
        "trial": draws["trial"],
        "centre": np.stack([draws["x_nm"], draws["y_nm"]], -1),
        "radius": draws["radius_nm"],
        "direction": np.stack([draws["push_dx"], draws["push_dy"]], -1),
        "distance": draws["push_distance_nm"],
    }
    n = len(x["trial"])
    out = {}
    for j, (stage, survey) in enumerate(surveys.items()):
        with_c = stage == "A+B" and settings.local is not None
        if isinstance(survey, Unsurveyed):  # step A refused its model or the survey found too few landmarks
            r = _failed(n, modelled=survey is not Unsurveyed.REFUSED)
        else:
            if with_c and settings.learning:
                r = learning_trials(survey, x, j, mesh, settings, earlier)
            else:
                r = stage_trials(survey, x, j, mesh, settings, settings.local if with_c else None)
            r |= {
                "modelled": np.ones(n, bool),
                "surveyed": np.ones(n, bool),
                "seen": np.isfinite(r["error_nm"]),
            }
            if with_c and settings.push:
                miss = r["push_final"] - r["push_goal"]
                first = first_push_miss(r)
                along, across = push_odds.components(first, x["direction"])
                r |= {
                    "push_error_nm": np.linalg.norm(miss, axis=-1),
                    "push_along_nm": np.sum(miss * x["direction"], axis=-1),
                    "push_first_error_nm": np.linalg.norm(first, axis=-1),
                    "push_first_along_nm": along,
                    "push_first_across_nm": across,
                }
        key = stage_key(stage)
        out[f"{key}_error_nm"] = r["error_nm"]
        out |= _xy(f"{key}_target", r["target"]) | _xy(f"{key}_miss", r["tip"] - x["centre"])
        if stage == "A+B":
            out |= {f"AB_{k}": r[k] for k in ("modelled", "surveyed", "seen", "outside_grid")}
        if with_c and settings.learning:
            out |= _xy("AB_offset", r["offset"]) | {"AB_learnt_from": r["learnt_from"]}
            out["AB_predicted_sd_nm"] = r["predicted_sd"]
            if settings.learning.pushes:
                out["push_learnt_from"] = r["push_learnt_from"]
        if with_c:
            out |= (
                {
                    "ABC_error_nm": r["c_error_nm"],
                    "ABC_found": r["c_found"],
                    "ABC_lines": r["c_lines"],
                    "ABC_local_scan_s": r["c_seconds"],
                }
                | _xy("ABC_centre", r["c_centre"])
                | _xy("ABC_miss", r["c_tip"] - x["centre"])
            )
        if with_c and settings.push:
            push = (
                "push_error_nm",
                "push_along_nm",
                "push_first_error_nm",
                "push_first_along_nm",
                "push_first_across_nm",
                "push_corrections",
                "push_contact",
                "push_withheld",
            )
            out |= {k: r[k] for k in push} | _xy("push_command", r["push_command"])
            out |= _xy("push_seen_moved", r["push_seen_moved"])
    return out


def _xy(name: str, v: np.ndarray) -> dict:
    """A (k, 2) nm column as two: ``<name>_x_nm`` and ``<name>_y_nm``."""
    return {f"{name}_x_nm": v[:, 0], f"{name}_y_nm": v[:, 1]}


def _failed(n: int, modelled: bool) -> dict:
    """The columns of ``n`` trials of a stage without a survey (``modelled``: step A gave a model)."""
    return {
        "target": np.full((n, 2), np.nan),
        "offset": np.full((n, 2), np.nan),
        "predicted_sd": np.full(n, np.nan),
        "learnt_from": np.zeros(n, int),
        "push_learnt_from": np.zeros(n, int),
        "tip": np.full((n, 2), np.nan),
        "c_centre": np.full((n, 2), np.nan),
        "c_tip": np.full((n, 2), np.nan),
        "modelled": np.full(n, modelled),
        "surveyed": np.zeros(n, bool),
        "seen": np.zeros(n, bool),
        "outside_grid": np.zeros(n, bool),
        "error_nm": np.full(n, np.nan),
        "c_error_nm": np.full(n, np.nan),
        "c_found": np.zeros(n, bool),
        "c_lines": np.zeros(n, int),
        "c_seconds": np.full(n, np.nan),
        "push_error_nm": np.full(n, np.nan),
        "push_along_nm": np.full(n, np.nan),
        "push_first_error_nm": np.full(n, np.nan),
        "push_first_along_nm": np.full(n, np.nan),
        "push_first_across_nm": np.full(n, np.nan),
        "push_corrections": np.zeros(n, int),
        "push_contact": np.zeros(n, bool),
        "push_command": np.full((n, 2), np.nan),
        "push_seen_moved": np.full((n, 2), np.nan),
        "push_withheld": np.zeros(n, bool),
    }


def predicted_push_success(r: dict, tolerance_radii: float) -> np.ndarray:
    """Each trial's predicted probability that its first push touches the particle and ends within
    ``tolerance_radii`` R of its goal (:mod:`~jaxafm.position.push_odds`), from the first pushes
    of the earlier trials on its scanner (trial order: the order a session would run them in):
    whether they touched their particles, and the misses of those that did, measured against the
    truth (the particle's true centre after the push: what a reference outside the instrument's
    frame would measure; a check in that frame cannot see its scale error over the push). NaN
    for a trial that did not push or had fewer than
    :data:`~jaxafm.position.push_odds.MIN_PUSHES` touching pushes before it."""
    p = np.full(len(r["trial"]), np.nan)
    push = push_vectors(r)
    command = push_commands(r)
    miss = push_odds.from_components(r["push_first_along_nm"], r["push_first_across_nm"], push)
    for s in np.unique(r["scanner"]):
        idx = np.flatnonzero(r["scanner"] == s)
        p[idx] = push_odds.odds_from_earlier(
            push[idx],
            miss[idx],
            r["push_contact"][idx],
            np.ones(len(idx), bool),
            tolerance_radii * r["radius_nm"][idx],
            command[idx],
        )
    return np.where(np.isfinite(r["push_first_error_nm"]), p, np.nan)


def stage_summary(errors: np.ndarray, success: np.ndarray, scan_s: float) -> dict:
    """Error quantiles (nm) over the trials that ran (NaN: no model, no landmark map, or the
    particle lay outside its image), the share that ran, and the success rate over all trials."""
    e = errors[np.isfinite(errors)]
    q = np.percentile(e, [50, 95, 99]) if e.size else np.full(3, np.nan)
    return {
        "error_median_nm": float(q[0]),
        "error_p95_nm": float(q[1]),
        "error_p99_nm": float(q[2]),
        "error_max_nm": float(e.max()) if e.size else float("nan"),
        "success_pct": 100 * float(np.mean(success)),
        "scan_time_s": float(scan_s),
        "trials": int(errors.size),
        "ran_pct": 100 * e.size / max(errors.size, 1),
    }


def noise_ceiling_pct(radius_nm: np.ndarray, noise_std_nm: np.ndarray, within_radii: float = 0.1) -> float:
    """The highest share of trials (%) that can end within ``within_radii`` R when the tip's
    position carries white noise of ``noise_std_nm`` per axis (each trial's scanner's): an error
    read at one sample carries that noise, whose length over two axes is Rayleigh, so even a tip
    whose mean position is exact ends beyond ``rho = within_radii R`` with probability
    ``exp(-rho^2 / (2 sigma^2))``; 100 less the trials' mean of it."""
    rho = within_radii * np.asarray(radius_nm, dtype=float)
    sigma = np.asarray(noise_std_nm, dtype=float)
    beyond = np.where(sigma > 0, np.exp(-(rho**2) / (2 * np.where(sigma > 0, sigma, 1.0) ** 2)), 0.0)
    return 100 * (1 - float(np.mean(beyond)))


def failure_modes(r: dict, margin_nm: float, max_lines: int, tolerance_radii: float) -> dict:
    """Why trials failed, stage by stage (counts of trials; the reasons of a stage exclude each other).

    A+B: step A refused its model (:func:`~jaxafm.identify.plausibility.implausible`), the survey
    found too few landmarks for a map, the particle lay outside the survey image,
    the target lay outside the landmarks found (the map extrapolated), or the error left is beyond
    the local scan's widest search margin (``margin_nm``). A+B+C: the search found no particle, the
    verification did not pass within ``max_lines``, or it passed on a centre more than 0.1 R off.
    Push: withheld (its odds below ``learning.min_push_odds``), the tip missed the particle, or
    the particle ended more than ``tolerance_radii`` R from its goal: short or long (along the
    push) or off the line (across it more than along).
    """
    if "AB_surveyed" not in r:
        return {}
    R = r["radius_nm"]
    ran = r["AB_surveyed"] & r["AB_seen"]
    e = r["AB_error_nm"]
    ab = {
        "step A: model refused (implausible)": ~r["AB_modelled"],
        "survey: too few landmarks": r["AB_modelled"] & ~r["AB_surveyed"],
        "particle outside the survey image": r["AB_surveyed"] & ~r["AB_seen"],
        "target outside the landmarks found": ran & r["AB_outside_grid"] & ~(e <= 0.1 * R),
        "error beyond the local scan's margin": ran & ~r["AB_outside_grid"] & (e > margin_nm),
    }
    modes = {"A+B": ab}
    not_run = {"not run (A+B above)": ~ran}
    if "ABC_error_nm" in r:
        bad = ran & ~(r["ABC_error_nm"] <= 0.1 * R)
        found, full = r["ABC_found"], r["ABC_lines"] >= max_lines
        modes["A+B+C"] = not_run | {
            "search found no particle": bad & ~found & ~full,
            f"not verified within {max_lines} lines": bad & ~found & full,
            "verified on a centre > 0.1 R off": bad & found,
        }
    if "push_error_nm" in r:
        tol = tolerance_radii * R
        withheld = ran & r["push_withheld"]
        missed = ran & ~withheld & ~r["push_contact"]
        off = ran & r["push_contact"] & ~(r["push_error_nm"] <= tol)
        along = r["push_along_nm"]
        across = np.sqrt(np.maximum(r["push_error_nm"] ** 2 - along**2, 0))
        modes["push"] = not_run | {
            "withheld (odds too low)": withheld,
            "tip missed the particle": missed,
            "short": off & (along < 0) & (-along >= across),
            "long": off & (along > 0) & (along >= across),
            "off the line": off & (across > np.abs(along)),
        }
    return {stage: {k: int(v.sum()) for k, v in reasons.items()} for stage, reasons in modes.items()}
