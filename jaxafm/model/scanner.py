"""The scanner model: drive voltages ``u_x(t), u_y(t)`` (V) -> tip position ``x(t), y(t)`` (nm).

One ``Axis`` per direction (hysteresis -> rate dependence -> creep), then the
two-axis effects (coupling, bow, drift, noise). An effect is on exactly when
its module is present: the truth simulator and a fitted model are the same
code with different modules switched in, and ``Scanner.effects`` names them.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import checks
from ..config.names import TRUTH_CLASSES, check_effect_names
from .effects import (
    Bow,
    Coupling,
    Creep,
    Drift,
    Noise,
    RateDependence,
    Vibration,
)
from .hysteresis import (
    AbstractHysteresis,
    Deadzone,
    GeneralizedPI,
    PrandtlIshlinskii,
    Preisach,
    warn_beyond_span,
)

Array = jax.Array


#: The linear dynamic stages of an axis after its hysteresis, in order.
STAGES = ("rate_dependence", "creep", "vibration")


class AxisState(eqx.Module):
    """Where one axis stands: its hysteresis operator's state (the plays, V; empty for a
    memoryless operator), the lag (nm), the creep lags plus rest level (nm) and the mechanical
    mode's position (nm) and velocity (nm/s) (empty without one)."""

    plays: Array
    lag: Array
    creep: tuple
    vibration: tuple = ()


