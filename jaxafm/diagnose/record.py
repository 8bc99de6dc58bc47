"""Sim-to-real gap diagnosis (``jaxafm diagnose``): where the nominal model misses, which effect is missing.

The nominal model is fitted to the training part of a record (the first
``train_fraction`` of it); each candidate effect is then added -- the same
module the simulator uses -- and the model refitted, warm-started from the
nominal fit. The gap is the rms residual ``sqrt(mean((d - model)^2))`` (nm) on
the held-out part, a later time window the fits never saw. A candidate is
significant when it shrinks the held-out gap by at least ``min_shrink_pct``
*and* the Bayesian information criterion of the training fit,

    BIC = n ln(RSS / n) + k ln n     (n residuals, k free parameters),

falls by at least ``min_delta_bic`` against the nominal model (Kass & Raftery:
10 is "very strong" evidence). Candidates are ranked by held-out shrink; the
verdict is the top significant one, or none.

Hysteresis weights start from a non-negative least-squares solve and are then
fitted unconstrained (outputs are linear in them, so Levenberg-Marquardt needs a
few steps); creep is one logarithmic rate ``gamma >= 0`` per axis.

Actuator records (one or two axes) are modelled as ``Plant``: one
:class:`~jaxafm.scanner.Axis` per output (hysteresis, rate dependence, creep),
then :class:`~jaxafm.effects.Coupling`, :class:`~jaxafm.effects.Bow` and the
deterministic part of :class:`~jaxafm.effects.Drift` (``v t``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from scipy.optimize import nnls

from ..identify.fit import _softplus_inv, evaluator, free_parameters, initial_model
from ..instrument.records import Record, read_record
from ..model.effects import (
    Bow,
    Coupling,
    Creep,
    Drift,
    RateDependence,
    check_effect_names,
)
from ..model.hysteresis import (
    Deadzone,
    GeneralizedPI,
    PrandtlIshlinskii,
    Preisach,
    play,
)
from ..model.scanner import Axis
from . import image as diagnose_image
from . import report as gap_report
from . import withheld

Array = jax.Array
#: Candidates for actuator records; the last two need two axes.
RECORD_CANDIDATES = ("asymmetry", "rate_dependence", "creep", "drift", "coupling", "bow")
TWO_AXIS = ("coupling", "bow")
CREEP_TAUS = (0.1, 100.0)  # s, the creep stage a candidate adds (2 lags per decade)
LAG0_S = 1e-3  # the rate-dependence lag a candidate starts from
GAMMA0 = 1e-4  # the creep rate (per decade) a candidate starts from
MIN_EXPLAINED = 0.5  # the nominal fit must explain this fraction of the output variance


class Plant(eqx.Module):
    """Drive ``u`` (T, k) V -> output (T, k) nm: one Axis per output, then coupling, bow, drift.

    ``p_i = axes[i](u_i, t)``; coupling ``x += xy y, y += yx x``; bow ``x += bx y^2, y += by x^2``;
    drift ``p += v (t - t_0)`` (the Drift module with sigma = 0).
    """

    axes: tuple
    coupling: Optional[Coupling] = None
    bow: Optional[Bow] = None
    drift: Optional[Drift] = None

    @property
    def effects(self) -> frozenset:
        own = {n for n in ("coupling", "bow", "drift") if getattr(self, n) is not None}
        return frozenset(own).union(*(a.effects for a in self.axes))


def _rebuild_extras(plant: Plant, scale: dict):
    """Order-one raw parameters of coupling, bow and drift, and the map back."""
    names = [n for n in ("coupling", "bow", "drift") if getattr(plant, n) is not None]
    raw = {}
    if plant.coupling is not None:
        raw["coupling"] = jnp.stack([plant.coupling.xy, plant.coupling.yx]) / 0.01
    if plant.bow is not None:
        raw["bow"] = jnp.stack([plant.bow.bx, plant.bow.by]) * scale["half_range"] / 0.01
    if plant.drift is not None:
        raw["drift"] = plant.drift.velocity * scale["duration"] / (0.01 * scale["range"])

    def rebuild(p):
        out = {}
        if "coupling" in p:
            out["coupling"] = Coupling(0.01 * p["coupling"][0], 0.01 * p["coupling"][1])
        if "bow" in p:
            b = 0.01 * p["bow"] / scale["half_range"]
            out["bow"] = Bow(b[0], b[1])
        if "drift" in p:
            out["drift"] = Drift(
                p["drift"] * 0.01 * scale["range"] / scale["duration"], jnp.zeros(2), jnp.asarray(1e-3)
            )
        return out

    return {n: raw[n] for n in names}, rebuild


def _scales(u, t, d) -> dict:
    rng = jnp.max(d, 0) - jnp.min(d, 0)
    return {
        "span": jnp.max(u, 0) - jnp.min(u, 0),
        "range_k": rng,
        "range": jnp.max(rng),
        "half_range": jnp.max(rng) / 2,
        "duration": t[-1] - t[0],
    }


def _hysteresis_parameters(h, span, rng):
    """Order-one raw parameters of a PI, generalised PI or Preisach operator, and the map back.

    Unlike :func:`jaxafm.fit.free_parameters`, weights, densities and dead-zone weights are
    not kept positive: the outputs stay linear in them, so Levenberg-Marquardt converges in a
    few steps from any start. A diagnosis compares fits and never inverts them.
    """
    ws = rng / span
    if isinstance(h, PrandtlIshlinskii):
        return (h.weights / ws, h.offset / rng), lambda p: PrandtlIshlinskii(
            h.thresholds, p[0] * ws, p[1] * rng
        )
    if isinstance(h, GeneralizedPI):
        raw, rebuild = _hysteresis_parameters(h.pi, span, rng)
        dz = h.deadzone
        return (raw, dz.upper_weights, dz.lower_weights), lambda p: GeneralizedPI(
            rebuild(p[0]), Deadzone(dz.slope, dz.upper, p[1], dz.lower, p[2], dz.centre)
        )
    tri = np.tril_indices(h.levels)
    scale = rng / len(tri[0])
    return (h.density[tri] / scale, h.offset / rng), lambda p: Preisach(
        jnp.zeros_like(h.density).at[tri].set(p[0] * scale), h.u_min, h.u_max, p[1] * rng, h.smooth
    )


def _axis_parameters(axis: Axis, span, rng):
    """Raw parameters of an Axis without creep: its hysteresis and, if present, its lag's tau."""
    raw_h, rebuild_h = _hysteresis_parameters(axis.hysteresis, span, rng)
    if axis.rate_dependence is None:
        return raw_h, lambda p: Axis(rebuild_h(p))
    raw_l, rebuild_l = free_parameters(axis.rate_dependence, span, rng)
    return (raw_h, raw_l), lambda p: Axis(rebuild_h(p[0]), rate_dependence=rebuild_l(p[1]))


