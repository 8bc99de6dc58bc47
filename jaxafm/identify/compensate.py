"""``jaxafm compensate CONFIG``: the drive voltages that make a saved model (one axis, or a
two-axis scanner) follow a wanted trajectory (the paper's step A, "exerting the input sequence on
the piezo-actuator").

The drive starts with the initialisation cycle ``{u2, u1}``: from the lower end ``u2`` of the
input range the model was fitted on, a ramp to its upper end ``u1`` over ``cycle_s``, which
wipes out the actuator's memory (the wiping-out property), so that the model knows its state.
From there the wanted trajectory is inverted through the analytic inverse (a PI or
generalised-PI operator, or a scanner whose axes have one: Kuhnen & Janocha) or the numerical
one (any model: per sample from the plays' state, through creep, rate dependence and a scanner's
coupling, bow and mean drift). The whole drive is then run through the
model: its tracking error is the model-predicted error of the drive. Writes ``drive.csv``
(``t_s,u_v``, or ``t_s,ux_v,uy_v``: what a controller loads), ``tracking.csv``, ``metrics.json``
and ``compensate.png`` (one per axis for a scanner).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import plots
from ..config import CompensateConfig, Trajectory, resolve_data_path
from ..config.names import LENGTH_TO_NM
from ..instrument.afm import Raster
from ..instrument.records import write_columns
from ..model.apply import axes_of, predict
from ..model.hysteresis import AbstractHysteresis
from ..model.scanner import Axis, Scanner, mean_scanner
from .fit import error_metrics
from .inverse import Compensator, invert_axis
from .predict import load

AXES = "xy"


def triangle(spec, centres: np.ndarray) -> tuple:
    """Times (T,) s and wanted positions (T, A) nm: on every axis, one triangle period per
    amplitude, each from the axis's centre up to ``+A``, down to ``-A`` and back."""
    n = max(4, int(round(spec.period_s * spec.sample_rate_hz)))
    phase = np.arange(n) / n
    unit = np.where(phase < 0.25, 4 * phase, np.where(phase < 0.75, 2 - 4 * phase, 4 * phase - 4))
    wave = np.concatenate([a * unit for a in spec.amplitudes_nm] + [[0.0]])
    return np.arange(len(wave)) / spec.sample_rate_hz, centres + wave[:, None]


def raster(spec, centres: np.ndarray) -> tuple:
    """Times (T,) s and wanted positions (T, 2) nm of a raster scan, trace and retrace per line."""
    centre = centres if spec.centre_nm is None else spec.centre_nm
    r = Raster(tuple(spec.size_nm), spec.pixels, spec.lines, spec.line_rate_hz, tuple(centre), spec.overscan)
    wanted = r.wanted().reshape(-1, 2)
    return r.sample_time * np.arange(len(wanted)), wanted


def read_trajectory(path: Path, axes: int) -> tuple:
    """Times (T,) s and wanted positions (T, A) nm from a CSV file with a header that names the
    columns with their units: ``t_s``, ``x_nm`` (or ``x_um``, ``x_µm``, ...) and, for a scanner,
    ``y_nm``.

    Raises:
        ValueError: naming the file: no header with units, non-numeric or non-finite rows, or
            times that do not increase.
    """
    if not path.is_file():
        raise FileNotFoundError(f"trajectory.path: {path} does not exist")
    header = path.read_text(encoding="utf-8", errors="replace").splitlines()[0].split(",")
    names = [h.strip() for h in header]
    units = {n.split("_", 1)[0]: n.split("_", 1)[1] for n in names if "_" in n}
    if units.get("t") != "s" or any(units.get(a) not in LENGTH_TO_NM for a in AXES[:axes]):
        columns = ",".join(["t_s"] + [f"{a}_nm" for a in AXES[:axes]])
        raise ValueError(
            f"trajectory.path: {path}: the header {names} must name the columns with their units, "
            f"t_s and {' and '.join(f'{a}_<unit>' for a in AXES[:axes])} (unit one of "
            f"{', '.join(LENGTH_TO_NM)}), e.g. '{columns}'"
        )
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as e:
        raise ValueError(f"trajectory.path: {path}: not numeric CSV rows ({e})") from None
    t = data[:, names.index("t_s")]
    x = np.stack([data[:, names.index(f"{a}_{units[a]}")] * LENGTH_TO_NM[units[a]] for a in AXES[:axes]], -1)
    if len(t) < 2 or not (np.isfinite(t).all() and np.isfinite(x).all()) or np.any(np.diff(t) <= 0):
        raise ValueError(f"trajectory.path: {path}: needs 2 or more finite rows with increasing t_s")
    return t - t[0], x


