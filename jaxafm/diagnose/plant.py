"""The model of an actuator record and its fit: ``Plant``, the nominal model's start, a candidate added.

Actuator records (one or two axes) are modelled as :class:`Plant`: a
:class:`~jaxafm.model.scanner.Scanner` -- one :class:`~jaxafm.model.scanner.Axis` per output
(hysteresis, rate dependence, creep, vibration), then :class:`~jaxafm.model.effects.Coupling`,
:class:`~jaxafm.model.effects.Bow` and the deterministic part of
:class:`~jaxafm.model.effects.Drift` (``v t``) -- the same modules, composed the same way, as
the simulator. Each candidate effect is added where it changes nothing (:func:`with_effect`), so
its refit starts from the nominal fit.

Hysteresis weights start from a non-negative least-squares solve (:func:`_nnls_start`) and are
then fitted unconstrained (outputs are linear in them, so Levenberg-Marquardt needs a few
steps); creep is one logarithmic rate ``gamma >= 0`` per axis over lags from 0.1 s to the record's
length; a mechanical mode (``vibration``) is a frequency below the Nyquist frequency and a
damping in (0, 1) per axis. Each module's parameters at order one are its own
(``free_parameters``), with the scales of :class:`RecordScales`. Units: nm, s, V.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from scipy.optimize import nnls

from ..config import DiagnoseNominal as Nominal  # the nominal model: its config schema
from ..identify.fit import initial_operator, solve
from ..model.effects import Bow, Coupling, Creep, Drift, RateDependence, Vibration
from ..model.hysteresis import (
    Deadzone,
    FactorizedPreisach,
    GeneralizedPI,
    Linear,
    Preisach,
    play,
)
from ..model.scanner import Axis, Scanner

Array = jax.Array
CREEP_TAU_MIN = 0.1  # s, the shortest creep lag; the longest is the record's length
CREEP_PER_DECADE = 2  # creep lags per decade of time
LAG0_S = 1e-3  # the rate-dependence lag a candidate starts from
GAMMA0 = 1e-4  # the creep rate (per decade) a candidate starts from
MAX_DAMPING = 0.7  # a mode rings (has a resonant peak) only below 1/sqrt(2); above, it is a lag
PROFILE_NODES = 5  # a factorised Preisach's profile over the relays' centres (docs/diagnosis.md)
# What a raw parameter of 1 stands for: 1 % (of coupling, of the creep per decade, of the
# output range for bow, drift and creep start, scaled as RecordScales says), and a 10 ms lag.
RELATIVE_SCALE = 0.01
LAG_SCALE_S = 0.01
SOLVER = "optimistix.levenberg_marquardt"
RTOL, ATOL = 1e-6, 1e-9


class Plant(eqx.Module):
    """Drive ``u`` (T, k) V -> output (T, k) nm: a :class:`~jaxafm.model.scanner.Scanner`, of
    which a one-output record (k = 1) drives the x axis alone (its y axis stands still at 0 nm,
    a zero line, and has no parameters).

    ``p_i = axes[i](u_i, t)``; coupling ``x += xy y, y += yx x``; bow ``x += bx y^2, y += by x^2``;
    drift ``p += v (t - t_0)`` (the Drift module with sigma = 0). A creep stage's lags start at
    ``creep_start`` (k,) nm from the hysteresis output's first value rather than relaxed there: a
    record that begins in the middle of a motion carries the creep of what came before it.
    """

    scanner: Scanner
    outputs: int = eqx.field(static=True)
    creep_start: Optional[Array] = None

    @classmethod
    def of(cls, axes: tuple, creep_start: Optional[Array] = None, **two_axis) -> Plant:
        """The plant with ``axes`` (one per output) and the two-axis modules ``two_axis``
        (``coupling``, ``bow``, ``drift``)."""
        still = Axis(Linear(jnp.zeros(()), jnp.zeros(())))
        x, y = (axes[0], still) if len(axes) == 1 else axes
        return cls(Scanner(x, y, **two_axis), len(axes), creep_start)

    @property
    def axes(self) -> tuple:
        """The axes the outputs come from."""
        return (self.scanner.x, self.scanner.y)[: self.outputs]

    @property
    def effects(self) -> frozenset:
        own = {n for n in ("coupling", "bow", "drift") if getattr(self.scanner, n) is not None}
        return frozenset(own).union(*(a.effects for a in self.axes))

    def with_axes(self, axes: tuple) -> Plant:
        """The same plant with other axes (one per output)."""
        s = self.scanner
        return Plant.of(axes, self.creep_start, coupling=s.coupling, bow=s.bow, drift=s.drift)

    def with_module(self, name: str, module) -> Plant:
        """The same plant with the two-axis module ``name`` (``coupling``, ``bow``, ``drift``)."""
        return dataclasses.replace(self, scanner=dataclasses.replace(self.scanner, **{name: module}))

    def predict(self, hysteresis: tuple, t: Array) -> Array:
        """The outputs (T, k) nm, given each axis's hysteresis output (T,) nm at times ``t``
        (T,) s: each axis's stages from rest (creep from ``creep_start``), then the scanner's
        two-axis stages, with the y axis still for one output."""
        start = jnp.zeros(self.outputs) if self.creep_start is None else self.creep_start
        cols = []
        for a, v, c in zip(self.axes, hysteresis, start):
            state = a.stages_at_rest(v[0])
            if a.creep is not None:  # its lags already off the rest level by the creep in progress
                level = v[0] + c
                state = eqx.tree_at(lambda s: s.creep, state, (jnp.full_like(a.creep.taus, level), level))
            cols.append(a.run_stages(v, t, state, t[0])[0])
        p = jnp.stack(cols + [jnp.zeros_like(cols[0])] * (2 - self.outputs), -1)
        return self.scanner.couple(p, t, jax.random.key(0), jnp.zeros(2), t[0], t[0])[0][:, : self.outputs]


class RecordScales(eqx.Module):
    """A record's sizes that set the plant's order-one scales.

    Attributes:
        span: the input span per axis (k,) V.
        range_k: the output range per axis (k,) nm.
        range: the largest output range (nm): the residuals' unit.
        duration: the record's length (s).
    """

    span: Array
    range_k: Array
    range: Array
    duration: Array

    @classmethod
    def of(cls, u, t, d) -> RecordScales:
        """The scales of drives ``u`` (T, k) V, times ``t`` (T,) s and outputs ``d`` (T, k) nm."""
        rng = jnp.max(d, 0) - jnp.min(d, 0)
        return cls(jnp.max(u, 0) - jnp.min(u, 0), rng, jnp.max(rng), t[-1] - t[0])

    @property
    def bow(self):
        """1 % of the range's bend over half the range (1/nm)."""
        return RELATIVE_SCALE / (self.range / 2)

    @property
    def drift(self):
        """1 % of the range over the record (nm/s)."""
        return RELATIVE_SCALE * self.range / self.duration