class Axis(eqx.Module):
    """One actuator axis: ``y = vibration(creep(lag(H[u])))`` in nm, for ``u`` in V and ``t`` in s."""

    hysteresis: AbstractHysteresis
    rate_dependence: Optional[RateDependence] = None
    creep: Optional[Creep] = None
    vibration: Optional[Vibration] = None

    @property
    def effects(self) -> frozenset:
        """The hysteresis operator's effects (a Preisach density holds its asymmetry itself,
        unnamed), plus ``rate_dependence``, ``creep`` and ``vibration`` when present."""
        stages = {n for n in STAGES if getattr(self, n) is not None}
        return self.hysteresis.effects | stages

    def without(self, name: str) -> Axis:
        """The same axis with the effect ``name`` switched off (unchanged if it does not hold it)."""
        if name in STAGES:
            return eqx.tree_at(lambda a: getattr(a, name), self, None, is_leaf=lambda v: v is None)
        h = self.hysteresis.without(name)
        return self if h is self.hysteresis else eqx.tree_at(lambda a: a.hysteresis, self, h)

    def predict(self, u: Array, t: Array, history=None) -> Array:
        """The output (T,) nm for a record's inputs ``u`` (T,) V at times ``t`` (T,) s, as
        every model of one axis is called (:meth:`AbstractHysteresis.predict`)."""
        return self(u, t, history)

    def free_parameters(
        self, u_span, d_range, positive: bool = True, lag_scale_s: float = 0.01, creep_scale: float = 0.01
    ) -> tuple:
        """The fitted parameters of the hysteresis, the lag and the creep at order one, and the
        map back: each stage's own ``free_parameters``, in the axis's order.

        Arguments:
            u_span: the span of the fitted input (V).
            d_range: the range of the fitted output (nm).
            positive: keep the hysteresis weights non-negative
                (:meth:`AbstractHysteresis.free_parameters`).
            lag_scale_s: the rate-dependence time constant (s) a raw value of about 1 stands for.
            creep_scale: the creep weight a raw value of 1 stands for (every weight its own, >= 0).

        Returns:
            ``(raw, rebuild)``: a tuple of the present stages' raw parameters and
            ``rebuild(raw) -> Axis``.

        Raises:
            TypeError: for an axis with a mechanical mode, whose bounds depend on the record
                (:meth:`~jaxafm.model.effects.Vibration.free_parameters`).
        """
        if self.vibration is not None:
            raise TypeError(
                "an Axis with a vibration stage: its frequency's bound is the record's Nyquist frequency; "
                "fit its stages' free_parameters one by one"
            )
        parts = {"hysteresis": self.hysteresis.free_parameters(u_span, d_range, positive)}
        if self.rate_dependence is not None:
            parts["rate_dependence"] = self.rate_dependence.free_parameters(lag_scale_s)
        if self.creep is not None:
            parts["creep"] = self.creep.free_parameters(creep_scale)
        raw = tuple(r for r, _ in parts.values())
        return raw, lambda p: Axis(**{n: rebuild(q) for (n, (_, rebuild)), q in zip(parts.items(), p)})

    def initial_state(self, u0, history=None) -> AxisState:
        """At rest at the input ``u0`` (V) after ``history``: the lags and creep relaxed there."""
        if history is not None:
            history = jnp.asarray(history, dtype=float)
            checks.finite("history", history)
        return _at_rest(self, jnp.asarray(u0, dtype=float), history)

    def run(self, u: Array, t: Array, state: AxisState, t0) -> tuple:
        """Positions (T,) nm and the next state, continuing from ``state`` reached at time ``t0``."""
        v, plays = self.hysteresis.run(u, state.plays)
        return self.run_stages(v, t, eqx.tree_at(lambda s: s.plays, state, plays), t0)

    def run_stages(self, v: Array, t: Array, state: AxisState, t0) -> tuple:
        """The stages after the hysteresis, in order (rate dependence, creep, vibration), on its
        output ``v`` (T,) nm at times ``t`` (T,) s, continuing from ``state`` at time ``t0``:
        positions (T,) nm and the next state (its plays as given)."""
        lag, creep, vibration = state.lag, state.creep, state.vibration
        if self.rate_dependence is not None:
            v, lag = self.rate_dependence.run(v, t, lag, t0)
        if self.creep is not None:
            v, creep = self.creep.run(v, t, creep, t0)
        if self.vibration is not None:
            v, vibration = self.vibration.run(v, t, vibration, t0)
        return v, AxisState(state.plays, lag, creep, vibration)

    def stages_at_rest(self, v0, plays: Array = None) -> AxisState:
        """The state of the stages after the hysteresis at rest at its output ``v0`` nm (the
        lags and the creep relaxed there, the mode still), with the hysteresis at ``plays``
        (none given: empty)."""
        plays = jnp.zeros((0,)) if plays is None else plays
        lag = jnp.zeros((0,)) if self.rate_dependence is None else self.rate_dependence.initial_state(v0)
        creep = () if self.creep is None else self.creep.initial_state(v0)
        vibration = () if self.vibration is None else self.vibration.initial_state(v0)
        return AxisState(plays, lag, creep, vibration)

    def __call__(self, u: Array, t: Array, history=None) -> Array:
        t = jnp.asarray(t, dtype=float)
        checks.some_samples("input u", u)
        checks.increasing("times t", t)
        if np.shape(t) != np.shape(u):
            raise ValueError(f"times t {np.shape(t)} and input u {np.shape(u)} must have the same shape")
        return self.dynamics(self.hysteresis(u, history), t)

    def dynamics(self, v: Array, t: Array) -> Array:
        """The rate-dependent stages applied to the hysteresis output ``v`` (nm)."""
        if self.rate_dependence is not None:
            v = self.rate_dependence(v, t)
        if self.creep is not None:
            v = self.creep(v, t)
        if self.vibration is not None:
            v = self.vibration(v, t)
        return v


@eqx.filter_jit
def _at_rest(axis: Axis, u0: Array, history) -> AxisState:
    """:meth:`Axis.initial_state`, compiled once per kind of axis: called eagerly, the one-sample
    run of the plays would trace and compile its scan anew at every call."""
    plays = axis.hysteresis.initial_state(u0, history)
    v0 = axis.hysteresis.run(jnp.reshape(u0, (1,)), plays)[0][0]
    return axis.stages_at_rest(v0, plays)


