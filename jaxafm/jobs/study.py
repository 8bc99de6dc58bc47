"""``jaxafm study CONFIG``: a Monte-Carlo positioning study.

Every trial is one particle of a drawn radius at a random place inside a landmark
cell (in its middle half, so the nearest indent is over a third of a cell away),
on a scanner drawn from the config's distributions. Consecutive trials share a
scanner (``trials_per_scanner``): its calibration scan, step A's identification
and one survey per stage (press the landmarks for B, image the workspace) run
once for them all (:func:`prepare_scanner`); the trials run as
:mod:`jaxafm.study.monte_carlo` says.

Trials run in batches of ``chunk`` trials. Every trial's draws are fixed before any runs, so
the results do not depend on the chunk size or the device count. Each chunk's results are
written to ``chunks/`` whole, and recorded in the run's manifest as they are
(:meth:`~jaxafm.jobs.folder.Output.write`); a resumed study reuses them and the identified models in
``scanners/``. At the end: ``trials.csv``, ``trials.npz``, ``metrics.json``, ``errors.png``.

In several JAX processes (``jax.distributed``; ``jaxafm study --coordinator``), the mesh spans
every process's devices and each chunk's trials are split over them all. Every process computes
each scanner's calibration scan, step A and surveys itself (deterministic: the same on the same
kind of CPU; :func:`~jaxafm.study.processes.check_same` checks that they agree, and that all run
the same config), and takes the decisions that depend on the output folder (which chunks are
done, which models are saved) from process 0
(:func:`~jaxafm.study.processes.from_process_0`), so all of them make the same collective calls
in the same order. Process 0 alone logs and writes: chunks, models, ``scanners.json`` and the
summary.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import numpy as np
from jax.sharding import Mesh

from .. import plots
from ..config import STUDY_PARAMETERS, StudyConfig
from ..config.study import CLASS_EFFECTS
from ..identify.step_a import twin_state
from ..instrument.afm import default_afm, run_cycle
from ..instrument.records import write_columns
from ..instrument.samples import Indented, Plane
from ..model.io import load_model, save_model
from ..position import survey
from ..position.positioning import Positioner
from ..position.survey import STAGES, stage_key
from ..study.learning import LEARNT_FINDS, learning_rounds, position_coverage
from ..study.monte_carlo import (
    NOTHING_OBSERVED,
    Learning,
    Observed,
    StageSurvey,
    TrialSettings,
    Unsurveyed,
    failure_modes,
    noise_ceiling_pct,
    predicted_push_success,
    push_vectors,
    run_chunk,
    stage_summary,
    with_chunk_observed,
)
from ..study.processes import check_same, from_process_0
from ..study.reliability import gate, reliability
from .calibrate import calibration_scans
from .folder import Output
from .run import (
    ImplausibleModel,
    identify_scanner,
    local_scan_settings,
    push_settings,
    read_scanner_model,
    workspace_layout,
)


def scanner_draws(cfg: StudyConfig) -> list:
    """``default_afm`` arguments for each of the study's scanners (drawn before any trial): the
    truth classes in turn, each scanner with the parameters of the effects its class holds."""
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
        truth = cfg.truth_classes[s % len(cfg.truth_classes)]
        held = {
            arg
            for effect, params in STUDY_PARAMETERS.items()
            if CLASS_EFFECTS.get(effect, truth) == truth
            for arg, _, _ in params.values()
        }
        d = {k: float(v[s]) for k, v in columns.items() if k in held}
        d["drift_nm_per_min"] = (d.pop("drift_x"), d.pop("drift_y"))
        draws.append(d | {"truth_class": truth})
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


def trial_settings(cfg: StudyConfig) -> TrialSettings:
    """What every trial of the study shares, as ``cfg`` sets it (step C with A+B+C, the push
    with push)."""
    return TrialSettings(
        cfg.seed,
        workspace_layout(cfg)[0],
        cfg.landmarks.approach_nm,
        local_scan_settings(cfg.local_scan) if "A+B+C" in cfg.stages else None,
        push_settings(cfg.push, cfg.learning.min_push_odds if cfg.learning else 0.0)
        if "push" in cfg.stages
        else None,
        None
        if cfg.learning is None
        else Learning(**cfg.learning.model_dump(), push_tolerance_radii=cfg.push.tolerance_radii),
    )


def prepare_scanner(cfg: StudyConfig, config_path: Path, s: int, params: dict, out: Output, log) -> tuple:
    """Scanner ``s`` (``default_afm(**params)``): its calibration scan, step A's model (identified,
    or read from ``scanners/`` in ``out`` when a resumed study saved it, or from
    ``calibration.model_file``) and one survey per stage. Returns ``({stage: StageSurvey or
    Unsurveyed}, what is worth keeping about the scanner)``."""
    work, grid, D = workspace_layout(cfg)
    afm = default_afm(**params)
    scans, sim = calibration_scans(cfg.calibration.simulate, cfg.calibration.grating, afm)
    start = run_cycle(afm, sim.lattice, sim.measured.state, sim.cycle, sim.key)
    stages = [st for st in STAGES if st.name in cfg.stages or (st.name == "A+B" and "A+B+C" in cfg.stages)]
    info = {"scanner": s, **params, "step_a_fit_s": 0.0}
    model = twin = None
    if any(st.with_a for st in stages):
        model = _step_a_model(cfg, config_path, s, scans, out, info, log)
        twin = None if model is None else twin_state(model, scans, sim.cycle).scanner
    surveys = {}
    for i, st in enumerate(stages):
        if st.with_a and model is None:
            surveys[st.name] = Unsurveyed.REFUSED
            continue
        pos = Positioner(afm, model if st.with_a else None)
        seen = survey.survey(
            pos,
            pos.start(start, twin if st.with_a else None),
            Indented.empty(Plane(), afm.tip, grid.n**2),
            work,
            jax.random.fold_in(jax.random.fold_in(jax.random.key(cfg.seed), 1 + s), i),
            D if st.with_b else None,
            cfg.landmarks.depth_nm,
            cfg.landmarks.approach_nm,
        )
        info[f"{st.key}_survey_s"] = seen.seconds
        if st.with_b:
            lm = cfg.landmarks
            M, D_found = survey.find_landmarks(seen.images, work, grid, D, lm.depth_nm)
            info[f"{st.key}_landmarks_found"] = len(M)
            maps = survey.landmark_maps(M, D_found, lm.interpolation, lm.m, lm.degree)
            if not maps:
                log(
                    f"scanner {s}, {st.name}: {len(M)} of the {grid.n**2} landmarks found, too few to map: "
                    "its trials fail"
                )
                surveys[st.name] = Unsurveyed.TOO_FEW
                continue
            pos = Positioner(afm, pos.model, maps[lm.interpolation[0]])
        mean_path = (seen.images.path_trace + seen.images.path_retrace) / 2
        surveys[st.name] = StageSurvey(pos, seen.stand, mean_path)
    return surveys, info


def _step_a_model(cfg: StudyConfig, config_path: Path, s: int, scans: tuple, out: Output, info: dict, log):
    """Scanner ``s``'s step A model: the one a resumed study saved in ``scanners/``, else
    identified from ``scans`` (or read from ``calibration.model_file``) and saved there;
    ``None`` where step A refused its model (the reason and the seconds go into ``info``)."""
    name = f"scanners/model_{s:05d}.json"
    if from_process_0((out.path / name).is_file()):
        return _load_saved(out.path / name)
    began = time.perf_counter()
    try:
        model, info["step_a_fit_s"] = identify_scanner(cfg, scans, config_path, lambda m: None)
    except ImplausibleModel as e:
        info |= {"step_a_fit_s": time.perf_counter() - began, "step_a_refused": str(e)}
        log(f"scanner {s}: {e}: its trials through step A fail")
        return None
    _save(out, name, lambda f: save_model(model, f))
    return model


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


def _save(out: Output, name: str, write) -> None:
    """``out.write(name, write)`` (recorded in the run's manifest, put in place whole) on process
    0 alone: one writer for a run in several processes."""
    if jax.process_index() == 0:
        out.write(name, write)


def _chunks(cfg: StudyConfig) -> list:
    """``(scanner, first trial, end)`` of every chunk: a chunk never spans two scanners."""
    out = []
    for s in range(cfg.scanners):
        a, b = s * cfg.trials_per_scanner, min((s + 1) * cfg.trials_per_scanner, cfg.trials)
        out += [(s, i, min(i + cfg.chunk, b)) for i in range(a, b, cfg.chunk)]
    return out


def chunk_file(a: int, b: int) -> str:
    """The file of the chunk of trials ``a`` to ``b`` (end excluded), relative to the output folder."""
    return f"chunks/trials_{a:08d}_{b:08d}.npz"


def run(
    cfg: StudyConfig,
    config_path: Path,
    out: Output,
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
    draws, scanners, mesh = _start(cfg, config_path, devices)
    out.prepare()
    chunks = _chunks(cfg)
    finished = from_process_0(np.array([(out.path / chunk_file(a, b)).is_file() for _, a, b in chunks]))
    todo = [c for c, f in zip(chunks, finished) if not f]
    done = cfg.trials - sum(b - a for _, a, b in todo)
    info = _read_json(out.path / "scanners.json") if writer else {}
    processes = f" in {jax.process_count()} processes" if jax.process_count() > 1 else ""
    log(
        f"{cfg.trials} trials on {cfg.scanners} scanner(s), {mesh.size} device(s){processes}, chunks of {cfg.chunk}"
        + (f"; resuming: {done} done" if done else "")
    )
    settings = trial_settings(cfg)
    push = push_vectors(draws)
    start = time.perf_counter()
    with tqdm(
        total=cfg.trials, initial=done, unit="trial", desc="study", smoothing=0.1, disable=not writer
    ) as bar:
        for s in sorted({c[0] for c in todo}):
            bar.set_postfix_str(f"scanner {s}: step A and surveys")
            began = time.perf_counter()
            surveys, now = prepare_scanner(cfg, config_path, s, scanners[s], out, log)
            now["step_a_and_surveys_s"] = time.perf_counter() - began
            kept = info.get(str(s), {})
            # a resumed scanner keeps its identification time
            info[str(s)] = (
                kept | now | {"step_a_fit_s": max(now["step_a_fit_s"], kept.get("step_a_fit_s", 0.0))}
            )
            _save(out, "scanners.json", lambda f: f.write_text(json.dumps(info, indent=1)))
            bar.set_postfix_str(f"scanner {s}: trials")
            mine = [c for c in todo if c[0] == s]
            began = time.perf_counter()
            earlier = _kept_observed(cfg, out, draws, s, mine[0][1]) if cfg.learning else NOTHING_OBSERVED
            for _, a, b in mine:
                r = run_chunk(surveys, {k: v[a:b] for k, v in draws.items()}, mesh, settings, earlier)
                earlier = with_chunk_observed(earlier, r, push[a:b]) if cfg.learning else NOTHING_OBSERVED
                _save(out, chunk_file(a, b), lambda f: np.savez(f, **r))
                bar.update(b - a)
            info[str(s)]["trials_s"] = time.perf_counter() - began
            _save(out, "scanners.json", lambda f: f.write_text(json.dumps(info, indent=1)))
    return _summarise_on_process_0(cfg, out, draws, info, time.perf_counter() - start, log)


def _kept_observed(cfg: StudyConfig, out: Output, draws: dict, s: int, a: int) -> Observed:
    """What scanner ``s``'s trials before trial ``a`` observed (step C's finds, the checked
    pushes), from the chunk files that a resumed study kept (all written before the run began,
    so every process reads them alike) and the trials' ``draws``."""
    seen = NOTHING_OBSERVED
    push = push_vectors(draws)
    for t, c, b in _chunks(cfg):
        if t == s and b <= a:
            columns = np.load(out.path / chunk_file(c, b))
            seen = with_chunk_observed(seen, columns, push[c:b])
    return seen


