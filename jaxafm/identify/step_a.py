"""The ``jaxafm calibrate`` run (step A): identify, invert, compensate, measure.

On the simulated AFM the run follows the paper (section III-A): the
initialisation cycle, one trace/retrace image of a lattice of known pitch,
identification, the cycle again, then the lattice re-imaged with each inverse
-- the paper's polynomial + neural network and the end-to-end model's
analytic and numerical inverses. Errors are measured against the true tip
path, which only a simulation knows. On measured images the run identifies
the scanner and reports the fit.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
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
from ..instrument.afm import AFM, Raster, RasterScan, default_afm, move, raster_scan
from ..instrument.images import read_image_file
from ..instrument.samples import Lattice, Plane, Tip
from ..model.io import describe, save_model
from ..model.scanner import Scanner
from . import features
from .calibration_scan import CalibrationScan
from .image_ops import sample_at
from .inverse import Compensator, train_neural_inverse
from .polynomial_baseline import BranchPolynomials, fit_polynomials
from .scan_model import KEY, ScanModel, ScanModelSpec
from .staged_fit import Identification, identify
from .stages import FitPlan

SETTLE_S = 0.5  # each leg of the initialisation cycle, s


@dataclasses.dataclass
class Simulation:
    """The simulated instrument, its lattice, and its calibration scan (``raster_scan``'s
    output: images, true tip paths, the state after it)."""

    afm: AFM
    lattice: Lattice
    cycle: np.ndarray
    measured: RasterScan
    key: jax.Array


def simulate_calibration(
    spec: SimulatedCalibration, grating: CalibrationLattice, afm: Optional[AFM] = None
) -> tuple:
    """The calibration scans of the simulated AFM (``default_afm()`` unless given), one per scan
    angle, each from rest after the initialisation cycle: ``(scans, Simulation)``; the
    simulation's ``measured`` is the last scan."""
    afm = default_afm() if afm is None else afm
    if spec.withheld:
        afm = afm.without(*spec.withheld)
    p = grating.pitch_nm
    lattice = Lattice(
        jnp.full(2, p),
        jnp.asarray(p / 4),
        jnp.asarray(-100.0 if grating.pits else 100.0),
        jnp.asarray(30.0),
        jnp.asarray(np.deg2rad(spec.lattice_rotation_deg)),
        jnp.array([0.13, 0.07]) * p,
    )
    cycle = np.array([[-afm.u_max, -afm.u_max], [afm.u_max, afm.u_max]])
    key, scans, t0 = jax.random.key(spec.seed), [], 0.0
    for k, angle in enumerate(spec.angles_deg):
        raster = Raster(spec.size_nm, spec.pixels, spec.pixels, line_rate=spec.line_rate_hz, angle_deg=angle)
        key_k = key if k == 0 else jax.random.fold_in(key, k)
        out = raster_scan(afm, lattice, afm.initial_state((0.0, 0.0), t0, cycle), raster, key=key_k)
        scans.append(
            CalibrationScan(
                out.trace,
                out.retrace,
                raster,
                p,
                np.asarray(afm.sensitivity),
                afm.u_max,
                (0.0, 0.0),
                t0,
                cycle,
                pits=grating.pits,
            )
        )
        t0 = float(out.state.scanner.t) + SETTLE_S * len(cycle)
    return tuple(scans), Simulation(afm, lattice, cycle, out, key_k)


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


def calibration_about(model, scans: tuple, source: str) -> dict:
    """What a scanner identified from ``scans`` says about itself in its model file
    (:func:`~jaxafm.model.io.describe`): the nominal drive (V) and positions (nm) over the
    calibration rasters, over-scan included, as its fitted ranges, and the drive history before them."""
    wanted = np.concatenate([s.raster.wanted().reshape(-1, 2) for s in scans])
    sens = np.asarray(scans[0].sensitivity)
    return describe(model, wanted / sens, wanted, history=scans[0].history, source=source)


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


