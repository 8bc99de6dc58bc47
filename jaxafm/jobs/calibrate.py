"""``jaxafm calibrate CONFIG`` (step A): identify, invert, compensate, measure.

On the simulated AFM the run follows the paper (section III-A): the
initialisation cycle, one trace/retrace image of a lattice of known pitch,
identification, the cycle again, then the lattice re-imaged with each inverse
-- the paper's polynomial + neural network and the end-to-end model's
analytic and numerical inverses. Errors are measured against the true tip
path, which only a simulation knows. On measured images the run identifies
the scanner and reports the fit. Writes ``model_NAME.json`` per usable model,
``validation_NAME.png`` per model, ``metrics.json`` and (simulated) ``compensation.png``.

Step A as configured here (:func:`calibration_scans`, :func:`identify_model`) is also the
step A of ``jaxafm run`` and ``jaxafm study``.
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
from ..config import (
    CalibrateConfig,
    CalibrationImages,
    CalibrationLattice,
    CalibrationModel,
    CalibrationSolver,
    SimulatedCalibration,
)
from ..config.calibrate import each_scan_once
from ..identify.calibration_scan import CalibrationScan
from ..identify.held_out import model_centres, nominal_centres, raw_errors
from ..identify.identifiability import ellipse_quantile, point_predictions
from ..identify.polynomial_baseline import fit_polynomials
from ..identify.scan_model import ScanModel, ScanModelSpec
from ..identify.staged_fit import Identification, identify
from ..identify.stages import FitPlan, chord_data
from ..identify.step_a import (
    Simulation,
    calibration_about,
    calibration_lattice,
    compensated_scan,
    model_compensator,
    paper_inverse,
    parameters_vs_truth,
    pitch_uniformity,
    position_errors,
    simulate_calibration,
)
from ..instrument.afm import AFM, Raster, default_afm
from ..model.io import save_model
from .folder import Output
from .inputs import read_image_pair, scan_settings, settings_line


def calibration_scans(
    spec: SimulatedCalibration, grating: CalibrationLattice, afm: Optional[AFM] = None
) -> tuple:
    """The configured calibration scans of the simulated AFM (``default_afm()`` unless given, less
    the ``withheld`` effects), one per scan angle: ``(scans, Simulation)``
    (:func:`~jaxafm.identify.step_a.simulate_calibration`)."""
    afm = default_afm() if afm is None else afm
    if spec.withheld:
        afm = afm.without(*spec.withheld)
    rasters = [
        Raster(spec.size_nm, spec.pixels, spec.pixels, line_rate=rate, angle_deg=angle)
        for angle, rate in spec.scans
    ]
    lattice = calibration_lattice(grating.pitch_nm, grating.pits, spec.lattice_rotation_deg)
    return simulate_calibration(afm, lattice, rasters, jax.random.key(spec.seed))


def read_calibration(
    spec: CalibrationImages, grating: CalibrationLattice, config_path: Path, log=print
) -> tuple:
    """The measured trace/retrace pairs (``data`` of ``config_path``) as
    :class:`~jaxafm.identify.calibration_scan.CalibrationScan`s, with the nominal sensitivity
    given or its default (:func:`nominal_sensitivity`)."""
    images, rasters, scanned, said = [], [], [], []
    for key, pair in spec.pairs:
        trace, retrace = read_image_pair(pair, config_path, key)
        how, source = scan_settings(pair, (trace, retrace), config_path, key)
        said.append(settings_line(key, how, source))
        if trace.shape != retrace.shape or not np.allclose(trace.size, retrace.size):
            raise ValueError(
                f"trace {trace.meta['source']} ({trace.shape} px, {trace.size} nm) and retrace "
                f"{retrace.meta['source']} ({retrace.shape} px, {retrace.size} nm) must cover the same raster"
            )
        if images and (trace.shape != images[0][0].shape or not np.allclose(trace.size, images[0][0].size)):
            first = images[0][0]
            raise ValueError(
                f"{key}: {trace.meta['source']} ({trace.shape} px, {trace.size} nm) and "
                f"data.scans.0: {first.meta['source']} ({first.shape} px, {first.size} nm) differ: "
                "the scans of one calibration must have one size and one pixel count"
            )
        images.append((trace, retrace))
        scanned.append((how["angle_deg"], how["line_rate_hz"]))
        try:
            each_scan_once(scanned, [k for k, _ in spec.pairs])  # with what the files' headers say
        except ValueError as e:
            raise ValueError(f"{config_path}: data: {e}") from None
        rasters.append(
            Raster(
                trace.size,
                trace.shape[1],
                trace.shape[0],
                line_rate=how["line_rate_hz"],
                overscan=how["overscan"],
                direction=how["lines"],
                angle_deg=how["angle_deg"],
            )
        )
    sensitivity = nominal_sensitivity(spec, rasters, log)
    for line in said:  # once every check has passed: a refusal is the run's first line
        log(line)
    return tuple(
        CalibrationScan(
            trace.z,
            retrace.z,
            raster,
            grating.pitch_nm,
            sensitivity,
            spec.u_max_v,
            (0.0, 0.0),
            0.0,
            spec.history_v,
            pits=grating.pits,
            off_line_sd=grating.off_line_chords_sd,
        )
        for (trace, retrace), raster in zip(images, rasters)
    )


def nominal_sensitivity(spec: CalibrationImages, rasters: list, log=print) -> tuple:
    """The nominal calibration (x, y) nm/V: ``data.sensitivity_nm_per_v`` if given; else the
    instrument's stated range over the drive range, ``scan_range_nm / (2 u_max_v)``; else the
    largest extent the scans reach (over-scan included, either axis) over ``u_max_v``, so that
    they just fit the drive. Refuses a given one that needs more than ``u_max_v``."""
    reach = np.max([np.abs(r.wanted().reshape(-1, 2)).max(axis=0) for r in rasters], axis=0)  # nm
    if spec.sensitivity_nm_per_v is not None:
        sensitivity = np.asarray(spec.sensitivity_nm_per_v, dtype=float)
        need = reach / sensitivity
        if need.max() > spec.u_max_v:
            raise ValueError(
                f"data.sensitivity_nm_per_v = {spec.sensitivity_nm_per_v} nm/V needs +-{need.max():.3g} V "
                f"to scan the images (+-{reach.max():.4g} nm with their over-scan), beyond data.u_max_v = "
                f"{spec.u_max_v:g} V: check both against the instrument's scan range"
            )
        return tuple(sensitivity)
    if spec.scan_range_nm is not None:
        span = np.broadcast_to(np.asarray(spec.scan_range_nm, dtype=float), (2,))
        sensitivity = span / (2 * spec.u_max_v)
        if np.any(reach > span / 2):
            raise ValueError(
                f"data.scan_range_nm = {spec.scan_range_nm} nm is smaller than the images "
                f"(+-{reach.max():.4g} nm with their over-scan): give the instrument's full scan range"
            )
        why = f"data.scan_range_nm / (2 data.u_max_v) = {spec.scan_range_nm} / (2 x {spec.u_max_v:g} V)"
    else:
        sensitivity = np.full(2, reach.max() / spec.u_max_v)
        why = f"the images' reach +-{reach.max():.4g} nm over data.u_max_v = {spec.u_max_v:g} V"
    log(
        f"nominal sensitivity (default): {sensitivity[0]:.4g} x {sensitivity[1]:.4g} nm/V from {why}; "
        "give data.sensitivity_nm_per_v or data.scan_range_nm if the instrument states them"
    )
    return tuple(float(v) for v in sensitivity)


def identify_model(
    scans: tuple,
    model: CalibrationModel,
    solver: CalibrationSolver,
    grating: CalibrationLattice,
    log=print,
    measured: bool = False,
) -> Identification:
    """Step A's identification (:func:`~jaxafm.identify.staged_fit.identify`) of the configured
    ``model`` from ``scans`` of ``grating`` (``measured`` images or simulated ones, which decides
    the default image stages, :meth:`~jaxafm.config.CalibrationSolver.image_blurs`) with the
    configured ``solver``."""
    spec = ScanModelSpec(
        model.kind,
        tuple(model.effects),
        model.operators,
        model.deadzones,
        model.levels,
        grating.rotation_rad,
        creep_onset=model.creep_onset,
        known=tuple((key, float(value), float(sd)) for key, (value, sd) in model.known.items()),
        chord_lengths=solver.chord_lengths,
    )
    max_steps = solver.max_steps if isinstance(solver.max_steps, int) else tuple(solver.max_steps)
    plan = FitPlan(
        solver.name,
        solver.image_blurs(measured),
        solver.coarsen,
        max_steps,
        hold_out=solver.hold_out,
        select=solver.select,
        wide_loop=solver.wide_loop,
        path_tolerance_nm=solver.path_tolerance_nm,
    )
    return identify(scans, spec, plan, log=log)


def run(cfg: CalibrateConfig, config_path: Path, out: Output, log=print) -> dict:
    """Identify every configured model; on the simulated AFM also compensate and re-image.
    Writes ``model_NAME.json`` (the fitted scanner; not for a model that fails the
    plausibility checks), ``metrics.json`` and figures into ``out``.

    Raises:
        ValueError: after writing the metrics and figures, when a model failed the
            plausibility checks or its inverse refused the compensated scan's drive (beyond the
            range it was fitted over), naming each.
    """
    scans, sim = _scans(cfg, config_path, log)
    for scan in scans:
        scan.features()  # bad images fail here, before the output folder is touched
    out.prepare()
    first = scans[0]
    metrics = {
        "pixels": first.raster.pixels,
        "calibration_size_nm": first.raster.size[0],
        "pitch_nm": cfg.grating.pitch_nm,
        "scan_angles_deg": [s.raster.angle_deg for s in scans],
        "scan_line_rates_hz": [s.raster.line_rate for s in scans],
        "sensitivity_nm_per_v": list(first.sensitivity),
    }
    comp = cfg.compensate if sim is not None else None
    if cfg.compensate is not None and sim is None:
        log("measured images: no instrument to re-image with, so no compensation study")
    work = None if comp is None else _compensated_raster(first.raster, comp.scan_fraction, comp.overscan)
    rows, images, failed, refused = [], {}, {}, {}
    if comp is not None:
        images = _baselines(sim, work, first, comp.paper_baseline, metrics, rows, log)
    source = "simulated calibration scan" if sim is not None else _files(cfg.data)
    for spec in cfg.models:
        ident = _identify(cfg, spec, scans, sim, source, out, metrics, log)
        if not ident.plausible:
            failed[spec.name] = ident.failures
            continue
        about = calibration_about(ident.model.scanner, scans, source)
        out.write(f"model_{spec.name}.json", lambda path: save_model(ident.model.scanner, path, about))
        for method in comp.inverses if comp is not None else ():
            volts = model_compensator(ident.model, scans, sim, method)
            try:
                image = _measure(sim, work, volts, f"{spec.name}_{method}", ident.seconds, metrics, rows)
            except ValueError as e:  # its inverse refuses a drive beyond the range it was fitted over
                metrics[f"{spec.name}_{method}_refused"] = str(e)
                log(f"  {spec.name} + {method}: compensated scan refused: {e}")
                refused[f"{spec.name} + {method}"] = str(e)
                continue
            if spec is cfg.models[0]:
                images[f"{spec.name} + {method}"] = image
    if rows:
        log(_table(rows, work))
        title = f"Step A on the simulated AFM: lattice of pitch {cfg.grating.pitch_nm:g} nm without (paper Fig. 6) "
        out.write(
            "compensation.png",
            lambda path: plots.compensation(images, work, path, title + "and with compensation (Fig. 7)"),
        )
    out.write_metrics(metrics)
    problems = [
        f"step A failed the plausibility checks, no model file saved for {name}: {', '.join(f)}"
        for name, f in failed.items()
    ] + [f"the compensated scan of {name} was refused: {why}" for name, why in refused.items()]
    if problems:  # the metrics and figures are written: they say why
        raise ValueError("; ".join(problems) + f" (metrics.json and figures in {out.path})")
    return metrics


def _scans(cfg: CalibrateConfig, config_path: Path, log) -> tuple:
    """The configured calibration scans, simulated (with their :class:`Simulation`) or read
    (with ``None``)."""
    if cfg.data is not None:
        return read_calibration(cfg.data, cfg.grating, config_path, log), None
    spec = cfg.simulate
    log(
        f"simulating the calibration scan(s) ({spec.pixels}² px, {spec.size_nm / 1e3:g} µm, "
        f"scan angle(s) {', '.join(f'{a:g}' for a in spec.angles_deg)} deg) ..."
    )
    return calibration_scans(spec, cfg.grating)


def _files(data: CalibrationImages) -> str:
    """The measured scans' files as the config names them: ``trace / retrace + ...``."""
    return " + ".join(f"{p.trace.path} / {p.retrace.path}" for _, p in data.pairs)


