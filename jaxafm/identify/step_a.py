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
    CalibrationModel,
    CalibrationSolver,
    Grating,
    SimulatedCalibration,
)
from ..instrument.afm import AFM, Raster, RasterScan, default_afm, move, raster_scan
from ..instrument.images import read_image_file
from ..instrument.samples import Lattice, Plane, Tip
from ..model.io import describe, save_model
from ..model.scanner import Scanner
from . import calibration, features
from .inverse import Compensator, train_neural_inverse

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


def simulate_calibration(spec: SimulatedCalibration, grating: Grating, afm: Optional[AFM] = None) -> tuple:
    """The calibration scan of the simulated AFM (``default_afm()`` unless given):
    ``(CalibrationScan, Simulation)``."""
    afm = default_afm() if afm is None else afm
    if spec.withheld:
        afm = afm.without(*spec.withheld)
    p = grating.pitch_nm
    lattice = Lattice(
        jnp.full(2, p),
        jnp.asarray(p / 4),
        jnp.asarray(-100.0 if grating.pits else 100.0),
        jnp.asarray(30.0),
        jnp.zeros(()),
        jnp.array([0.13, 0.07]) * p,
    )
    raster = Raster(spec.size_nm, spec.pixels, spec.pixels, line_rate=spec.line_rate_hz)
    cycle = np.array([[-afm.u_max, -afm.u_max], [afm.u_max, afm.u_max]])
    key = jax.random.key(spec.seed)
    out = raster_scan(afm, lattice, afm.initial_state((0.0, 0.0), 0.0, cycle), raster, key=key)
    scan = calibration.CalibrationScan(
        out.trace,
        out.retrace,
        raster,
        p,
        np.asarray(afm.sensitivity),
        afm.u_max,
        (0.0, 0.0),
        0.0,
        cycle,
        pits=grating.pits,
    )
    return scan, Simulation(afm, lattice, cycle, out, key)


def read_calibration(
    spec: CalibrationImages, grating: Grating, config_path: Path
) -> calibration.CalibrationScan:
    """A measured trace/retrace pair (``data:`` of ``config_path``) as a
    :class:`~jaxafm.identify.calibration.CalibrationScan`."""
    trace, retrace = (
        read_image_file(getattr(spec, k), config_path, f"data.{k}") for k in ("trace", "retrace")
    )
    if trace.shape != retrace.shape or not np.allclose(trace.size, retrace.size):
        raise ValueError(
            f"trace {trace.meta['source']} ({trace.shape} px, {trace.size} nm) and retrace "
            f"{retrace.meta['source']} ({retrace.shape} px, {retrace.size} nm) must cover the same raster"
        )
    raster = Raster(trace.size, trace.shape[1], trace.shape[0], line_rate=spec.line_rate_hz)
    need = np.asarray(trace.size) / 2 / np.asarray(spec.sensitivity_nm_per_v)
    if need.max() > spec.u_max_v:
        raise ValueError(
            f"data.sensitivity_nm_per_v = {spec.sensitivity_nm_per_v} nm/V needs +-{need.max():.3g} V "
            f"to scan the {trace.size[0]:g} x {trace.size[1]:g} nm image, beyond data.u_max_v = "
            f"{spec.u_max_v:g} V: check both against the instrument's scan range"
        )
    return calibration.CalibrationScan(
        trace.z,
        retrace.z,
        raster,
        grating.pitch_nm,
        spec.sensitivity_nm_per_v,
        spec.u_max_v,
        (0.0, 0.0),
        0.0,
        spec.history_v,
        pits=grating.pits,
    )


def calibration_about(model, scan: calibration.CalibrationScan, source: str) -> dict:
    """What a scanner identified from ``scan`` says about itself in its model file
    (:func:`~jaxafm.model.io.describe`): the nominal drive (V) and positions (nm) over the
    calibration raster, over-scan included, as its fitted ranges, and the drive history before it."""
    wanted = scan.raster.wanted().reshape(-1, 2)
    return describe(model, wanted / np.asarray(scan.sensitivity), wanted, history=scan.history, source=source)


def identify_model(
    scan: calibration.CalibrationScan, model: CalibrationModel, solver: CalibrationSolver, log=print
) -> calibration.Identification:
    """Step A's identification (:func:`~jaxafm.identify.calibration.identify`) of the configured
    ``model`` from ``scan`` with the configured ``solver``."""
    return calibration.identify(
        scan,
        kind=model.kind,
        effects=model.effects,
        operators=model.operators,
        deadzones=model.deadzones,
        levels=model.levels,
        solver=solver.name,
        blur_px=solver.blur_px,
        max_steps=solver.max_steps,
        log=log,
    )


def drive_range(scan: calibration.CalibrationScan) -> np.ndarray:
    """The drive (2, 2) V [min, max] per axis that the calibration scan covered, over-scan included."""
    r = scan.raster
    return np.stack(
        [
            scan.volts(np.array([[0, -r.margin], [0, r.pixels - 1 + r.margin]]))[:, 0],
            scan.volts(np.array([[0, 0], [r.lines - 1, 0]]))[:, 1],
        ]
    )