class ScannerState(eqx.Module):
    """Where the scanner stands after a drive: both axes, the drift's wander (2,) nm,
    the time of the last sample ``t`` (s) and the drift's time origin (s)."""

    x: AxisState
    y: AxisState
    wander: Array
    t: Array
    origin: Array


class Scanner(eqx.Module):
    """Two axes plus coupling, bow, drift and noise; call with ``u`` (T, 2) V, ``t`` (T,) s.

    ``scanner(u, t, key, history)`` starts at rest at ``u[0]``. To drive on
    where a previous drive stopped (a scan, then a move, then a press), use
    ``p, state = scanner.run(u, t, state, key)`` from ``initial_state``:
    running two halves in turn equals running the whole.
    """

    x: Axis
    y: Axis
    coupling: Optional[Coupling] = None
    bow: Optional[Bow] = None
    drift: Optional[Drift] = None
    noise: Optional[Noise] = None

    @property
    def effects(self) -> frozenset:
        own = {n for n in ("coupling", "bow", "drift", "noise") if getattr(self, n) is not None}
        return frozenset(own) | self.x.effects | self.y.effects

    def initial_state(self, u0, t0=0.0, history=None) -> ScannerState:
        """At rest at the drive ``u0`` (2,) V at time ``t0`` s, after ``history`` (H, 2) V."""
        u0 = jnp.asarray(u0, dtype=float)
        if u0.shape != (2,):
            raise ValueError(f"the starting drive u0 must have shape (2,) V, got {u0.shape}")
        hx = hy = None
        if history is not None:
            history = jnp.asarray(history, dtype=float)
            if history.ndim != 2 or history.shape[1] != 2:
                raise ValueError(f"history must have shape (H, 2) V, got {history.shape}")
            hx, hy = history[:, 0], history[:, 1]
        t0 = jnp.asarray(t0, dtype=float)
        return ScannerState(
            self.x.initial_state(u0[0], hx), self.y.initial_state(u0[1], hy), jnp.zeros(2), t0, t0
        )

    def run(self, u: Array, t: Array, state: ScannerState, key: Optional[Array] = None) -> tuple:
        """Tip positions (T, 2) nm for drive ``u`` (T, 2) V at times ``t`` (T,) s after
        ``state``, and the state after the last sample."""
        u = _drive(u)
        t = jnp.asarray(t, dtype=float)
        if t.shape != u.shape[:1]:
            raise ValueError(f"times t {t.shape} must have one entry per drive sample {u.shape[:1]}")
        checks.increasing("times t", t)
        if checks.is_concrete(t) and checks.is_concrete(state.t) and t[0] < state.t:
            raise ValueError(
                f"times t start at {float(t[0])} s, before the state's last sample at "
                f"{float(state.t)} s: drive forward in time"
            )
        random = [n for n in ("drift", "noise") if getattr(self, n) is not None]
        if random and key is None:
            raise ValueError(
                f"the scanner has the random effect(s) {random}: pass a PRNG key, "
                "e.g. scanner(u, t, key=jax.random.key(0))"
            )
        x, sx = self.x.run(u[:, 0], t, state.x, state.t)
        y, sy = self.y.run(u[:, 1], t, state.y, state.t)
        p, wander = self.couple(jnp.stack([x, y], axis=-1), t, key, state.wander, state.t, state.origin)
        return p, ScannerState(sx, sy, wander, t[-1], state.origin)

    def couple(self, p: Array, t: Array, key: Optional[Array], wander: Array, t0, origin) -> tuple:
        """The two-axis stages after the axes, in order, on the axes' positions ``p`` (T, 2) nm at
        times ``t`` (T,) s: coupling, bow, drift (since ``origin``, its wander continuing from
        ``wander`` (2,) nm at ``t0``) and noise (``key`` draws the random parts). Returns the
        positions (T, 2) nm and the wander after the last sample."""
        if self.coupling is not None:
            p = self.coupling(p)
        if self.bow is not None:
            p = self.bow(p)
        if key is not None:
            k_drift, k_noise = jax.random.split(key)
        if self.drift is not None:
            d, wander = self.drift.run(t, k_drift, wander, t0, origin)
            p = p + d
        if self.noise is not None:
            p = p + self.noise(p.shape, k_noise)
        return p, wander

    def __call__(self, u: Array, t: Array, key: Optional[Array] = None, history=None) -> Array:
        """Tip positions (T, 2) nm from rest at ``u[0]``; ``history``: per-axis pre-history (H, 2) V.
        A drive far beyond the span the scanner's hysteresis covers warns
        (:func:`~jaxafm.model.hysteresis.warn_beyond_span`)."""
        u = _drive(u)
        warn_beyond_span({"x": self.x.hysteresis, "y": self.y.hysteresis}, u)
        t = jnp.asarray(t, dtype=float)
        return self.run(
            u, t, self.initial_state(u[0], t[0] if t.ndim == 1 and t.size else 0.0, history), key
        )[0]

    def predict(self, u: Array, t: Array, history=None) -> Array:
        """The mean positions (T, 2) nm for drives ``u`` (T, 2) V at times ``t`` (T,) s from rest
        after ``history`` (H, 2) V: without the random parts (:func:`mean_scanner`), as every
        model is applied to a record (:meth:`Axis.predict`)."""
        return mean_scanner(self)(u, t, jax.random.key(0), history)

    def without(self, *names: str) -> Scanner:
        """The same scanner with the named effects switched off."""
        check_effect_names(names, "Scanner.without")
        s = self
        for n in names:
            if n in ("coupling", "bow", "drift", "noise"):
                s = eqx.tree_at(lambda m: getattr(m, n), s, None, is_leaf=lambda v: v is None)
            s = eqx.tree_at(lambda m: (m.x, m.y), s, (s.x.without(n), s.y.without(n)))
        return s