def _model_fn(plant: Plant, u, t, d, history):
    """``(raw0, predict, to_plant)``: order-one parameters of ``plant``, ``predict(raw)`` (T, k) nm
    and the fitted plant. A creep stage is fitted as one logarithmic rate ``gamma`` per axis
    (weights ``gamma / 2`` on lags two per decade, :meth:`Creep.logarithmic`), ``gamma >= 0``."""
    s = _scales(u, t, d)
    inner = [dataclasses.replace(a, creep=None) for a in plant.axes]
    parts = [_axis_parameters(a, s["span"][i], s["range_k"][i]) for i, a in enumerate(inner)]
    evals = [
        evaluator(a, u[:, i], t, None if history is None else history[:, i]) for i, a in enumerate(inner)
    ]
    creeps = [a.creep for a in plant.axes]
    gamma0 = tuple(_softplus_inv(2 * c.weights[0] / 0.01) for c in creeps if c is not None)
    extras0, rebuild_extras = _rebuild_extras(plant, s)
    raw0 = (tuple(p[0] for p in parts), extras0, gamma0)

    def axes(raw):
        gammas = iter(0.01 * jax.nn.softplus(g) for g in raw[2])
        return tuple(
            dataclasses.replace(
                rb(r), creep=None if c is None else Creep(c.taus, jnp.full_like(c.taus, next(gammas) / 2))
            )
            for (_, rb), r, c in zip(parts, raw[0], creeps)
        )

    def predict(raw):
        cols = []
        for f, a in zip(evals, axes(raw)):
            v = f(dataclasses.replace(a, creep=None))
            cols.append(v if a.creep is None else a.creep(v, t))
        p = jnp.stack(cols, -1)
        ex = rebuild_extras(raw[1])
        if "coupling" in ex:
            p = ex["coupling"](p)
        if "bow" in ex:
            p = ex["bow"](p)
        if "drift" in ex:
            p = p + ex["drift"](t, jax.random.key(0))[:, : p.shape[1]]
        return p

    return raw0, predict, lambda raw: Plant(axes(raw), **rebuild_extras(raw[1]))


