"""``jaxafm run CONFIG``: the paper's full positioning strategy on the simulated AFM.

Step A identifies the scanner from a grating (as ``jaxafm calibrate``). Then,
from the same instrument state after the initialisation cycle, each stage of
the ablation works on a fresh field of nanoparticles:

- **open loop** and **A**: image the workspace with the nominal (A: the
  model-compensated) drive, find the particles, go to each;
- **B** and **A+B**: press the N x N landmark grid, image the workspace, find
  the indents and the particles, go to each particle through the landmark map
  (eq. 4-5 and the polynomial surface, both);
- **A+B+C**: after A+B, the local scan on each particle, the move to the centre
  it found, and the push.

Targets are the particles as found in the workspace image, which is how a user
picks them; errors are the true tip's distance from the true particle centre
at the end of a 0.2 s dwell. Every target is an independent trial from the
state after the workspace image (``vmap``). Writes ``metrics.json``, ``trials.npz`` (every
trial's results), ``model_scanner.json`` and figures.

The workspace layout, step A's model and the local-scan and push settings as configured here
are also those of ``jaxafm study``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import plots
from ..config import LocalScanSpec, Positioning, PushSpec, RunConfig, resolve_data_path
from ..identify.step_a import calibration_about, twin_state
from ..instrument.afm import AFM, AFMState, Raster, default_afm, run_cycle
from ..instrument.samples import Indented, Particles
from ..model.io import load_model, save_model
from ..model.scanner import Scanner, ScannerState
from ..position import survey
from ..position.landmarks import LandmarkGrid
from ..position.positioning import LocalScan, Positioner, Push
from ..position.survey import STAGES, Stage, stage_key
from ..position.trials import TrialResults, nearby, trials
from .calibrate import calibration_scans, identify_model
from .folder import Output


def workspace_layout(cfg: Positioning) -> tuple:
    """The workspace raster (5 % over-scan each side), step B's landmark grid in its image
    (eq. 3) and the grid's wanted positions ``D`` (N*N, 2) nm, as ``cfg`` sets them."""
    ws = cfg.workspace
    work = Raster(
        ws.size_nm, ws.pixels, ws.pixels, line_rate=ws.line_rate_hz, centre=tuple(ws.centre_nm), overscan=0.05
    )
    grid = LandmarkGrid(cfg.landmarks.n, cfg.landmarks.start_px, cfg.landmarks.step_px, ws.pixels)
    return work, grid, grid.positions(work)


def local_scan_settings(spec: LocalScanSpec) -> LocalScan:
    """Step C's settings a config's ``local_scan`` gives (``move_time`` keeps its default)."""
    return LocalScan(
        spec.points,
        spec.line_time_s,
        margin=spec.margin_nm,
        widenings=spec.widenings,
        max_lines=spec.max_lines,
        height_tolerance=spec.height_tolerance,
        centre_tolerance=spec.centre_tolerance,
        centre_floor=spec.centre_floor_nm,
        condition_y=spec.condition_y,
    )


def push_settings(spec: PushSpec, min_odds: float = 0.0) -> Push:
    """The push's settings a config's ``push`` gives (``gap``, ``samples`` and
    ``correct_beyond`` keep their defaults), pushes with odds below ``min_odds`` withheld."""
    return Push(
        lead_in=spec.lead_in_nm, speed=spec.speed_nm_per_s, corrections=spec.corrections, min_odds=min_odds
    )


class ImplausibleModel(ValueError):
    """Step A's identified model failed its plausibility checks (the message says which)."""


