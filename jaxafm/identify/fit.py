"""Fit hysteresis operators to an input/output record with gradient solvers.

The model stays in physical units (V in, nm out). The solver works on raw
parameters scaled to order one (weights in units of ``range/span``, offsets in
units of ``range``) so that every Jacobian column is of similar size;
non-negative weights and densities go through ``softplus``. Threshold grids are
fixed: with them, PI and Preisach outputs are linear in their weights, so the
least-squares problem is well posed from any positive start.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxopt
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from .. import checks
from ..config.names import LINEAR_SOLVERS, SOLVERS
from ..model.apply import evaluator
from ..model.hysteresis import (
    Deadzone,
    GeneralizedPI,
    Linear,
    PrandtlIshlinskii,
    Preisach,
)
from . import geodesic, linear

Array = jax.Array
MODEL_KINDS = ("linear", "pi", "gpi", "preisach")
#: how much worse (relative) a model may train than one it contains before it is called a
#: solver failure: the solvers' tolerances leave well under 1e-3 of the loss
NESTING_TOLERANCE = 1e-3


def initial_operator(kind: str, u, d, *, operators: int = 20, levels: int = 20, deadzones: int = 3):
    """A start for ``kind`` from the record's ranges: the straight line through the data.

    ``pi``: ``operators`` thresholds evenly over half the input span (wider
    plays never move on a loop within the span); ``gpi``: the same plus
    ``deadzones`` dead zones each side over the output half-range;
    ``preisach``: a plane of ``levels`` levels over the input span.
    """
    u, d = np.asarray(u, dtype=float), np.asarray(d, dtype=float)
    gain, offset = np.polyfit(u, d, 1)
    u_lo, u_hi = u.min(), u.max()
    span, rng = u_hi - u_lo, d.max() - d.min()
    if kind == "linear":
        return Linear(jnp.asarray(gain), jnp.asarray(offset))
    if kind in ("pi", "gpi", "preisach") and not gain > 0:
        raise ValueError(
            f"the output falls as the input rises (slope {gain:.3g} nm/V), but {kind} models have "
            "non-negative weights and rise: negate the output (or the input) before fitting"
        )
    if kind in ("pi", "gpi"):
        # small positive weights on every play so softplus starts with a gradient
        pi = PrandtlIshlinskii.uniform(operators, span / 2, gain, offset, others=1e-3)
        if kind == "pi":
            return pi
        steps = (np.arange(deadzones) + 1) / (deadzones + 1) * rng / 2
        return GeneralizedPI(pi, Deadzone.identity(-steps, steps, centre=float(np.mean(d))))
    if kind == "preisach":
        margin = 1e-6 * span
        return Preisach.uniform(levels, u_lo - margin, u_hi + margin, total=rng / 2, offset=float(np.mean(d)))
    raise ValueError(f"unknown model kind {kind!r}; one of {', '.join(MODEL_KINDS)}")


@dataclasses.dataclass(frozen=True)
class FitResult:
    """A fitted model and how the solver got there.

    Attributes:
        model: the fitted model, the same structure as the start.
        solver: the solver's name (one of ``SOLVERS`` or ``LINEAR_SOLVERS``).
        converged: whether the solver met its tolerances within ``max_steps``.
        steps: the solver's steps (or function evaluations, for scipy).
        loss: the final mean squared residual, in (fraction of the output range)^2.
        seconds: the solve's wall time (s).
        message: one line saying how the solve ended.
    """

    model: object
    solver: str
    converged: bool
    steps: int
    loss: float
    seconds: float
    message: str


def fit_operator(
    model,
    u,
    d,
    *,
    t=None,
    solver: str = "optimistix.levenberg_marquardt",
    max_steps: int = 2000,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    history=None,
    settle: int = 0,
) -> FitResult:
    """Least-squares fit of ``model(u, [t,] history) ~ d``; residuals in fractions of the output range.

    ``model`` is a hysteresis operator or an :class:`~jaxafm.model.scanner.Axis`
    (hysteresis plus creep; ``t`` in s). Threshold grids stay as given. The
    model runs over the whole of ``u``; the first ``settle`` samples (a
    transient the model is not meant to follow) are left out of the loss.

    ``solver="jaxafm.nnls"`` (PI and Preisach operators only) solves the non-negative least
    squares exactly (:func:`~jaxafm.identify.linear.fit_weights`); ``max_steps``, ``rtol`` and
    ``atol`` are then unused.

    Never raises for a solver that stops early: ``converged`` and ``message``
    say so, with the last loss.
    """
    if solver not in LINEAR_SOLVERS:
        check_solver(solver, max_steps, rtol, atol)
    u, d = jnp.asarray(u, dtype=float), jnp.asarray(d, dtype=float)
    _check_record(u, d, t)
    if not 0 <= settle < len(d) - 1:
        raise ValueError(f"settle={settle} samples must be >= 0 and leave data to fit (record has {len(d)})")
    d_range = float(d[settle:].max() - d[settle:].min())
    if solver in LINEAR_SOLVERS:
        return _fit_linear(model, u, d, history, settle, d_range)
    raw0, rebuild = model.free_parameters(float(u.max() - u.min()), d_range)
    forward = evaluator(model, u, t, history)

    def residuals(raw, _=None):
        return (forward(rebuild(raw))[settle:] - d[settle:]) / d_range

    def loss(raw, _=None):
        r = residuals(raw)
        return 0.5 * jnp.mean(r**2)

    start = time.perf_counter()
    raw, steps, ok = solve(solver, residuals, loss, raw0, max_steps, rtol, atol)
    final = float(2 * loss(raw))
    seconds = time.perf_counter() - start
    message = (
        f"{solver}: converged in {steps} steps"
        if ok
        else f"{solver}: did NOT converge in {steps} steps (max_steps={max_steps}); last loss {final:.3e}"
    )
    return FitResult(rebuild(raw), solver, ok, steps, final, seconds, message)


def _fit_linear(model, u, d, history, settle: int, d_range: float) -> FitResult:
    """:func:`fit_operator` with ``jaxafm.nnls``: converged unless its scipy fallback stopped short."""
    start = time.perf_counter()
    fit = linear.fit_weights(model, u, d, history=history, settle=settle)
    seconds = time.perf_counter() - start
    final = fit.mean_square / d_range**2
    message = {
        "pivoting": f"jaxafm.nnls: solved in {fit.steps} pivoting steps",
        "scipy nnls": f"jaxafm.nnls: pivoting did not end in {fit.steps} steps; solved by scipy's nnls",
    }.get(fit.how, f"jaxafm.nnls: did NOT converge (pivoting, then scipy's nnls); last loss {final:.3e}")
    ok = fit.how != "scipy nnls stopped short"
    return FitResult(fit.model, "jaxafm.nnls", ok, fit.steps, final, seconds, message)


def check_solver(solver: str, max_steps: int, rtol: float, atol: float) -> None:
    """Raise for an unknown solver, a step limit that is not a whole number >= 1, or a tolerance
    that is not finite and > 0 (naming the argument and the value)."""
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; one of {', '.join(SOLVERS)}")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 1):
        raise ValueError(f"max_steps must be a whole number >= 1, got {max_steps!r}")
    checks.positive("rtol", rtol)
    checks.positive("atol", atol)


def _check_record(u, d, t) -> None:
    """Input and output of one length, finite, and both moving (a constant one identifies nothing)."""
    if u.shape[:1] != d.shape[:1] or (t is not None and np.shape(t)[:1] != u.shape[:1]):
        raise ValueError(
            f"u {u.shape}, d {d.shape}" + ("" if t is None else f" and t {np.shape(t)}") + " must have "
            "the same number of samples"
        )
    for name, x, unit in (("input u", u, "V"), ("output d", d, "nm")):
        checks.finite(name, x)
        if x.size and float(x.max() - x.min()) == 0:
            raise ValueError(
                f"{name} is constant ({float(x[0]):g} {unit}): a fit needs a moving input and output"
            )


def solve(
    solver: str,
    residuals: Callable,
    loss: Callable,
    raw0,
    max_steps: int,
    rtol: float,
    atol: float,
    args=None,
    curvature: str = "jvp",
) -> tuple:
    """Minimise with the named solver: every fit of the package goes through here.

    Pass data through ``args``, not closures, with module-level functions: the
    compiled solver is then reused for other data of the same shapes.

    Arguments:
        solver: one of :data:`~jaxafm.config.names.SOLVERS` (``library.method``).
        residuals: ``residuals(raw, args)``, the residual vector (least-squares solvers).
        loss: ``loss(raw, args)``, the scalar loss (minimisers: BFGS, L-BFGS).
        raw0: the start, a pytree of order-one parameters.
        max_steps: the step limit (function evaluations for scipy).
        rtol: relative tolerance.
        atol: absolute tolerance.
        args: the data, passed to ``residuals`` and ``loss``.
        curvature: how the geodesic solver has its second derivative
            (:func:`~jaxafm.identify.geodesic.solve`).

    Returns:
        ``(raw, steps, converged)``: the solution (the structure of ``raw0``), the steps taken
        and whether the solver met its tolerances.
    """
    library, method = solver.split(".")
    flat0, unravel, packed = _packed(raw0, args)
    if library == "optimistix":
        x, steps, ok = _optimistix(method, residuals, loss, flat0, packed, max_steps, rtol, atol)
    elif library == "jaxafm":  # Levenberg-Marquardt with geodesic acceleration, on the host
        x, steps, ok = geodesic.solve(_flat(residuals), flat0, packed, max_steps, rtol, atol, curvature)
    elif library == "scipy":
        x, steps, ok = _scipy(residuals, flat0, packed, max_steps, rtol, atol)
    else:
        x, steps, ok = _jaxopt(method, residuals, loss, flat0, unravel, args, max_steps, rtol, atol)
    return unravel(jnp.asarray(x)), steps, ok


def _optimistix(method: str, residuals, loss, flat0, packed, max_steps, rtol, atol) -> tuple:
    """:func:`solve` with optimistix (jitted): BFGS on ``loss``, else a least-squares solver."""
    if method == "bfgs":
        sol = optx.minimise(
            _flat(loss), optx.BFGS(rtol=rtol, atol=atol), flat0, packed, max_steps=max_steps, throw=False
        )
    else:
        cls = {
            "levenberg_marquardt": optx.LevenbergMarquardt,
            "gauss_newton": optx.GaussNewton,
            "dogleg": optx.Dogleg,
        }[method]
        # normal equations + Cholesky: the parameters are few, the residuals many (7x faster than QR)
        opt = cls(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
        sol = optx.least_squares(_flat(residuals), opt, flat0, packed, max_steps=max_steps, throw=False)
    return sol.value, int(sol.stats["num_steps"]), bool(sol.result == optx.RESULTS.successful)


def _scipy(residuals, flat0, packed, max_steps, rtol, atol) -> tuple:
    """:func:`solve` with scipy's trust-region reflective least squares on the host, the
    Jacobian by jax (forward mode); steps are function evaluations."""
    from scipy.optimize import least_squares

    fun, jac = _jitted(residuals)
    res = least_squares(
        lambda x: np.asarray(fun(x, packed)),
        np.asarray(flat0),
        jac=lambda x: np.asarray(jac(x, packed)),
        method="trf",
        max_nfev=max_steps,
        xtol=rtol,
        ftol=rtol,
        gtol=atol,
    )
    return res.x, int(res.nfev), bool(res.status > 0)


def _jaxopt(method: str, residuals, loss, flat0, unravel, args, max_steps, rtol, atol) -> tuple:
    """:func:`solve` with jaxopt: L-BFGS on ``loss``, Levenberg-Marquardt (relative step or
    gradient, as optimistix's rtol/atol) or Gauss-Newton on ``residuals``."""
    if method == "lbfgs":
        opt = jaxopt.LBFGS(fun=lambda x, a: loss(unravel(x), a), maxiter=max_steps, tol=atol)
    elif method == "levenberg_marquardt":
        opt = jaxopt.LevenbergMarquardt(
            residual_fun=lambda x, a: residuals(unravel(x), a),
            maxiter=max_steps,
            stop_criterion="madsen-nielsen",
            xtol=rtol,
            gtol=atol,
        )
    else:
        opt = jaxopt.GaussNewton(
            residual_fun=lambda x, a: residuals(unravel(x), a), maxiter=max_steps, tol=atol
        )
    flat, state = opt.run(flat0, args)
    steps = int(state.iter_num)
    return flat, steps, bool(steps < max_steps)


def clear_caches() -> None:
    """Forget the jitted residual functions and Jacobians kept for reuse (:func:`solve`'s), as
    ``jax.clear_caches`` forgets JAX's: the next solve compiles afresh (for timing a first solve)."""
    _flat.cache_clear()
    _jitted.cache_clear()


@functools.lru_cache(maxsize=64)
def _flat(fn: Callable) -> Callable:
    """``fn(raw, args)`` as a function of one flat vector ``x``, called with ``(tree, shapes,
    args)``: the same function object for the same ``fn``, so a solver compiled for it is reused."""

    def flat(x, packed):
        tree, shapes, args = packed
        sizes = np.cumsum([int(np.prod(s)) for s in shapes])[:-1]
        leaves = [v.reshape(s) for v, s in zip(jnp.split(x, sizes), shapes)]
        return fn(jax.tree_util.tree_unflatten(tree, leaves), args)

    return flat


def _packed(raw, args) -> tuple:
    """``raw`` as one flat vector (every solver gets one: a Jacobian of many leaves compiles once
    per leaf), its ``unravel``, and ``(tree, shapes, args)``, the argument of :func:`_flat`'s
    functions: the function and the tree's layout travel in it, so their compilation is reused."""
    flat, unravel = ravel_pytree(raw)
    leaves, tree = jax.tree_util.tree_flatten(raw)
    return flat, unravel, (tree, tuple(jnp.shape(v) for v in leaves), args)


def residual_values(residuals: Callable, raw, args) -> np.ndarray:
    """``residuals(raw, args)`` through the jitted function the geodesic solver uses
    (:func:`~jaxafm.identify.geodesic.compiled`): after such a fit, or for other data of the same
    shapes, nothing is compiled again."""
    flat, _, packed = _packed(raw, args)
    return np.asarray(geodesic.compiled(_flat(residuals))[0](np.asarray(flat, dtype=np.float64), packed))


def linearisation(residuals: Callable, raw, args) -> tuple:
    """``(r, J)``: ``residuals(raw, args)`` (n,) and their Jacobian (n, k) with respect to the flat
    parameters (``raw`` raveled, :func:`jax.flatten_util.ravel_pytree`'s order), through the
    jitted functions the geodesic solver uses: after such a fit nothing is compiled again."""
    flat, _, packed = _packed(raw, args)
    r, J = geodesic.compiled(_flat(residuals))[1](np.asarray(flat, dtype=np.float64), packed)
    return np.asarray(r), np.asarray(J)


@functools.lru_cache(maxsize=64)
def _jitted(residuals: Callable) -> tuple:
    """``residuals`` (:func:`_flat`) and its forward-mode Jacobian, jitted once."""
    return eqx.filter_jit(_flat(residuals)), eqx.filter_jit(jax.jacfwd(_flat(residuals)))


def bic(rss: float, n: int, k: int) -> float:
    """The Bayesian information criterion ``n ln(RSS / n) + k ln n`` of a least-squares fit.

    Arguments:
        rss: residual sum of squares (nm^2) over the training data.
        n: number of training residuals.
        k: number of free parameters.

    Returns:
        The BIC (dimensionless; only differences between fits to the same data mean anything).
    """
    return n * np.log(max(rss, 1e-300) / n) + k * np.log(n)


def error_metrics(pred, d, d_range: Optional[float] = None) -> dict:
    """rms and max error, in nm and in % of the output range."""
    pred, d = np.asarray(pred), np.asarray(d)
    d_range = float(d.max() - d.min()) if d_range is None else d_range
    e = pred - d
    rms, worst = float(np.sqrt(np.mean(e**2))), float(np.max(np.abs(e)))
    return {
        "rms_error_nm": rms,
        "max_error_nm": worst,
        "rms_error_pct": 100 * rms / d_range,
        "max_error_pct": 100 * worst / d_range,
    }


def inside_range(u, fitted) -> np.ndarray:
    """Which samples (T,) of the input ``u`` ((T,) or (T, A) V) lie inside the ``fitted`` range
    ((A, 2) V: one [min, max] per axis) on every axis."""
    lo, hi = np.asarray(fitted, dtype=float).reshape(-1, 2).T
    u = np.reshape(np.asarray(u, dtype=float), (len(u), -1))
    return np.all((u >= lo) & (u <= hi), axis=1)


def range_metrics(pred, d, inside: np.ndarray, d_range: float) -> dict:
    """:func:`error_metrics` on the samples ``inside`` the fitted input range (keys ``inside_``)
    and on the others (``outside_``, where there are any), and the share outside
    (``outside_share_pct``): a model scored beyond the range it was fitted on extrapolates."""
    pred, d = np.asarray(pred), np.asarray(d)
    out = {"outside_share_pct": 100 * float(np.mean(~inside))}
    for name, where in (("inside", inside), ("outside", ~inside)):
        if where.any():
            out |= {f"{name}_{k}": v for k, v in error_metrics(pred[where], d[where], d_range).items()}
    return out