@eqx.filter_jit
def _fit(plant: Plant, u, t, d, weight, history, max_steps: int):
    """Levenberg-Marquardt fit of ``plant`` to ``d`` where ``weight`` is 1 (0: not fitted).

    Compiled once per plant structure and data shape; the data are arguments.
    Returns the fitted plant, its prediction (T, k) nm and the solver's step count.
    """
    raw0, predict, to_plant = _model_fn(plant, u, t, d, history)
    scale = _scales(u, t, d)["range"]

    def residuals(raw, _):
        return ((predict(raw) - d) * weight[:, None] / scale).ravel()

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9, linear_solver=lx.Normal(lx.Cholesky()))
    sol = optx.least_squares(residuals, solver, raw0, max_steps=max_steps, throw=False)
    return to_plant(sol.value), predict(sol.value), sol.stats["num_steps"]


def n_parameters(plant: Plant, u, t, d) -> int:
    """Free parameters of ``plant`` (what the fit moves)."""
    raw0 = _model_fn(plant, jnp.asarray(u), jnp.asarray(t), jnp.asarray(d), None)[0]
    return int(ravel_pytree(raw0)[0].size)


@dataclasses.dataclass(frozen=True)
class Nominal:
    """The nominal model: hysteresis ``kind`` (pi, gpi, preisach) and its other ``effects``."""

    kind: str = "pi"
    effects: tuple = ("hysteresis",)
    operators: int = 20
    deadzones: int = 3
    levels: int = 20


def nominal_plant(spec: Nominal, u: np.ndarray, d: np.ndarray, train: np.ndarray, history=None) -> Plant:
    """The nominal model's start for outputs ``d`` (T, k) nm from drives ``u`` (T, k) V: the
    hysteresis fitted to the ``train`` samples by non-negative least squares (see :func:`_nnls_start`)."""
    kind = "gpi" if spec.kind == "pi" and "asymmetry" in spec.effects else spec.kind
    axes = []
    for i in range(u.shape[1]):
        try:
            h = initial_model(
                kind,
                u[train, i],
                d[train, i],
                operators=spec.operators,
                levels=spec.levels,
                deadzones=spec.deadzones,
            )
        except ValueError as e:
            raise ValueError(
                f"the nominal model ({spec.kind}) cannot be fitted to output {i + 1}: {e}"
            ) from None
        h = _nnls_start(h, u[:, i], d[:, i], train, None if history is None else history[:, i])
        axes.append(_with_stages(Axis(h), spec.effects))
    plant = Plant(tuple(axes))
    for name in ("coupling", "bow", "drift"):
        if name in spec.effects:
            plant = _add(plant, name, u, d)
    return plant


def _nnls_start(h, u, d, train, history):
    """PI and Preisach outputs are linear in their weights (density) for fixed thresholds:
    ``d ~ offset + A w``, ``w >= 0``, solved exactly (scipy ``nnls``) so the gradient fit starts
    at the optimum instead of crawling out of ``softplus``'s flat region."""
    pi = h.pi if isinstance(h, GeneralizedPI) else h
    u, history = jnp.asarray(u), None if history is None else jnp.asarray(history)
    if isinstance(h, Preisach):
        tri = np.tril_indices(h.levels)
        a = np.asarray(h.relay_states(play(u, h.radii(), history)))[:, tri[0], tri[1]]
    else:
        a = np.asarray(play(u, pi.radii(), history))
    a = np.concatenate([a, np.ones((len(u), 1)), -np.ones((len(u), 1))], 1)[train]
    scale = np.linalg.norm(a, axis=0) + 1e-12
    w = nnls(a / scale, np.asarray(d)[train], maxiter=50 * a.shape[1])[0] / scale
    floor = 1e-6 * np.max(w[:-2])  # softplus needs > 0
    weights, offset = jnp.asarray(np.maximum(w[:-2], floor)), jnp.asarray(w[-2] - w[-1])
    if isinstance(h, Preisach):
        density = jnp.zeros_like(h.density).at[tri].set(weights)
        return Preisach(density, h.u_min, h.u_max, offset, h.smooth)
    pi = PrandtlIshlinskii(pi.thresholds, weights, offset)
    return dataclasses.replace(h, pi=pi) if isinstance(h, GeneralizedPI) else pi


