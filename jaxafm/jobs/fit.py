"""``jaxafm fit CONFIG``: hysteresis models fitted to one actuator record (measured or simulated),
validated on its held-out part. Writes ``model_NAME.json`` per model, ``metrics.json`` and
``fit.png``."""

from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import plots
from ..config import ActuatorFitConfig, ModelSpec, SimulatedData
from ..identify.fit import (
    NESTING_TOLERANCE,
    FitResult,
    error_metrics,
    fit_operator,
    initial_operator,
    inside_range,
    range_metrics,
)
from ..identify.uncertainty import posterior_of
from ..instrument.records import Record
from ..model.apply import predict
from ..model.effects import Creep, RateDependence
from ..model.io import describe, save_model
from ..model.posterior import linear_band, linearise
from ..model.scanner import Axis, default_scanner
from .folder import Output
from .inputs import read_record_file

#: the creep stage a fit starts from: 1 % per decade, the low end of published piezo creep
#: (docs/index.md); a start at zero leaves the lags' softplus weights almost no gradient
MODEL_CREEP = dict(gamma=0.01, tau_min=0.1, tau_max=100.0)
MODEL_LAG_S = 0.005  # the rate-dependence lag a fit starts from


def load_record(cfg: ActuatorFitConfig, config_path: Path) -> tuple[Record, object]:
    """The configured record, and the true axis model when it is simulated (else ``None``)."""
    if cfg.data is not None:
        return read_record_file(cfg.data, config_path), None
    return simulate_record(cfg.simulate)


def simulate_record(spec: SimulatedData) -> tuple[Record, Axis]:
    """One axis of :func:`~jaxafm.model.scanner.default_scanner` with the chosen effects, driven
    as ``spec`` says."""
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


def run(cfg: ActuatorFitConfig, config_path: Path, out: Output, log=print) -> dict:
    """Fit every configured model, write parameters, ``metrics.json`` and a figure into ``out``.

    Everything is read and checked before ``out.prepare()`` readies the output folder.
    """
    record, truth = load_record(cfg, config_path)
    split, settle = _split(record, cfg.train_fraction, cfg.settle_s)
    u, d = record.u[:split], record.d[:split]
    starts = {}
    for spec in cfg.models:  # every start before the folder is touched: a falling output fails here
        try:
            starts[spec.name] = _build(spec, u, d)
        except ValueError as e:
            raise ValueError(f"{record.meta['source']}: models.{spec.name}: {e}") from None
    out.prepare()
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
    history = None if cfg.history_v is None else jnp.asarray(cfg.history_v)
    predictions, rows = {}, []
    for spec in cfg.models:
        res = _fit(spec, starts[spec.name], record, split, settle, history, log)
        predictions[spec.name] = pred = predict(res.model, record.u, record.t, history)
        post, spread, post_s = _posterior(res.model, record, split, settle, history)
        about = describe(
            res.model,
            u,
            d,
            history=cfg.history_v,
            source=record.meta["source"],
            train_fraction=cfg.train_fraction,
        )
        out.write(f"model_{spec.name}.json", lambda path: save_model(res.model, path, about, post))
        scores = _scores(spec.name, pred, record, split, settle)
        metrics |= (
            scores
            | _band_scores(spec.name, spread, record.d, split)
            | _rate_lag(spec.name, res.model, record, log)
            | {
                f"{spec.name}_posterior_s": post_s,
                f"{spec.name}_fit_s": res.seconds,
                f"{spec.name}_solver_steps": res.steps,
                f"{spec.name}_converged": res.converged,
            }
        )
        if truth is not None:  # simulated: distance to the noiseless truth on the held-out part
            clean = record.meta["clean_output_nm"]
            metrics[f"{spec.name}_heldout_vs_truth_rms_error_pct"] = error_metrics(
                pred[split:], clean[split:], metrics["output_range_nm"]
            )["rms_error_pct"]
        rows.append((spec.name, spec.solver_name, scores, res.seconds, res.converged))
    metrics |= _nesting(cfg.models, metrics, log)
    title = Path(record.meta["source"]).name
    out.write("fit.png", lambda path: plots.actuator_fit(record, predictions, split, path, title=title))
    out.write_metrics(metrics)
    log(_table(rows))
    return metrics


