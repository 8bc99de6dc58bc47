"""The ``jaxafm fit`` run: hysteresis models fitted to one actuator record, validated on held-out data."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import plots
from ..config import ActuatorFitConfig, SimulatedData, resolve_data_path
from ..instrument.records import Record, read_record
from ..model.apply import predict
from ..model.effects import Creep, RateDependence
from ..model.io import describe, save_model
from ..model.scanner import Axis, default_scanner
from .fit import error_metrics, fit_operator, initial_operator

MODEL_CREEP = dict(gamma=0.0, tau_min=0.1, tau_max=100.0)  # the creep stage a fit starts from
MODEL_LAG_S = 0.005  # the rate-dependence lag a fit starts from


def load_record(cfg: ActuatorFitConfig, config_path: Path) -> tuple[Record, object]:
    """The configured record, and the true axis model when it is simulated (else ``None``)."""
    if cfg.data is not None:
        spec = cfg.data.model_dump(exclude={"path"})
        return read_record(resolve_data_path(cfg.data.path, config_path), **spec), None
    return simulate_record(cfg.simulate)


def simulate_record(spec: SimulatedData) -> tuple[Record, Axis]:
    """One axis of :func:`default_scanner` with the chosen effects, driven as ``spec`` says."""
    names = set(spec.effects)
    others = {"hysteresis", "asymmetry", "rate_dependence", "creep"} - names
    truth = default_scanner().without(*others).x
    t = np.arange(int(round(spec.duration_s * spec.sample_rate_hz))) / spec.sample_rate_hz
    envelope = 0.55 + 0.45 * np.cos(2 * np.pi * t / spec.modulation_period_s)
    u = spec.amplitude_v * envelope * np.sin(2 * np.pi * spec.frequency_hz * t)
    clean = np.asarray(truth(jnp.asarray(u), jnp.asarray(t)))
    noise = spec.noise_nm * np.asarray(jax.random.normal(jax.random.key(spec.seed), clean.shape))
    meta = {
        "source": f"simulated: default_scanner().x with {sorted(names)}, noise {spec.noise_nm} nm",
        "samples": len(t),
        "clean_output_nm": clean,
    }
    return Record(t, u, clean + noise, meta), truth


def _build(spec, u, d):
    model = initial_operator(
        spec.kind, u, d, operators=spec.operators, levels=spec.levels, deadzones=spec.deadzones
    )
    if not (spec.creep or spec.rate_dependence):
        return model
    return Axis(
        model,
        rate_dependence=RateDependence(jnp.asarray(MODEL_LAG_S)) if spec.rate_dependence else None,
        creep=Creep.logarithmic(**MODEL_CREEP) if spec.creep else None,
    )


def run(cfg: ActuatorFitConfig, config_path: Path, out: Path, prepare=lambda: None, log=print) -> dict:
    """Fit every configured model, write parameters, ``metrics.json`` and a figure into ``out``.

    Everything is read and checked before ``prepare()`` readies the output folder.
    """
    record, truth = load_record(cfg, config_path)
    if record.u.ndim != 1 or record.d.ndim != 1:
        raise ValueError(
            f"{record.meta['source']}: `jaxafm fit` fits one axis, but the record has "
            f"{record.u.shape[1:] or 1} input and {record.d.shape[1:] or 1} output columns; "
            "map one input and one output column"
        )
    split = record.split(cfg.train_fraction)
    settle = int(round(cfg.settle_s / np.median(np.diff(record.t))))
    if split - settle < 10:
        raise ValueError(
            f"settle_s={cfg.settle_s} s leaves {split - settle} training samples; "
            f"the training part is {record.t[split] - record.t[0]:.3g} s long"
        )
    history = None if cfg.history_v is None else jnp.asarray(cfg.history_v)
    u, d = record.u[:split], record.d[:split]
    starts = {}
    for spec in cfg.models:  # every start before the folder is touched: a falling output fails here
        try:
            starts[spec.name] = _build(spec, u, d)
        except ValueError as e:
            raise ValueError(f"{record.meta['source']}: models.{spec.name}: {e}") from None
    prepare()
    d_range = float(record.d.max() - record.d.min())
    log(
        f"record: {record.meta['source']} - {len(record)} samples, output range {d_range / 1e3:.2f} µm; "
        f"train {split - settle} samples after {settle} settling, hold out {len(record) - split}"
    )
    metrics = {
        "output_range_nm": d_range,
        "train_samples": split - settle,
        "heldout_samples": len(record) - split,
    }
    predictions, rows = {}, []
    for spec in cfg.models:
        extras = "".join(f" + {e}" for e in ("rate_dependence", "creep") if getattr(spec, e))
        log(f"fitting {spec.name} ({spec.kind}{extras}) with {spec.solver_name} ...")
        res = fit_operator(
            starts[spec.name],
            u,
            d,
            t=record.t[:split],
            solver=spec.solver_name,
            max_steps=spec.max_steps,
            history=history,
            settle=settle,
        )
        if not res.converged:
            log(f"  WARNING: {res.message}")
        pred = predict(res.model, record.u, record.t, history)
        predictions[spec.name] = pred
        about = describe(
            res.model,
            u,
            d,
            history=cfg.history_v,
            source=record.meta["source"],
            train_fraction=cfg.train_fraction,
        )
        save_model(res.model, out / f"model_{spec.name}.json", about)
        train = error_metrics(pred[settle:split], record.d[settle:split], d_range)
        held = error_metrics(pred[split:], record.d[split:], d_range)
        row = {f"{spec.name}_train_{k}": v for k, v in train.items()}
        row |= {f"{spec.name}_heldout_{k}": v for k, v in held.items()}
        row |= {
            f"{spec.name}_fit_s": res.seconds,
            f"{spec.name}_solver_steps": res.steps,
            f"{spec.name}_converged": res.converged,
        }
        if truth is not None:  # simulated: distance to the noiseless truth on the held-out part
            clean = record.meta["clean_output_nm"]
            row[f"{spec.name}_heldout_vs_truth_rms_error_pct"] = error_metrics(
                pred[split:], clean[split:], d_range
            )["rms_error_pct"]
        metrics |= row
        rows.append(
            (
                spec.name,
                spec.solver_name,
                train["rms_error_pct"],
                held["rms_error_pct"],
                held["max_error_pct"],
                res.seconds,
                res.converged,
            )
        )
    plots.actuator_fit(record, predictions, split, out / "fit.png", title=Path(record.meta["source"]).name)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    log(_table(rows))
    return metrics


def _table(rows) -> str:
    head = f"{'model':14s} {'solver':32s} {'train rms':>10s} {'held-out rms':>13s} {'held-out max':>13s} {'fit':>7s}"
    lines = [head, "-" * len(head)]
    for name, solver, tr, va, mx, sec, ok in rows:
        lines.append(
            f"{name:14s} {solver:32s} {tr:9.3f}% {va:12.3f}% {mx:12.3f}% {sec:6.1f}s"
            + ("" if ok else "  (not converged)")
        )
    lines.append("errors in % of the output range")
    return "\n".join(lines)