def _drive(u) -> Array:
    """A scanner's drive ``u`` as an array, checked: (T, 2) V, one sample or more."""
    u = jnp.asarray(u, dtype=float)
    if u.ndim != 2 or u.shape[1] != 2:
        raise ValueError(f"drive voltages u must have shape (T, 2), got {u.shape}")
    checks.some_samples("drive voltages u", u)
    return u


def mean_scanner(model: Scanner) -> Scanner:
    """The scanner without its random parts: no position noise, no drift wander (its mean
    drift kept)."""
    model = model.without("noise")
    if model.drift is None:
        return model
    return eqx.tree_at(lambda m: m.drift.sigma, model, jnp.zeros_like(model.drift.sigma))


def pi_with_loop_width(n: int, span: float, travel: float, loop_width: float) -> PrandtlIshlinskii:
    """:meth:`PrandtlIshlinskii.with_loop_width`: a major loop over ``span`` V that moves
    ``travel`` nm and is ``loop_width`` (a fraction of the travel) wide."""
    return PrandtlIshlinskii.with_loop_width(n, span, travel, loop_width)


def default_scanner(
    u_range: float = 10.0,
    travel: float = 10_000.0,
    loop_width: float = 0.15,
    creep_gamma: float = 0.01,
    coupling: float = 0.02,
    bow: float = 2e-6,
    drift_nm_per_min: tuple = (3.0, -1.8),
    drift_sigma: float = 0.05,
    noise_std: float = 0.2,
    n_operators: int = 16,
    truth_class: str = "generalised_pi",
    rate_tau: float = 2e-3,
    vibration_hz: float = 150.0,
    vibration_damping: float = 0.05,
) -> Scanner:
    """The default simulated tube scanner (figures from docs/conventions.md).

    Drive ``-u_range..+u_range`` V moves about ``travel`` nm; the major loop is
    about ``loop_width`` of range wide and asymmetric (dead zones compress the
    top and stretch the bottom, x and y a little differently); creep
    ``creep_gamma`` per decade; linear coupling ``coupling`` (x from y) and
    ``-0.6 coupling`` (y from x); bow ``bow`` 1/nm; drift ``drift_nm_per_min``
    plus an Ornstein–Uhlenbeck wander of ``drift_sigma`` nm/sqrt(s); white
    position noise ``noise_std`` nm. From a virgin state at 0 V (``history=[[0, 0]]``), ``u = 0``
    is ``x = y = 0``.

    ``truth_class`` (:data:`TRUTH_CLASSES`) chooses the hysteresis's model class, to try a
    fitted model on a truth of another shape: ``generalised_pi`` (the above: ``n_operators``
    plays and dead zones), ``preisach`` (a smooth Preisach plane of ``2 n_operators`` levels
    whose loop is as wide, its asymmetry from an off-centre density instead of dead zones:
    :meth:`~jaxafm.model.hysteresis.Preisach.with_loop_width`; more of its relays lie below
    the middle, so from the virgin state ``u = 0`` is about 3 % of the travel above 0),
    ``rate_dependent`` (the generalised PI then a lag of ``rate_tau`` s: loops that widen with
    the drive's rate) or
    ``resonant`` (the generalised PI then a mechanical mode of ``vibration_hz`` Hz and damping
    ``vibration_damping``).

    Raises:
        ValueError: naming the argument, for a value that is not finite, a range or travel that
            is not > 0, a width, creep rate, wander or noise below 0, or an unknown class.
    """
    for name, value in (("u_range (V)", u_range), ("travel (nm)", travel)):
        checks.positive(f"default_scanner: {name}", value)
    for name, value in (
        ("loop_width", loop_width),
        ("creep_gamma (per decade)", creep_gamma),
        ("drift_sigma (nm/sqrt(s))", drift_sigma),
        ("noise_std (nm)", noise_std),
    ):
        checks.nonnegative(f"default_scanner: {name}", value)
    for name, value in (("coupling", coupling), ("bow (1/nm)", bow), ("drift_nm_per_min", drift_nm_per_min)):
        checks.finite(f"default_scanner: {name}", value)
    if not (isinstance(n_operators, (int, np.integer)) and n_operators >= 2):
        raise ValueError(f"default_scanner: n_operators must be a whole number >= 2, got {n_operators!r}")

    if truth_class not in TRUTH_CLASSES:
        raise ValueError(f"default_scanner: truth_class must be one of {TRUTH_CLASSES}, got {truth_class!r}")

    def axis(upper_w: tuple, lower_w: tuple, centre: float) -> Axis:
        if truth_class == "preisach":
            h = Preisach.with_loop_width(2 * n_operators, u_range, travel, loop_width, centre, 1.2)
        else:
            pi = pi_with_loop_width(n_operators, 2 * u_range, travel, loop_width)
            half = travel / 2
            asym = Deadzone(
                jnp.ones(()),
                jnp.array([0.2, 0.6]) * half,
                jnp.array(upper_w),
                jnp.array([-0.2, -0.6]) * half,
                jnp.array(lower_w),
            )
            h = GeneralizedPI(pi, asym)
        return Axis(
            h,
            RateDependence(jnp.asarray(rate_tau)) if truth_class == "rate_dependent" else None,
            Creep.logarithmic(creep_gamma),
            Vibration(jnp.asarray(vibration_hz), jnp.asarray(vibration_damping))
            if truth_class == "resonant"
            else None,
        )

    return Scanner(
        axis((-0.08, -0.12), (0.06, 0.08), -0.2),
        axis((-0.06, -0.10), (0.04, 0.06), -0.15),
        coupling=Coupling(jnp.asarray(coupling), jnp.asarray(-0.6 * coupling)),
        bow=Bow(jnp.asarray(bow), jnp.asarray(-0.5 * bow)),
        drift=Drift(
            jnp.asarray(drift_nm_per_min, dtype=float) / 60.0, jnp.full(2, drift_sigma), jnp.asarray(1e-3)
        ),
        noise=Noise(jnp.full(2, noise_std)),
    )