def paper_inverse(poly: calibration.BranchPolynomials, sensitivity, samples: int = 400) -> Callable:
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
    """Linearity error (max |x error| along the fast axis, % of the scan width) and position
    errors (nm) of a scan against its wanted pixels, trace and retrace. The one whole-image
    translation that no image observes (the lattice's phase) is removed: errors are about
    the mean error of trace and retrace together."""
    wanted = np.stack(
        np.meshgrid(
            raster.origin[0] + raster.pixel_size[0] * np.arange(raster.pixels),
            raster.origin[1] + raster.pixel_size[1] * np.arange(raster.lines),
        ),
        -1,
    )
    e = np.stack([np.asarray(out.path_trace), np.asarray(out.path_retrace)]) - wanted
    offset = e.reshape(-1, 2).mean(axis=0)
    e = e - offset
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


def twin_state(scanner: Scanner, scan: calibration.CalibrationScan, cycle: np.ndarray):
    """Where a fitted ``scanner`` stands after replaying every drive the instrument saw: the
    calibration scan, then the initialisation ``cycle`` again (an ``AFMState``)."""
    twin = AFM(scanner, Tip(), jnp.asarray(scan.sensitivity), None, u_max=scan.u_max, dilate=False)
    s = raster_scan(
        twin, Plane(), twin.initial_state(scan.u0, scan.t0, cycle), scan.raster, key=calibration.KEY
    ).state
    return run_cycle(twin, Plane(), s, cycle, calibration.KEY)


def model_compensator(
    model: calibration.ScanModel, scan: calibration.CalibrationScan, sim: Simulation, method: str
) -> Compensator:
    """The model's inverse from the state its twin reaches (:func:`twin_state`), so it knows
    where its plays and creep stand."""
    s = twin_state(model.scanner, scan, sim.cycle)
    return Compensator(
        model.scanner,
        s.scanner,
        s.u,
        drive_range(scan),
        method,
        history=jnp.asarray(sim.cycle),
        u_max=scan.u_max,
    )


def parameters_vs_truth(afm: AFM, model: calibration.ScanModel) -> dict:
    """Fitted against true values for the parameters both have."""
    t, m, out = afm.scanner, model.scanner, {}
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
    Writes ``model_NAME.json`` (the fitted scanner), ``metrics.json`` and figures into ``out``."""
    if cfg.simulate is not None:
        log(
            f"simulating the calibration scan ({cfg.simulate.pixels}² px, {cfg.simulate.size_nm / 1e3:g} µm) ..."
        )
        scan, sim = simulate_calibration(cfg.simulate, cfg.grating)
    else:
        scan, sim = read_calibration(cfg.data, cfg.grating, config_path), None
    scan.features()  # bad images fail here, before the output folder is touched
    prepare()
    metrics: dict = {
        "pixels": scan.raster.pixels,
        "calibration_size_nm": scan.raster.size[0],
        "pitch_nm": cfg.grating.pitch_nm,
    }
    comp = cfg.compensate if sim is not None else None
    if cfg.compensate is not None and sim is None:
        log("measured images: no instrument to re-image with, so no compensation study")
    work = (
        None
        if comp is None
        else Raster(
            comp.scan_fraction * scan.raster.size[0],
            scan.raster.pixels,
            scan.raster.lines,
            line_rate=scan.raster.line_rate,
            overscan=comp.overscan,
        )
    )
    rows, images = [], {}
    if comp is not None:
        images["uncompensated"] = _measure(sim, work, None, "uncompensated", 0.0, metrics, rows)
        if comp.paper_baseline:
            start = time.perf_counter()
            volts = paper_inverse(calibration.fit_polynomials(scan), np.asarray(sim.afm.sensitivity))
            fit_s = time.perf_counter() - start
            log(f"paper: polynomials + networks in {fit_s:.1f} s")
            images["paper (poly + NN)"] = _measure(sim, work, volts, "paper", fit_s, metrics, rows)
    for spec in cfg.models:
        log(f"identifying {spec.name} ({spec.kind}, {', '.join(spec.effects) or 'no other effects'}) ...")
        ident = identify_model(scan, spec, cfg.solver, log)
        if not ident.converged:
            n = sum(not s.converged for s in ident.stages)
            log(
                f"  WARNING: {spec.name}: {n} of {len(ident.stages)} stages stopped at max_steps="
                f"{cfg.solver.max_steps} before converging (last loss {ident.stages[-1].loss:.3e}); "
                "raise solver.max_steps for a tighter fit"
            )
        source = (
            "simulated calibration scan"
            if sim is not None
            else f"{cfg.data.trace.path} / {cfg.data.retrace.path}"
        )
        about = calibration_about(ident.model.scanner, scan, source)
        save_model(ident.model.scanner, out / f"model_{spec.name}.json", about)
        metrics |= {
            f"{spec.name}_fit_s": ident.seconds,
            f"{spec.name}_converged": ident.converged,
            f"{spec.name}_stages": [s.message for s in ident.stages],
            f"{spec.name}_image_rms_pct": 100 * float(np.sqrt(ident.stages[-1].loss)),
        }
        if sim is not None:
            metrics |= {f"{spec.name}_{k}": v for k, v in parameters_vs_truth(sim.afm, ident.model).items()}
        if comp is not None:
            for method in comp.inverses:
                volts = model_compensator(ident.model, scan, sim, method)
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
    return metrics


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