def _axis_parameters(axis: Axis, span, rng, nyquist) -> tuple:
    """Raw parameters of one axis and the map back: its hysteresis and lag
    (:meth:`~jaxafm.model.scanner.Axis.free_parameters`), its creep as one rate
    ``gamma >= 0`` (weights ``gamma / 2`` on lags two per decade, :func:`creep_stage`) and its
    mode below the Nyquist frequency, each present one's own ``free_parameters``."""
    # Unlike identification, PI weights are not kept positive: the outputs stay linear in them, so
    # Levenberg-Marquardt converges in a few steps from any start, and a diagnosis never inverts
    # them. A Preisach density is: the cells a training drive never reaches are free without it,
    # and a negative density there makes the held-out loops wild (held-out gaps of um, not nm).
    inner = dataclasses.replace(axis, creep=None, vibration=None)
    positive = isinstance(axis.hysteresis, Preisach)
    parts = [inner.free_parameters(span, rng, positive, lag_scale_s=LAG_SCALE_S)]
    if axis.creep is not None:
        parts.append(axis.creep.free_parameters(RELATIVE_SCALE / CREEP_PER_DECADE, rate=True))
    if axis.vibration is not None:
        parts.append(axis.vibration.free_parameters(nyquist, MAX_DAMPING))

    def rebuild(p):
        out = parts[0][1](p[0])
        stages = [n for n in ("creep", "vibration") if getattr(axis, n) is not None]
        return dataclasses.replace(out, **{n: rb(q) for n, (_, rb), q in zip(stages, parts[1:], p[1:])})

    return tuple(r for r, _ in parts), rebuild


