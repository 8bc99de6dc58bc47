"""The ``jaxafm run`` job: the paper's full positioning strategy on the simulated AFM.

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
state after the workspace image (``vmap``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from skimage import registration

from .. import plots
from ..config import Positioning, RunConfig, resolve_data_path
from ..identify.step_a import (
    calibration_about,
    identify_model,
    run_cycle,
    simulate_calibration,
    twin_state,
)
from ..instrument.afm import Raster, RasterScan, default_afm
from ..instrument.samples import Indented, Particles
from ..model.io import load_model, save_model
from ..model.scanner import Scanner
from .landmarks import LandmarkGrid, LandmarkMap, find_features, match_grid, usable_degree
from .positioning import (
    LocalScan,
    Positioner,
    Push,
    goto,
    local_scan,
    press_at,
    push_and_check,
    raster,
)

STAGES = (("open_loop", False, False), ("A", True, False), ("B", False, True), ("A+B", True, True))
NEARBY = 8  # particles each trial's local scan sees (the others lie beyond its lines)


def particle_field(cfg: RunConfig, grid: LandmarkGrid, D: np.ndarray) -> Particles:
    """Particles in the landmark grid's cells, ``per_cell`` x ``per_cell`` to a cell, jittered by up
    to 1/8 of their spacing: the nearest indent is at least about a third of a cell away."""
    spec = cfg.particles
    rng = np.random.default_rng(spec.seed)
    a = cfg.particle_spacing_nm
    k = (np.arange((grid.n - 1) * spec.per_cell) + 0.5) * a
    sites = D.min(axis=0) + np.stack(np.meshgrid(k, k), -1).reshape(-1, 2)
    centres = sites + rng.uniform(-a / 8, a / 8, sites.shape)
    radii = rng.uniform(*spec.radius_nm, len(centres))
    return Particles(jnp.asarray(centres), jnp.asarray(radii))


class ImplausibleModel(ValueError):
    """Step A's identified model failed its plausibility checks (the message says which)."""


