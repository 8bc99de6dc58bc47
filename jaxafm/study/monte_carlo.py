"""Monte-Carlo positioning studies: ``jaxafm study CONFIG``.

Every trial is one particle of a drawn radius at a random place inside a landmark
cell (in its middle half, so the nearest indent is over a third of a cell away),
on a scanner drawn from the config's distributions. Consecutive trials share a
scanner (``trials_per_scanner``): its calibration scan, step A's identification
and one survey per stage (press the landmarks for B, image the workspace) run
once for them all. A trial's target is where its particle appears in that
stage's survey image (the wanted position at which the mean of the true trace
and retrace paths passes over the particle's centre: a particle finder without
error); the trial then goes there (open loop, A, B, A+B), and for A+B+C runs
the local scan from there, moves to the centre it found and pushes.

Trials run in jitted, vmapped batches of ``chunk`` trials, sharded over every
JAX device (``jax.sharding``; one mesh axis ``trials``). Each trial's random
key is ``fold_in(seed, trial)``, and its draws are fixed before any runs, so the
results do not depend on the chunk size or the device count. Each chunk's
results are written atomically to ``chunks/``; a resumed study reuses them and
the identified models in ``scanners/``.

In several JAX processes (``jax.distributed``; ``jaxafm study --coordinator``), the mesh spans
every process's devices and each chunk's trials are split over them all. Every process computes
each scanner's calibration scan, step A and surveys itself (deterministic: the same on the same
kind of CPU; :func:`_check_same` checks that they agree, and that all run the same config), and
takes the decisions that depend on the output folder (which chunks are done, which models are
saved) from process 0 (:func:`_from_process_0`), so all of them make the same collective calls
in the same order. Process 0 alone logs and writes: chunks, models, ``scanners.json`` and the
summary.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .. import plots
from ..config import STUDY_PARAMETERS, StudyConfig
from ..identify.step_a import run_cycle, simulate_calibration, twin_state
from ..instrument.afm import default_afm
from ..instrument.records import write_columns
from ..instrument.samples import Indented, Particles, Plane
from ..model.io import load_model, save_model
from ..position.positioning import LocalScan, Positioner, Push
from ..position.strategy import (
    ImplausibleModel,
    find_landmarks,
    identify_scanner,
    landmark_maps,
    load_fixed_scanner,
    stage_key,
    survey,
    trials,
)
from ..position.strategy import workspace_layout as _layout

#: survey stages: name -> (step A, step B); A+B+C and the push go on from A+B's survey
SURVEYS = {"open_loop": (False, False), "A": (True, False), "B": (False, True), "A+B": (True, True)}
#: why a scanner's stage has no survey (its trials fail)
REFUSED, TOO_FEW = "step A refused its model", "too few landmarks"


def scanner_draws(cfg: StudyConfig) -> list:
    """``default_afm`` arguments for each of the study's scanners (drawn before any trial)."""
    rng = np.random.default_rng([cfg.seed, 1])
    columns = {}
    for effect, params in STUDY_PARAMETERS.items():
        for name, (arg, _, default) in params.items():
            dist = cfg.scanner.get(effect, {}).get(name)
            columns[arg] = (
                dist.draw(rng, cfg.scanners) if dist is not None else np.full(cfg.scanners, default)
            )
    draws = []
    for s in range(cfg.scanners):
        d = {k: float(v[s]) for k, v in columns.items()}
        d["drift_nm_per_min"] = (d.pop("drift_x"), d.pop("drift_y"))
        draws.append(d)
    return draws