def read_scanner_model(cfg: Positioning, config_path: Path) -> Optional[Scanner]:
    """The scanner in ``calibration.model_file`` (None without one), checked.

    Steps B and C drive the model as a twin of the instrument, whose state after each drive they
    carry on from (:func:`~jaxafm.identify.inverse.inverse_and_state`): a drift's wander and
    position noise are random, so a twin has neither. A model file with them is refused here,
    before any work, rather than run without them: the file would not be the model that runs.

    Raises:
        ValueError: naming the key and the file: missing, not a saved model, not a scanner, or a
            scanner with drift or noise.
    """
    if cfg.calibration.model_file is None:
        return None
    path = resolve_data_path(cfg.calibration.model_file, config_path)
    try:
        model = load_model(path)
    except (OSError, ValueError) as e:
        raise ValueError(f"calibration.model_file: {e}") from None
    if not isinstance(model, Scanner):
        raise ValueError(
            f"calibration.model_file: {path} holds a {type(model).__name__}, not a two-axis scanner "
            "(a model_*.json written by `jaxafm calibrate` or `jaxafm run`)"
        )
    random = [e for e in ("drift", "noise") if getattr(model, e) is not None]
    if random:
        raise ValueError(
            f"calibration.model_file: {path} holds a scanner with {' and '.join(random)}: steps B and C "
            "drive the model as a twin of the instrument, carrying on from its state after each drive, "
            "and the state after random effects is unknown; save the scanner without them (e.g. "
            f"model.without({', '.join(repr(e) for e in random)}))"
        )
    return model


def identify_scanner(cfg: Positioning, scans: tuple, config_path: Path, log) -> tuple:
    """Step A's model: identified from ``scans``, or read from ``model_file``; and the seconds.

    Raises:
        ImplausibleModel: when the identified model fails step A's plausibility checks.
    """
    spec = cfg.calibration
    if spec.model_file is not None:
        log(f"step A: the scanner model from {resolve_data_path(spec.model_file, config_path)}")
        return read_scanner_model(cfg, config_path), 0.0
    m = spec.model
    log(f"step A: identifying {m.name} ({m.kind}, {', '.join(m.effects)}) from the calibration scan ...")
    ident = identify_model(scans, m, spec.solver, spec.grating, log)
    if not ident.plausible:
        raise ImplausibleModel(f"step A identified no usable scanner: {'; '.join(ident.failures)}")
    if not ident.converged:
        log(
            f"  WARNING: identification stopped at max_steps={spec.solver.max_steps} (last loss "
            f"{ident.stages[-1].loss:.3e})"
        )
    return ident.model.scanner, ident.seconds


@dataclasses.dataclass(frozen=True)
class _Layout:
    """The task: the workspace raster ``work``, step B's landmark ``grid`` with its wanted positions
    ``D`` (N*N, 2) nm, and the ``particles``."""

    work: Raster
    grid: LandmarkGrid
    D: np.ndarray
    particles: Particles


@dataclasses.dataclass(frozen=True)
class _Start:
    """Where every stage starts: the instrument, step A's ``model``, the instrument's ``state``
    after the calibration scan and the cycle, the ``twin``'s state, and step A's seconds."""

    afm: AFM
    model: Scanner
    state: AFMState
    twin: ScannerState
    fit_s: float
    scan_s: float


@dataclasses.dataclass
class _Ablation:
    """What the stages found: the ``metrics``, the table's ``rows`` (label, error summary or
    ``None``, scanning seconds or why the stage failed), the ``figures``' data, each stage's
    ``errors`` (nm) and the ``arrays`` of ``trials.npz``."""

    metrics: dict
    rows: list = dataclasses.field(default_factory=list)
    figures: dict = dataclasses.field(default_factory=dict)
    errors: dict = dataclasses.field(default_factory=dict)
    arrays: dict = dataclasses.field(default_factory=dict)