def wanted_trajectory(spec: Trajectory, config_path: Path, fitted_nm: np.ndarray) -> tuple:
    """The configured trajectory (T, A) nm, checked against the output range ``fitted_nm``
    (A, 2) the model was fitted on."""
    axes, centres = len(fitted_nm), fitted_nm.mean(axis=1)
    if spec.path is not None:
        t, x = read_trajectory(resolve_data_path(spec.path, config_path), axes)
    elif spec.triangle is not None:
        centre = centres if spec.triangle.centre_nm is None else np.full(axes, spec.triangle.centre_nm)
        t, x = triangle(spec.triangle, centre)
    elif axes == 2:
        t, x = raster(spec.raster, centres)
    else:
        raise ValueError(
            "trajectory.raster: a raster needs a two-axis scanner model; this model drives one axis"
        )
    bad = (x < fitted_nm[:, 0]) | (x > fitted_nm[:, 1])
    if bad.any():
        k, a = np.argwhere(bad)[0]
        lo, hi = fitted_nm[a]
        raise ValueError(
            f"trajectory: {100 * bad.any(axis=1).mean():.1f} % of the wanted positions lie outside the "
            f"output range the model was fitted on, {AXES[a]} in [{lo:.1f}, {hi:.1f}] nm (first: "
            f"{x[k, a]:.1f} nm at {t[k]:.3g} s); a model cannot be trusted beyond its data: keep the "
            "trajectory inside it"
        )
    return t, x


def ranges(about: dict, model_path: Path) -> tuple:
    """The input (A, 2) V and output (A, 2) nm ranges a model file says it was fitted on."""
    if about.get("input_range_v") is None or about.get("output_range_nm") is None:
        raise ValueError(
            f"model: {model_path} does not say the input and output range it was fitted on (a file "
            "from an older jaxafm, or a scanner saved without them): fit it again"
        )
    return np.asarray(about["input_range_v"], dtype=float), np.asarray(about["output_range_nm"], dtype=float)


def choose_method(model, method: str) -> str:
    """``analytic`` for an operator that has an exact inverse (PI, generalised PI, a line) or a
    scanner whose axes have one, else ``numerical``; an explicit ``analytic`` for another model
    is an error."""
    if isinstance(model, Scanner):
        exact = all(a.hysteresis.has_inverse for a in (model.x, model.y))
    else:
        exact = isinstance(model, AbstractHysteresis) and model.has_inverse
    if method == "analytic" and not exact:
        raise ValueError(
            f"method: analytic needs PI, generalised-PI or linear hysteresis (on a scanner, on both "
            f"axes; on one axis, without creep or rate dependence), but the model is a "
            f"{type(model).__name__} with {', '.join(sorted(model.effects)) or 'no effects'}: use numerical"
        )
    return method if method != "auto" else ("analytic" if exact else "numerical")


def drive(model, t: np.ndarray, x: np.ndarray, u_range: np.ndarray, cycle_s: float, method: str) -> tuple:
    """The whole drive: the initialisation cycle, then the inverse of the trajectory.

    Arguments:
        model: a one-axis model or a scanner.
        t: times (T,) s; x: wanted positions (T, A) nm.
        u_range: the fitted input range (A, 2) V; the cycle runs from its lower to its upper end.
        cycle_s: the cycle's duration, s.
        method: ``analytic`` or ``numerical``.

    Returns:
        Times (C + T,) s, drives (C + T, A) V and C, the number of cycle samples.

    Raises:
        ValueError: the trajectory needs a drive outside ``u_range``.
    """
    dt = float(np.median(np.diff(t)))
    n = max(2, int(round(cycle_s / dt)))
    u_cycle = np.linspace(u_range[:, 0], u_range[:, 1], n)  # (n, A)
    t_cycle = dt * np.arange(n)
    times = t_cycle[-1] + dt + t
    if isinstance(model, Scanner):
        u = _scanner_inverse(mean_scanner(model), x, times, u_cycle, t_cycle, u_range, method)
    else:
        u = _axis_inverse(model, x[:, 0], times, u_cycle[:, 0], t_cycle, u_range[0], method)[:, None]
    return np.concatenate([t_cycle, times]), np.concatenate([u_cycle, u]), n