def trial_draws(cfg: StudyConfig, D: np.ndarray) -> dict:
    """Every trial's particle (centre (T, 2) nm, radius (T,) nm) and push (unit direction (T, 2),
    distance (T,) nm); directions whose goal would leave the landmark grid are reversed."""
    rng = np.random.default_rng([cfg.seed, 2])
    n, T = cfg.landmarks.n, cfg.trials
    lo, hi = D.min(0), D.max(0)
    cell = (hi - lo) / (n - 1)
    corner = lo + rng.integers(0, n - 1, (T, 2)) * cell
    centre = corner + rng.uniform(0.25, 0.75, (T, 2)) * cell
    radius = cfg.particle_radius_nm.draw(rng, T)
    angle = rng.uniform(0, 2 * np.pi, T)
    distance = rng.uniform(*cfg.push.distance_nm, T)
    direction = np.stack([np.cos(angle), np.sin(angle)], -1)
    goal = centre + distance[:, None] * direction
    direction[np.any((goal < lo) | (goal > hi), axis=1)] *= -1
    return {
        "trial": np.arange(T),
        "scanner": np.arange(T) // cfg.trials_per_scanner,
        "x_nm": centre[:, 0],
        "y_nm": centre[:, 1],
        "radius_nm": radius,
        "push_dx": direction[:, 0],
        "push_dy": direction[:, 1],
        "push_distance_nm": distance,
    }


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


def prepare_scanner(cfg: StudyConfig, config_path: Path, s: int, params: dict, out: Path, log) -> tuple:
    """Scanner ``s``: its calibration scan, step A's model (identified, or read from ``scanners/``
    when a resumed study saved it, or from ``calibration.model_file``) and one survey per stage.
    Returns ``{stage: (positioner, stand, mean path (rows, cols, 2) nm) or why there is none}``
    (:data:`REFUSED` or :data:`TOO_FEW`: the stage's trials fail) and what is worth keeping about it."""
    work, grid, D = _layout(cfg)
    afm = default_afm(**params)
    scans, sim = simulate_calibration(cfg.calibration.simulate, cfg.calibration.grating, afm)
    start = run_cycle(afm, sim.lattice, sim.measured.state, sim.cycle, sim.key)
    stages = [st for st in SURVEYS if st in cfg.stages or (st == "A+B" and "A+B+C" in cfg.stages)]
    info = {"scanner": s, **params, "step_a_fit_s": 0.0}
    model = twin = None
    if any(SURVEYS[st][0] for st in stages):
        saved = out / "scanners" / f"model_{s:05d}.json"
        if _from_process_0(saved.is_file()):
            model = _load_saved(saved)
        else:
            began = time.perf_counter()
            try:
                model, info["step_a_fit_s"] = identify_scanner(cfg, scans, config_path, lambda m: None)
                _atomic(saved, lambda f: save_model(model, f))
            except ImplausibleModel as e:
                info |= {"step_a_fit_s": time.perf_counter() - began, "step_a_refused": str(e)}
                log(f"scanner {s}: {e}: its trials through step A fail")
        twin = None if model is None else twin_state(model, scans, sim.cycle).scanner
    contexts = {}
    for i, st in enumerate(stages):
        with_a, with_b = SURVEYS[st]
        if with_a and model is None:
            contexts[st] = REFUSED
            continue
        pos = Positioner(afm, model if with_a else None)
        images, _, stand, info[f"{stage_key(st)}_survey_s"] = survey(
            cfg,
            pos,
            pos.start(start, twin if with_a else None),
            Indented.empty(Plane(), afm.tip, grid.n**2),
            work,
            grid,
            D,
            with_b,
            jax.random.fold_in(jax.random.fold_in(jax.random.key(cfg.seed), 1 + s), i),
        )
        if with_b:
            M, D_found = find_landmarks(images, work, grid, D, cfg.landmarks.depth_nm)
            info[f"{stage_key(st)}_landmarks_found"] = len(M)
            maps = landmark_maps(M, D_found, cfg.landmarks)
            if not maps:
                log(
                    f"scanner {s}, {st}: {len(M)} of the {grid.n**2} landmarks found, too few to map: its trials fail"
                )
                contexts[st] = TOO_FEW
                continue
            pos = Positioner(afm, pos.model, maps[cfg.landmarks.interpolation[0]])
        mean_path = (images.path_trace + images.path_retrace) / 2
        contexts[st] = (pos, stand, mean_path)
    return contexts, info


def _shard(arrays: dict, mesh: Mesh, size: int) -> dict:
    """``arrays`` (leading axis: trials) padded to ``size`` trials, a multiple of the device count
    (repeating the last trial), and split over the mesh's devices."""
    sharding = NamedSharding(mesh, PartitionSpec("trials"))

    def put(a):
        a = np.concatenate([a, np.repeat(a[-1:], size - len(a), 0)])
        return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])

    return {k: put(v) for k, v in arrays.items()}