def _fit(spec: ModelSpec, start, record: Record, split: int, settle: int, history, log) -> FitResult:
    """One configured model fitted from ``start`` to the training part of ``record``."""
    extras = "".join(f" + {e}" for e in ("rate_dependence", "creep") if getattr(spec, e))
    log(f"fitting {spec.name} ({spec.kind}{extras}) with {spec.solver_name} ...")
    res = fit_operator(
        start,
        record.u[:split],
        record.d[:split],
        t=record.t[:split],
        solver=spec.solver_name,
        max_steps=spec.max_steps,
        history=history,
        settle=settle,
    )
    if not res.converged:
        log(f"  WARNING: {res.message}")
    return res


def contains(rich: ModelSpec, plain: ModelSpec) -> bool:
    """Whether the model ``rich`` holds ``plain`` as a special case: the same plays (or levels)
    with its effects and more, or a generalised PI over ``plain``'s PI (dead zones at the
    identity). Its best fit then trains at least as well as ``plain``'s."""
    if rich.name == plain.name or (plain.creep and not rich.creep):
        return False
    if plain.rate_dependence and not rich.rate_dependence:
        return False
    if rich.kind == plain.kind == "preisach":
        return rich.levels == plain.levels
    if rich.kind == plain.kind == "gpi":
        return (rich.operators, rich.deadzones) == (plain.operators, plain.deadzones)
    if plain.kind == "pi" and rich.kind in ("pi", "gpi"):
        return rich.operators == plain.operators
    return plain.kind == rich.kind == "linear"


def _nesting(specs: list, metrics: dict, log) -> dict:
    """Per model, the name of a model it contains that trains better (its training rms more
    than :data:`NESTING_TOLERANCE` below), with a warning: the richer model's best fit cannot
    be worse, so its solver stopped short of it (a start where a gradient vanishes, a step
    limit). ``{name}_trains_worse_than``: that name, or None."""
    out = {}
    for rich in specs:
        rms = metrics[f"{rich.name}_train_rms_error_nm"]
        worse = [
            p.name
            for p in specs
            if contains(rich, p) and rms > (1 + NESTING_TOLERANCE) * metrics[f"{p.name}_train_rms_error_nm"]
        ]
        out[f"{rich.name}_trains_worse_than"] = worse[0] if worse else None
        if worse:
            plain = metrics[f"{worse[0]}_train_rms_error_nm"]
            log(
                f"WARNING: {rich.name} trains worse than {worse[0]}, a model it contains ({rms:.4g} nm "
                f"against {plain:.4g} nm rms): its best fit cannot be, so the solver stopped short of it "
                f"(converged: {metrics[f'{rich.name}_converged']}); raise max_steps or try another solver"
            )
    return out


def _posterior(model, record: Record, split: int, settle: int, history) -> tuple:
    """``(posterior, band, seconds)``: the fitted ``model``'s posterior from its training part
    (:func:`~jaxafm.identify.uncertainty.posterior_of`, AR(1) noise model), its 90 % band over
    the whole record, and the wall time both took (s): one linearisation serves both."""
    start = time.perf_counter()
    u, d = record.u[:split], record.d[:split]
    span, d_range = float(u.max() - u.min()), float(d[settle:].max() - d[settle:].min())
    y, G = linearise(model, span, d_range, record.u, record.t, history)
    post = posterior_of(G[settle:split], y[settle:split] - d[settle:], span, d_range, "ar1")
    return post, linear_band(y, G, post), time.perf_counter() - start