def _axis_inverse(model, x, times, u_cycle, t_cycle, u_range, method) -> np.ndarray:
    """One axis's drive (T,) V after the cycle: exact inverse or per-sample numerical inverse."""
    if method == "analytic":
        u = np.asarray(model.inverse()(jnp.asarray(x), history=model(jnp.asarray(u_range))))
        saturated = (u < u_range[0]) | (u > u_range[1])
    else:
        axis = model if isinstance(model, Axis) else Axis(model)
        state = axis.initial_state(u_cycle[0])
        _, state = axis.run(jnp.asarray(u_cycle), jnp.asarray(t_cycle), state, jnp.asarray(t_cycle[0]))
        u, saturated = invert_axis(
            axis, jnp.asarray(x), jnp.asarray(times), state, t_cycle[-1], u_cycle[-1], *u_range
        )
        u, saturated = np.asarray(u), np.asarray(saturated)
    margin = 1e-6 * (u_range[1] - u_range[0])
    bad = saturated & ((u <= u_range[0] + margin) | (u >= u_range[1] - margin))
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(
            f"trajectory: the wanted {x[k]:.1f} nm at {times[k] - times[0]:.3g} s needs a drive beyond the "
            f"fitted input range [{u_range[0]:.3g}, {u_range[1]:.3g}] V ({100 * bad.mean():.1f} % of the samples)"
        )
    return u


def _scanner_inverse(model: Scanner, x, times, u_cycle, t_cycle, u_range, method) -> np.ndarray:
    """A scanner's drive (T, 2) V after the cycle, through step A's :class:`Compensator`."""
    state = model.initial_state(u_cycle[0], t_cycle[0])
    _, state = model.run(jnp.asarray(u_cycle), jnp.asarray(t_cycle), state, jax.random.key(0))
    volts = Compensator(
        model,
        state,
        jnp.asarray(u_cycle[-1]),
        u_range,
        method,
        history=jnp.asarray(u_range.T),  # {u2, u1} per axis: what the cycle leaves in the plays
        u_max=float(np.abs(u_range).max()),
    )
    try:
        return np.asarray(volts(jnp.asarray(x), jnp.asarray(times)))
    except ValueError as e:
        raise ValueError(f"trajectory: {e}") from None


def run(cfg: CompensateConfig, config_path: Path, out: Path, prepare=lambda: None, log=print) -> dict:
    """Compute the drive, check it through the model (and ``check_models``), and write the
    results into ``out``."""
    model, about, model_path = load(cfg.model, config_path)
    u_range, y_range = ranges(about, model_path)
    t, x = wanted_trajectory(cfg.trajectory, config_path, y_range)
    method = choose_method(model, cfg.method)
    others = [load(m, config_path) for m in cfg.check_models]
    for other, _, path in others:
        if axes_of(other) != axes_of(model):
            raise ValueError(
                f"check_models: {path} drives {axes_of(other)} axis(es), the model {axes_of(model)}"
            )
    times, u, n = drive(model, t, x, u_range, cfg.cycle_s, method)
    prepare()
    log(f"{method} inverse of {model_path.name}: {len(t)} samples after a {n}-sample initialisation cycle")
    through = {"": model} | {f"check_{path.stem}_": other for other, _, path in others}
    outputs = {label: _output(m, u, times)[n:] for label, m in through.items()}
    tags = [""] if u.shape[1] == 1 else [f"{a}_" for a in AXES]
    metrics = {
        "method": method,
        "samples": len(u),
        "cycle_samples": n,
        "fitted_input_range_v": u_range.tolist(),
        "fitted_output_range_nm": y_range.tolist(),
    }
    for label, y in outputs.items():
        for k, tag in enumerate(tags):
            scores = error_metrics(y[:, k], x[:, k], float(np.ptp(y_range[k])))
            metrics |= {f"{label}{tag}tracking_{key}": v for key, v in scores.items()}
            log(
                f"  {'through ' + label[6:-1] if label else 'the model'}{' axis ' + tag[0] if tag else ''}: "
                f"tracking error rms {scores['rms_error_nm']:.3g} nm ({scores['rms_error_pct']:.4f} % of "
                f"the fitted range), max {scores['max_error_nm']:.3g} nm ({scores['max_error_pct']:.4f} %)"
            )
    y = outputs[""]
    for k, tag in enumerate(tags):
        plots.compensated_drive(
            times,
            u[:, k],
            n,
            x[:, k],
            y[:, k],
            out / f"compensate{'_' + tag[0] if tag else ''}.png",
            title=f"{method} inverse of {model_path.name}" + (f", axis {tag[0]}" if tag else ""),
        )
    volts = {"u_v": u[:, 0]} if len(tags) == 1 else {f"u{a}_v": u[:, k] for k, a in enumerate(AXES)}
    write_columns(out / "drive.csv", {"t_s": times} | volts)
    tracked = {}
    for k, tag in enumerate(tags):
        tracked |= {
            f"wanted_{tag}nm": x[:, k],
            f"model_{tag}nm": y[:, k],
            f"error_{tag}nm": y[:, k] - x[:, k],
        }
    write_columns(out / "tracking.csv", {"t_s": times[n:]} | tracked)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return metrics


def _output(model, u: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The model's output (T, A) nm for the drive (T, A) V."""
    return predict(model, u if axes_of(model) == 2 else u[:, 0], times).reshape(u.shape)