def run(cfg: RunConfig, config_path: Path, out: Output, log=print) -> dict:
    """Step A, then the ablation and the push; writes ``metrics.json``, ``trials.npz`` (every
    trial's results), the fitted scanner and figures into ``out``."""
    afm, layout = _setup(cfg, config_path)
    out.prepare()
    start = _step_a(cfg, afm, config_path, out, log)
    done = _Ablation(
        {
            "step_a_fit_s": start.fit_s,
            "step_a_scan_s": start.scan_s,
            "particles": len(layout.particles.radii),
            "workspace_nm": cfg.workspace.size_nm,
            "workspace_pixels": cfg.workspace.pixels,
            "landmarks_n": layout.grid.n,
            "drift_x_nm_per_min": cfg.drift_nm_per_min[0],
            "drift_y_nm_per_min": cfg.drift_nm_per_min[1],
        }
    )
    for i, stage in enumerate(STAGES):
        if stage.name in cfg.stages:
            _stage(cfg, i, stage, start, layout, done, log)
    for label, s, scan_s in done.rows:
        if s is not None:
            done.metrics |= {f"{stage_key(label)}_error_{k}": v for k, v in s.items()} | {
                f"{stage_key(label)}_scan_time_s": scan_s
            }
    log(_table(done.rows, done.metrics))
    _figures(done.figures, layout.work, out)
    if done.errors:  # else no stage ran: the table says why
        out.write("errors.png", lambda path: plots.stage_errors(done.errors, path))
    out.write("trials.npz", lambda path: np.savez_compressed(path, **done.arrays))
    return out.write_metrics(done.metrics)


def _setup(cfg: RunConfig, config_path: Path) -> tuple:
    """The instrument and the task (:class:`_Layout`); every check that can fail runs here,
    before any step."""
    afm = default_afm(drift_nm_per_min=tuple(cfg.drift_nm_per_min))
    work, grid, D = workspace_layout(cfg)
    afm.check_range(afm.nominal_volts(np.asarray(work.wanted()).reshape(-1, 2)))
    read_scanner_model(cfg, config_path)
    spec = cfg.particles
    field = survey.particle_field(
        D.min(axis=0), (grid.n - 1) * spec.per_cell, cfg.particle_spacing_nm, spec.radius_nm, spec.seed
    )
    return afm, _Layout(work, grid, D, field)


def _step_a(cfg: RunConfig, afm: AFM, config_path: Path, out: Output, log) -> _Start:
    """Step A: the calibration scan, the model (identified or read; saved as
    ``model_scanner.json``), and the initialisation cycle after the scan, on the instrument and
    on the model's twin."""
    sim_spec = cfg.calibration.simulate
    log(f"step A: the calibration scan ({sim_spec.pixels}² px, {sim_spec.size_nm / 1e3:g} µm) ...")
    scans, sim = calibration_scans(sim_spec, cfg.calibration.grating, afm)
    model, fit_s = identify_scanner(cfg, scans, config_path, log)
    about = calibration_about(model, scans, "simulated calibration scan")
    out.write("model_scanner.json", lambda path: save_model(model, path, about))
    return _Start(
        afm,
        model,
        run_cycle(afm, sim.lattice, sim.measured.state, sim.cycle, sim.key),
        twin_state(model, scans, sim.cycle).scanner,
        fit_s,
        sum(s.raster.lines / s.raster.line_rate for s in scans),
    )