def plant_parameters(plant: Plant, s: RecordScales, nyquist) -> tuple:
    """``(raw, rebuild)``: the order-one parameters of ``plant`` (each axis's, the two-axis
    modules', the creep starts in 1 % of the axis's range) and ``rebuild(raw) -> Plant``."""
    axes = [_axis_parameters(a, s.span[i], s.range_k[i], nyquist) for i, a in enumerate(plant.axes)]
    sc = plant.scanner
    scales = {"coupling": RELATIVE_SCALE, "bow": s.bow, "drift": s.drift}
    two_axis = {n: getattr(sc, n).free_parameters(scales[n]) for n in scales if getattr(sc, n) is not None}
    crept = [i for i, a in enumerate(plant.axes) if a.creep is not None]
    start0 = jnp.zeros(plant.outputs) if plant.creep_start is None else plant.creep_start
    raw = (
        tuple(r for r, _ in axes),
        {n: r for n, (r, _) in two_axis.items()},
        tuple(start0[i] / (RELATIVE_SCALE * s.range_k[i]) for i in crept),
    )

    def rebuild(p):
        start = jnp.zeros(plant.outputs)
        for i, r in zip(crept, p[2]):
            start = start.at[i].set(r * RELATIVE_SCALE * s.range_k[i])
        modules = {n: rb(p[1][n]) for n, (_, rb) in two_axis.items()}
        fitted = tuple(rb(q) for (_, rb), q in zip(axes, p[0]))
        return Plant.of(fitted, start if crept else None, **modules)

    return raw, rebuild


def _hysteresis(plant: Plant, u, history) -> tuple:
    """Per axis, the evaluator of its hysteresis on its drive ``u[:, i]``, plays run once (the
    threshold grids stay fixed: :meth:`~jaxafm.model.hysteresis.AbstractHysteresis.evaluator`)."""
    return tuple(
        a.hysteresis.evaluator(u[:, i], None if history is None else history[:, i])
        for i, a in enumerate(plant.axes)
    )


def _predict(raw, plant: Plant, hysteresis: tuple, t, d, scales: RecordScales) -> Array:
    """The outputs (T, k) nm of the plant ``raw`` stands for (:func:`plant_parameters`)."""
    fitted = plant_parameters(plant, scales, 0.5 / jnp.median(jnp.diff(t)))[1](raw)
    return fitted.predict(tuple(f(a.hysteresis) for f, a in zip(hysteresis, fitted.axes)), t)


def _residuals(raw, args) -> Array:
    """``(model - d) weight / range``, flat: the plant fit's residuals; ``args = (plant, the axes'
    hysteresis evaluators, t, d, weight, scales)``, the plays run once before the fit."""
    plant, hysteresis, t, d, weight, scales = args
    return ((_predict(raw, plant, hysteresis, t, d, scales) - d) * weight[:, None] / scales.range).ravel()


def _loss(raw, args) -> Array:
    return 0.5 * jnp.sum(_residuals(raw, args) ** 2)


def _whitened_residuals(raw, args) -> Array:
    """``L (d - model) / range``, flat: the residuals whitened by a drift's wander
    (:class:`~jaxafm.diagnose.wander.Whitener`, which holds the training samples);
    ``args = (plant, the axes' hysteresis evaluators, t, d, whitener, scales)``."""
    plant, hysteresis, t, d, whiten, scales = args
    return (whiten(d - _predict(raw, plant, hysteresis, t, d, scales)) / scales.range).ravel()


def _whitened_loss(raw, args) -> Array:
    return 0.5 * jnp.sum(_whitened_residuals(raw, args) ** 2)


@eqx.filter_jit
def _start(plant: Plant, u, t, d, history) -> tuple:
    """``(raw0, hysteresis evaluators, scales)`` of a fit of ``plant`` to the record."""
    scales = RecordScales.of(u, t, d)
    raw0 = plant_parameters(plant, scales, 0.5 / jnp.median(jnp.diff(t)))[0]
    return raw0, _hysteresis(plant, u, history), scales


@eqx.filter_jit
def _finish(raw, plant: Plant, hysteresis: tuple, t, d, scales: RecordScales) -> tuple:
    """The fitted plant and its outputs (T, k) nm."""
    fitted = plant_parameters(plant, scales, 0.5 / jnp.median(jnp.diff(t)))[1](raw)
    return fitted, _predict(raw, plant, hysteresis, t, d, scales)


