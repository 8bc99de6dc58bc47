"""The model of an actuator record and its fit: ``Plant``, the nominal model's start, a candidate added.

Actuator records (one or two axes) are modelled as :class:`Plant`: one
:class:`~jaxafm.model.scanner.Axis` per output (hysteresis, rate dependence, creep), then
:class:`~jaxafm.model.effects.Coupling`, :class:`~jaxafm.model.effects.Bow` and the
deterministic part of :class:`~jaxafm.model.effects.Drift` (``v t``) -- the same modules the
simulator uses. Each candidate effect is added where it changes nothing (:func:`with_effect`),
so its refit starts from the nominal fit.

Hysteresis weights start from a non-negative least-squares solve (:func:`_nnls_start`) and are
then fitted unconstrained (outputs are linear in them, so Levenberg-Marquardt needs a few
steps); creep is one logarithmic rate ``gamma >= 0`` per axis. Units: nm, s, V.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from scipy.optimize import nnls

from ..config import DiagnoseNominal as Nominal  # the nominal model: its config schema
from ..identify.fit import evaluator, free_parameters, initial_model
from ..model.effects import Bow, Coupling, Creep, Drift, RateDependence
from ..model.hysteresis import Deadzone, GeneralizedPI, softplus_inverse
from ..model.scanner import Axis

Array = jax.Array
CREEP_TAUS = (0.1, 100.0)  # s, the creep stage a candidate adds (2 lags per decade)
LAG0_S = 1e-3  # the rate-dependence lag a candidate starts from
GAMMA0 = 1e-4  # the creep rate (per decade) a candidate starts from


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


def _axis_parameters(axis: Axis, span, rng):
    """Raw parameters of an Axis without creep: its hysteresis and, if present, its lag's tau."""
    # Unlike identification, weights and densities are not kept positive: the outputs stay linear
    # in them, so Levenberg-Marquardt converges in a few steps from any start. A diagnosis compares
    # fits and never inverts them.
    raw_h, rebuild_h = axis.hysteresis.free_parameters(span, rng, positive=False)
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
    gamma0 = tuple(softplus_inverse(2 * c.weights[0] / 0.01) for c in creeps if c is not None)
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
def fit_plant(plant: Plant, u, t, d, weight, history, max_steps: int):
    """Levenberg-Marquardt fit of ``plant`` to ``d`` where ``weight`` is 1 (0: not fitted).

    The residuals ``(model - d) weight / range`` are scaled by the outputs' largest range.
    Compiled once per plant structure and data shape; the data are arguments.

    Arguments:
        plant: the start (its structure says what is fitted).
        u: drives (T, k) V.
        t: times (T,) s.
        d: outputs (T, k) nm.
        weight: (T,) 1 on the training samples, 0 elsewhere.
        history: inputs (H, k) V applied before ``t[0]``, or ``None``.
        max_steps: the solver's step limit.

    Returns:
        The fitted plant, its prediction (T, k) nm and the solver's step count.
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


def title(spec: Nominal) -> str:
    """The nominal model in words, e.g. ``symmetric PI (20 plays) + creep``."""
    extra = [e for e in spec.effects if e != "hysteresis"]
    preisach = spec.kind == "preisach"
    return (
        {"pi": "symmetric PI", "gpi": "generalised PI", "preisach": "Preisach"}[spec.kind]
        + f" ({spec.levels if preisach else spec.operators} {'levels' if preisach else 'plays'})"
        + "".join(f" + {e}" for e in extra)
    )


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
            plant = with_effect(plant, name, u, d)
    return plant


def _nnls_start(h, u, d, train, history):
    """PI and Preisach outputs are linear in their weights (density) for fixed thresholds:
    ``d ~ offset + A w``, ``w >= 0``, solved exactly (scipy ``nnls``) so the gradient fit starts
    at the optimum instead of crawling out of ``softplus``'s flat region."""
    u, history = jnp.asarray(u), None if history is None else jnp.asarray(history)
    a = np.asarray(h.design_matrix(u, history))
    a = np.concatenate([a, np.ones((len(u), 1)), -np.ones((len(u), 1))], 1)[train]
    scale = np.linalg.norm(a, axis=0) + 1e-12
    w = nnls(a / scale, np.asarray(d)[train], maxiter=50 * a.shape[1])[0] / scale
    floor = 1e-6 * np.max(w[:-2])  # softplus needs > 0
    weights, offset = jnp.asarray(np.maximum(w[:-2], floor)), jnp.asarray(w[-2] - w[-1])
    return h.with_weights(weights, offset)


def _with_stages(axis: Axis, names) -> Axis:
    lag = RateDependence(jnp.asarray(LAG0_S)) if "rate_dependence" in names else axis.rate_dependence
    creep = Creep.logarithmic(GAMMA0, *CREEP_TAUS) if "creep" in names else axis.creep
    return Axis(axis.hysteresis, rate_dependence=lag, creep=creep)


def with_effect(plant: Plant, name: str, u, d) -> Plant:
    """``plant`` plus the candidate effect ``name``, started where it changes nothing.

    Arguments:
        plant: the fitted nominal model.
        name: ``rate_dependence``, ``creep``, ``asymmetry`` (dead zones of a
            :class:`~jaxafm.model.hysteresis.GeneralizedPI`, identity at the start), ``coupling``,
            ``bow`` or ``drift``.
        u: the training drives (T, k) V.
        d: the training outputs (T, k) nm (the dead zones' steps: 1/4, 2/4, 3/4 of half their range).

    Returns:
        The plant with the candidate's module.
    """
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