def _compensated_raster(calibrated: Raster, scan_fraction: float, overscan: float) -> Raster:
    """The raster the compensated scans image: ``scan_fraction`` of the calibration scan, with
    its pixels, lines and line rate."""
    return Raster(
        scan_fraction * calibrated.size[0],
        calibrated.pixels,
        calibrated.lines,
        line_rate=calibrated.line_rate,
        overscan=overscan,
    )


def _baselines(sim: Simulation, work: Raster, first, paper: bool, metrics: dict, rows: list, log) -> dict:
    """The lattice imaged along the nominal drive and (``paper``, at scan angle 0) along the
    paper's polynomial + neural-network inverse of the first scan; their errors go into
    ``metrics`` and ``rows``. Returns the images by label."""
    images = {"uncompensated": _measure(sim, work, None, "uncompensated", 0.0, metrics, rows)}
    if paper and first.raster.angle_deg == 0:
        start = time.perf_counter()
        volts = paper_inverse(fit_polynomials(first), np.asarray(sim.afm.sensitivity))
        fit_s = time.perf_counter() - start
        log(f"paper: polynomials + networks in {fit_s:.1f} s")
        images["paper (poly + NN)"] = _measure(sim, work, volts, "paper", fit_s, metrics, rows)
    return images


def _identify(
    cfg: CalibrateConfig,
    spec: CalibrationModel,
    scans: tuple,
    sim,
    source: str,
    out: Output,
    metrics: dict,
    log,
) -> Identification:
    """Step A's identification of the model ``spec``, logged (a model that fails the
    plausibility checks with the failures), its metrics (and, simulated, its parameters against
    the truth) added to ``metrics`` and its validation figure written."""
    log(f"identifying {spec.name} ({spec.kind}, {', '.join(spec.effects) or 'no other effects'}) ...")
    ident = identify_model(scans, spec, cfg.solver, cfg.grating, log, measured=cfg.data is not None)
    if not ident.converged:
        n = sum(not s.converged for s in ident.stages)
        log(
            f"  WARNING: {spec.name}: {n} of {len(ident.stages)} stages stopped at max_steps="
            f"{cfg.solver.max_steps} before converging (last loss {ident.stages[-1].loss:.3e}); "
            "raise solver.max_steps for a tighter fit"
        )
    metrics |= {f"{spec.name}_{k}": v for k, v in identification_metrics(ident).items()}
    if sim is not None:
        metrics |= {f"{spec.name}_{k}": v for k, v in parameters_vs_truth(sim, ident.model).items()}
    log(f"  {spec.name}: what the scans determine (value +- standard deviation):")
    for q in ident.quantities:
        log(f"    {q.line()}")
    log(_path_line(spec.name, ident))
    log(_validation_line(spec.name, ident))
    view = validation_view(scans, ident.model, cfg.solver.hold_out, ident.chords)
    title = f"Step A, {spec.name}, on {source} ({scans[0].name})"
    v = ident.validation
    if v.get("held_out_features"):
        title += (
            f"\nheld-out features in every image of every scan: {v['held_out_raw_rms_nm']:.4g} nm rms raw"
            f" -> {v['held_out_rms_nm']:.4g} nm corrected"
        )
    out.write(f"validation_{spec.name}.png", lambda path: plots.step_a_validation(view, path, title))
    if not ident.plausible:
        log(f"  FAILED: {spec.name} is not a usable scanner, not saved:")
        for f in ident.failures:
            log(f"    - {f}")
    return ident