def _with_stages(axis: Axis, names) -> Axis:
    lag = RateDependence(jnp.asarray(LAG0_S)) if "rate_dependence" in names else axis.rate_dependence
    creep = Creep.logarithmic(GAMMA0, *CREEP_TAUS) if "creep" in names else axis.creep
    return Axis(axis.hysteresis, rate_dependence=lag, creep=creep)


def not_applicable(name: str, plant: Plant, spec: Nominal) -> Optional[str]:
    """Why candidate ``name`` cannot be tried on this record and model, or ``None``."""
    if name in plant.effects or name in spec.effects:
        return "already in the nominal model"
    if name in ("feedback_lag", "tip"):
        return "an imaging effect: it needs AFM images, not an actuator record"
    if name == "noise":
        return "white noise is what the residual should be; it is no candidate"
    if name in TWO_AXIS and len(plant.axes) < 2:
        return "needs a record with two axes (t, ux, uy, x, y)"
    if name == "asymmetry" and spec.kind == "preisach":
        return "a Preisach density holds its own asymmetry"
    return None


def _add(plant: Plant, name: str, u, d) -> Plant:
    """``plant`` plus the candidate ``name``, started where it changes nothing."""
    if name in ("rate_dependence", "creep"):
        return dataclasses.replace(plant, axes=tuple(_with_stages(a, [name]) for a in plant.axes))
    if name == "asymmetry":
        axes = []
        for i, a in enumerate(plant.axes):
            steps = (np.arange(3) + 1) / 4 * np.ptp(d[:, i]) / 2
            dz = Deadzone.identity(-steps, steps, centre=float(np.mean(d[:, i])))
            axes.append(dataclasses.replace(a, hysteresis=GeneralizedPI(a.hysteresis, dz)))
        return dataclasses.replace(plant, axes=tuple(axes))
    zero = jnp.zeros(())
    module = {
        "coupling": lambda: Coupling(zero, zero),
        "bow": lambda: Bow(zero, zero),
        "drift": lambda: Drift(jnp.zeros(2), jnp.zeros(2), jnp.asarray(1e-3)),
    }[name]()
    return dataclasses.replace(plant, **{name: module})


@dataclasses.dataclass(frozen=True)
class Rules:
    """When a candidate counts: held-out gap shrinks by ``min_shrink_pct`` % and the training
    BIC falls by ``min_delta_bic``; fits stop after ``max_steps`` Levenberg-Marquardt steps."""

    min_shrink_pct: float = 5.0
    min_delta_bic: float = 10.0
    max_steps: int = 300


