"""``jaxafm compensate CONFIG``: the drive voltages that make a saved one-axis model follow a
wanted trajectory (the paper's step A, "exerting the input sequence on the piezo-actuator").

The drive starts with the initialisation cycle ``{u2, u1}``: from the lower end ``u2`` of the
input range the model was fitted on, a ramp to its upper end ``u1`` over ``cycle_s``, which
wipes out the actuator's memory (the wiping-out property), so that the model knows its state.
From there the wanted trajectory is inverted through the analytic inverse (a PI or
generalised-PI operator: Kuhnen & Janocha) or the numerical one (any model: per sample from
the plays' state, through creep and rate dependence). The whole drive is then run through the
model: its tracking error is the model-predicted error of the drive. Writes ``drive.csv``
(``t_s,u_v``: what a controller loads), ``tracking.csv``, ``metrics.json`` and
``compensate.png``.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .. import plots
from ..config import CompensateConfig, Trajectory, resolve_data_path
from ..config.names import LENGTH_TO_NM
from ..model.apply import axes_of, predict
from ..model.hysteresis import AbstractHysteresis
from ..model.scanner import Axis
from .fit import error_metrics
from .inverse import invert_axis
from .predict import load


def triangle(spec, centre_nm: float) -> tuple:
    """Times (T,) s and wanted positions (T,) nm: one triangle period per amplitude, each
    from the centre up to ``+A``, down to ``-A`` and back."""
    n = max(4, int(round(spec.period_s * spec.sample_rate_hz)))
    phase = np.arange(n) / n
    unit = np.where(phase < 0.25, 4 * phase, np.where(phase < 0.75, 2 - 4 * phase, 4 * phase - 4))
    x = np.concatenate([centre_nm + a * unit for a in spec.amplitudes_nm] + [[centre_nm]])
    return np.arange(len(x)) / spec.sample_rate_hz, x


def read_trajectory(path: Path) -> tuple:
    """Times (T,) s and wanted positions (T,) nm from a CSV file with a header that names the
    columns with their units: ``t_s`` and ``x_nm`` (or ``x_um``, ``x_µm``, ...).

    Raises:
        ValueError: naming the file: no header with units, non-numeric or non-finite rows, or
            times that do not increase.
    """
    if not path.is_file():
        raise FileNotFoundError(f"trajectory.path: {path} does not exist")
    header = path.read_text(encoding="utf-8", errors="replace").splitlines()[0].split(",")
    names = [h.strip() for h in header]
    units = {n.split("_", 1)[0]: n.split("_", 1)[1] for n in names if "_" in n}
    if units.get("t") != "s" or units.get("x") not in LENGTH_TO_NM:
        raise ValueError(
            f"trajectory.path: {path}: the header {names} must name the columns with their units, "
            f"t_s and x_<unit> (unit one of {', '.join(LENGTH_TO_NM)}), e.g. 't_s,x_nm'"
        )
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as e:
        raise ValueError(f"trajectory.path: {path}: not numeric CSV rows ({e})") from None
    t = data[:, names.index("t_s")]
    x = data[:, names.index(f"x_{units['x']}")] * LENGTH_TO_NM[units["x"]]
    if len(t) < 2 or not (np.isfinite(t).all() and np.isfinite(x).all()) or np.any(np.diff(t) <= 0):
        raise ValueError(f"trajectory.path: {path}: needs 2 or more finite rows with increasing t_s")
    return t - t[0], x


def wanted_trajectory(spec: Trajectory, config_path: Path, fitted_nm: np.ndarray) -> tuple:
    """The configured trajectory, checked against the output range the model was fitted on."""
    if spec.path is not None:
        t, x = read_trajectory(resolve_data_path(spec.path, config_path))
    else:
        centre = float(np.mean(fitted_nm)) if spec.triangle.centre_nm is None else spec.triangle.centre_nm
        t, x = triangle(spec.triangle, centre)
    lo, hi = fitted_nm
    bad = (x < lo) | (x > hi)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(
            f"trajectory: {100 * bad.mean():.1f} % of the wanted positions lie outside the output range "
            f"the model was fitted on, [{lo:.1f}, {hi:.1f}] nm (first: {x[k]:.1f} nm at {t[k]:.3g} s); "
            "a model cannot be trusted beyond its data: keep the trajectory inside it"
        )
    return t, x


def ranges(about: dict, model_path: Path) -> tuple:
    """The input (V) and output (nm) ranges a one-axis model file says it was fitted on."""
    if about.get("input_range_v") is None or about.get("output_range_nm") is None:
        raise ValueError(
            f"model: {model_path} does not say the input and output range it was fitted on (a file "
            "from an older jaxafm): fit it again with `jaxafm fit`"
        )
    return np.asarray(about["input_range_v"][0], dtype=float), np.asarray(
        about["output_range_nm"][0], dtype=float
    )


def choose_method(model, method: str) -> str:
    """``analytic`` for an operator that has an exact inverse (PI, generalised PI, a line),
    else ``numerical``; an explicit ``analytic`` for another model is an error."""
    exact = isinstance(model, AbstractHysteresis) and model.has_inverse
    if method == "analytic" and not exact:
        raise ValueError(
            f"method: analytic needs a PI, generalised-PI or linear operator alone, but the model is a "
            f"{type(model).__name__} with {', '.join(sorted(model.effects)) or 'no effects'}: use numerical"
        )
    return method if method != "auto" else ("analytic" if exact else "numerical")


def drive(model, t: np.ndarray, x: np.ndarray, u_range: np.ndarray, cycle_s: float, method: str) -> tuple:
    """The whole drive: the initialisation cycle, then the inverse of the trajectory.

    Returns:
        Times (C + T,) s, drives (C + T,) V and C, the number of cycle samples.

    Raises:
        ValueError: the trajectory needs a drive outside ``u_range``.
    """
    dt = float(np.median(np.diff(t)))
    n = max(2, int(round(cycle_s / dt)))
    u_cycle = np.linspace(u_range[0], u_range[1], n)
    t_cycle = dt * np.arange(n)
    times = t_cycle[-1] + dt + t
    if method == "analytic":
        history = jnp.asarray(u_range)  # {u2, u1}: what the cycle leaves in the plays
        u = np.asarray(model.inverse()(jnp.asarray(x), history=model(history)))
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
            f"trajectory: the wanted {x[k]:.1f} nm at {t[k]:.3g} s needs a drive beyond the fitted input "
            f"range [{u_range[0]:.3g}, {u_range[1]:.3g}] V ({100 * bad.mean():.1f} % of the samples)"
        )
    return np.concatenate([t_cycle, times]), np.concatenate([u_cycle, u]), n


def run(cfg: CompensateConfig, config_path: Path, out: Path, prepare=lambda: None, log=print) -> dict:
    """Compute the drive, check it through the model, and write the results into ``out``."""
    model, about, model_path = load(cfg.model, config_path)
    if axes_of(model) != 1:
        raise ValueError(f"model: {model_path} is a two-axis scanner; `jaxafm compensate` drives one axis")
    u_range, y_range = ranges(about, model_path)
    t, x = wanted_trajectory(cfg.trajectory, config_path, y_range)
    method = choose_method(model, cfg.method)
    checks = [load(m, config_path) for m in cfg.check_models]
    for other, _, path in checks:
        if axes_of(other) != 1:
            raise ValueError(f"check_models: {path} is a two-axis scanner, not a model of this axis")
    times, u, n = drive(model, t, x, u_range, cfg.cycle_s, method)
    prepare()
    y = predict(model, u, times)[n:]
    span = float(y_range[1] - y_range[0])
    scores = error_metrics(y, x, span)
    metrics = {
        "method": method,
        "samples": len(u),
        "cycle_samples": n,
        "fitted_input_range_v": u_range.tolist(),
        "fitted_output_range_nm": y_range.tolist(),
    } | {f"tracking_{k}": v for k, v in scores.items()}
    log(
        f"{method} inverse of {model_path.name}: {len(t)} samples after a {n}-sample cycle "
        f"[{u_range[0]:.3g} -> {u_range[1]:.3g}] V; model-predicted tracking error rms "
        f"{scores['rms_error_nm']:.3g} nm ({scores['rms_error_pct']:.4f} % of the fitted range), "
        f"max {scores['max_error_nm']:.3g} nm"
    )
    for other, _, path in checks:
        other_scores = error_metrics(predict(other, u, times)[n:], x, span)
        metrics |= {f"check_{path.stem}_tracking_{k}": v for k, v in other_scores.items()}
        log(
            f"  through {path.name}: tracking error rms {other_scores['rms_error_nm']:.3g} nm "
            f"({other_scores['rms_error_pct']:.3f} %), max {other_scores['max_error_nm']:.3g} nm "
            f"({other_scores['max_error_pct']:.3f} %)"
        )
    _csv(out / "drive.csv", {"t_s": times, "u_v": u})
    _csv(out / "tracking.csv", {"t_s": times[n:], "wanted_nm": x, "model_nm": y, "error_nm": y - x})
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    plots.compensated_drive(
        times, u, n, x, y, out / "compensate.png", title=f"{method} inverse of {model_path.name}"
    )
    return metrics


def _csv(path: Path, columns: dict) -> None:
    names = list(columns)
    data = np.stack([np.asarray(columns[k], dtype=float) for k in names], -1)
    np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt="%.10g")