def load_fixed_scanner(cfg: Positioning, config_path: Path) -> Optional[Scanner]:
    """The scanner in ``calibration.model_file`` (None without one), checked.

    Raises:
        ValueError: naming the key and the file: missing, not a saved model, or not a scanner.
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
    return model


def identify_scanner(cfg: Positioning, scans: tuple, config_path: Path, log) -> tuple:
    """Step A's model: identified from ``scans``, or read from ``model_file``; and the seconds.

    Raises:
        ValueError: when the identified model fails step A's plausibility checks.
    """
    spec = cfg.calibration
    if spec.model_file is not None:
        log(f"step A: the scanner model from {resolve_data_path(spec.model_file, config_path)}")
        return load_fixed_scanner(cfg, config_path), 0.0
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


def _near(sample: Indented, centre: jax.Array) -> Particles:
    """The ``NEARBY`` particles of ``sample`` nearest ``centre``: what a trial's moves, local
    scan and push see, imaged in closed form. The indents are left out: a simplification,
    as the particles lie about a quarter of a landmark cell or more from the nearest one."""
    parts = sample.base
    k = min(NEARBY, parts.radii.shape[0])
    idx = lax.top_k(-jnp.sum((parts.centres - centre) ** 2, axis=-1), k)[1]
    return Particles(parts.centres[idx], parts.radii[idx], parts.substrate)


@eqx.filter_jit
def trials(
    pos: Positioner,
    seen: Particles,
    stand,
    targets,
    truth,
    radii,
    directions,
    distances,
    keys,
    local: LocalScan = None,
    push_spec: Push = None,
    approach: float = 0.0,
) -> dict:
    """Go to every target (K, 2) nm from ``stand``, one independent trial each (``vmap``), with
    ``seen`` (batched over the trials) the particles each trial's tip meets; with ``local``,
    then step C, and with ``push_spec`` the push. The move to the target makes ``approach``
    (:func:`~jaxafm.position.positioning.goto`). Errors against the true centres ``truth``."""

    def one(near, target, p, R, d, dist, key):
        k = jax.random.split(key, 4)
        xy, _, s = goto(pos, near, stand, target, k[0], approach=approach)
        out = {"tip": xy, "error_nm": jnp.linalg.norm(xy - p)}
        if local is None:
            return out
        res, s = local_scan(pos, near, s, target, R, k[1], local)
        xy_c, _, s = goto(pos, near, s, res.centre, k[2])
        out |= {
            "c_tip": xy_c,
            "c_error_nm": jnp.linalg.norm(xy_c - p),
            "c_found": res.found,
            "c_lines": res.lines,
            "c_seconds": res.seconds,
            "c_centre": res.centre,
            "c_starts": res.starts,
            "c_ends": res.ends,
            "c_phases": res.phases,
        }
        if push_spec is None:
            return out
        final, touched, path, first, made, s = push_and_check(
            pos, near, s, res.centre, p, R, d, dist, k[3], push_spec, local, approach, stand.wanted
        )
        return out | {
            "push_final": final,
            "push_first": first,
            "push_corrections": made,
            "push_contact": touched,
            "push_goal": p + dist * d,
            "push_path": path[::8],
        }

    return jax.vmap(one)(seen, targets, truth, radii, directions, distances, keys)


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


def find_targets(images: RasterScan, work: Raster, particles: Particles, cfg: RunConfig) -> tuple:
    """The particles found in the workspace images (K, 2) nm, and the index of the true particle
    each one is (from the true tip path over its pixel); unmatched finds are dropped."""
    spec = cfg.particles
    spacing = cfg.particle_spacing_nm
    found = _trace_and_retrace(
        images,
        work,
        lambda z: find_features(
            z,
            work,
            len(particles.radii) + 16,
            pits=False,
            min_height=spec.radius_nm[0],
            min_distance_nm=spacing / 3,
            window_nm=spec.radius_nm[1] + 20.0,
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


def landmark_maps(M: np.ndarray, D: np.ndarray, spec) -> dict:
    """Step B's maps ``{method: LandmarkMap}`` on the landmarks found, ``M`` seen where ``D`` was
    pressed: the polynomial at the highest degree up to ``spec.degree`` that they over-determine,
    the pairwise map over at most as many as were found. Empty when fewer than 3 were found.
    Where the found landmarks do not cover a target, the polynomial extrapolates (the nearest
    usable map)."""
    if len(M) < 3:
        return {}
    degree = max(usable_degree(len(M), spec.degree), 1)  # 3 or 4 landmarks: a plane through them
    return {m: LandmarkMap(M, D, m, min(spec.m, len(M)), degree) for m in spec.interpolation}


def stage_key(label: str) -> str:
    """A stage label as a metrics key: ``"A+B (polynomial)"`` -> ``"AB_polynomial"``."""
    return label.replace("+", "").replace(" (", "_").replace(")", "")


def _summary(e: np.ndarray) -> dict:
    return {
        "median_nm": float(np.median(e)),
        "p95_nm": float(np.percentile(e, 95)),
        "max_nm": float(e.max()),
        "targets": int(e.size),
    }


def workspace_layout(cfg: Positioning) -> tuple:
    """The workspace raster (5 % over-scan each side), step B's landmark grid in its image
    (eq. 3) and the grid's wanted positions ``D`` (N*N, 2) nm, as ``cfg`` sets them."""
    ws = cfg.workspace
    work = Raster(
        ws.size_nm, ws.pixels, ws.pixels, line_rate=ws.line_rate_hz, centre=tuple(ws.centre_nm), overscan=0.05
    )
    grid = LandmarkGrid(cfg.landmarks.n, cfg.landmarks.start_px, cfg.landmarks.step_px, ws.pixels)
    return work, grid, grid.positions(work)


def _setup(cfg: RunConfig, config_path: Path) -> tuple:
    """The instrument, the workspace raster, the landmark grid with its wanted positions ``D``, and
    the particles; every check that can fail runs here, before any step."""
    afm = default_afm(drift_nm_per_min=tuple(cfg.drift_nm_per_min))
    work, grid, D = workspace_layout(cfg)
    afm.check_range(afm.nominal_volts(np.asarray(work.wanted()).reshape(-1, 2)))
    load_fixed_scanner(cfg, config_path)
    return afm, work, grid, D, particle_field(cfg, grid, D)


def survey(
    cfg: Positioning, pos: Positioner, stand, sample, work: Raster, grid: LandmarkGrid, D, with_b: bool, key
) -> tuple:
    """Press the landmarks (with ``with_b``) and image the workspace: the images, the sample with
    its indents, the stand after, and the seconds it took."""
    k_press, k_scan = jax.random.split(key)
    t0 = float(stand.afm.scanner.t)
    if with_b:
        for j, d in enumerate(D):
            sample, stand, _ = press_at(
                pos,
                sample,
                stand,
                jnp.asarray(d),
                cfg.landmarks.depth_nm,
                jax.random.fold_in(k_press, j),
                approach=cfg.landmarks.approach_nm,
            )
    images, stand = raster(pos, sample, stand, work, k_scan)
    return images, sample, stand, float(stand.afm.scanner.t) - t0