def _stage(cfg: RunConfig, i: int, stage: Stage, start: _Start, layout: _Layout, done: _Ablation, log):
    """One stage (the ``i``-th of :data:`~jaxafm.position.survey.STAGES`): its survey
    (:func:`_survey`), then the trials to each particle found, through each landmark map (B;
    A+B: step C and the push through the first)."""
    key_survey, key_trials = jax.random.split(jax.random.fold_in(jax.random.key(cfg.seed), i))
    surveyed = _survey(cfg, stage, start, layout, key_survey, done, log)
    if surveyed is None:
        return
    seen, targets, which, maps = surveyed
    particles, D = layout.particles, layout.D
    truth, radii = particles.centres[which], particles.radii[which]
    directions, distances = _push_goals(
        cfg, targets, which, particles, start.afm.tip.radius, np.stack([D.min(0), D.max(0)])
    )
    keys = jax.random.split(key_trials, len(targets))
    near = jax.vmap(lambda p: nearby(seen.sample, p))(truth)
    scan_s = seen.seconds + (start.scan_s if stage.with_a else 0.0)
    for j, (suffix, frame) in enumerate(maps.items()):
        with_c = stage.with_a and stage.with_b and j == 0
        began = time.perf_counter()
        r = jax.tree_util.tree_map(
            np.asarray,
            trials(
                Positioner(start.afm, start.model if stage.with_a else None, frame),
                near,
                seen.stand,
                jnp.asarray(targets),
                truth,
                radii,
                jnp.asarray(directions),
                jnp.asarray(distances),
                keys,
                local_scan_settings(cfg.local_scan) if with_c else None,
                push_settings(cfg.push) if with_c else None,
                cfg.landmarks.approach_nm if stage.with_b else 0.0,
            ),
        )
        label = stage.name + suffix
        done.arrays |= _columns(label, r) | {
            f"{label}/truth": np.asarray(truth),
            f"{label}/radius": np.asarray(radii),
            f"{label}/target": targets,
        }
        done.rows.append((label, _summary(r.error_nm), scan_s))
        done.errors[label] = r.error_nm
        s = done.rows[-1][1]
        log(
            f"  {label}: median {s['median_nm']:.1f} nm, worst {s['max_nm']:.1f} nm "
            f"({time.perf_counter() - began:.1f} s)"
        )
        if with_c:
            done.rows.append(
                ("A+B+C" + suffix, _summary(r.step_c.error_nm), scan_s + float(r.step_c.scan.seconds.mean()))
            )
            done.errors["A+B+C" + suffix] = r.step_c.error_nm
            done.metrics |= _step_c_metrics(r, np.asarray(radii), cfg.push.tolerance_radii)
            done.figures["trials"] = (r, np.asarray(truth), np.asarray(radii))


def _survey(cfg: RunConfig, stage: Stage, start: _Start, layout: _Layout, key, done: _Ablation, log):
    """A stage's survey, and the particles found in it: ``(survey, targets, which, maps)``, with
    ``maps`` ``{label suffix: landmark map or None}``; ``None`` (a row saying why in ``done``)
    when there is nothing to go to. With B, only the targets inside the landmarks found."""
    name, afm = stage.name, start.afm
    work, grid, D, particles = layout.work, layout.grid, layout.D, layout.particles
    log(f"{name}: {'pressing the landmarks, ' if stage.with_b else ''}imaging the workspace ...")
    pos = Positioner(afm, start.model if stage.with_a else None)
    seen = survey.survey(
        pos,
        pos.start(start.state, start.twin if stage.with_a else None),
        Indented.empty(particles, afm.tip, capacity=grid.n**2),
        work,
        key,
        D if stage.with_b else None,
        cfg.landmarks.depth_nm,
        cfg.landmarks.approach_nm,
    )
    targets, which = survey.find_targets(
        seen.images, work, particles, cfg.particles.radius_nm, cfg.particle_spacing_nm
    )
    found = f"{len(targets)} of the {len(particles.radii)} particles found"
    maps = {"": None}
    if stage.with_b:
        lm = cfg.landmarks
        M, D_found = survey.find_landmarks(seen.images, work, grid, D, lm.depth_nm)
        done.figures["landmarks" + ("_A" if stage.with_a else "")] = (seen.images, D, M, D_found)
        done.metrics[f"{stage.key}_landmarks_found"] = len(M)
        found_maps = survey.landmark_maps(M, D_found, lm.interpolation, lm.m, lm.degree)
        if len(M) < grid.n**2:
            log(f"  {name}: {len(M)} of the {grid.n**2} landmarks found in the workspace image")
        if not found_maps:
            done.rows += [
                (name + f" ({m})", None, "too few landmarks in the image") for m in lm.interpolation
            ]
            return None
        maps = {f" ({m})": frame for m, frame in found_maps.items()}
        inside = np.all((targets >= M.min(0)) & (targets <= M.max(0)), axis=1)
        targets, which = targets[inside], which[inside]
        found += f", {len(targets)} inside the landmark grid"
    log(f"  {found}; {'pressing and ' if stage.with_b else ''}imaging took {seen.seconds:.0f} s")
    if len(targets) == 0:
        log(f"  {name}: no particle to go to (no results for this stage)")
        done.rows += [(name + suffix, None, "no particle found in the image") for suffix in maps]
        return None
    return seen, targets, which, maps


