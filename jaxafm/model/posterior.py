"""A fitted model's uncertainty, and the band it puts around a prediction.

A :class:`Posterior` is a Gaussian at a fit's solution, made from the fit's residuals and their
Jacobian (:func:`linearise`) by :func:`jaxafm.identify.uncertainty.posterior_of`: over the fit's
raw parameters ``theta`` (the model's ``free_parameters(input_span_v, output_range_nm)``,
order-one numbers), centred on the fitted model's, with covariance ``C`` (the fitted estimate's
spread under the noise model), and the spread ``s`` (nm) a new measurement has about the model
where its parameters are right: the noise plus what the model class leaves unexplained, as
measured out of sample on the training record.

The band (:func:`band`) of a prediction ``y(theta)`` at each sample is

    sd_t^2 = g_t^T C g_t + s^2,    g_t = d y_t / d theta,
    y_t +- z sd_t,                 z = Phi^-1((1 + level) / 2),

the delta method for the parameters plus the measurement's own spread (Bishop 2006, sec. 5.7.3).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from scipy.stats import norm

from .. import checks
from .apply import evaluator
from .hysteresis import Preisach

#: the noise models a posterior is made with (:func:`jaxafm.identify.uncertainty.posterior_of`)
METHODS = ("ar1", "blocks", "iid")


@dataclasses.dataclass(frozen=True)
class Posterior:
    """A Gaussian over a fitted model's raw parameters and a new measurement's spread.

    Attributes:
        covariance: (k, k) of the raw parameters ``model.free_parameters(input_span_v,
            output_range_nm)[0]``, raveled (:func:`jax.flatten_util.ravel_pytree`'s order).
        residual_sd_nm: ``s``, a new measurement's spread about the model (nm).
        input_span_v: the fitted input's span (V), which sets the raw parameters' scale.
        output_range_nm: the fitted output's range (nm), likewise.
        method: the noise model it was made with (one of :data:`METHODS`).
        block_samples: the samples of one block of correlated residuals, over which the spread
            was measured out of sample (1 for ``iid``).
    """

    covariance: np.ndarray
    residual_sd_nm: float
    input_span_v: float
    output_range_nm: float
    method: str
    block_samples: int = 1

    def to_dict(self) -> dict:
        """The JSON form a model file keeps (:func:`jaxafm.model.io.save_model`)."""
        return dataclasses.asdict(self) | {"covariance": np.asarray(self.covariance).tolist()}

    @classmethod
    def from_dict(cls, doc, model, where: str = "uncertainty") -> Posterior:
        """The posterior ``doc`` (:meth:`to_dict`) of ``model``, checked.

        Raises:
            ValueError: naming ``where`` and the key: a missing or unknown key, a method not in
                :data:`METHODS`, a covariance that is not square with one row per raw parameter
                of ``model``, not symmetric, not finite or not positive definite, a spread,
                span or range that is not finite and > 0.
        """
        if not isinstance(doc, dict) or set(doc) != {f.name for f in dataclasses.fields(cls)}:
            keys = sorted(doc) if isinstance(doc, dict) else type(doc).__name__
            raise ValueError(
                f"{where}: keys {keys}, expected {sorted(f.name for f in dataclasses.fields(cls))}"
            )
        if doc["method"] not in METHODS:
            raise ValueError(f"{where}.method: {doc['method']!r} is not one of {', '.join(METHODS)}")
        for key in ("residual_sd_nm", "input_span_v", "output_range_nm"):
            checks.positive(f"{where}.{key}", doc[key])
        post = cls(**(doc | {"covariance": np.asarray(doc["covariance"], dtype=float)}))
        k = raw_parameters(model, post).size
        _check_covariance(post.covariance, k, f"{where}.covariance")
        return post


def _check_covariance(C: np.ndarray, k: int, where: str) -> None:
    """Refuse a covariance that is not (k, k), finite, symmetric and positive definite."""
    if C.shape != (k, k):
        raise ValueError(f"{where}: shape {C.shape}, but the model has {k} raw parameters: ({k}, {k})")
    if not np.all(np.isfinite(C)):
        raise ValueError(f"{where}: holds a number that is not finite")
    scale = np.max(np.abs(C))
    if np.max(np.abs(C - C.T)) > 1e-9 * scale:
        raise ValueError(f"{where}: not symmetric (largest |C - C^T| {np.max(np.abs(C - C.T)):.3g})")
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        low = float(np.linalg.eigvalsh(C)[0])
        raise ValueError(
            f"{where}: not positive definite (smallest eigenvalue {low:.3g}); was the file edited by hand?"
        ) from None


def raw_parameters(model, posterior: Posterior) -> np.ndarray:
    """The flat raw parameters (k,) of ``model`` in the posterior's scale."""
    raw, _ = model.free_parameters(posterior.input_span_v, posterior.output_range_nm)
    return np.asarray(ravel_pytree(raw)[0])


@dataclasses.dataclass(frozen=True)
class Band:
    """A prediction ``mean`` (T,) nm with its predictive ``sd`` (T,) nm (module docstring) and
    the ``level`` of its band."""

    mean: np.ndarray
    sd: np.ndarray
    level: float

    def bounds(self, level: Optional[float] = None) -> tuple:
        """``(lower, upper)`` (T,) nm at ``level`` (default: the band's)."""
        z = float(norm.ppf(0.5 + check_level(self.level if level is None else level) / 2))
        return self.mean - z * self.sd, self.mean + z * self.sd

    def coverage(self, measured, level: Optional[float] = None, start: int = 0) -> float:
        """The fraction of ``measured`` (T,) nm inside the band at ``level``, from sample
        ``start`` on."""
        lower, upper = (b[start:] for b in self.bounds(level))
        measured = np.asarray(measured)[start:]
        return float(np.mean((measured >= lower) & (measured <= upper)))

    def width(self, level: Optional[float] = None, start: int = 0) -> float:
        """The band's mean width (nm) at ``level``, from sample ``start`` on."""
        lower, upper = self.bounds(level)
        return float(np.mean(upper[start:] - lower[start:]))


def check_level(level, where: str = "level") -> float:
    """``level`` as a float in (0, 1), or a ValueError naming ``where`` and the value."""
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0 < level < 1:
        raise ValueError(f"{where}: {level!r} is not a probability in (0, 1), e.g. 0.9 for a 90 % band")
    return float(level)


def band(model, posterior: Optional[Posterior], u, t=None, history=None, level: float = 0.9) -> Band:
    """The prediction of a one-axis ``model`` for the input ``u`` (T,) V (times ``t`` (T,) s,
    ``history`` as :func:`jaxafm.model.apply.predict`) with its band at ``level``.

    Raises:
        ValueError: ``level`` outside (0, 1), or no ``posterior`` (a model file written without
            one: refit it with ``jaxafm fit`` to have one).
    """
    level = check_level(level)
    if posterior is None:
        raise ValueError(
            "the model has no uncertainty (its file holds none: models from `jaxafm fit` carry one); "
            "refit it with `jaxafm fit` for a band, or predict without one"
        )
    y, G = linearise(model, posterior.input_span_v, posterior.output_range_nm, u, t, history)
    return linear_band(y, G, posterior, level)


def linear_band(y: np.ndarray, G: np.ndarray, posterior: Posterior, level: float = 0.9) -> Band:
    """The band about the prediction ``y`` (T,) nm whose Jacobian with respect to the
    posterior's raw parameters is ``G`` (T, k) (module docstring): ``g_t^T C g_t`` a block of
    :data:`BAND_ROWS` rows at a time, so that no (T, k) product is stored beside ``G``."""
    G, C = np.asarray(G), posterior.covariance
    var = np.empty(len(G))
    for start in range(0, len(G), BAND_ROWS):
        g = G[start : start + BAND_ROWS]
        var[start : start + BAND_ROWS] = np.einsum("ij,ij->i", g @ C, g)
    return Band(np.asarray(y), np.sqrt(var + posterior.residual_sd_nm**2), check_level(level))


#: rows of a band's Jacobian taken at a time by :func:`linear_band`
BAND_ROWS = 1024


def linearise(model, input_span_v: float, output_range_nm: float, u, t=None, history=None) -> tuple:
    """``(y, G)``: the one-axis ``model``'s prediction (T,) nm for the input ``u`` (T,) V and
    its Jacobian (T, k) with respect to the raw parameters
    ``model.free_parameters(input_span_v, output_range_nm)`` (raveled), by forward mode through
    the fit's evaluator (:func:`~jaxafm.model.apply.evaluator`: the plays run once, outside the
    derivative); a Preisach plane's in closed form (:func:`_linear_in_density`)."""
    u = jnp.asarray(u, dtype=float)
    t = None if t is None else jnp.asarray(t, dtype=float)
    history = None if history is None else jnp.asarray(history, dtype=float)
    y, G = _linearise(model, u, t, history, float(input_span_v), float(output_range_nm))
    return np.asarray(y), np.asarray(G)


#: XLA's options for :func:`_linearise`, which a fit or a prediction runs once: its compilation,
#: not its run, is most of its time, and XLA's backend optimisation level 0 shortens the one more
#: than it lengthens the other (``experiments/bench_band.py`` times both, each model at both levels)
ONE_SHOT = {"xla_backend_optimization_level": 0}


@eqx.filter_jit(compiler_options=ONE_SHOT)
def _linearise(model, u, t, history, input_span_v: float, output_range_nm: float) -> tuple:
    """:func:`linearise`, jitted: the spans are static, the model and the data traced."""
    raw, rebuild = model.free_parameters(input_span_v, output_range_nm)
    flat, unravel = ravel_pytree(raw)
    to_model = lambda x: rebuild(unravel(x))
    if type(model) is Preisach:
        return _linear_in_density(model, u, history, to_model, flat)
    forward = evaluator(model, u, t, history)
    f = lambda x: forward(to_model(x))
    return f(flat), jax.jacfwd(f)(flat)


def _linear_in_density(model: Preisach, u, history, to_model, flat) -> tuple:
    """``(y, G)`` of a Preisach plane, whose output is linear in its density:
    ``y = offset + R w`` with ``R`` (T, m) the lower triangle's relay states
    (:meth:`~jaxafm.model.hysteresis.Preisach.design_matrix`) and ``w`` (m,) its densities. Each
    raw parameter sets one density (through softplus) or the offset
    (:meth:`~jaxafm.model.hysteresis.Preisach.free_parameters`), so ``d(w, offset) / d theta`` is
    diagonal and ``G = [R, 1] diag(d(w, offset) / d theta)``: one column scaling, where forward
    mode would carry each of the k tangents through the (T, n, n) relay states."""
    tri = model._triangle()
    weights = lambda x: (lambda m: jnp.append(m.density[tri], m.offset))(to_model(x))
    R = jnp.column_stack([model.design_matrix(u, history), jnp.ones(u.shape[0])])
    w, slopes = jax.jvp(weights, (flat,), (jnp.ones_like(flat),))  # the diagonal's entries
    return R @ w, R * slopes