def fit_plant(plant: Plant, u, t, d, weight, history, max_steps: int, whiten=None) -> tuple:
    """Levenberg-Marquardt fit (:func:`~jaxafm.identify.fit.solve`) of ``plant`` to ``d`` where
    ``weight`` is 1 (0: not fitted).

    The residuals ``(model - d) weight / range`` are scaled by the outputs' largest range; with
    ``whiten`` (a :class:`~jaxafm.diagnose.wander.Whitener`, which holds the training samples in
    place of ``weight``), ``whiten(d - model) / range``: the plant fitted under a drift's wander.
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
    raw0, hysteresis, scales = _start(plant, u, t, d, history)
    if whiten is None:
        args, residuals, loss = (plant, hysteresis, t, d, weight, scales), _residuals, _loss
    else:
        args, residuals, loss = (plant, hysteresis, t, d, whiten, scales), _whitened_residuals, _whitened_loss
    raw, steps, _ = solve(SOLVER, residuals, loss, raw0, max_steps, RTOL, ATOL, args)
    fitted, prediction = _finish(raw, plant, hysteresis, t, d, scales)
    return fitted, prediction, steps


def n_parameters(plant: Plant, u, t, d) -> int:
    """Free parameters of ``plant`` (what the fit moves)."""
    scales = RecordScales.of(jnp.asarray(u), jnp.asarray(t), jnp.asarray(d))
    raw0 = plant_parameters(plant, scales, 0.5 / jnp.median(jnp.diff(jnp.asarray(t))))[0]
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
            h = initial_operator(
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
            h = _alternating_start(
                FactorizedPreisach.from_plane(h, PROFILE_NODES), u[:, i], d[:, i], train, hist
            )
        axes.append(Axis(_nnls_start(h, u[:, i], d[:, i], train, hist)))
    plant = Plant.of(tuple(axes))
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
    return Creep.logarithmic(gamma, CREEP_TAU_MIN, span, CREEP_PER_DECADE)


def with_effect(plant: Plant, name: str, u, d, t, mode: Optional[tuple] = None, deadzones: int = 3) -> Plant:
    """``plant`` plus the candidate effect ``name``, started where it changes nothing (or nearly).

    Arguments:
        plant: the fitted nominal model.
        name: ``rate_dependence``, ``creep`` (:func:`creep_stage`), ``vibration`` (a mode per
            axis at ``mode[k] = (frequency Hz, damping)``), ``asymmetry`` (dead zones of a
            :class:`~jaxafm.model.hysteresis.GeneralizedPI`, identity at the start), ``coupling``,
            ``bow`` or ``drift``.
        u: the training drives (T, k) V.
        d: the training outputs (T, k) nm (``asymmetry``'s dead zones: ``deadzones`` steps a side,
            evenly over half their range: 1/4, 2/4, 3/4 for 3).
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
        return plant.with_axes(
            tuple(dataclasses.replace(a, **{name: stage[name](k)}) for k, a in enumerate(plant.axes))
        )
    if name == "asymmetry":
        axes = []
        for i, a in enumerate(plant.axes):
            steps = (np.arange(deadzones) + 1) / (deadzones + 1) * np.ptp(d[:, i]) / 2
            dz = Deadzone.identity(-steps, steps, centre=float(np.mean(d[:, i])))
            axes.append(dataclasses.replace(a, hysteresis=GeneralizedPI(a.hysteresis, dz)))
        return plant.with_axes(tuple(axes))
    zero = jnp.zeros(())
    module = {
        "coupling": lambda: Coupling(zero, zero),
        "bow": lambda: Bow(zero, zero),
        "drift": lambda: Drift(jnp.zeros(2), jnp.zeros(2), jnp.asarray(1e-3)),
    }[name]()
    return plant.with_module(name, module)


def sizes(plant: Plant) -> dict:
    """The fitted size of each effect ``plant`` has beyond its hysteresis, per axis (units in
    the keys): lag ``tau``, creep ``gamma``, the mode's frequency and damping, coupling, bow,
    drift velocity."""
    out = {}
    for name, key, get in (
        ("rate_dependence", "rate_dependence_tau_s", lambda m: float(m.tau)),
        ("creep", "creep_gamma_per_decade", lambda m: float(CREEP_PER_DECADE * m.weights[0])),
        ("vibration", "vibration_frequency_hz", lambda m: float(m.frequency)),
        ("vibration", "vibration_damping", lambda m: float(m.damping)),
    ):
        if getattr(plant.axes[0], name) is not None:
            out[key] = [get(getattr(a, name)) for a in plant.axes]
    s = plant.scanner
    if s.coupling is not None:
        out["coupling_xy_yx"] = [float(s.coupling.xy), float(s.coupling.yx)]
    if s.bow is not None:
        out["bow_per_nm"] = [float(s.bow.bx), float(s.bow.by)]
    if s.drift is not None:
        out["drift_nm_per_s"] = np.asarray(s.drift.velocity)[: plant.outputs].tolist()
    return out