def drive_range(scans: tuple) -> np.ndarray:
    """The drive (2, 2) V [min, max] per axis that the calibration scans covered, over-scan included."""
    u = np.concatenate([s.raster.wanted().reshape(-1, 2) / np.asarray(s.sensitivity) for s in scans])
    return np.stack([u.min(axis=0), u.max(axis=0)], axis=-1)


def paper_inverse(poly: BranchPolynomials, sensitivity, samples: int = 400) -> Callable:
    """The paper's inverse: per branch, a network trained on (position, voltage) pairs of the
    polynomial over the drive its feature points covered. Beyond the positions it was
    trained on the drive goes on at the nominal ``sensitivity`` (2,) nm/V: the polynomial
    has no data there."""
    nets, ends = {}, {}
    for name, k in (("x_up", 0), ("x_down", 0), ("y", 1)):
        u = np.linspace(*poly.u_range[k], samples)
        x = poly.branch(name, u)
        nets[name] = train_neural_inverse(x, u)[0]
        ends[name] = (float(x.min()), float(x.max()))

    def inverse(name, x, k):
        inside = jnp.clip(x, *ends[name])
        return nets[name](inside) + (x - inside) / sensitivity[k]

    def volts(xy, t):
        xy = jnp.asarray(xy)
        rising = jnp.diff(xy[:, 0], prepend=xy[0, 0] - 1.0) >= 0
        ux = jnp.where(rising, inverse("x_up", xy[:, 0], 0), inverse("x_down", xy[:, 0], 0))
        return jnp.stack([ux, inverse("y", xy[:, 1], 1)], -1)

    return volts


def position_errors(out: RasterScan, raster: Raster) -> dict:
    """Linearity error (max |error| along the fast axis, % of the scan width) and position
    errors (nm) of a scan against its wanted pixels, trace and retrace, in the scan's frame
    (x: its fast axis, y: its slow axis; the stage's x and y at 0 degrees). The one
    whole-image translation that no image observes (the lattice's phase) is removed: errors
    are about the mean error of trace and retrace together."""
    rows, cols = np.meshgrid(np.arange(raster.lines), np.arange(raster.pixels), indexing="ij")
    wanted = raster.nominal(np.stack([rows.ravel(), cols.ravel()], -1)).reshape(
        raster.lines, raster.pixels, 2
    )
    e = np.stack([np.asarray(out.path_trace), np.asarray(out.path_retrace)]) - wanted
    e = (e - e.reshape(-1, 2).mean(axis=0)) @ raster.rotation  # stage -> scan frame
    width = raster.size[0]
    return {
        "linearity_error_trace_pct": 100 * float(np.abs(e[0, ..., 0]).max()) / width,
        "linearity_error_retrace_pct": 100 * float(np.abs(e[1, ..., 0]).max()) / width,
        "x_rms_error_nm": float(np.sqrt(np.mean(e[..., 0] ** 2))),
        "y_max_error_nm": float(np.abs(e[..., 1]).max()),
        "y_rms_error_nm": float(np.sqrt(np.mean(e[..., 1] ** 2))),
    }


def pitch_uniformity(out: RasterScan, raster: Raster, pitch: float) -> dict:
    """Spread of the local x pitch (% of its mean) in the trace and the retrace image."""
    px = tuple(pitch / p for p in raster.pixel_size)
    result = {}
    for k in ("trace", "retrace"):
        f = features.lattice_features(np.asarray(getattr(out, k)), px, f"{k} image")
        spread = features.pitch_spread(features.local_pitch(f, raster.pixel_size))
        result |= {
            f"pitch_std_{k}_pct": spread["pitch_std_pct"],
            f"pitch_ptp_{k}_pct": spread["pitch_ptp_pct"],
        }
    return result


def run_cycle(afm: AFM, sample, state, cycle: np.ndarray, key):
    """The initialisation cycle from ``state``: a move to each drive of ``cycle`` (H, 2) V in turn,
    each held ``SETTLE_S`` s; returns the state after it."""
    for target in cycle:
        _, state = move(afm, sample, state, target, SETTLE_S, key=key)
    return state