def _columns(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a[:, None] if a.ndim == 1 else a


def _fit_report(plant: Plant, record: Record, train: np.ndarray, split: int, history, rules: Rules) -> dict:
    """Fit ``plant`` on the ``train`` samples; residuals ``d - model`` (T, k) nm, gaps and BIC."""
    u, d = _columns(record.u), _columns(record.d)
    fitted, pred, steps = _fit(
        plant,
        jnp.asarray(u),
        jnp.asarray(record.t),
        jnp.asarray(d),
        jnp.asarray(train, dtype=float),
        history,
        rules.max_steps,
    )
    r = d - np.asarray(pred)
    n = int(train.sum()) * d.shape[1]
    rss = float(np.sum(r[train] ** 2))
    k = n_parameters(plant, u, record.t, d)
    return {
        "plant": fitted,
        "residual": r,
        "steps": int(steps),
        "parameters": k,
        "train_rms_nm": float(np.sqrt(rss / n)),
        "heldout_gap_nm": float(np.sqrt(np.mean(r[split:] ** 2))),
        "bic": n * np.log(max(rss, 1e-300) / n) + k * np.log(n),
    }


def diagnose_record(
    record: Record,
    spec: Nominal,
    candidates,
    train_fraction: float = 0.6,
    settle: int = 0,
    history=None,
    rules: Rules = Rules(),
    log=print,
) -> dict:
    """Fit the nominal model, then nominal + each candidate; rank the candidates (module docstring).

    Returns the nominal fit, the candidate rows (best first), the skipped
    candidates with the reason, the verdict (a name or ``None``) and the split index.
    """
    check_effect_names(candidates, "candidates")
    split = record.split(train_fraction)
    u, d = _columns(record.u), _columns(record.d)
    train = np.zeros(len(record), bool)
    train[settle:split] = True
    hist = (
        None
        if history is None
        else jnp.broadcast_to(jnp.asarray(history, dtype=float)[:, None], (len(history), u.shape[1]))
    )
    nominal = _fit_report(nominal_plant(spec, u, d, train, hist), record, train, split, hist, rules)
    _check_fitted(nominal, d, train, spec)
    log(
        f"nominal ({spec.kind} + {', '.join(spec.effects)}): train rms {nominal['train_rms_nm']:.3g} nm, "
        f"held-out gap {nominal['heldout_gap_nm']:.3g} nm"
    )
    rows, skipped = [], {}
    for name in candidates:
        why = not_applicable(name, nominal["plant"], spec)
        if why:
            skipped[name] = why
            continue
        fit = _fit_report(
            _add(nominal["plant"], name, u[:split], d[:split]), record, train, split, hist, rules
        )
        rows.append(gap_report.candidate_row(name, nominal, fit, rules, solver_steps=fit["steps"]))
        log(gap_report.candidate_line(rows[-1]))
    rows.sort(key=lambda r: -r["shrink_pct"])
    verdict = next((r["effect"] for r in rows if r["significant"]), None)
    return {
        "nominal": nominal,
        "candidates": rows,
        "skipped": skipped,
        "verdict": verdict,
        "split": split,
        "train": train,
    }


def _check_fitted(nominal: dict, d: np.ndarray, train: np.ndarray, spec: Nominal) -> None:
    """Raise when the nominal model explains less than :data:`MIN_EXPLAINED` of the output variance."""
    r = nominal["residual"][train]
    explained = 1 - np.sum(r**2) / np.sum((d[train] - d[train].mean(0)) ** 2)
    if not np.isfinite(explained) or explained < MIN_EXPLAINED:
        raise ValueError(
            f"the nominal model ({spec.kind}) cannot be fitted to this record: it explains {100 * explained:.0f} % "
            f"of the output variance (at least {100 * MIN_EXPLAINED:.0f} % needed); check that the input and "
            "output columns belong together (data.input_columns, data.output_columns) and that the output "
            "follows the input"
        )


def _load(cfg, config_path: Path) -> Record:
    from ..config import resolve_data_path

    if cfg.data is None:
        s = cfg.simulate
        return withheld.simulate_record(
            s.withheld, s.magnitude, s.seed, s.duration_s, s.sample_rate_hz, s.noise_nm
        )
    spec = cfg.data.model_dump(exclude={"path"})
    path = resolve_data_path(cfg.data.path, config_path)
    if spec["output_unit"] is None and spec["output_columns"] is not None:
        raise ValueError(
            f"{path}: the record's output unit is missing: set data.output_unit in {config_path} "
            "(e.g. output_unit: um)"
        )
    record = read_record(path, **spec)
    return dataclasses.replace(record, meta=record.meta | {"source": cfg.data.path})  # as the config gives it


def run(cfg, config_path: Path, out: Path, prepare=lambda: None, log=print) -> dict:
    """Diagnose the configured record or image; write ``diagnosis.json``, ``metrics.json``,
    ``residuals.png`` and ``report.md`` into ``out``. Everything is read and checked before ``prepare()``."""
    rules = Rules(cfg.min_shrink_pct, cfg.min_delta_bic, cfg.max_steps)
    if cfg.image is not None:
        return _run_image(cfg, Path(config_path), Path(out), rules, prepare, log)
    if cfg.scans is not None:
        return _run_scans(cfg, Path(config_path), Path(out), rules, prepare, log)
    record = _load(cfg, Path(config_path))
    try:
        split = record.split(cfg.train_fraction)
    except ValueError as e:
        raise ValueError(f"{e}: give a longer record, or change train_fraction in {config_path}") from None
    settle = int(round(cfg.settle_s / np.median(np.diff(record.t))))
    if split - settle < 10:
        raise ValueError(
            f"settle_s={cfg.settle_s} s leaves {split - settle} training samples: lower settle_s "
            f"or raise train_fraction in {config_path}"
        )
    spec = Nominal(
        cfg.nominal.kind,
        tuple(cfg.nominal.effects),
        cfg.nominal.operators,
        cfg.nominal.deadzones,
        cfg.nominal.levels,
    )
    d = _columns(record.d)
    history = None if cfg.history_v is None else np.asarray(cfg.history_v, dtype=float)
    log(
        f"record: {record.meta['source']} - {len(record)} samples x {d.shape[1]} output(s); train "
        f"{split - settle}, hold out {len(record) - split}"
    )
    res = diagnose_record(record, spec, cfg.candidates, cfg.train_fraction, settle, history, rules, log)
    prepare()
    return gap_report.write_outputs(res, record, _model_name(spec), rules, settle, Path(out), log)


def _run_image(cfg, config_path: Path, out: Path, rules: Rules, prepare, log) -> dict:
    from ..config import resolve_data_path
    from ..instrument.images import read_image

    check_effect_names(cfg.candidates, "candidates")
    image = read_image(resolve_data_path(cfg.image.path, config_path))
    image = dataclasses.replace(image, meta=image.meta | {"source": cfg.image.path})  # as the config gives it
    log(
        f"image: {image.meta.get('source')} - {image.shape[0]} x {image.shape[1]} px; nominal: hysteresis-only "
        "scanner (fast-axis nonlinearity)"
    )
    res = diagnose_image.diagnose_image(image, cfg.candidates, cfg.train_fraction, rules)
    for c in res["candidates"]:
        log(gap_report.candidate_line(c))
    prepare()
    return diagnose_image.write_outputs(res, image, rules, out, log)


def _run_scans(cfg, config_path: Path, out: Path, rules: Rules, prepare, log) -> dict:
    from . import scans as S

    sc = cfg.scans
    grating = withheld.SIM_GRATING if sc.grating is None else S.GratingSpec(**sc.grating.model_dump())
    res = S.diagnose_scans(
        _scan_pairs(sc, config_path, log), grating, cfg.candidates, cfg.train_fraction, rules
    )
    n = res["nominal"]
    log(f"nominal: train rms {n['train_rms_nm']:.3g} nm, held-out gap {n['heldout_gap_nm']:.3g} nm")
    for c in res["candidates"]:
        log(gap_report.candidate_line(c))
    prepare()
    return S.write_outputs(res, rules, out, log)


def _scan_pairs(sc, config_path: Path, log) -> list:
    """The configured trace/retrace pairs: simulated, or read from files."""
    from ..config import resolve_data_path
    from ..instrument.images import read_image
    from .scans import ScanPair

    if sc.simulate is not None:
        s = sc.simulate
        what = (
            f" with {s.withheld} {s.magnitude:g} {withheld.SCAN_UNITS[s.withheld]}"
            if s.withheld
            else " (a control)"
        )
        log(f"simulating trace/retrace pairs at {', '.join(f'{r:g}' for r in s.line_rates_hz)} Hz{what}")
        return withheld.simulate_scans(
            s.withheld, s.magnitude, s.seed, s.line_rates_hz, s.lines, s.pixels, noise_nm=s.noise_nm
        )
    pairs = []
    for i, p in enumerate(sc.pairs):
        tr, re = (read_image(resolve_data_path(f, config_path)) for f in (p.trace, p.retrace))
        if tr.shape != re.shape:
            raise ValueError(
                f"{config_path}: scans.pairs[{i}]: the trace ({tr.shape}) and retrace ({re.shape}) "
                "images differ in size"
            )
        dt = 1.0 / (2 * p.line_rate_hz * tr.shape[1] * (1 + 2 * p.overscan))  # s between two pixels
        pairs.append(ScanPair(np.asarray(tr.z), np.asarray(re.z), tuple(tr.pixel_size), dt, p.trace))
    return pairs


def _model_name(spec: Nominal) -> str:
    extra = [e for e in spec.effects if e != "hysteresis"]
    return (
        {"pi": "symmetric PI", "gpi": "generalised PI", "preisach": "Preisach"}[spec.kind]
        + f" ({spec.operators if spec.kind != 'preisach' else spec.levels} "
        + ("plays" if spec.kind != "preisach" else "levels")
        + ")"
        + "".join(f" + {e}" for e in extra)
    )