def identification_metrics(ident: Identification) -> dict:
    """What ``metrics.json`` keeps of one identification: time, convergence, each stage's
    message, acceptance and held-out residual (nm), the held-out validation and the tip path's
    sd, the fitted lattice rotation, each quantity with its sd (and ``<key>_unmeasured``, why,
    for one the scans cannot show), and the plausibility checks."""
    lattice, spec = ident.model.lattice, ident.spec
    out = {
        "fit_s": ident.seconds,
        "converged": ident.converged,
        "stages": [s.message for s in ident.stages],
        "stages_accepted": list(ident.accepted),
        "held_out_nm_by_stage": [None if not np.isfinite(v) else v for v in ident.held_out_nm],
        "lattice_rotation_deg": float(np.rad2deg(lattice.angle)),
        "model_kind": spec.kind,
        "model_operators": spec.levels if spec.kind == "preisach" else spec.operators,
        "model_effects": list(spec.effects),
        "model_ladder": [f"{r.label}: {r.reason}" for r in ident.rungs],
        "plausible": ident.plausible,
        "failures": list(ident.failures),
    }
    if ident.image_rms_pct is not None:
        out["image_rms_pct"] = ident.image_rms_pct
    for q in ident.quantities:
        out |= {q.key: q.value, f"{q.key}_sd": q.sd if np.isfinite(q.sd) else None}
        if q.unmeasured:
            out[f"{q.key}_unmeasured"] = q.unmeasured
    return out | ident.validation