def _split(record: Record, train_fraction: float, settle_s: float) -> tuple:
    """The first held-out sample and the settling samples left out of training.

    Raises:
        ValueError: the record is not one axis, or the settling leaves under 10 training samples.
    """
    if record.u.ndim != 1 or record.d.ndim != 1:
        raise ValueError(
            f"{record.meta['source']}: `jaxafm fit` fits one axis, but the record has "
            f"{record.u.shape[1:] or 1} input and {record.d.shape[1:] or 1} output columns; "
            "map one input and one output column"
        )
    split = record.split(train_fraction)
    settle = int(round(settle_s / np.median(np.diff(record.t))))
    if split - settle < 10:
        raise ValueError(
            f"settle_s={settle_s} s leaves {split - settle} training samples; "
            f"the training part is {record.t[split] - record.t[0]:.3g} s long"
        )
    return split, settle


def _scores(name: str, pred, record: Record, split: int, settle: int) -> dict:
    """A model's errors on the training part (after the settling) and the held-out part, in nm
    and % of the output range; the held-out part's also inside and outside the training part's
    input range, and the share outside (:func:`~jaxafm.identify.fit.range_metrics`)."""
    d_range = float(record.d.max() - record.d.min())
    train = error_metrics(pred[settle:split], record.d[settle:split], d_range)
    held = error_metrics(pred[split:], record.d[split:], d_range)
    u = record.u
    inside = inside_range(u[split:], [[u[:split].min(), u[:split].max()]])
    held |= range_metrics(pred[split:], record.d[split:], inside, d_range)
    return {f"{name}_train_{k}": v for k, v in train.items()} | {
        f"{name}_heldout_{k}": v for k, v in held.items()
    }


def _rate_lag(name: str, model, record: Record, log) -> dict:
    """A fitted rate-dependence lag (s), and whether the record determined it: a lag that ends
    below the sample interval changes no sample (the ZOH step's memory ``exp(-dt / tau)`` is
    below ``1/e``) and predicts what the model without it does; it is reported as not
    identified, with a warning. ``{}`` for a model without one."""
    lag = getattr(model, "rate_dependence", None)
    if lag is None:
        return {}
    tau, dt = float(lag.tau), float(np.median(np.diff(record.t)))
    identified = tau >= dt
    if not identified:
        log(
            f"  WARNING: {name}: rate dependence not identified: its lag ended at {tau * 1e6:.3g} µs, below "
            f"the sample interval {dt * 1e6:.3g} µs, where it changes no sample; the model predicts what "
            "the one without it does (no drive in the record is fast enough to show a lag)"
        )
    return {f"{name}_rate_lag_s": tau, f"{name}_rate_lag_identified": identified}


def _band_scores(name: str, spread, d, split: int) -> dict:
    """How often the held-out measurements fall inside the model's 90 % and 50 % bands, and the
    bands' mean widths (nm)."""
    out = {}
    for level in (0.9, 0.5):
        pct = round(100 * level)
        out[f"{name}_heldout_coverage_{pct}_pct"] = 100 * spread.coverage(d, level, split)
        out[f"{name}_heldout_band_{pct}_width_nm"] = spread.width(level, split)
    return out


def _table(rows) -> str:
    head = f"{'model':14s} {'solver':32s} {'train rms':>10s} {'held-out rms':>13s} {'held-out max':>13s} {'fit':>7s}"
    lines = [head, "-" * len(head)]
    for name, solver, scores, sec, ok in rows:
        tr, va, mx = (
            scores[f"{name}_{k}"]
            for k in ("train_rms_error_pct", "heldout_rms_error_pct", "heldout_max_error_pct")
        )
        lines.append(
            f"{name:14s} {solver:32s} {tr:9.3f}% {va:12.3f}% {mx:12.3f}% {sec:6.1f}s"
            + ("" if ok else "  (not converged)")
        )
    lines.append("errors in % of the output range")
    return "\n".join(lines)