def _replicate(tree, mesh: Mesh):
    """Every array of ``tree`` copied to each of the mesh's devices. With several processes, each
    puts its own copy once one collective has checked that all hold the same (:func:`_check_same`;
    ``jax.device_put`` would check each array on its own, a collective and a compilation each)."""
    arrays, rest = eqx.partition(tree, eqx.is_array)
    sharding = NamedSharding(mesh, PartitionSpec())
    if jax.process_count() == 1:
        return eqx.combine(jax.device_put(arrays, sharding), rest)
    host = jax.tree_util.tree_map(np.asarray, arrays)
    _check_same(
        host,
        "computed another survey or step A model than process 0: each process computes them itself, "
        "so all must run the same JAX on the same kind of CPU",
    )
    put = lambda a: jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])
    return eqx.combine(jax.tree_util.tree_map(put, host), rest)


def _check_same(tree, differs: str) -> None:
    """Check that every process holds the same NumPy arrays ``tree``: one gather of a SHA-256
    digest of them.

    Raises:
        RuntimeError: on every process, where one holds other values than process 0: naming
            them, then ``differs``.
    """
    from jax.experimental import multihost_utils

    digest = hashlib.sha256()
    for a in jax.tree_util.tree_leaves(tree):
        digest.update(f"{a.shape}{a.dtype}".encode() + np.ascontiguousarray(a).tobytes())
    every = multihost_utils.process_allgather(np.frombuffer(digest.digest(), np.uint32))
    other = [p for p in range(len(every)) if not np.array_equal(every[p], every[0])]
    if other:
        raise RuntimeError(f"process(es) {', '.join(map(str, other))} {differs}")


def _gather(tree, n: int) -> dict:
    """The first ``n`` trials of ``tree`` (arrays split over the mesh) as NumPy arrays, on every
    process (gathered from all of them: a collective)."""
    if jax.process_count() > 1:  # pragma: no cover - several processes
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree_util.tree_map(lambda a: np.array(a)[:n], tree)


def _from_process_0(value) -> np.ndarray:
    """``value`` (a NumPy scalar or array of the same shape on every process) as process 0 has it,
    on every process: a collective with several processes, ``np.asarray(value)`` with one."""
    if jax.process_count() == 1:
        return np.asarray(value)
    from jax.experimental import multihost_utils

    return multihost_utils.broadcast_one_to_all(np.asarray(value))


def _load_saved(path: Path):
    """A scanner model that process 0 saw in ``scanners/`` (the other processes read it there).

    Raises:
        OSError: another process cannot read it: the output folder is not on a shared filesystem.
    """
    try:
        return load_model(path)
    except FileNotFoundError:
        raise OSError(
            f"process {jax.process_index()}: {path} (saved by process 0) is missing here: the output "
            "folder must be on a filesystem that every process sees"
        ) from None


#: A vmapped local scan runs as many lines as its slowest trial, and most end within 3-4 lines:
#: every trial first runs with at most this many, then those still searching run again, alone.
FIRST_PASS_LINES = 6