def _validation_line(name: str, ident: Identification) -> str:
    v = ident.validation
    if not v.get("held_out_features"):
        return f"  {name}: no features held out"
    return (
        f"  {name}: {v['held_out_features']} held-out features, residual {v['held_out_raw_rms_nm']:.1f} nm raw -> "
        f"{v['held_out_rms_nm']:.1f} nm rms corrected; their local pitch spread "
        f"{v['held_out_pitch_std_raw_pct']:.2f} % raw -> {v['held_out_pitch_std_corrected_pct']:.2f} % corrected; "
        f"distances between them {v['held_out_distance_error_max_raw_pct']:.2f} % raw -> "
        f"{v['held_out_distance_error_max_corrected_pct']:.2f} % corrected at most; the features' widths "
        f"spread {v['feature_width_spread_along_raw_pct']:.2f} % raw -> "
        f"{v['feature_width_spread_along_corrected_pct']:.2f} % corrected along the lines, "
        f"{v['feature_width_spread_across_raw_pct']:.2f} % -> {v['feature_width_spread_across_corrected_pct']:.2f} % "
        "across them; lattice rotation "
        f"{float(np.rad2deg(ident.model.lattice.angle)):.3f} deg"
    ) + _coverage_words(v)


def _path_line(name: str, ident: Identification) -> str:
    """How far the parameters the scans leave open move the tip path, and which quantity
    would settle most of it (:class:`~jaxafm.identify.identifiability.Determination`)."""
    v = ident.validation
    q = next(q for q in ident.quantities if q.key == v["path_settled_most_by"])
    return (
        f"  {name}: the tip path's sd over the images {v['path_sd_rms_nm']:.1f} nm rms (x "
        f"{v['path_sd_x_rms_nm']:.1f}, y {v['path_sd_y_rms_nm']:.1f} nm; it may be open by "
        f"{v['path_tolerance_nm']:.1f} nm, solver.path_tolerance_nm); knowing the {q.name} would "
        f"settle {v['path_settled_most_pct']:.0f} % of its variance"
    )