def compensated_scan(sim: Simulation, raster: Raster, volts: Optional[Callable]) -> tuple:
    """The cycle again, then the lattice imaged along the drive ``volts(xy, t)`` (nominal if
    ``None``); returns the scan and the seconds the inverse took for the whole raster."""
    s = run_cycle(sim.afm, sim.lattice, sim.measured.state, sim.cycle, sim.key)
    if volts is None:
        return raster_scan(sim.afm, sim.lattice, s, raster, key=sim.key), 0.0
    seconds = []

    def timed(xy, t):  # the raster's whole drive in one call, timed
        start = time.perf_counter()
        u = jax.block_until_ready(volts(xy, t))
        seconds.append(time.perf_counter() - start)
        return u

    return raster_scan(sim.afm, sim.lattice, s, raster, volts=timed, key=sim.key), seconds[0]


def twin_state(scanner: Scanner, scans: tuple, cycle: np.ndarray):
    """Where a fitted ``scanner`` stands after replaying every drive the instrument saw since
    its last rest: the last calibration scan, then the initialisation ``cycle`` again (an
    ``AFMState``)."""
    scan = scans[-1]
    twin = AFM(scanner, Tip(), jnp.asarray(scan.sensitivity), None, u_max=scan.u_max, dilate=False)
    s = raster_scan(twin, Plane(), twin.initial_state(scan.u0, scan.t0, cycle), scan.raster, key=KEY).state
    return run_cycle(twin, Plane(), s, cycle, KEY)


def model_compensator(model: ScanModel, scans: tuple, sim: Simulation, method: str) -> Compensator:
    """The model's inverse from the state its twin reaches (:func:`twin_state`), so it knows
    where its plays and creep stand."""
    s = twin_state(model.scanner, scans, sim.cycle)
    return Compensator(
        model.scanner,
        s.scanner,
        s.u,
        drive_range(scans),
        method,
        history=jnp.asarray(sim.cycle),
        u_max=scans[0].u_max,
    )


def parameters_vs_truth(sim: Simulation, model: ScanModel) -> dict:
    """Fitted against true values for the parameters both have. The lattice's true rotation is
    measured, as the fit's, from the direction the x piezo moves the tip
    (:meth:`~jaxafm.identify.scan_model.ScanModel.free_parameters`): its stage angle less
    ``atan(coupling.yx)``."""
    afm = sim.afm
    t, m, out = afm.scanner, model.scanner, {}
    if model.rotation_free:
        yx = 0.0 if t.coupling is None else float(t.coupling.yx)
        out["true_lattice_rotation_deg"] = float(np.rad2deg(float(sim.lattice.angle) - np.arctan(yx)))
    pairs = {
        "coupling_xy": lambda s: s.coupling.xy,
        "coupling_yx": lambda s: s.coupling.yx,
        "bow_x_per_nm": lambda s: s.bow.bx,
        "bow_y_per_nm": lambda s: s.bow.by,
    }
    for name, get in pairs.items():
        part = name.split("_")[0]
        if getattr(t, part) is not None and getattr(m, part) is not None:
            out |= {f"true_{name}": float(get(t)), f"fit_{name}": float(get(m))}
    if afm.feedback is not None and model.feedback is not None:
        out |= {
            "true_feedback_tau_s": float(afm.feedback.tau),
            "fit_feedback_tau_s": float(model.feedback.tau),
        }
    for a in ("x", "y"):
        if getattr(t, a).creep is not None and getattr(m, a).creep is not None:
            out |= {
                f"true_creep_per_decade_{a}": _per_decade(getattr(t, a).creep),
                f"fit_creep_per_decade_{a}": _per_decade(getattr(m, a).creep),
            }
    return out


def _per_decade(creep) -> float:
    """Creep per decade of time (fraction) of a logarithmic bank: mean weight x lags per decade."""
    per_decade = 1 / np.diff(np.log10(np.asarray(creep.taus)))[0]
    return float(np.mean(creep.weights) * per_decade)