#: the push directions tried for a particle, in turns of 15 degrees from the drawn one: the drawn,
#: its reverse, then each turned on by another 15 degrees
_PUSH_TURNS = np.stack([np.arange(12), np.arange(12) + 12], -1).ravel() * np.pi / 12


def _push_goals(cfg: RunConfig, targets, which, particles: Particles, tip_radius: float, box) -> tuple:
    """A random direction and distance per particle (the same for every stage), for the
    ``particles`` numbered ``which`` and seen at ``targets`` (T, 2) nm. A push must end
    inside the landmark grid (``box``: its lower and upper corner, nm) and keep the particle
    apart from every other: along the push its centre stays ``R + R'`` from another's (R, R'
    their radii: they never touch, as the pushes move one particle and two that touched would
    pass through each other), and at the goal ``(R + r) + (R' + r)`` (r the tip's radius: their
    images' reach), so that a local scan there sees it alone. A direction that breaks either rule
    is turned (:data:`_PUSH_TURNS`: its reverse first) to the first that keeps both; the drawn
    one stays where none does."""
    rng = np.random.default_rng(cfg.seed + 1)
    n = len(particles.radii)
    angle = rng.uniform(0, 2 * np.pi, n)[which]
    distances = rng.uniform(*cfg.push.distance_nm, n)[which]
    turned = angle[:, None] + _PUSH_TURNS  # (T, K)
    directions = np.stack([np.cos(turned), np.sin(turned)], -1)  # (T, K, 2)
    goal = targets[:, None] + distances[:, None, None] * directions
    inside = np.all((goal >= box[0]) & (goal <= box[1]), axis=-1)
    centres, radii = np.asarray(particles.centres), np.asarray(particles.radii)
    rel = centres[None, :] - centres[which][:, None]  # (T, N, 2): the others from the pushed one
    d = distances[:, None, None]
    along = np.einsum("tnd,tkd->tkn", rel, directions)  # (T, K, N)
    path = np.linalg.norm(rel[:, None] - np.clip(along, 0.0, d)[..., None] * directions[:, :, None], axis=-1)
    end = np.linalg.norm(rel[:, None] - d[..., None] * directions[:, :, None], axis=-1)
    touch = radii[which][:, None, None] + radii[None, None, :]
    itself = (np.arange(n)[None, :] == which[:, None])[:, None]
    apart = np.all(itself | ((path >= touch) & (end >= touch + 2 * tip_radius)), axis=-1)
    first = np.argmax(inside & apart, axis=1)  # 0 (the drawn direction) where none keeps both
    return directions[np.arange(len(which)), first], distances


def _columns(label: str, r: TrialResults) -> dict:
    """The trials' results as the columns of ``trials.npz``, named ``LABEL/NAME`` (in the order
    of the names): ``tip``, ``error_nm``; step C's ``c_tip``, ``c_error_nm``, ``c_found``,
    ``c_lines``, ``c_seconds``, ``c_centre``, ``c_starts``, ``c_ends``, ``c_phases``; the push's
    ``push_final``, ``push_first``, ``push_corrections``, ``push_contact``, ``push_goal``,
    ``push_path``."""
    columns = {"tip": r.tip, "error_nm": r.error_nm}
    if r.step_c is not None:
        c, scan = r.step_c, r.step_c.scan
        columns |= {
            "c_tip": c.tip,
            "c_error_nm": c.error_nm,
            "c_found": scan.found,
            "c_lines": scan.lines,
            "c_seconds": scan.seconds,
            "c_centre": scan.centre,
            "c_starts": scan.starts,
            "c_ends": scan.ends,
            "c_phases": scan.phases,
        }
    if r.push is not None:
        columns |= {
            "push_final": r.push.final,
            "push_first": r.push.first.final,
            "push_corrections": r.push.corrections,
            "push_contact": r.push.first.contact,
            "push_goal": r.push_goal,
            "push_path": r.push.first.path,
        }
    return {f"{label}/{k}": columns[k] for k in sorted(columns)}