def stage_trials(
    cfg: StudyConfig, context: tuple, x: dict, stage: int, mesh: Mesh, local=None, push_spec=None
) -> dict:
    """:func:`~jaxafm.position.strategy.trials` for the trials ``x`` (NumPy columns) on one stage's survey
    ``context``, split over the mesh. With ``local``, in two passes (:data:`FIRST_PASS_LINES`);
    each trial's key is ``fold_in(fold_in(seed, trial), stage)``, so the second pass gives what one
    pass with every line would. Returns NumPy columns (trials first)."""
    pos, stand, mean_path = _replicate(context, mesh)
    work = _layout(cfg)[0]
    target, seen = jax.vmap(image_position, (None, None, None, 0))(
        mean_path, jnp.asarray(work.origin), jnp.asarray(work.pixel_size), jnp.asarray(x["centre"])
    )
    x = x | {"target": np.asarray(target)}
    frame = context[0].frame
    box = (np.asarray(frame.measured).min(0), np.asarray(frame.measured).max(0)) if frame else None
    root = jax.random.fold_in(jax.random.key(cfg.seed), 0)

    def call(idx, spec, size):
        a = _shard({k: v[idx] for k, v in x.items()}, mesh, size)
        seen = jax.vmap(lambda c, R: Particles(c[None], R[None]))(
            a["centre"], a["radius"]
        )  # a particle per trial
        keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.fold_in(root, i), stage))(a["trial"])
        return _gather(
            trials(
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
                push_spec if spec else None,
                cfg.landmarks.approach_nm if pos.frame is not None else 0.0,
            ),
            len(idx),
        )

    every = np.arange(len(x["trial"]))
    first = -(-every.size // mesh.size) * mesh.size
    outside = (
        np.zeros(len(every), bool)
        if box is None
        else np.any((x["target"] < box[0]) | (x["target"] > box[1]), axis=1)
    )
    if local is None or local.max_lines <= FIRST_PASS_LINES:
        return _unseen(call(every, local, first), np.asarray(seen)) | {"outside_grid": outside}
    r = call(every, dataclasses.replace(local, max_lines=FIRST_PASS_LINES), first)
    again = np.flatnonzero(~r["c_found"] & (r["c_lines"] >= FIRST_PASS_LINES))
    size = -(-max(first // 16, 1) // mesh.size) * mesh.size  # one more shape to compile per batch size
    for start in range(0, again.size, size):
        idx = again[start : start + size]
        r2 = call(idx, local, size)
        r = {k: v for k, v in r.items() if v.shape[1:] == r2[k].shape[1:]}  # drops the per-line records
        for k in r:
            r[k][idx] = r2[k]
    return _unseen(r, np.asarray(seen)) | {"outside_grid": outside}


def _unseen(r: dict, seen: np.ndarray) -> dict:
    """Trials whose particle lies outside the survey image have no target: their errors are NaN
    and nothing of theirs counts as found or pushed."""
    for k, v in r.items():
        if v.dtype == bool:
            v[~seen] = False
        elif k.endswith("error_nm") or k.startswith("push_final"):
            v[~seen] = np.nan
    return r


def run_chunk(cfg: StudyConfig, contexts: dict, draws: dict, mesh: Mesh) -> dict:
    """The results of the trials in ``draws`` (one scanner's), columns keyed by stage, run as one
    batch split over the ``mesh``'s devices (``contexts`` replicated on them)."""
    local = LocalScan.from_config(cfg.local_scan)
    push_spec = Push.from_config(cfg.push) if "push" in cfg.stages else None
    x = {
        "trial": draws["trial"],
        "centre": np.stack([draws["x_nm"], draws["y_nm"]], -1),
        "radius": draws["radius_nm"],
        "direction": np.stack([draws["push_dx"], draws["push_dy"]], -1),
        "distance": draws["push_distance_nm"],
    }
    n = len(x["trial"])
    out = {}
    for j, (st, ctx) in enumerate(contexts.items()):
        with_c = st == "A+B" and "A+B+C" in cfg.stages
        if isinstance(ctx, str):  # step A refused its model or the survey found too few landmarks
            r = {
                "modelled": np.full(n, ctx != REFUSED),
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
                "push_corrections": np.zeros(n, int),
                "push_contact": np.zeros(n, bool),
            }
        else:
            r = stage_trials(cfg, ctx, x, j, mesh, local if with_c else None, push_spec)
            r |= {
                "modelled": np.ones(n, bool),
                "surveyed": np.ones(n, bool),
                "seen": np.isfinite(r["error_nm"]),
            }
            if with_c and push_spec:
                miss = r["push_final"] - r["push_goal"]
                r |= {
                    "push_error_nm": np.linalg.norm(miss, axis=-1),
                    "push_along_nm": np.sum(miss * x["direction"], axis=-1),
                    "push_first_error_nm": np.linalg.norm(r["push_first"] - r["push_goal"], axis=-1),
                }
        out[f"{stage_key(st)}_error_nm"] = r["error_nm"]
        if st == "A+B":
            out |= {f"AB_{k}": r[k] for k in ("modelled", "surveyed", "seen", "outside_grid")}
        if with_c:
            out |= {
                "ABC_error_nm": r["c_error_nm"],
                "ABC_found": r["c_found"],
                "ABC_lines": r["c_lines"],
                "ABC_local_scan_s": r["c_seconds"],
            }
        if with_c and push_spec:
            out |= {
                k: r[k]
                for k in (
                    "push_error_nm",
                    "push_along_nm",
                    "push_first_error_nm",
                    "push_corrections",
                    "push_contact",
                )
            }
    return out


def _atomic(path: Path, write) -> None:
    """``write(tmp)`` then rename onto ``path``: a reader sees the old file or the whole new one."""
    if jax.process_index() != 0:  # pragma: no cover - several hosts: one writer
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp{os.getpid()}.{path.name}")  # same suffix: np.savez adds none
    write(tmp)
    os.replace(tmp, path)


def _chunks(cfg: StudyConfig) -> list:
    """``(scanner, first trial, end)`` of every chunk: a chunk never spans two scanners."""
    out = []
    for s in range(cfg.scanners):
        a, b = s * cfg.trials_per_scanner, min((s + 1) * cfg.trials_per_scanner, cfg.trials)
        out += [(s, i, min(i + cfg.chunk, b)) for i in range(a, b, cfg.chunk)]
    return out


def chunk_path(out: Path, a: int, b: int) -> Path:
    return out / "chunks" / f"trials_{a:08d}_{b:08d}.npz"


def run(
    cfg: StudyConfig,
    config_path: Path,
    out: Path,
    prepare=lambda: None,
    log=print,
    resume: bool = False,
    devices=None,
) -> dict:
    """The whole study into ``out``; returns the metrics (see the module docstring).

    ``resume``: keep the chunks and scanner models already in ``out`` (the caller has checked
    that they come from the same config: ``jaxafm study`` does, through the run manifest).

    In several JAX processes, every process calls it alike; only process 0 logs, writes and
    returns the metrics (the others return ``{}`` once it has written them).
    """
    from tqdm.auto import tqdm

    writer = jax.process_index() == 0
    log = log if writer else lambda message: None
    work, grid, D = _layout(cfg)
    default_afm().check_range(default_afm().nominal_volts(np.asarray(work.wanted()).reshape(-1, 2)))
    draws = trial_draws(cfg, D)
    scanners = scanner_draws(cfg)
    mesh = Mesh(np.array(jax.devices() if devices is None else devices), ("trials",))
    load_fixed_scanner(cfg, config_path)
    if jax.process_count() > 1:
        from .._version import __version__

        text = json.dumps([cfg.model_dump(mode="json"), __version__], sort_keys=True)
        _check_same(
            np.frombuffer(text.encode(), np.uint8),
            "run another config or jaxafm version than process 0: give them all the same",
        )
    prepare()
    chunks = _chunks(cfg)
    finished = _from_process_0(np.array([chunk_path(out, a, b).is_file() for _, a, b in chunks]))
    todo = [c for c, f in zip(chunks, finished) if not f]
    done = cfg.trials - sum(b - a for _, a, b in todo)
    info = _read_json(out / "scanners.json") if writer else {}
    processes = f" in {jax.process_count()} processes" if jax.process_count() > 1 else ""
    log(
        f"{cfg.trials} trials on {cfg.scanners} scanner(s), {mesh.size} device(s){processes}, chunks of {cfg.chunk}"
        + (f"; resuming: {done} done" if done else "")
    )
    start = time.perf_counter()
    with tqdm(
        total=cfg.trials, initial=done, unit="trial", desc="study", smoothing=0.1, disable=not writer
    ) as bar:
        for s in sorted({c[0] for c in todo}):
            bar.set_postfix_str(f"scanner {s}: step A and surveys")
            contexts, now = prepare_scanner(cfg, config_path, s, scanners[s], out, log)
            info[str(s)] = (
                info.get(str(s), {})
                | now
                | {  # a resumed scanner keeps its identification time
                    "step_a_fit_s": max(now["step_a_fit_s"], info.get(str(s), {}).get("step_a_fit_s", 0.0))
                }
            )
            _atomic(out / "scanners.json", lambda f: f.write_text(json.dumps(info, indent=1)))
            bar.set_postfix_str(f"scanner {s}: trials")
            for _, a, b in (c for c in todo if c[0] == s):
                r = run_chunk(cfg, contexts, {k: v[a:b] for k, v in draws.items()}, mesh)
                _atomic(chunk_path(out, a, b), lambda f: np.savez(f, **r))
                bar.update(b - a)
    return _summarise_on_process_0(cfg, out, draws, info, time.perf_counter() - start, log)


def _summarise_on_process_0(
    cfg: StudyConfig, out: Path, draws: dict, info: dict, seconds: float, log
) -> dict:
    """:func:`summarise` on process 0 (``{}`` on the others), which then tells the others whether
    it succeeded, so that every process ends together (or fails, naming process 0)."""
    if jax.process_count() == 1:
        return summarise(cfg, out, draws, info, seconds, log)
    metrics = {}
    try:
        if jax.process_index() == 0:
            metrics = summarise(cfg, out, draws, info, seconds, log)
    except BaseException:
        _from_process_0(np.int32(0))
        raise
    if not _from_process_0(np.int32(1)):
        raise RuntimeError("process 0 failed to summarise the study: its message says why")
    return metrics


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def load_results(cfg: StudyConfig, out: Path, draws: dict) -> dict:
    """Every trial's draws and results, columns (trials,), from the chunk files."""
    parts = [dict(np.load(chunk_path(out, a, b))) for _, a, b in _chunks(cfg)]
    return draws | {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


STAGE_LABELS = {"open_loop": "open loop", "A": "A", "B": "B", "AB": "A+B", "ABC": "A+B+C", "push": "push"}


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


def summarise(cfg: StudyConfig, out: Path, draws: dict, info: dict, seconds: float, log) -> dict:
    """``trials.csv``, ``trials.npz``, ``metrics.json``, the table and the figures."""
    r = load_results(cfg, out, draws)
    calib_s = cfg.calibration.simulate.pixels / cfg.calibration.simulate.line_rate_hz
    tol = cfg.push.tolerance_radii
    rows = {}
    for key, label in STAGE_LABELS.items():
        if f"{key}_error_nm" not in r:
            continue
        e = r[f"{key}_error_nm"]
        survey = "AB" if key in ("ABC", "push") else key
        with_a = key in ("A", "AB", "ABC", "push")
        # over the scanners that scanned (a refused scanner surveys nothing)
        surveyed = [v[f"{survey}_survey_s"] for v in info.values() if f"{survey}_survey_s" in v]
        scan_s = (np.mean(surveyed) if surveyed else np.nan) + (calib_s if with_a else 0)
        if key in ("ABC", "push"):
            scan_s += float(np.nanmean(r["ABC_local_scan_s"]))
        success = (
            (r["push_contact"] & (e <= tol * r["radius_nm"])) if key == "push" else e <= 0.1 * r["radius_nm"]
        )
        rows[label] = stage_summary(e, success, scan_s)
    metrics = {
        "trials": cfg.trials,
        "scanners": cfg.scanners,
        "trials_per_scanner": cfg.trials_per_scanner,
        "wall_s": seconds,
        "push_tolerance_radii": tol,
    }
    for label, s in rows.items():
        metrics |= {f"{stage_key(label.replace('open loop', 'open_loop'))}_{k}": v for k, v in s.items()}
    if "push_first_error_nm" in r:
        first = r["push_contact"] & (r["push_first_error_nm"] <= tol * r["radius_nm"])
        metrics |= {
            "push_first_success_pct": 100 * float(np.mean(first)),
            "push_corrections_mean": float(np.mean(r["push_corrections"])),
        }
    if "ABC_found" in r:
        metrics |= {
            "ABC_found_pct": 100 * float(np.mean(r["ABC_found"])),
            "ABC_lines_mean": float(np.mean(r["ABC_lines"])),
        }
    modes = failure_modes(r, cfg)
    metrics["failure_modes"] = modes
    _atomic(out / "trials.npz", lambda f: np.savez_compressed(f, **r))
    _atomic(out / "trials.csv", lambda f: write_columns(f, r))
    _atomic(out / "metrics.json", lambda f: f.write_text(json.dumps(metrics, indent=1)))
    errors = {label: r[f"{stage_key(label.replace('open loop', 'open_loop'))}_error_nm"] for label in rows}
    plots.study_errors(errors, r["radius_nm"], out / "errors.png")
    log(table(rows, tol))
    if "push_first_success_pct" in metrics:
        log(
            f"push: {metrics['push_first_success_pct']:.1f} % within {tol:g} R after the first push, "
            f"{metrics['push_success_pct']:.1f} % after the checks ({metrics['push_corrections_mean']:.2f} "
            "corrective pushes per trial)"
        )
    if modes:
        log(failure_table(modes, cfg.trials))
    return metrics


def failure_modes(r: dict, cfg: StudyConfig) -> dict:
    """Why trials failed, stage by stage (counts of trials; the reasons of a stage exclude each other).

    A+B: step A refused its model (:func:`~jaxafm.identify.plausibility.implausible`), the survey
    found too few landmarks for a map, the particle lay outside the survey image,
    the target lay outside the landmarks found (the map extrapolated), or the error left is beyond
    the local scan's search margin. A+B+C: the search found no particle, the verification did not
    pass within ``max_lines``, or it passed on a centre more than 0.1 R off. Push: the tip missed the
    particle, or the particle ended more than the tolerance from its goal: short or long (along the
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
        "error beyond the local scan's margin": ran & ~r["AB_outside_grid"] & (e > cfg.local_scan.margin_nm),
    }
    modes = {"A+B": ab}
    not_run = {"not run (A+B above)": ~ran}
    if "ABC_error_nm" in r:
        bad = ran & ~(r["ABC_error_nm"] <= 0.1 * R)
        found, full = r["ABC_found"], r["ABC_lines"] >= cfg.local_scan.max_lines
        modes["A+B+C"] = not_run | {
            "search found no particle": bad & ~found & ~full,
            f"not verified within {cfg.local_scan.max_lines} lines": bad & ~found & full,
            "verified on a centre > 0.1 R off": bad & found,
        }
    if "push_error_nm" in r:
        tol = cfg.push.tolerance_radii * R
        missed = ran & ~r["push_contact"]
        off = ran & r["push_contact"] & ~(r["push_error_nm"] <= tol)
        along = r["push_along_nm"]
        across = np.sqrt(np.maximum(r["push_error_nm"] ** 2 - along**2, 0))
        modes["push"] = not_run | {
            "tip missed the particle": missed,
            "short": off & (along < 0) & (-along >= across),
            "long": off & (along > 0) & (along >= across),
            "off the line": off & (across > np.abs(along)),
        }
    return {stage: {k: int(v.sum()) for k, v in reasons.items()} for stage, reasons in modes.items()}


def failure_table(modes: dict, trials: int) -> str:
    """The failure modes as a table: stage, reason, trials, share of all trials."""
    lines = [f"{'stage':7s} {'why a trial failed':42s} {'trials':>7s} {'share':>7s}"]
    lines.append("-" * len(lines[0]))
    for stage, reasons in modes.items():
        for why, n in reasons.items():
            lines.append(f"{stage:7s} {why:42s} {n:7d} {100 * n / trials:6.1f}%")
    return "\n".join(lines)


def table(rows: dict, tolerance_radii: float) -> str:
    head = (
        f"{'stage':10s} {'trials':>7s} {'ran':>6s} {'median':>9s} {'p95':>9s} {'p99':>9s} {'worst':>9s} "
        f"{'success':>8s} {'scanning':>9s}"
    )
    lines = [head, "-" * len(head)]
    for label, s in rows.items():
        lines.append(
            f"{label:10s} {s['trials']:7d} {s['ran_pct']:5.1f}% {s['error_median_nm']:7.1f}nm "
            f"{s['error_p95_nm']:7.1f}nm "
            f"{s['error_p99_nm']:7.1f}nm {s['error_max_nm']:7.1f}nm {s['success_pct']:7.1f}% "
            f"{s['scan_time_s']:8.0f}s"
        )
    lines.append(
        f"ran: trials with a model, a landmark map (B) and their particle in the survey image; error (over those): "
        f"true tip to true particle centre after a 0.2 s dwell (push: the particle's final "
        f"centre to its goal); success (over all): error <= 0.1 R (push: within {tolerance_radii:g} R); scanning: "
        "mean time spent scanning and pressing per scanner (A: calibration image; B: landmarks + "
        "workspace image; A+B+C: plus the mean local scan)"
    )
    return "\n".join(lines)
