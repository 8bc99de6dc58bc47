"""The model of an actuator record and its fit: ``Plant``, the nominal model's start, a candidate added.

Actuator records (one or two axes) are modelled as :class:`Plant`: one
:class:`~jaxafm.model.scanner.Axis` per output (hysteresis, rate dependence, creep), then
:class:`~jaxafm.model.effects.Coupling`, :class:`~jaxafm.model.effects.Bow` and the
deterministic part of :class:`~jaxafm.model.effects.Drift` (``v t``) -- the same modules the
simulator uses. Each candidate effect is added where it changes nothing (:func:`with_effect`),
so its refit starts from the nominal fit.

Hysteresis weights start from a non-negative least-squares solve (:func:`_nnls_start`) and are
then fitted unconstrained (outputs are linear in them, so Levenberg-Marquardt needs a few
steps); creep is one logarithmic rate ``gamma >= 0`` per axis over lags from 0.1 s to the record's
length; a mechanical mode (``vibration``) is a frequency below the Nyquist frequency and a
damping in (0, 1) per axis. Units: nm, s, V.
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
from ..model.effects import Bow, Coupling, Creep, Drift, RateDependence, Vibration
from ..model.hysteresis import Deadzone, FactorizedPreisach, GeneralizedPI, Preisach, play, softplus_inverse
from ..model.scanner import Axis

Array = jax.Array
CREEP_TAU_MIN = 0.1  # s, the shortest creep lag; the longest is the record's length (2 lags per decade)
LAG0_S = 1e-3  # the rate-dependence lag a candidate starts from
GAMMA0 = 1e-4  # the creep rate (per decade) a candidate starts from
MAX_DAMPING = 0.7  # a mode rings (has a resonant peak) only below 1/sqrt(2); above, it is a lag


class Plant(eqx.Module):
    """Drive ``u`` (T, k) V -> output (T, k) nm: one Axis per output, then coupling, bow, drift.

    ``p_i = axes[i](u_i, t)``; coupling ``x += xy y, y += yx x``; bow ``x += bx y^2, y += by x^2``;
    drift ``p += v (t - t_0)`` (the Drift module with sigma = 0). A creep stage's lags start at
    ``creep_start`` (k,) nm from the hysteresis output's first value rather than relaxed there: a
    record that begins in the middle of a motion carries the creep of what came before it.
    """

    axes: tuple
    coupling: Optional[Coupling] = None
    bow: Optional[Bow] = None
    drift: Optional[Drift] = None
    creep_start: Optional[Array] = None

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
    # Unlike identification, PI weights are not kept positive: the outputs stay linear in them, so
    # Levenberg-Marquardt converges in a few steps from any start, and a diagnosis never inverts
    # them. A Preisach density is: the cells a training drive never reaches are free without it,
    # and a negative density there makes the held-out loops wild (held-out gaps of um, not nm).
    positive = isinstance(axis.hysteresis, Preisach)
    raw_h, rebuild_h = axis.hysteresis.free_parameters(span, rng, positive=positive)
    if axis.rate_dependence is None:
        return raw_h, lambda p: Axis(rebuild_h(p))
    raw_l, rebuild_l = free_parameters(axis.rate_dependence, span, rng)
    return (raw_h, raw_l), lambda p: Axis(rebuild_h(p[0]), rate_dependence=rebuild_l(p[1]))


def _model_fn(plant: Plant, u, t, d, history):
    """``(raw0, predict, to_plant)``: order-one parameters of ``plant``, ``predict(raw)`` (T, k) nm
    and the fitted plant. A creep stage is fitted as one logarithmic rate ``gamma`` per axis
    (weights ``gamma / 2`` on lags two per decade, :meth:`Creep.logarithmic`), ``gamma >= 0``; a
    mechanical mode as ``frequency = f_N sigmoid(a)`` below the Nyquist frequency ``f_N`` and
    ``damping = MAX_DAMPING sigmoid(b)``."""
    s = _scales(u, t, d)
    nyquist = 0.5 / jnp.median(jnp.diff(t))
    inner = [dataclasses.replace(a, creep=None, vibration=None) for a in plant.axes]
    parts = [_axis_parameters(a, s["span"][i], s["range_k"][i]) for i, a in enumerate(inner)]
    evals = [
        evaluator(a, u[:, i], t, None if history is None else history[:, i]) for i, a in enumerate(inner)
    ]
    creeps = [a.creep for a in plant.axes]
    modes = [a.vibration for a in plant.axes]
    crept = [i for i, c in enumerate(creeps) if c is not None]
    gamma0 = tuple(softplus_inverse(2 * creeps[i].weights[0] / 0.01) for i in crept)
    start0 = jnp.zeros(len(plant.axes)) if plant.creep_start is None else plant.creep_start
    start0 = tuple(start0[i] / (0.01 * s["range_k"][i]) for i in crept)
    logit = lambda p: jnp.log(p) - jnp.log1p(-p)
    mode0 = tuple(
        jnp.stack([logit(m.frequency / nyquist), logit(m.damping / MAX_DAMPING)])
        for m in modes
        if m is not None
    )
    extras0, rebuild_extras = _rebuild_extras(plant, s)
    raw0 = (tuple(p[0] for p in parts), extras0, gamma0, mode0, start0)

    def creep_start(raw):
        out = jnp.zeros(len(plant.axes))
        for i, r in zip(crept, raw[4]):
            out = out.at[i].set(r * 0.01 * s["range_k"][i])
        return out

    def axes(raw):
        gammas = iter(0.01 * jax.nn.softplus(g) for g in raw[2])
        fitted_modes = iter(jax.nn.sigmoid(m) for m in raw[3])
        out = []
        for (_, rb), r, c, m in zip(parts, raw[0], creeps, modes):
            creep = None if c is None else Creep(c.taus, jnp.full_like(c.taus, next(gammas) / 2))
            mode = None if m is None else next(fitted_modes)
            vib = None if m is None else Vibration(nyquist * mode[0], MAX_DAMPING * mode[1])
            out.append(dataclasses.replace(rb(r), creep=creep, vibration=vib))
        return tuple(out)

    def predict(raw):
        cols = []
        starts = creep_start(raw)
        for k, (f, a) in enumerate(zip(evals, axes(raw))):
            v = f(dataclasses.replace(a, creep=None, vibration=None))
            if a.creep is not None:
                level = v[0] + starts[k]
                v = a.creep.run(v, t, (jnp.full_like(a.creep.taus, level), level), t[0])[0]
            cols.append(v if a.vibration is None else a.vibration(v, t))
        p = jnp.stack(cols, -1)
        ex = rebuild_extras(raw[1])
        if "coupling" in ex:
            p = ex["coupling"](p)
        if "bow" in ex:
            p = ex["bow"](p)
        if "drift" in ex:
            p = p + ex["drift"](t, jax.random.key(0))[:, : p.shape[1]]
        return p

    def to_plant(raw):
        return Plant(axes(raw), **rebuild_extras(raw[1]), creep_start=creep_start(raw) if crept else None)

    return raw0, predict, to_plant


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


def nominal_plant(
    spec: Nominal, u: np.ndarray, d: np.ndarray, t: np.ndarray, train: np.ndarray, history=None
) -> Plant:
    """The nominal model's start for outputs ``d`` (T, k) nm from drives ``u`` (T, k) V at times
    ``t`` (T,) s: the hysteresis fitted to the ``train`` samples by non-negative least squares
    (see :func:`_nnls_start`), then the spec's other effects, each started where it changes nothing.
    A Preisach plane is a :class:`~jaxafm.model.hysteresis.FactorizedPreisach` (a PI density times
    a profile over the relays' centres): a free density of ``levels (levels + 1) / 2`` cells
    leaves the cells the training drive never reaches free, and its held-out gaps are then far
    worse than the symmetric PI's on PI-shaped data (4.7 against 2.7 nm on a simulated control)."""
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
        hist = None if history is None else history[:, i]
        if kind == "preisach":
            h = _alternating_start(FactorizedPreisach.from_plane(h), u[:, i], d[:, i], train, hist)
        axes.append(Axis(_nnls_start(h, u[:, i], d[:, i], train, hist)))
    plant = Plant(tuple(axes))
    for name in ("rate_dependence", "creep", "coupling", "bow", "drift"):
        if name in spec.effects:
            plant = with_effect(plant, name, u, d, t)
    return plant


def _alternating_start(h: FactorizedPreisach, u, d, train, history, sweeps: int = 15) -> FactorizedPreisach:
    """A factorised Preisach density fitted to ``d`` by alternating non-negative least squares:
    the output is linear in the play lines' weights for a fixed profile, and in the profile's
    node values for fixed weights (the profile is piecewise linear in them), so each half-step
    is one exact ``nnls`` solve. Levenberg-Marquardt from a flat profile crawls instead (300
    steps left a simulated control's training rms at 3.7 nm against 3.1 nm 300 steps later)."""
    n, k = h.levels, h.profile.shape[0]
    states = np.asarray(h.relay_states(play(jnp.asarray(u), h.radii(), history)))[np.asarray(train)]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    lower, line = i >= j, np.clip(i - j, 0, n - 1)
    c = (i + j) / max(2 * n - 2, 1)
    hats = np.stack([np.interp(c, np.linspace(0, 1, k), np.eye(k)[m]) for m in range(k)])  # (K, n, n)
    onehot = (line[..., None] == np.arange(n)) & lower[..., None]
    y = np.asarray(d)[np.asarray(train)]
    lines, profile = np.asarray(h.lines), np.ones(k)

    def solve(a):
        a = np.concatenate([a, np.ones((len(a), 1)), -np.ones((len(a), 1))], 1)
        scale = np.linalg.norm(a, axis=0) + 1e-12
        w = nnls(a / scale, y, maxiter=50 * a.shape[1])[0] / scale
        return w[:-2], w[-2] - w[-1]

    for _ in range(sweeps):
        g = np.tensordot(profile, hats, 1)
        lines, offset = solve(np.einsum("tij,ijm->tm", states * g, onehot))
        profile, offset = solve(np.einsum("tij,mij->tm", states, hats * lines[line] * lower))
        norm = max(np.mean(profile), 1e-12)
        profile, lines = profile / norm, lines * norm
    floor = 1e-6 * max(np.max(lines), 1e-12)
    start = dataclasses.replace(h, profile=jnp.asarray(np.maximum(profile, 1e-3)))
    return start.with_weights(jnp.asarray(np.maximum(lines, floor)), jnp.asarray(offset))


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


def creep_stage(t: np.ndarray, gamma: float = GAMMA0) -> Creep:
    """Logarithmic creep of ``gamma`` per decade over lags from :data:`CREEP_TAU_MIN` to the
    record's length ``t[-1] - t[0]`` (two per decade), so a long hold tells creep from drift.

    Raises:
        ValueError: for a record shorter than one decade above :data:`CREEP_TAU_MIN` (1 s).
    """
    span = float(t[-1] - t[0])
    if span < 10 * CREEP_TAU_MIN:
        raise ValueError(
            f"the record lasts {span:.3g} s: too short for a creep stage, whose lags span "
            f"{CREEP_TAU_MIN:g} s to the record's length (at least one decade, {10 * CREEP_TAU_MIN:g} s)"
        )
    return Creep.logarithmic(gamma, CREEP_TAU_MIN, span)


def with_effect(plant: Plant, name: str, u, d, t, mode: Optional[tuple] = None) -> Plant:
    """``plant`` plus the candidate effect ``name``, started where it changes nothing (or nearly).

    Arguments:
        plant: the fitted nominal model.
        name: ``rate_dependence``, ``creep`` (:func:`creep_stage`), ``vibration`` (a mode per
            axis at ``mode[k] = (frequency Hz, damping)``), ``asymmetry`` (dead zones of a
            :class:`~jaxafm.model.hysteresis.GeneralizedPI`, identity at the start), ``coupling``,
            ``bow`` or ``drift``.
        u: the training drives (T, k) V.
        d: the training outputs (T, k) nm (the dead zones' steps: 1/4, 2/4, 3/4 of half their range).
        t: the record's times (T,) s (the creep stage spans them).
        mode: where a vibration candidate starts, per axis (Hz, dimensionless).

    Returns:
        The plant with the candidate's module.
    """
    stage = {
        "rate_dependence": lambda k: RateDependence(jnp.asarray(LAG0_S)),
        "creep": lambda k: creep_stage(np.asarray(t)),
        "vibration": lambda k: Vibration(jnp.asarray(mode[k][0]), jnp.asarray(mode[k][1])),
    }
    if name in stage:
        return dataclasses.replace(
            plant,
            axes=tuple(dataclasses.replace(a, **{name: stage[name](k)}) for k, a in enumerate(plant.axes)),
        )
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


def sizes(plant: Plant) -> dict:
    """The fitted size of each effect ``plant`` has beyond its hysteresis, per axis (units in
    the keys): lag ``tau``, creep ``gamma``, the mode's frequency and damping, coupling, bow,
    drift velocity."""
    out = {}
    for name, key, get in (
        ("rate_dependence", "rate_dependence_tau_s", lambda m: float(m.tau)),
        ("creep", "creep_gamma_per_decade", lambda m: float(2 * m.weights[0])),
        ("vibration", "vibration_frequency_hz", lambda m: float(m.frequency)),
        ("vibration", "vibration_damping", lambda m: float(m.damping)),
    ):
        if getattr(plant.axes[0], name) is not None:
            out[key] = [get(getattr(a, name)) for a in plant.axes]
    if plant.coupling is not None:
        out["coupling_xy_yx"] = [float(plant.coupling.xy), float(plant.coupling.yx)]
    if plant.bow is not None:
        out["bow_per_nm"] = [float(plant.bow.bx), float(plant.bow.by)]
    if plant.drift is not None:
        out["drift_nm_per_s"] = np.asarray(plant.drift.velocity)[: len(plant.axes)].tolist()
    return out