def _coverage_words(v: dict) -> str:
    """How well the fit predicted the held-out features' errors
    (:func:`~jaxafm.identify.identifiability.position_check`), in words; '' without them."""
    if "held_out_coverage_90_pct" not in v:
        return ""
    return (
        f"; predicted their errors as {v['held_out_predicted_rms_nm']:.1f} nm rms (they were "
        f"{v['held_out_offsets_rms_nm']:.1f} nm along the scan axes), its 90 % / 50 % ellipses held "
        f"{v['held_out_coverage_90_pct']:.0f} % / {v['held_out_coverage_50_pct']:.0f} % of them"
    )


@dataclasses.dataclass(frozen=True)
class ValidationView:
    """What step A's validation figure shows (:func:`~jaxafm.plots.step_a_validation`) of the
    first scan's trace: nm throughout; the images and chords in the scan's nominal frame
    (``extent`` [x0, x1, y0, y1]), the placed image, sites and errors in the stage frame;
    ``held_ellipse`` (n, 2, 2) nm^2, each corrected held-out error's predicted 90 % ellipse, the
    errors ``x`` with ``x^T E^-1 x <= 1`` (``None``: not computed)."""

    levelled: np.ndarray
    background: np.ndarray
    extent: tuple
    chords_fitted: np.ndarray
    chords_held: np.ndarray
    placed: np.ndarray
    placed_extent: tuple
    sites: np.ndarray
    chord_mid: np.ndarray
    chord_offsets: np.ndarray
    shift_at: np.ndarray
    shift_raw: np.ndarray
    shift_corrected: np.ndarray
    held_sites: np.ndarray
    held_raw: np.ndarray
    held_corrected: np.ndarray
    held_out: bool
    held_ellipse: Optional[np.ndarray] = None


