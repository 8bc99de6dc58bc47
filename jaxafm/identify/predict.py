"""``jaxafm predict CONFIG``: a saved model applied to a record's input, and scored where the
record has measured output.

The model runs over the whole record from the history its file names (or the config's
``history_v``); the scores cover the samples from ``evaluate_from`` on, in nm and in % of the
record's output range, overall and per branch (input rising or falling), exactly as
``jaxafm fit`` scores its held-out part. Writes ``prediction.csv``, ``metrics.json`` and
``predict.png`` (one figure per axis for a scanner).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from .. import plots
from ..config import PredictConfig, resolve_data_path
from ..instrument.records import Record, read_record, write_columns
from ..model.apply import axes_of, input_history, predict
from ..model.io import read_model_file
from .fit import error_metrics


def load(model_spec: str, config_path: Path) -> tuple:
    """The model file named by a config's ``model`` key: ``(model, about, path)``.

    Raises:
        ValueError: naming the key and the file.
    """
    path = resolve_data_path(model_spec, config_path)
    try:
        return (*read_model_file(path), path)
    except (OSError, ValueError) as e:
        raise ValueError(f"model: {e}") from None


def outside_range(u: np.ndarray, about: dict) -> tuple:
    """The fraction of input samples outside the range the model was fitted on, and the range
    ((axes, 2) V; None where the file does not say)."""
    fitted = about.get("input_range_v")
    if fitted is None:
        return 0.0, None
    lo, hi = np.asarray(fitted, dtype=float).T
    u = np.reshape(u, (len(u), -1))
    return float(np.mean(np.any((u < lo) | (u > hi), axis=1))), np.asarray(fitted)


def branch_metrics(pred: np.ndarray, d: np.ndarray, u: np.ndarray, d_range: float) -> dict:
    """Scores on the rising (du > 0) and falling (du < 0) samples of one axis."""
    du = np.diff(u, prepend=u[0])
    du[0] = du[1] if len(du) > 1 else 0.0
    out = {}
    for name, where in (("rising", du > 0), ("falling", du < 0)):
        if where.sum():
            out |= {f"{name}_{k}": v for k, v in error_metrics(pred[where], d[where], d_range).items()}
    return out


def run(cfg: PredictConfig, config_path: Path, out: Path, prepare=lambda: None, log=print) -> dict:
    """Predict the record's output with the model, score it, and write the results into ``out``."""
    model, about, model_path = load(cfg.model, config_path)
    record = read_record(
        resolve_data_path(cfg.data.path, config_path),
        **cfg.data.model_dump(exclude={"path"}),
        require_output=False,
    )
    axes = axes_of(model)
    if record.u.ndim != axes:
        raise ValueError(
            f"data: the model {model_path.name} drives {axes} axis(es), but the record maps "
            f"{1 if record.u.ndim == 1 else record.u.shape[1]} input column(s)"
        )
    start = record.split(cfg.evaluate_from) if cfg.evaluate_from > 0 else 0
    history = input_history(about, cfg.history_v)
    share, fitted = outside_range(record.u, about)
    prepare()
    if share > 0:
        log(
            f"WARNING: {100 * share:.1f} % of the record's input samples lie outside the range the "
            f"model was fitted on ({fitted.tolist()} V): expect larger errors there"
        )
    pred = predict(model, record.u, record.t, history).reshape(record.u.shape)
    if record.d is None:
        log(f"the record has no output columns: the prediction only ({len(record)} samples)")
        _write_csv(out / "prediction.csv", record, pred)
        return {"samples": len(record), "outside_fitted_range_pct": 100 * share}
    metrics = {
        "samples": len(record),
        "evaluated_samples": len(record) - start,
        "outside_fitted_range_pct": 100 * share,
    }
    if cfg.estimate_offset:
        fit_part = slice(0, start) if start else slice(None)
        offset = np.mean(record.d[fit_part] - pred[fit_part], axis=0)
        pred = pred + offset
        metrics["offset_nm"] = np.atleast_1d(offset).tolist()
        where = "the part before evaluate_from" if start else "the whole record"
        log(f"sensor offset re-estimated on {where}: {np.round(offset, 1)} nm")
    per_axis = (
        [(record.u, record.d, pred)]
        if axes == 1
        else [(record.u[:, k], record.d[:, k], pred[:, k]) for k in range(2)]
    )
    for k, (u, d, p) in enumerate(per_axis):
        tag = "" if axes == 1 else "xy"[k] + "_"
        d_range = float(d.max() - d.min())
        scores = error_metrics(p[start:], d[start:], d_range) | branch_metrics(
            p[start:], d[start:], u[start:], d_range
        )
        metrics |= {f"{tag}output_range_nm": d_range} | {f"{tag}{key}": v for key, v in scores.items()}
        log(
            f"{tag or ''}rms {scores['rms_error_nm']:.1f} nm ({scores['rms_error_pct']:.3f} % of range), "
            f"max {scores['max_error_nm']:.1f} nm ({scores['max_error_pct']:.3f} %) over samples {start}..{len(record)}"
        )
        plots.actuator_fit(
            dataclasses.replace(record, u=u, d=d) if axes == 2 else record,
            {model_path.stem: p},
            start,
            out / f"predict{'_' + tag[0] if tag else ''}.png",
            title=f"{model_path.name} on {Path(record.meta['source']).name}",
        )
    _write_csv(out / "prediction.csv", record, pred)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return metrics


def _write_csv(path: Path, record: Record, pred: np.ndarray) -> None:
    """One row per sample: time, input, predicted output, and the measured one and the difference
    where the record has it."""
    u, p = (np.reshape(a, (len(record), -1)) for a in (record.u, pred))
    d = None if record.d is None else np.reshape(record.d, (len(record), -1))
    columns = {"t_s": record.t}
    for k in range(u.shape[1]):
        a = "" if u.shape[1] == 1 else "xy"[k]
        columns |= {f"u{a}_v": u[:, k], f"predicted{a}_nm": p[:, k]}
        if d is not None:
            columns |= {f"measured{a}_nm": d[:, k], f"error{a}_nm": p[:, k] - d[:, k]}
    write_columns(path, columns)
