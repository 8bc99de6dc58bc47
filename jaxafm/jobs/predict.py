"""``jaxafm predict CONFIG``: a saved model applied to a record's input, and scored where the
record has measured output.

The model runs over the whole record from the history its file names (or the config's
``history_v``); the scores cover the samples from ``evaluate_from`` on, in nm and in % of the
record's output range, overall and per branch (input rising or falling), exactly as
``jaxafm fit`` scores its held-out part. A model from ``jaxafm fit`` carries its uncertainty
(:mod:`jaxafm.model.posterior`): the prediction then has a band at ``level`` (default 90 %),
written as ``lower_nm``/``upper_nm`` columns, scored by how often the measured output falls in
it (``coverage_pct``) and drawn in ``predict_band.png``. Writes ``prediction.csv``,
``metrics.json`` and ``predict.png`` (one figure per axis for a scanner).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .. import plots
from ..config import PredictConfig
from ..identify.fit import error_metrics, inside_range, range_metrics
from ..instrument.records import Record, write_columns
from ..model.apply import axes_of, input_history, predict
from ..model.posterior import band
from .folder import Output
from .inputs import read_model_and_posterior, read_record_file


def fitted_range(u: np.ndarray, about: dict) -> tuple:
    """Which input samples (T,) lie inside the range the model was fitted on, and that range
    ((axes, 2) V); ``(None, None)`` where the file does not say."""
    fitted = about.get("input_range_v")
    if fitted is None:
        return None, None
    return inside_range(u, fitted), np.asarray(fitted)


def branch_metrics(pred: np.ndarray, d: np.ndarray, u: np.ndarray, d_range: float) -> dict:
    """Scores on the rising (du > 0) and falling (du < 0) samples of one axis."""
    du = np.diff(u, prepend=u[0])
    du[0] = du[1] if len(du) > 1 else 0.0
    out = {}
    for name, where in (("rising", du > 0), ("falling", du < 0)):
        if where.sum():
            out |= {f"{name}_{k}": v for k, v in error_metrics(pred[where], d[where], d_range).items()}
    return out


#: the limit (% of the record's output range) of a prediction's rms error on a record most of
#: whose input samples lie outside the range the model was fitted on: past it ``jaxafm predict``
#: refuses (:func:`run`)
EXTRAPOLATION_LIMIT_PCT = 50.0


def run(cfg: PredictConfig, config_path: Path, out: Output, log=print) -> dict:
    """Predict the record's output with the model, score it, and write the results into ``out``.

    Refused: a record most of whose input samples lie outside the range the model file says the
    model was fitted on, where the rms error on an axis exceeds :data:`EXTRAPOLATION_LIMIT_PCT` %
    of the output range. That is no prediction of the model's but its extrapolation, and its
    numbers, once in a results table, would be quoted as the model's accuracy: a warning in a log
    or in ``metrics.json`` is lost on the way. The error names the share outside, the fitted
    range and the error, before anything but the run's manifest is written; a model fitted on
    the record's range predicts it.

    Raises:
        ValueError: naming the key, the file and the value: a record the model cannot take, or
            the extrapolation above.
    """
    model, about, posterior, model_path = read_model_and_posterior(cfg.model, config_path)
    if posterior is None and cfg.level is not None:
        raise ValueError(
            f"level: {cfg.level} asks for a band, but the model file {model_path} holds no uncertainty "
            "(models from `jaxafm fit` carry one; a calibrated scanner or an older file does not): "
            "refit it with `jaxafm fit`, or remove `level`"
        )
    record = read_record_file(cfg.data, config_path, require_output=False)
    axes = axes_of(model)
    if record.u.ndim != axes:
        raise ValueError(
            f"data: the model {model_path.name} drives {axes} axis(es), but the record maps "
            f"{1 if record.u.ndim == 1 else record.u.shape[1]} input column(s)"
        )
    start = record.split(cfg.evaluate_from) if cfg.evaluate_from > 0 else 0
    inside, fitted = fitted_range(record.u, about)
    share = 0.0 if inside is None else float(np.mean(~inside))
    history = input_history(about, cfg.history_v)
    pred = predict(model, record.u, record.t, history).reshape(record.u.shape)
    spread = (
        None if posterior is None else band(model, posterior, record.u, record.t, history, cfg.level or 0.9)
    )
    metrics = {"samples": len(record)} | (
        {} if record.d is None else {"evaluated_samples": len(record) - start}
    )
    metrics["outside_fitted_range_pct"] = 100 * share
    offset = None
    if record.d is not None and cfg.estimate_offset:
        fit_part = slice(0, start) if start else slice(None)
        offset = np.mean(record.d[fit_part] - pred[fit_part], axis=0)
        pred = pred + offset
        if spread is not None:
            spread = dataclasses.replace(spread, mean=spread.mean + offset)
        metrics["offset_nm"] = np.atleast_1d(offset).tolist()
    tags = [None] if axes == 1 else [0, 1]
    scores = [] if record.d is None else [_scores(record, pred, k, start, inside) for k in tags]
    _check_extrapolation(dict(zip(tags, scores)), share, fitted, model_path)
    out.prepare()
    if share > 0:
        log(
            f"WARNING: {100 * share:.1f} % of the record's input samples lie outside the range the "
            f"model was fitted on ({fitted.tolist()} V): expect larger errors there"
        )
    if record.d is None:
        log(f"the record has no output columns: the prediction only ({len(record)} samples)")
    if offset is not None:
        where = "the part before evaluate_from" if start else "the whole record"
        log(f"sensor offset re-estimated on {where}: {np.round(offset, 1)} nm")
    for k, axis_scores in zip(tags, scores):
        metrics |= axis_scores
        _log_and_plot(record, pred, k, start, axis_scores, model_path, out, log)
    if spread is not None:
        metrics |= _band(record, spread, start, model_path, out, log)
    out.write("prediction.csv", lambda path: _write_csv(path, record, pred, spread))
    return out.write_metrics(metrics)


def _band(record: Record, spread, start: int, model_path: Path, out: Output, log) -> dict:
    """The band's level, mean width and (where the record has output) coverage from sample
    ``start`` on, logged and drawn in ``predict_band.png``."""
    pct = f"{100 * spread.level:g}"
    scores = {"band_level": spread.level, "band_width_nm": spread.width(start=start)}
    line = f"{pct} % band: mean width {scores['band_width_nm']:.1f} nm"
    if record.d is not None:
        scores["coverage_pct"] = 100 * spread.coverage(record.d, start=start)
        line += f", holds {scores['coverage_pct']:.1f} % of the measured samples"
        title = f"{model_path.name} on {Path(record.meta['source']).name}"
        out.write("predict_band.png", lambda path: plots.prediction_band(record, spread, start, path, title))
    log(line)
    return scores


def _scores(record: Record, pred: np.ndarray, k, start: int, inside) -> dict:
    """One axis's scores from sample ``start`` on (``k``: the axis of a scanner; ``None``: the
    record's one axis), keys as in ``metrics.json`` (``x_``, ``y_`` before a scanner's): overall,
    per branch, and inside and outside the model's fitted input range where its file says it
    (``inside``: which samples lie in it; :func:`~jaxafm.identify.fit.range_metrics`)."""
    u, d, p = _axis(record, pred, k)
    tag = _tag(k)
    d_range = float(d.max() - d.min())
    scores = error_metrics(p[start:], d[start:], d_range) | branch_metrics(
        p[start:], d[start:], u[start:], d_range
    )
    if inside is not None:
        scores |= range_metrics(p[start:], d[start:], inside[start:], d_range)
    return {f"{tag}output_range_nm": d_range} | {f"{tag}{key}": v for key, v in scores.items()}


def _tag(k) -> str:
    """What the metrics keys of axis ``k`` start with: ``x_``, ``y_``; nothing for the one axis (None)."""
    return "" if k is None else "xy"[k] + "_"


def _axis(record: Record, pred: np.ndarray, k) -> tuple:
    """The input, the measured and the predicted output of axis ``k`` (None: the one axis)."""
    return (record.u, record.d, pred) if k is None else (record.u[:, k], record.d[:, k], pred[:, k])


def _check_extrapolation(scores: dict, share: float, fitted, model_path: Path) -> None:
    """Refuse a prediction that is the model's extrapolation (:func:`run`); ``scores``: axis ->
    its scores (:func:`_scores`).

    Raises:
        ValueError: most input samples outside the fitted range and an rms error above
            :data:`EXTRAPOLATION_LIMIT_PCT` % of the output range.
    """
    if share <= 0.5:
        return
    for k, axis_scores in scores.items():
        key = f"{_tag(k)}rms_error_pct"
        rms = axis_scores[key]
        if rms > EXTRAPOLATION_LIMIT_PCT:
            raise ValueError(
                f"model: {model_path}: {100 * share:.1f} % of the record's input samples lie outside the "
                f"range the model was fitted on ({fitted.tolist()} V), and its rms error there is "
                f"{rms:.4g} % of the record's output range ({key}), past the limit of "
                f"{EXTRAPOLATION_LIMIT_PCT:g} %: that is an extrapolation, not a prediction of this model. "
                "Fit a model on data that cover the record's input range"
            )


def _log_and_plot(
    record: Record, pred: np.ndarray, k, start: int, scores: dict, model_path: Path, out: Output, log
) -> None:
    """Log one axis's scores and write its figure ``predict.png`` (``predict_x.png``, ...)."""
    tag = _tag(k)
    log(
        f"{tag}rms {scores[f'{tag}rms_error_nm']:.1f} nm ({scores[f'{tag}rms_error_pct']:.3f} % of range), "
        f"max {scores[f'{tag}max_error_nm']:.1f} nm ({scores[f'{tag}max_error_pct']:.3f} %) over samples "
        f"{start}..{len(record)}"
    )
    u, d, p = _axis(record, pred, k)
    axis = record if k is None else dataclasses.replace(record, u=u, d=d)
    title = f"{model_path.name} on {Path(record.meta['source']).name}"
    out.write(
        f"predict{'_' + tag[0] if tag else ''}.png",
        lambda path: plots.actuator_fit(axis, {model_path.stem: p}, start, path, title=title),
    )


def _write_csv(path: Path, record: Record, pred: np.ndarray, spread=None) -> None:
    """One row per sample: time, input, predicted output, the band's bounds where the model has
    one, and the measured one and the difference where the record has it."""
    u, p = (np.reshape(a, (len(record), -1)) for a in (record.u, pred))
    d = None if record.d is None else np.reshape(record.d, (len(record), -1))
    columns = {"t_s": record.t}
    for k in range(u.shape[1]):
        a = "" if u.shape[1] == 1 else "xy"[k]
        columns |= {f"u{a}_v": u[:, k], f"predicted{a}_nm": p[:, k]}
        if spread is not None:  # one axis: only `jaxafm fit` models carry an uncertainty
            columns |= dict(zip(("lower_nm", "upper_nm"), spread.bounds()))
        if d is not None:
            columns |= {f"measured{a}_nm": d[:, k], f"error{a}_nm": p[:, k] - d[:, k]}
    write_columns(path, columns)