def _push_goals(cfg: RunConfig, targets: np.ndarray, which: np.ndarray, n: int, box: np.ndarray) -> tuple:
    """A random direction and distance per particle (the same for every stage); directions whose
    goal would leave the landmark grid are reversed."""
    rng = np.random.default_rng(cfg.seed + 1)
    angle = rng.uniform(0, 2 * np.pi, n)[which]
    distances = rng.uniform(*cfg.push.distance_nm, n)[which]
    directions = np.stack([np.cos(angle), np.sin(angle)], -1)
    goal = targets + distances[:, None] * directions
    directions[np.any((goal < box[0]) | (goal > box[1]), axis=1)] *= -1
    return directions, distances


def run(cfg: RunConfig, config_path: Path, out: Path, prepare=lambda: None, log=print) -> dict:
    """Step A, then the ablation and the push; writes ``metrics.json``, ``trials.npz`` (every
    trial's results), the fitted scanner and figures into ``out``."""
    afm, work, grid, D, particles = _setup(cfg, config_path)
    box = np.stack([D.min(0), D.max(0)])
    prepare()
    log(
        f"step A: the calibration scan ({cfg.calibration.simulate.pixels}² px, "
        f"{cfg.calibration.simulate.size_nm / 1e3:g} µm) ..."
    )
    scans, sim = simulate_calibration(cfg.calibration.simulate, cfg.calibration.grating, afm)
    model, fit_s = identify_scanner(cfg, scans, config_path, log)
    save_model(
        model, out / "model_scanner.json", calibration_about(model, scans, "simulated calibration scan")
    )
    calib_s = sum(s.raster.lines / s.raster.line_rate for s in scans)
    start_state = run_cycle(afm, sim.lattice, sim.measured.state, sim.cycle, sim.key)
    twin = twin_state(model, scans, sim.cycle).scanner
    metrics = {
        "step_a_fit_s": fit_s,
        "step_a_scan_s": calib_s,
        "particles": len(particles.radii),
        "workspace_nm": cfg.workspace.size_nm,
        "workspace_pixels": cfg.workspace.pixels,
        "landmarks_n": grid.n,
        "drift_x_nm_per_min": cfg.drift_nm_per_min[0],
        "drift_y_nm_per_min": cfg.drift_nm_per_min[1],
    }
    local = LocalScan.from_config(cfg.local_scan)
    rows, figures, errors, arrays = [], {}, {}, {}
    for i, (name, with_a, with_b) in enumerate(STAGES):
        if name not in cfg.stages:
            continue
        log(f"{name}: {'pressing the landmarks, ' if with_b else ''}imaging the workspace ...")
        pos = Positioner(afm, model if with_a else None)
        key_survey, key_trials = jax.random.split(jax.random.fold_in(jax.random.key(cfg.seed), i))
        images, sample, stand, prep_s = survey(
            cfg,
            pos,
            pos.start(start_state, twin if with_a else None),
            Indented.empty(particles, afm.tip, capacity=grid.n**2),
            work,
            grid,
            D,
            with_b,
            key_survey,
        )
        targets, which = find_targets(images, work, particles, cfg)
        found = f"{len(targets)} of the {len(particles.radii)} particles found"
        maps = {"": None}
        if with_b:
            M, D_found = find_landmarks(images, work, grid, D, cfg.landmarks.depth_nm)
            figures["landmarks" + ("_A" if with_a else "")] = (images, D, M, D_found)
            metrics[f"{stage_key(name)}_landmarks_found"] = len(M)
            found_maps = landmark_maps(M, D_found, cfg.landmarks)
            if len(M) < grid.n**2:
                log(f"  {name}: {len(M)} of the {grid.n**2} landmarks found in the workspace image")
            if not found_maps:
                rows += [
                    (name + f" ({m})", None, "too few landmarks in the image")
                    for m in cfg.landmarks.interpolation
                ]
                continue
            maps = {f" ({m})": lm for m, lm in found_maps.items()}
            inside = np.all((targets >= M.min(0)) & (targets <= M.max(0)), axis=1)
            targets, which = targets[inside], which[inside]
            found += f", {len(targets)} inside the landmark grid"
        log(f"  {found}; {'pressing and ' if with_b else ''}imaging took {prep_s:.0f} s")
        if len(targets) == 0:
            log(f"  {name}: no particle to go to (no results for this stage)")
            rows += [(name + suffix, None, "no particle found in the image") for suffix in maps]
            continue
        truth, radii = particles.centres[which], particles.radii[which]
        directions, distances = _push_goals(cfg, targets, which, len(particles.radii), box)
        keys = jax.random.split(key_trials, len(targets))
        seen = jax.vmap(lambda p: _near(sample, p))(truth)
        scan_s = prep_s + (calib_s if with_a else 0.0)
        for j, (suffix, frame) in enumerate(maps.items()):
            with_c = with_a and with_b and j == 0
            start = time.perf_counter()
            r = jax.tree_util.tree_map(
                np.asarray,
                trials(
                    Positioner(afm, pos.model, frame),
                    seen,
                    stand,
                    jnp.asarray(targets),
                    truth,
                    radii,
                    jnp.asarray(directions),
                    jnp.asarray(distances),
                    keys,
                    local if with_c else None,
                    Push.from_config(cfg.push) if with_c else None,
                    cfg.landmarks.approach_nm if with_b else 0.0,
                ),
            )
            label = name + suffix
            arrays |= {f"{label}/{k}": v for k, v in r.items()} | {
                f"{label}/truth": np.asarray(truth),
                f"{label}/radius": np.asarray(radii),
                f"{label}/target": targets,
            }
            rows.append((label, _summary(r["error_nm"]), scan_s))
            errors[label] = r["error_nm"]
            log(
                f"  {label}: median {rows[-1][1]['median_nm']:.1f} nm, worst {rows[-1][1]['max_nm']:.1f} nm "
                f"({time.perf_counter() - start:.1f} s)"
            )
            if with_c:
                rows.append(
                    ("A+B+C" + suffix, _summary(r["c_error_nm"]), scan_s + float(r["c_seconds"].mean()))
                )
                errors["A+B+C" + suffix] = r["c_error_nm"]
                metrics |= _step_c_metrics(r, np.asarray(radii), cfg.push.tolerance_radii)
                figures["trials"] = (r, np.asarray(truth), np.asarray(radii))
    for label, s, scan_s in rows:
        if s is not None:
            metrics |= {f"{stage_key(label)}_error_{k}": v for k, v in s.items()} | {
                f"{stage_key(label)}_scan_time_s": scan_s
            }
    log(_table(rows, metrics))
    _figures(figures, work, out)
    if errors:  # else no stage ran: the table says why
        plots.stage_errors(errors, out / "errors.png")
    np.savez_compressed(out / "trials.npz", **arrays)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return metrics