def _start(cfg: StudyConfig, config_path: Path, devices) -> tuple:
    """Every check that can fail, before the output folder is touched, and what the study is
    made of: every trial's draws, every scanner's, and the mesh of ``devices`` (default: every
    device of every process)."""
    work, _, D = workspace_layout(cfg)
    default_afm().check_range(default_afm().nominal_volts(np.asarray(work.wanted()).reshape(-1, 2)))
    draws = trial_draws(cfg, D)
    scanners = scanner_draws(cfg)
    mesh = Mesh(np.array(jax.devices() if devices is None else devices), ("trials",))
    read_scanner_model(cfg, config_path)
    if jax.process_count() > 1:
        from .._version import __version__

        text = json.dumps([cfg.model_dump(mode="json"), __version__], sort_keys=True)
        check_same(
            np.frombuffer(text.encode(), np.uint8),
            "run another config or jaxafm version than process 0: give them all the same",
        )
    return draws, scanners, mesh


def _summarise_on_process_0(
    cfg: StudyConfig, out: Output, draws: dict, info: dict, seconds: float, log
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
        from_process_0(np.int32(0))
        raise
    if not from_process_0(np.int32(1)):
        raise RuntimeError("process 0 failed to summarise the study: its message says why")
    return metrics


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def load_results(cfg: StudyConfig, out: Output, draws: dict) -> dict:
    """Every trial's draws and results, columns (trials,), from the chunk files."""
    parts = [dict(np.load(out.path / chunk_file(a, b))) for _, a, b in _chunks(cfg)]
    return draws | {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


#: the metrics that are this machine's wall-clock seconds (s), not results: the whole command's, and
#: summed over the scanners, their step A and surveys' and their trials' (each scanner's in
#: ``scanners.json``, as the run that made them took them)
WALL_TIMES = ("wall_s", "step_a_and_surveys_s", "trials_s")

STAGE_LABELS = {"open_loop": "open loop", "A": "A", "B": "B", "AB": "A+B", "ABC": "A+B+C", "push": "push"}


def summarise(cfg: StudyConfig, out: Output, draws: dict, info: dict, seconds: float, log) -> dict:
    """``trials.csv``, ``trials.npz``, ``metrics.json``, the table and the figures."""
    r = load_results(cfg, out, draws)
    calib_s = sum(cfg.calibration.simulate.pixels / rate for _, rate in cfg.calibration.simulate.scans)
    tol = cfg.push.tolerance_radii
    rows, successes = {}, {}
    for key, label in STAGE_LABELS.items():
        if f"{key}_error_nm" not in r:
            continue
        e = r[f"{key}_error_nm"]
        base = "AB" if key in ("ABC", "push") else key  # the stage whose survey it goes on from
        with_a = key in ("A", "AB", "ABC", "push")
        # over the scanners that scanned (a refused scanner surveys nothing)
        surveyed = [v[f"{base}_survey_s"] for v in info.values() if f"{base}_survey_s" in v]
        scan_s = (np.mean(surveyed) if surveyed else np.nan) + (calib_s if with_a else 0)
        if key in ("ABC", "push"):
            scan_s += float(np.nanmean(r["ABC_local_scan_s"]))
        success = (
            (r["push_contact"] & (e <= tol * r["radius_nm"])) if key == "push" else e <= 0.1 * r["radius_nm"]
        )
        rows[label] = stage_summary(e, success, scan_s)
        successes[key] = success
    metrics = {
        "trials": cfg.trials,
        "scanners": cfg.scanners,
        "trials_per_scanner": cfg.trials_per_scanner,
        "wall_s": seconds,
        **{k: sum(v.get(k, 0.0) for v in info.values()) for k in WALL_TIMES[1:]},
        "push_tolerance_radii": tol,
    }
    for label, s in rows.items():
        metrics |= {f"{stage_key(label.replace('open loop', 'open_loop'))}_{k}": v for k, v in s.items()}
    odds = None
    if "push_first_error_nm" in r:
        first = r["push_contact"] & (r["push_first_error_nm"] <= tol * r["radius_nm"])
        metrics |= {
            "push_first_success_pct": 100 * float(np.mean(first)),
            "push_corrections_mean": float(np.mean(r["push_corrections"])),
        }
        if cfg.learning and cfg.learning.min_push_odds > 0:
            ran = np.isfinite(r["push_error_nm"])  # a withheld push leaves its particle where it was
            made = ran & ~r["push_withheld"]
            metrics |= {
                "push_gate_min_odds": cfg.learning.min_push_odds,
                "push_withheld_pct": 100 * float(np.mean(r["push_withheld"][ran])),
                "push_success_of_made_pct": 100 * float(np.mean(successes["push"][made]))
                if made.any()
                else None,
            }
        odds = _push_odds(r, first, tol, metrics)
        tried = np.isfinite(r["push_error_nm"]) & ~r["push_withheld"]
        metrics["push_gate"] = gate(r["push_first_predicted"], successes["push"], tried)
    if "ABC_found" in r:
        metrics |= {
            "ABC_found_pct": 100 * float(np.mean(r["ABC_found"])),
            "ABC_lines_mean": float(np.mean(r["ABC_lines"])),
        }
        sigma = np.array([info.get(str(s), {}).get("noise_std", np.nan) for s in r["scanner"]])
        if np.all(np.isfinite(sigma)):  # each scanner's noise as drawn (scanners.json)
            metrics["ABC_noise_ceiling_pct"] = noise_ceiling_pct(r["radius_nm"], sigma)
    learnt = learning_rounds(r, cfg.learning.round_trials) if "AB_learnt_from" in r else None
    coverage = position_coverage(r) if "AB_predicted_sd_nm" in r else None
    if learnt:
        metrics["AB_learning"] = learnt
    if coverage:
        metrics["AB_position_coverage"] = coverage
    if len(cfg.truth_classes) > 1:
        truth = np.array([info[str(s)]["truth_class"] for s in r["scanner"]])
        metrics["truth_classes"] = {
            c: {"trials": int(np.sum(truth == c))}
            | {f"{key}_success_pct": 100 * float(np.mean(ok[truth == c])) for key, ok in successes.items()}
            for c in cfg.truth_classes
        }
    widest = float(local_scan_settings(cfg.local_scan).search_margin(cfg.local_scan.widenings))
    modes = failure_modes(r, widest, cfg.local_scan.max_lines, tol)
    metrics["failure_modes"] = modes
    out.write("trials.npz", lambda f: np.savez_compressed(f, **r))
    out.write("trials.csv", lambda f: write_columns(f, r))
    out.write_metrics(metrics)
    errors = {label: r[f"{stage_key(label.replace('open loop', 'open_loop'))}_error_nm"] for label in rows}
    out.write("errors.png", lambda f: plots.study_errors(errors, r["radius_nm"], f))
    if odds and odds["trials"]:
        out.write("push_odds.png", lambda f: plots.push_reliability(odds, r["push_first_predicted"], f))
    if learnt:
        out.write("learning.png", lambda f: plots.learning_curve(learnt, f))
    if coverage:
        out.write("position_coverage.png", lambda f: plots.position_coverage(coverage, f))
    log(table(rows, tol))
    if "push_first_success_pct" in metrics:
        log(
            f"push: {metrics['push_first_success_pct']:.1f} % within {tol:g} R after the first push, "
            f"{metrics['push_success_pct']:.1f} % after the checks ({metrics['push_corrections_mean']:.2f} "
            "corrective pushes per trial)"
        )
    if "push_withheld_pct" in metrics:
        log(
            f"push: {metrics['push_withheld_pct']:.1f} % withheld (predicted success below "
            f"{100 * cfg.learning.min_push_odds:g} %); of the pushes made, {metrics['push_success_of_made_pct']:.1f} % "
            "succeeded"
        )
    if odds:
        log(odds_table(odds, cfg.trials))
    if "push_gate" in metrics:
        log(gate_line(metrics["push_gate"]))
    if learnt:
        log(learning_table(learnt))
    if coverage:
        log(coverage_line(coverage))
    if "truth_classes" in metrics:
        log(class_table(metrics["truth_classes"]))
    if modes:
        log(failure_table(modes, cfg.trials))
    if "ABC_noise_ceiling_pct" in metrics:
        log(
            f"A+B+C: the tip's white position noise alone (each scanner's noise_std per axis) allows at most "
            f"{metrics['ABC_noise_ceiling_pct']:.1f} % of the trials within 0.1 R at the dwell's last sample"
        )
    return metrics


def _push_odds(r: dict, first: np.ndarray, tol: float, metrics: dict) -> dict:
    """Each trial's first-push odds (:func:`~jaxafm.study.monte_carlo.predicted_push_success`)
    as the column ``push_first_predicted`` of ``r``, scored against whether its first push
    succeeded, ``first`` (:func:`~jaxafm.study.reliability.reliability`), into ``metrics``;
    returns the scores."""
    r["push_first_predicted"] = predicted_push_success(r, tol)
    odds = reliability(r["push_first_predicted"], first)
    metrics |= {f"push_first_{k}": v for k, v in odds.items() if k != "bins"}
    metrics["push_first_reliability"] = odds["bins"]
    return odds


def odds_table(odds: dict, trials: int) -> str:
    """The first push's predicted success against what happened, per tenth of prediction."""
    if not odds["trials"]:
        return "first push: no predicted success (no scanner had enough pushes before a trial)"
    lines = [
        f"first push, predicted before it from the earlier pushes on its scanner: {odds['trials']} of "
        f"{trials} trials, Brier {odds['brier']:.4f} (the overall rate's {odds['brier_base_rate']:.4f})",
        f"{'predicted':>11s} {'trials':>7s} {'mean':>7s} {'observed':>9s}",
    ]
    for b in odds["bins"]:
        lines.append(
            f"{100 * b['lo']:4.0f}-{100 * b['hi']:3.0f} % {b['trials']:7d} {b['predicted_pct']:6.1f}% "
            f"{b['observed_pct']:8.1f}%"
        )
    return "\n".join(lines)


def learning_table(learnt: dict) -> str:
    """The A+B error per scanner in its first round and once learnt from enough finds."""
    never = learnt["unlearnt_scanners"]
    lines = [
        f"A+B learning from step C's finds, over the {len(learnt['learnt_scanners'])} scanners that reached "
        f"{LEARNT_FINDS} finds: median {learnt['first_round_median_nm']:.1f} nm in their first rounds (no finds), "
        f"{learnt['learnt_median_nm']:.1f} nm once aimed by {LEARNT_FINDS} or more (ratio {learnt['learnt_ratio']:.2f})"
        + (f"; never reached {LEARNT_FINDS}: scanner {', '.join(map(str, never))}" if never else ""),
        f"{'scanner':>8s} {'first round':>12s} {f'>= {LEARNT_FINDS} finds':>13s}",
    ]
    for s, e in learnt["per_scanner"].items():
        lines.append(f"{s:8d} {e[0]:10.1f}nm {learnt['per_scanner_learnt'][s]:11.1f}nm")
    return "\n".join(lines) + f"\n(rounds of {learnt['round_trials']} trials)"


def gate_line(rows: list) -> str:
    """What a gate on the first push's odds would have done, per threshold."""
    parts = [
        f"at {100 * g['min_odds']:g} %: {g['made_pct']:.1f} % made, {g['success_of_made_pct']:.1f} % of them succeeded"
        for g in rows
    ]
    return "push withheld below its odds (read from these pushes): " + "; ".join(parts)


def coverage_line(coverage: dict) -> str:
    """The predicted A+B spread's coverage at 50 and 90 %: of the true A+B errors and of step C's
    finds about the aims, over all trials and the learnt ones."""
    at = {level: i for i, level in enumerate(coverage["levels"])}
    what = {"true": "true A+B errors", "find": "step C's finds about the aim"}
    lines = ["the spread the tracker predicted for each A+B move, against"]
    for kind, label in what.items():
        for name in ("all", "learnt"):
            v = coverage[kind][name]
            lines.append(
                f"  {label}, {name} ({v['trials']} trials, median sd {v['sd_median_nm']:.1f} nm): "
                f"{v['covered_pct'][at[0.5]]:.1f} % within the 50 % radius, {v['covered_pct'][at[0.9]]:.1f} % "
                "within the 90 %"
            )
    return "\n".join(lines)


def class_table(classes: dict) -> str:
    """Each stage's success per truth class (the true scanners' model class)."""
    keys = [k for k in STAGE_LABELS if f"{k}_success_pct" in next(iter(classes.values()))]
    lines = [f"{'truth class':16s} {'trials':>7s}" + "".join(f" {STAGE_LABELS[k]:>9s}" for k in keys)]
    for c, v in classes.items():
        lines.append(f"{c:16s} {v['trials']:7d}" + "".join(f" {v[f'{k}_success_pct']:8.1f}%" for k in keys))
    return "\n".join(lines) + "\n(success per stage, over the trials on the scanners of each truth class)"


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