def run(cfg: CalibrateConfig, config_path: Path, out: Path, prepare=lambda: None, log=print) -> dict:
    """Identify every configured model; on the simulated AFM also compensate and re-image.
    Writes ``model_NAME.json`` (the fitted scanner; not for a model that fails the
    plausibility checks), ``metrics.json`` and figures into ``out``.

    Raises:
        ValueError: after writing the metrics and figures, when a model failed the
            plausibility checks (naming each failure).
    """
    if cfg.simulate is not None:
        sim_spec = cfg.simulate
        log(
            f"simulating the calibration scan(s) ({sim_spec.pixels}² px, {sim_spec.size_nm / 1e3:g} µm, "
            f"scan angle(s) {', '.join(f'{a:g}' for a in sim_spec.angles_deg)} deg) ..."
        )
        scans, sim = simulate_calibration(sim_spec, cfg.grating)
    else:
        scans, sim = read_calibration(cfg.data, cfg.grating, config_path, log), None
    for scan in scans:
        scan.features()  # bad images fail here, before the output folder is touched
    prepare()
    first = scans[0]
    metrics: dict = {
        "pixels": first.raster.pixels,
        "calibration_size_nm": first.raster.size[0],
        "pitch_nm": cfg.grating.pitch_nm,
        "scan_angles_deg": [s.raster.angle_deg for s in scans],
        "sensitivity_nm_per_v": list(first.sensitivity),
    }
    comp = cfg.compensate if sim is not None else None
    if cfg.compensate is not None and sim is None:
        log("measured images: no instrument to re-image with, so no compensation study")
    work = (
        None
        if comp is None
        else Raster(
            comp.scan_fraction * first.raster.size[0],
            first.raster.pixels,
            first.raster.lines,
            line_rate=first.raster.line_rate,
            overscan=comp.overscan,
        )
    )
    rows, images, failed = [], {}, {}
    if comp is not None:
        images["uncompensated"] = _measure(sim, work, None, "uncompensated", 0.0, metrics, rows)
        if comp.paper_baseline and first.raster.angle_deg == 0:
            start = time.perf_counter()
            volts = paper_inverse(fit_polynomials(first), np.asarray(sim.afm.sensitivity))
            fit_s = time.perf_counter() - start
            log(f"paper: polynomials + networks in {fit_s:.1f} s")
            images["paper (poly + NN)"] = _measure(sim, work, volts, "paper", fit_s, metrics, rows)
    source = (
        "simulated calibration scan"
        if sim is not None
        else " + ".join(f"{p.trace.path} / {p.retrace.path}" for _, p in cfg.data.pairs)
    )
    for spec in cfg.models:
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
            scans[0], ident.model, out / f"validation_{spec.name}.png", spec.name, source, cfg.solver.hold_out
        )
        if not ident.plausible:
            failed[spec.name] = ident.failures
            log(f"  FAILED: {spec.name} is not a usable scanner, not saved:")
            for f in ident.failures:
                log(f"    - {f}")
            continue
        about = calibration_about(ident.model.scanner, scans, source)
        save_model(ident.model.scanner, out / f"model_{spec.name}.json", about)
        if comp is not None:
            for method in comp.inverses:
                volts = model_compensator(ident.model, scans, sim, method)
                name = f"{spec.name}_{method}"
                image = _measure(sim, work, volts, name, ident.seconds, metrics, rows)
                if spec is cfg.models[0]:
                    images[f"{spec.name} + {method}"] = image
    if rows:
        log(_table(rows, work))
        plots.compensation(
            images,
            work,
            out / "compensation.png",
            f"Step A on the simulated AFM: lattice of pitch {cfg.grating.pitch_nm:g} nm "
            "without (paper Fig. 6) and with compensation (Fig. 7)",
        )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    if failed:
        raise ValueError(
            "step A failed the plausibility checks, no model file saved for "
            + "; ".join(f"{name}: {', '.join(f)}" for name, f in failed.items())
            + f" (metrics.json and validation figures in {out})"
        )
    return metrics


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