def _summary(e: np.ndarray) -> dict:
    return {
        "median_nm": float(np.median(e)),
        "p95_nm": float(np.percentile(e, 95)),
        "max_nm": float(e.max()),
        "targets": int(e.size),
    }


def _step_c_metrics(r: TrialResults, radii: np.ndarray, tolerance_radii: float) -> dict:
    e_c, push = r.step_c.error_nm, r.push
    push_err = np.linalg.norm(push.final - r.push_goal, axis=-1)
    success = push.first.contact & (push_err <= tolerance_radii * radii)
    first = push.first.contact & (
        np.linalg.norm(push.first.final - r.push_goal, axis=-1) <= tolerance_radii * radii
    )
    return {
        "ABC_error_over_radius_median": float(np.median(e_c / radii)),
        "ABC_error_over_radius_max": float(np.max(e_c / radii)),
        "ABC_within_0p1R_pct": 100 * float(np.mean(e_c < 0.1 * radii)),
        "ABC_found_pct": 100 * float(np.mean(r.step_c.scan.found)),
        "ABC_lines_mean": float(np.mean(r.step_c.scan.lines)),
        "ABC_local_scan_s_mean": float(np.mean(r.step_c.scan.seconds)),
        "push_trials": int(radii.size),
        "push_tolerance_radii": tolerance_radii,
        "push_success_pct": 100 * float(np.mean(success)),
        "push_first_success_pct": 100 * float(np.mean(first)),
        "push_corrections_mean": float(np.mean(push.corrections)),
        "push_error_median_nm": float(np.median(push_err)),
        "push_error_max_nm": float(np.max(push_err)),
    }


def _table(rows, metrics) -> str:
    head = f"{'stage':22s} {'targets':>7s} {'median':>9s} {'p95':>9s} {'worst':>9s} {'scanning':>9s}"
    lines = [head, "-" * len(head)]
    for label, s, scan_s in rows:
        if s is None:  # a stage that could not run: scan_s holds why
            lines.append(f"{label:22s} {'failed: ' + scan_s:>44s}")
            continue
        lines.append(
            f"{label:22s} {s['targets']:7d} {s['median_nm']:7.1f}nm {s['p95_nm']:7.1f}nm "
            f"{s['max_nm']:7.1f}nm {scan_s:8.0f}s"
        )
    lines.append(
        "error: true tip to true particle centre after a 0.2 s dwell; scanning: time spent "
        "scanning and pressing (A: calibration image; B: landmarks + workspace image; C: mean local scan)"
    )
    if "push_success_pct" in metrics:
        lines.append(
            f"A+B+C: error under 0.1 R for {metrics['ABC_within_0p1R_pct']:.1f} % of targets "
            f"(worst {metrics['ABC_error_over_radius_max']:.3f} R); local scan verified for "
            f"{metrics['ABC_found_pct']:.1f} %, {metrics['ABC_lines_mean']:.1f} lines, "
            f"{metrics['ABC_local_scan_s_mean']:.1f} s on average"
        )
        lines.append(
            f"push: {metrics['push_success_pct']:.1f} % of {metrics['push_trials']} particles end within "
            f"{metrics['push_tolerance_radii']:g} R of the goal (median miss "
            f"{metrics['push_error_median_nm']:.1f} nm, worst {metrics['push_error_max_nm']:.1f} nm); "
            f"{metrics['push_first_success_pct']:.1f} % after the first push, "
            f"{metrics['push_corrections_mean']:.2f} corrective pushes per particle"
        )
    return "\n".join(lines)


def _figures(figures: dict, work: Raster, out: Output) -> None:
    if "landmarks_A" in figures:
        maps = {
            "B (nominal drive)": figures.get("landmarks"),
            "A+B (compensated drive)": figures["landmarks_A"],
        }
        out.write("landmarks.png", lambda path: plots.landmarks(maps, work, path))
    if "trials" in figures:
        out.write("local_scan.png", lambda path: plots.local_scans(*figures["trials"], path))
        out.write("push.png", lambda path: plots.pushes(*figures["trials"], path))