def _step_c_metrics(r: dict, radii: np.ndarray, tolerance_radii: float) -> dict:
    e_c = r["c_error_nm"]
    push_err = np.linalg.norm(r["push_final"] - r["push_goal"], axis=-1)
    success = r["push_contact"] & (push_err <= tolerance_radii * radii)
    first = r["push_contact"] & (
        np.linalg.norm(r["push_first"] - r["push_goal"], axis=-1) <= tolerance_radii * radii
    )
    return {
        "ABC_error_over_radius_median": float(np.median(e_c / radii)),
        "ABC_error_over_radius_max": float(np.max(e_c / radii)),
        "ABC_within_0p1R_pct": 100 * float(np.mean(e_c < 0.1 * radii)),
        "ABC_found_pct": 100 * float(np.mean(r["c_found"])),
        "ABC_lines_mean": float(np.mean(r["c_lines"])),
        "ABC_local_scan_s_mean": float(np.mean(r["c_seconds"])),
        "push_trials": int(radii.size),
        "push_tolerance_radii": tolerance_radii,
        "push_success_pct": 100 * float(np.mean(success)),
        "push_first_success_pct": 100 * float(np.mean(first)),
        "push_corrections_mean": float(np.mean(r["push_corrections"])),
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


def _figures(figures: dict, work: Raster, out: Path) -> None:
    if "landmarks_A" in figures:
        plots.landmarks(
            {
                "B (nominal drive)": figures.get("landmarks"),
                "A+B (compensated drive)": figures["landmarks_A"],
            },
            work,
            out / "landmarks.png",
        )
    if "trials" in figures:
        plots.local_scans(*figures["trials"], out / "local_scan.png")
        plots.pushes(*figures["trials"], out / "push.png")