def validation_view(scans: tuple, model: ScanModel, held_out: bool, chords: tuple = ()) -> ValidationView:
    """The first scan's :class:`ValidationView` through the fitted ``model``; with the training
    chords ``chords`` (:attr:`~jaxafm.identify.staged_fit.Identification.chords`), the held-out
    features' predicted 90 % ellipses too."""
    scan = scans[0]
    ft, fr = scan.features()
    image = ft.chords.image
    r = scan.raster
    in_scan = lambda rc: np.asarray(r.origin) + np.asarray(rc)[..., ::-1] * np.asarray(r.pixel_size)
    extent = (r.origin[0] - r.pixel_size[0] / 2, r.origin[0] + r.size[0] - r.pixel_size[0] / 2)
    extent += (r.origin[1] - r.pixel_size[1] / 2, r.origin[1] + r.size[1] - r.pixel_size[1] / 2)
    ij = ft.chord_indices()
    held = (ij.sum(axis=1) % 2 == 1) & held_out
    path, path_retrace = (np.asarray(p) for p in model.paths(scan))
    shift = float(model.edge_delay) / r.sample_time
    tips = np.asarray(model.chord_ends(jnp.asarray(path), jnp.asarray(ft.chords.ends), shift))
    offsets = np.asarray(
        model.chord_offsets(
            jnp.asarray(tips), jnp.asarray(ij, dtype=float), jnp.asarray(ft.chords.along_lines)
        )
    )
    placed, placed_extent = _placed(path, image.levelled * image.height)
    keys = np.unique(ft.ij, axis=0)
    slope = np.asarray(model.chord_slope)
    parts = [[(f.chords.ends, f.chord_indices(), f.chords.along_lines) for f in (ft, fr)]]
    (raw_t, raw_r), (cor_t, cor_r) = (
        nominal_centres((scan,), parts, slope)[0],
        model_centres(model, (scan,), parts)[0],
    )
    fast = r.rotation[:, 0]
    both = [(k, i, j) for i, k in enumerate(raw_t[0]) for j in np.flatnonzero(np.all(raw_r[0] == k, axis=1))]
    at = np.array([raw_t[1][i] @ fast for _, i, _ in both])
    shift_raw = np.array([(raw_r[1][j] - raw_t[1][i]) @ fast for _, i, j in both])
    shift_cor = np.array([(cor_r[1][j] - cor_t[1][i]) @ fast for _, i, j in both])
    test = [[(ft.chords.ends[held], ij[held], ft.chords.along_lines[held])]]
    train = [[(ft.chords.ends[~held], ij[~held], ft.chords.along_lines[~held])]]
    if held.any():
        hk, hc = model_centres(model, (scan,), test)[0][0]
        sites_h = np.asarray(model.lattice.sites(jnp.asarray(hk, dtype=float)))
        raw_e = raw_errors((scan,), train, test, slope)
        cor_e = hc - sites_h
        cov = _held_out_covariances(scans, model, chords, test, hk) if chords else None
        ellipse = None if cov is None else ellipse_quantile(0.9) * cov
    else:
        sites_h = raw_e = cor_e = np.zeros((0, 2))
        ellipse = None
    return ValidationView(
        image.levelled * image.height,
        image.background,
        extent,
        in_scan(ft.chords.ends[~held]),
        in_scan(ft.chords.ends[held]),
        placed,
        placed_extent,
        np.asarray(model.lattice.sites(jnp.asarray(keys, dtype=float))),
        in_scan(ft.chords.ends.mean(axis=1)),
        offsets,
        at,
        shift_raw,
        shift_cor,
        sites_h,
        raw_e,
        cor_e,
        held_out,
        ellipse,
    )


