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

import time
from pathlib import Path
from typing import Optional

import jax
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
from ..identify.calibration_scan import CalibrationScan
from ..identify.image_ops import sample_at
from ..identify.polynomial_baseline import fit_polynomials
from ..identify.scan_model import ScanModel, ScanModelSpec
from ..identify.staged_fit import Identification, identify
from ..identify.stages import FitPlan
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
from .inputs import read_image_file


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
        Raster(spec.size_nm, spec.pixels, spec.pixels, line_rate=spec.line_rate_hz, angle_deg=angle)
        for angle in spec.angles_deg
    ]
    lattice = calibration_lattice(grating.pitch_nm, grating.pits, spec.lattice_rotation_deg)
    return simulate_calibration(afm, lattice, rasters, jax.random.key(spec.seed))


def read_calibration(
    spec: CalibrationImages, grating: CalibrationLattice, config_path: Path, log=print
) -> tuple:
    """The measured trace/retrace pairs (``data`` of ``config_path``) as
    :class:`~jaxafm.identify.calibration_scan.CalibrationScan`s, with the nominal sensitivity
    given or its default (:func:`nominal_sensitivity`)."""
    images, rasters = [], []
    for key, pair in spec.pairs:
        trace, retrace = (
            read_image_file(getattr(pair, k), config_path, f"{key}.{k}") for k in ("trace", "retrace")
        )
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
        rasters.append(
            Raster(
                trace.size,
                trace.shape[1],
                trace.shape[0],
                line_rate=pair.line_rate_hz,
                overscan=pair.overscan,
                direction=pair.lines,
                angle_deg=pair.angle_deg,
            )
        )
    sensitivity = nominal_sensitivity(spec, rasters, log)
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
    scans: tuple, model: CalibrationModel, solver: CalibrationSolver, grating: CalibrationLattice, log=print
) -> Identification:
    """Step A's identification (:func:`~jaxafm.identify.staged_fit.identify`) of the configured
    ``model`` from ``scans`` of ``grating`` with the configured ``solver``."""
    spec = ScanModelSpec(
        model.kind, tuple(model.effects), model.operators, model.deadzones, model.levels, grating.rotation_rad
    )
    max_steps = solver.max_steps if isinstance(solver.max_steps, int) else tuple(solver.max_steps)
    plan = FitPlan(solver.name, tuple(solver.blur_px), solver.coarsen, max_steps, hold_out=solver.hold_out)
    return identify(scans, spec, plan, log=log)


