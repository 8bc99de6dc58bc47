"""``jaxafm compensate CONFIG``: the drive voltages that make a saved model (one axis, or a
two-axis scanner) follow a wanted trajectory, after the initialisation cycle
(:func:`~jaxafm.identify.compensate.drive`). The whole drive is then run through the model: its
tracking error is the model-predicted error of the drive. A model that carries its uncertainty
(one axis, from ``jaxafm fit``) also says how far the actuator itself is expected to stray from
the wanted trajectory under that drive: the 90 % band of its prediction
(:func:`jaxafm.model.posterior.band`), as ``expected_error_90_nm`` (the band's mean half-width)
and ``lower_nm``/``upper_nm`` columns of ``tracking.csv``. Writes ``drive.csv`` (``t_s,u_v``,
or ``t_s,ux_v,uy_v``: what a controller loads), ``tracking.csv``, ``metrics.json`` and
``compensate.png`` (one per axis for a scanner).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import plots
from ..config import CompensateConfig, RasterTrajectory, Trajectory, Triangle, resolve_data_path
from ..config.names import LENGTH_TO_NM
from ..identify.compensate import choose_method, drive
from ..identify.fit import error_metrics
from ..instrument.afm import Raster
from ..instrument.records import write_columns
from ..model.apply import axes_of, predict
from ..model.posterior import band
from .folder import Output
from .inputs import read_model, read_model_and_posterior

AXES = "xy"


def triangle(spec: Triangle, centres: np.ndarray) -> tuple:
    """Times (T,) s and wanted positions (T, A) nm: on every axis, one triangle period per
    amplitude, each from the axis's centre up to ``+A``, down to ``-A`` and back."""
    n = max(4, int(round(spec.period_s * spec.sample_rate_hz)))
    phase = np.arange(n) / n
    unit = np.where(phase < 0.25, 4 * phase, np.where(phase < 0.75, 2 - 4 * phase, 4 * phase - 4))
    wave = np.concatenate([a * unit for a in spec.amplitudes_nm] + [[0.0]])
    return np.arange(len(wave)) / spec.sample_rate_hz, centres + wave[:, None]


def raster(spec: RasterTrajectory, centres: np.ndarray) -> tuple:
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
        ValueError: naming the file: no header with units, a column for an axis the model does
            not drive, non-numeric rows, a non-finite value or times that do not increase (with
            the column and the data row, counted from 1 below the header).
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
    extra = [n for n in names if "_" in n and n.split("_", 1)[0] in tuple(AXES[axes:])]
    if extra:
        raise ValueError(
            f"trajectory.path: {path}: the column {extra[0]} wants a {extra[0][0]} axis, but the model "
            f"drives one axis (x alone): remove the column, or give a two-axis scanner model"
        )
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as e:
        raise ValueError(f"trajectory.path: {path}: not numeric CSV rows ({e})") from None
    columns = ["t_s"] + [f"{a}_{units[a]}" for a in AXES[:axes]]
    used = {c: data[:, names.index(c)] for c in columns}
    _check_rows(path, used)
    t = used["t_s"]
    x = np.stack([used[c] * LENGTH_TO_NM[c.split("_", 1)[1]] for c in columns[1:]], -1)
    return t - t[0], x


def _check_rows(path: Path, columns: dict) -> None:
    """Two rows or more, every value finite, ``t_s`` increasing from row to row.

    Raises:
        ValueError: naming the file, the column and the data row (1: the first below the header).
    """
    if len(columns["t_s"]) < 2:
        raise ValueError(f"trajectory.path: {path}: needs 2 or more data rows, has {len(columns['t_s'])}")
    for name, values in columns.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise ValueError(
                f"trajectory.path: {path}: column {name}, data row {bad[0] + 1}: {values[bad[0]]} is not a "
                f"finite number ({bad.size} such row(s))"
            )
    t = columns["t_s"]
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = back[0] + 1
        raise ValueError(
            f"trajectory.path: {path}: needs increasing t_s, but data row {i + 1} ({t[i]:g} s) is not "
            f"after data row {i} ({t[i - 1]:g} s)"
        )


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


def run(cfg: CompensateConfig, config_path: Path, out: Output, log=print) -> dict:
    """Compute the drive, check it through the model (and ``check_models``), and write the
    results into ``out``."""
    model, about, posterior, model_path = read_model_and_posterior(cfg.model, config_path)
    u_range, y_range = ranges(about, model_path)
    t, x = wanted_trajectory(cfg.trajectory, config_path, y_range)
    method = choose_method(model, cfg.method)
    others = [read_model(m, config_path) for m in cfg.check_models]
    for other, _, path in others:
        if axes_of(other) != axes_of(model):
            raise ValueError(
                f"check_models: {path} drives {axes_of(other)} axis(es), the model {axes_of(model)}"
            )
    times, u, n = drive(model, t, x, u_range, cfg.cycle_s, method)
    out.prepare()
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
        metrics |= _tracking(label, y, x, y_range, tags, log)
    spread = None if posterior is None else band(model, posterior, u[:, 0], times)
    if spread is not None:
        lower, upper = (b[n:] for b in spread.bounds())
        metrics["expected_error_90_nm"] = float(np.mean(upper - lower) / 2)
        log(
            f"  the actuator itself, driven so: within ±{metrics['expected_error_90_nm']:.3g} nm of the model's "
            "path 90 % of the time (the model's uncertainty, mean half-width of its band)"
        )
    y = outputs[""]
    for k, tag in enumerate(tags):
        title = f"{method} inverse of {model_path.name}" + (f", axis {tag[0]}" if tag else "")
        out.write(
            f"compensate{'_' + tag[0] if tag else ''}.png",
            lambda path: plots.compensated_drive(times, u[:, k], n, x[:, k], y[:, k], path, title=title),
        )
    volts = {"u_v": u[:, 0]} if len(tags) == 1 else {f"u{a}_v": u[:, k] for k, a in enumerate(AXES)}
    out.write("drive.csv", lambda path: write_columns(path, {"t_s": times} | volts))
    tracked = {}
    for k, tag in enumerate(tags):
        tracked |= {
            f"wanted_{tag}nm": x[:, k],
            f"model_{tag}nm": y[:, k],
            f"error_{tag}nm": y[:, k] - x[:, k],
        }
    if spread is not None:
        tracked |= {"lower_nm": lower, "upper_nm": upper}
    out.write("tracking.csv", lambda path: write_columns(path, {"t_s": times[n:]} | tracked))
    return out.write_metrics(metrics)


def _tracking(label: str, y: np.ndarray, x: np.ndarray, y_range: np.ndarray, tags: list, log) -> dict:
    """The tracking errors of the output ``y`` (T, A) nm of the model ``label`` names ("": the
    model; ``check_NAME_``: a check model) against the wanted ``x``, per axis, logged."""
    metrics = {}
    for k, tag in enumerate(tags):
        scores = error_metrics(y[:, k], x[:, k], float(np.ptp(y_range[k])))
        metrics |= {f"{label}{tag}tracking_{key}": v for key, v in scores.items()}
        log(
            f"  {'through ' + label[6:-1] if label else 'the model'}{' axis ' + tag[0] if tag else ''}: "
            f"tracking error rms {scores['rms_error_nm']:.3g} nm ({scores['rms_error_pct']:.4f} % of "
            f"the fitted range), max {scores['max_error_nm']:.3g} nm ({scores['max_error_pct']:.4f} %)"
        )
    return metrics


def _output(model, u: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The model's output (T, A) nm for the drive (T, A) V."""
    return predict(model, u if axes_of(model) == 2 else u[:, 0], times).reshape(u.shape)