def _held_out_covariances(scans: tuple, model: ScanModel, train: tuple, test: list, keys) -> np.ndarray:
    """The predicted covariance (n, 2, 2) nm^2 of the error of each held-out feature ``keys`` of
    the first scan's trace (its chords ``test``), in the stage frame
    (:func:`~jaxafm.identify.identifiability.point_predictions`, whose offsets run along the
    scan's fast and slow axes); NaN for a feature with chords one way only."""
    got = point_predictions(model, scans, train, chord_data(test, scans, 1))
    turn = np.asarray(scans[0].raster.rotation)  # columns: the fast and the slow axis
    out = np.full((len(keys), 2, 2), np.nan)
    where = {tuple(k): i for i, k in enumerate(got.keys[:, 1:])}
    for n, k in enumerate(np.asarray(keys)):
        if tuple(k) in where:
            out[n] = turn @ got.covariance[where[tuple(k)]] @ turn.T
    return out


def _placed(path: np.ndarray, z: np.ndarray) -> tuple:
    """The image ``z`` (lines, pixels) resampled onto a regular grid of the stage positions
    ``path`` (lines, pixels, 2) nm where its pixels were taken, and the grid's extent."""
    from scipy.interpolate import griddata

    xy = path.reshape(-1, 2)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], z.shape[1]), np.linspace(lo[1], hi[1], z.shape[0]))
    return griddata(xy, z.ravel(), (gx, gy), method="linear"), (lo[0], hi[0], lo[1], hi[1])


def _measure(sim, work, volts, name, fit_s, metrics, rows) -> dict:
    """The compensated scan along ``volts``; its errors go into ``metrics`` and ``rows``."""
    image, inverse_s = compensated_scan(sim, work, volts)
    m = position_errors(image, work) | pitch_uniformity(image, work, float(sim.lattice.pitch[0]))
    metrics |= {f"{name}_{k}": v for k, v in m.items()} | {
        f"{name}_fit_s": fit_s,
        f"{name}_inverse_s": inverse_s,
    }
    rows.append((name, m, fit_s, inverse_s))
    return image


def _table(rows, work: Raster) -> str:
    head = (
        f"{'inverse':24s} {'lin. trace':>10s} {'lin. retrace':>12s} {'x rms':>8s} {'y max':>8s} "
        f"{'pitch std':>9s} {'fit':>7s} {'inverse':>8s}"
    )
    lines = [head, "-" * len(head)]
    for name, m, fit_s, inv_s in rows:
        lines.append(
            f"{name:24s} {m['linearity_error_trace_pct']:9.2f}% {m['linearity_error_retrace_pct']:11.2f}% "
            f"{m['x_rms_error_nm']:6.1f}nm {m['y_max_error_nm']:6.1f}nm {m['pitch_std_trace_pct']:8.2f}% "
            f"{fit_s:6.1f}s {inv_s:7.2f}s"
        )
    lines.append(
        f"linearity: max |x error| over the {work.size[0] / 1e3:g} µm image, % of its width; "
        "pitch std: spread of the local pitch (trace), % of the pitch"
    )
    return "\n".join(lines)