def run(cfg: CalibrateConfig, config_path: Path, out: Output, log=print) -> dict:
    """Identify every configured model; on the simulated AFM also compensate and re-image.
    Writes ``model_NAME.json`` (the fitted scanner; not for a model that fails the
    plausibility checks), ``metrics.json`` and figures into ``out``.

    Raises:
        ValueError: after writing the metrics and figures, when a model failed the
            plausibility checks (naming each failure).
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
        "sensitivity_nm_per_v": list(first.sensitivity),
    }
    comp = cfg.compensate if sim is not None else None
    if cfg.compensate is not None and sim is None:
        log("measured images: no instrument to re-image with, so no compensation study")
    work = None if comp is None else _compensated_raster(first.raster, comp.scan_fraction, comp.overscan)
    rows, images, failed = [], {}, {}
    if comp is not None:
        images = _baselines(sim, work, first, comp.paper_baseline, metrics, rows, log)
    source = "simulated calibration scan" if sim is not None else _files(cfg.data)
    for spec in cfg.models:
        ident = _identify(cfg, spec, scans, sim, source, out, metrics, log)
        if not ident.plausible:
            failed[spec.name] = ident.failures
            continue
        about = calibration_about(ident.model.scanner, scans, source)
        save_model(ident.model.scanner, out.file(f"model_{spec.name}.json"), about)
        for method in comp.inverses if comp is not None else ():
            volts = model_compensator(ident.model, scans, sim, method)
            image = _measure(sim, work, volts, f"{spec.name}_{method}", ident.seconds, metrics, rows)
            if spec is cfg.models[0]:
                images[f"{spec.name} + {method}"] = image
    if rows:
        log(_table(rows, work))
        title = f"Step A on the simulated AFM: lattice of pitch {cfg.grating.pitch_nm:g} nm without (paper Fig. 6) "
        plots.compensation(
            images, work, out.file("compensation.png"), title + "and with compensation (Fig. 7)"
        )
    out.write_metrics(metrics)
    if failed:  # the metrics and figures are written: they say why
        raise ValueError(
            "step A failed the plausibility checks, no model file saved for "
            + "; ".join(f"{name}: {', '.join(f)}" for name, f in failed.items())
            + f" (metrics.json and validation figures in {out.path})"
        )
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
    ident = identify_model(scans, spec, cfg.solver, cfg.grating, log)
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
    log(_validation_line(spec.name, ident))
    _validation_figure(
        scans[0], ident.model, out.file(f"validation_{spec.name}.png"), spec.name, source, cfg.solver.hold_out
    )
    if not ident.plausible:
        log(f"  FAILED: {spec.name} is not a usable scanner, not saved:")
        for f in ident.failures:
            log(f"    - {f}")
    return ident


def identification_metrics(ident: Identification) -> dict:
    """What ``metrics.json`` keeps of one identification: time, convergence, each stage's
    message, acceptance and held-out residual (nm), the held-out validation, the fitted lattice
    rotation, and the plausibility checks."""
    kept = [s for s, ok in zip(ident.stages, ident.accepted) if ok]
    lattice = ident.model.lattice
    out = {
        "fit_s": ident.seconds,
        "converged": ident.converged,
        "stages": [s.message for s in ident.stages],
        "stages_accepted": list(ident.accepted),
        "held_out_nm_by_stage": [None if not np.isfinite(v) else v for v in ident.held_out_nm],
        "image_rms_pct": 100 * float(np.sqrt(kept[-1].loss)),
        "lattice_rotation_deg": float(np.rad2deg(lattice.angle)),
        "plausible": ident.plausible,
        "failures": list(ident.failures),
    }
    return out | ident.validation


def _validation_line(name: str, ident: Identification) -> str:
    v = ident.validation
    if not v.get("held_out_features"):
        return f"  {name}: no features held out"
    return (
        f"  {name}: {v['held_out_features']} held-out features, residual {v['held_out_rms_nm']:.2f} nm rms; "
        f"their local pitch spread {v.get('held_out_pitch_std_raw_pct', float('nan')):.2f} % raw -> "
        f"{v.get('held_out_pitch_std_corrected_pct', float('nan')):.2f} % corrected; lattice rotation "
        f"{float(np.rad2deg(ident.model.lattice.angle)):.3f} deg"
    )


def _validation_figure(scan: CalibrationScan, model: ScanModel, path, name, source, held_out: bool):
    """:func:`~jaxafm.plots.step_a_validation` for the first scan: measured against model
    trace, and its held-out features (the odd sites of a checkerboard) raw and corrected."""
    ft, _ = scan.features()
    held = ft.ij.sum(axis=1) % 2 == 1
    rc, ij = ft.rc[held], ft.ij[held]
    sites = np.asarray(model.lattice.sites(ij))
    corrected = sample_at(model.paths(scan)[0], rc) - sites
    raw = scan.raster.nominal(rc) - sites
    r = scan.raster
    extent = [r.origin[0] - r.pixel_size[0] / 2, r.origin[0] + r.size[0] - r.pixel_size[0] / 2]
    extent += [r.origin[1] - r.pixel_size[1] / 2, r.origin[1] + r.size[1] - r.pixel_size[1] / 2]
    plots.step_a_validation(
        np.asarray(scan.trace),
        np.asarray(model.image(scan).trace),
        extent,
        sites,
        raw - raw.mean(axis=0),
        corrected - corrected.mean(axis=0),
        path,
        f"Step A, {name}, on {source} ({scan.name}): the image fit and its "
        + ("held-out features" if held_out else "features"),
        held_out,
    )


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
