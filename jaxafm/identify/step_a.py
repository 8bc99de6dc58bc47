"""Step A on the simulated AFM (paper section III-A): the calibration scans of a lattice, each
after the initialisation cycle; the fitted scanner's twin that follows every drive the instrument
saw; its inverse as a compensator; the lattice re-imaged along a compensated drive; the paper's
polynomial + neural-network inverse; and the errors that only a simulation, knowing the true tip
path, can measure.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..instrument.afm import AFM, SETTLE_S, Raster, RasterScan, raster_scan, run_cycle
from ..instrument.samples import Lattice, Plane, Tip
from ..model.io import describe
from ..model.scanner import Scanner
from . import features
from .calibration_scan import CalibrationScan, drive_range
from .held_out import fit_sites, path_floor
from .inverse import Compensator, train_neural_inverse
from .polynomial_baseline import BranchPolynomials
from .scan_model import KEY, ScanModel


@dataclasses.dataclass
class Simulation:
    """The simulated instrument, its lattice, and its calibration scan (``raster_scan``'s
    output: images, true tip paths, the state after it)."""

    afm: AFM
    lattice: Lattice
    cycle: np.ndarray
    measured: RasterScan
    key: jax.Array


def calibration_lattice(pitch_nm: float, pits: bool = False, rotation_deg: float = 0.0) -> Lattice:
    """The simulated calibration lattice of ``pitch_nm`` (both axes): round features of radius a
    quarter pitch, 100 nm high (pillars) or deep (``pits``), with 30 nm edges, turned by
    ``rotation_deg`` on the stage, one feature at (0.13, 0.07) pitch."""
    p = pitch_nm
    return Lattice(
        jnp.full(2, p),
        jnp.asarray(p / 4),
        jnp.asarray(-100.0 if pits else 100.0),
        jnp.asarray(30.0),
        jnp.asarray(np.deg2rad(rotation_deg)),
        jnp.array([0.13, 0.07]) * p,
    )


def simulate_calibration(afm: AFM, lattice: Lattice, rasters: Sequence[Raster], key: jax.Array) -> tuple:
    """The calibration scans of ``lattice`` by ``afm``, one along each raster in turn, each from
    rest after the initialisation cycle ``+-u_max`` (the k-th scan's key is ``key`` folded with
    k, the first's ``key`` itself).

    Returns:
        ``(scans, simulation)``: the scans (a tuple of
        :class:`~jaxafm.identify.calibration.CalibrationScan`) and the :class:`Simulation`,
        whose ``measured`` is the last scan.
    """
    pitch, pits = float(lattice.pitch[0]), bool(lattice.depth < 0)
    cycle = np.array([[-afm.u_max, -afm.u_max], [afm.u_max, afm.u_max]])
    scans, t0 = [], 0.0
    for k, raster in enumerate(rasters):
        key_k = key if k == 0 else jax.random.fold_in(key, k)
        out = raster_scan(afm, lattice, afm.initial_state((0.0, 0.0), t0, cycle), raster, key=key_k)
        scans.append(
            CalibrationScan(
                out.trace,
                out.retrace,
                raster,
                pitch,
                np.asarray(afm.sensitivity),
                afm.u_max,
                (0.0, 0.0),
                t0,
                cycle,
                pits=pits,
            )
        )
        t0 = float(out.state.scanner.t) + SETTLE_S * len(cycle)
    return tuple(scans), Simulation(afm, lattice, cycle, out, key_k)


def calibration_about(model, scans: tuple, source: str) -> dict:
    """What a scanner identified from ``scans`` says about itself in its model file
    (:func:`~jaxafm.model.io.describe`): the nominal drive (V) and positions (nm) over the
    calibration rasters, over-scan included, as its fitted ranges, and the drive history before them."""
    wanted = np.concatenate([s.raster.wanted().reshape(-1, 2) for s in scans])
    sens = np.asarray(scans[0].sensitivity)
    return describe(model, wanted / sens, wanted, history=scans[0].history, source=source)


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
                f"true_creep_per_decade_{a}": float(getattr(t, a).creep.per_decade),
                f"fit_creep_per_decade_{a}": float(getattr(m, a).creep.per_decade),
            }
    return out


def true_scan_model(sim: Simulation) -> ScanModel:
    """The simulated instrument as a scan model: its scanner without noise (the tip path the
    simulator drove, to its noise), its z feedback and its lattice."""
    return ScanModel(sim.afm.scanner.without("noise"), sim.afm.feedback, sim.lattice, rotation_free=True)


def held_out_floor(sim: Simulation, scans: tuple) -> float:
    """The held-out residual a perfect model would score on the simulated ``scans`` (nm rms,
    :func:`~jaxafm.identify.held_out.path_floor`) through the simulator's own tip path, with no
    edge delay: the simulated z lag, stepped once a pixel, has all but settled within a pixel at
    1 Hz and 128 px or fewer (docs/step_a.md)."""
    true = true_scan_model(sim)
    return path_floor(scans, [true.paths(scan) for scan in scans])


def tip_path_error(sim: Simulation, model: ScanModel, scans: tuple) -> np.ndarray:
    """How far (2,) nm rms along x and y the fitted ``model`` puts the tip from where the simulator
    put it, over every pixel of every scan, trace and retrace, after the one rigid motion of the
    whole path no image can see (:func:`~jaxafm.identify.held_out.fit_sites`), against
    :func:`true_scan_model`'s."""
    true = true_scan_model(sim)
    stack = lambda m: np.concatenate([np.asarray(p).reshape(-1, 2) for scan in scans for p in m.paths(scan)])
    fitted, path = stack(model), stack(true)
    e = fit_sites(fitted, path)(fitted) - path
    return np.sqrt(np.mean(e**2, axis=0))
