"""What the calibration scans determine of a fitted scanner: its physical quantities with their
standard deviations, and those the data leave open.

At the fitted model the chord stage's residuals ``r`` and their Jacobian ``J`` give the
parameters' covariance ``C`` (:func:`~jaxafm.identify.uncertainty.covariance`, cluster-robust
with each feature's chords one cluster: they share the feature's shape irregularity), with a
weak prior of one order-one unit of each raw parameter (its natural scale,
:meth:`~jaxafm.identify.scan_model.ScanModel.free_parameters`): a direction the data do not fix
keeps that width instead of the pseudo-inverse's zero. A quantity ``q(theta)`` of the model --
an axis's gain and loop, a creep rate, the coupling -- has the standard deviation
``sqrt(g^T C g)``, ``g`` its gradient (the delta method).

A quantity is *determined* when its standard deviation is at most a third of its size or its
resolution (:data:`RESOLUTION`, what is physically negligible: a loop of 0.2 % of the travel,
a coupling of 1e-3), whichever is larger: a loop of 0 +- 0.1 % is determined (there is none),
one of 50 +- 40 nm is not.

The loops are given twice: as each scan shows it (the model's retrace less its trace along the
fast axis, mid-line: what the data measure) and per axis over the whole drive range the scans
reach (a major loop the scans may never have traced: a scan turned against the piezo axes, or
a small one, drives each piezo over part of its range in each line, so the full loop is
extrapolated and may well be undetermined). An axis that no line drives back and forth
(:data:`MIN_STROKE`: a 0-degree scan's slow axis) shows one branch and no loop: its loop is
*not determined* whatever its sd, which measures only how well the model class's extrapolation
is pinned.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .calibration_scan import line_strokes
from .held_out import hat_trace
from .quantities import quantities as quantity_table
from .scan_model import ScanModel
from .stages import chord_linearisation, feature_groups, feature_keys
from .uncertainty import covariance

#: what is physically negligible, per unit of a quantity (its own units; % of travel for loops)
RESOLUTION = {
    "nm/V": 0.1,
    "% of travel": 0.2,
    "nm": 1.0,
    "per decade": 0.002,
    "s": 1e-4,
    "": 1e-3,
    "1/nm": 1e-8,
    "nm/s": 0.01,
    "deg": 0.01,
}


@dataclasses.dataclass(frozen=True)
class Quantity:
    """One physical quantity of the fitted model: ``value`` and ``sd`` in ``unit``; ``key``: its
    name in ``metrics.json``, units included."""

    key: str
    name: str
    value: float
    sd: float
    unit: str
    unmeasured: str = ""  # why the scans cannot show it at all, whatever its sd says

    @property
    def determined(self) -> bool:
        small = self.sd <= max(abs(self.value), 3 * RESOLUTION.get(self.unit, 0.0)) / 3
        return bool(small and not self.unmeasured)

    def line(self) -> str:
        state = "determined" if self.determined else "NOT determined"
        why = f" ({self.unmeasured})" if self.unmeasured else ""
        return f"{self.name:42s} {self.value:12.4g} +- {self.sd:10.3g} {self.unit:12s} {state}{why}"


#: the least stroke (a fraction of an axis's drive range) some line must drive a piezo back and
#: forth over for the scans to show that axis's loop: below it only the model class says how wide
#: the loop is, from the one branch the scans trace (a generalised PI's loop follows from its
#: branch's curvature; a real scanner's need not)
MIN_STROKE = 0.1


def _unmeasured_loops(scans: tuple) -> dict:
    """Per axis loop quantity the scans never trace, why (:func:`line_strokes`)."""
    return {
        f"{a}_loop_pct_of_travel": f"no line drives the {a} piezo back and forth over more than "
        f"{100 * MIN_STROKE:.0f} % of its range ({100 * stroke:.0f} %): the model class extrapolates it"
        for a, stroke in zip("xy", line_strokes(scans))
        if stroke < MIN_STROKE
    }


def chord_covariance(model: ScanModel, scans: tuple, chords: tuple) -> np.ndarray:
    """The covariance (k, k) of the model's raw parameters (raveled) from the chord stage's data
    ``chords`` on ``scans``: cluster-robust, one feature a cluster, with one order-one unit of
    each raw parameter and a Preisach density's smoothness prior where the data say nothing
    (module docstring)."""
    return _covariance(chords, chord_linearisation(model, scans, chords))


def _covariance(chords: tuple, linearised: tuple) -> np.ndarray:
    """:func:`chord_covariance` from the chords' linearisation ``(r, J, smooth)``."""
    r, J, smooth = linearised
    groups = feature_groups(chords, len(r))
    real = groups >= 0
    prior = np.mean(r[real] ** 2) * np.eye(J.shape[1]) + smooth
    return covariance(J[real], r[real], groups[real], prior)


#: the tip path's uncertainty in :func:`identifiability` is taken on at most about this many
#: lines of an image and pixels of a line (a smooth field: every pixel adds nothing but time)
PATH_SAMPLES = 64


class Determination(NamedTuple):
    """What the calibration scans determine of a fitted model (:func:`identifiability`): its
    ``quantities`` (:class:`Quantity`), ``path_sd_nm`` (2,) the rms over the images of how far
    the parameters the data leave open move the tip path along x and y
    (:func:`path_covariance`), and ``settles``, per quantity key the share (%) of that path
    variance which knowing the quantity exactly would remove."""

    quantities: list
    path_sd_nm: np.ndarray
    settles: dict

    @property
    def path_rms_nm(self) -> float:
        """The path's sd (nm), rms over the pixels, both axes together."""
        return float(np.sqrt(np.sum(self.path_sd_nm**2)))

    @property
    def settled_most(self) -> tuple:
        """``(quantity, share %)``: the :class:`Quantity` whose knowledge would settle most of
        the path's variance."""
        key, share = max(self.settles.items(), key=lambda item: item[1])
        return next(q for q in self.quantities if q.key == key), share


def identifiability(model: ScanModel, scans: tuple, chords: tuple, drive: np.ndarray) -> Determination:
    """The model's :class:`Quantity` list, each with its standard deviation from the chord
    stage's data ``chords`` on ``scans`` (module docstring), and the tip path's uncertainty on
    a grid of about :data:`PATH_SAMPLES` squared pixels an image: with ``P_p`` a pixel's
    position gradient and ``g`` a quantity's, knowing the quantity removes
    ``|P_p C g|^2 / g^T C g`` of the pixel's variance ``tr P_p C P_p^T`` (a Gaussian's
    conditional variance): ``settles`` is its sum over the pixels against the variance's."""
    model = model.as_float64()
    raw, rebuild = model.free_parameters(scans[0])
    C = chord_covariance(model, scans, chords)
    defined = quantity_table(model, scans, drive)
    q = lambda raw: jnp.stack([jnp.asarray(d.of(rebuild(raw)), dtype=float) for d in defined])
    flat, unravel = jax.flatten_util.ravel_pytree(raw)
    with (
        warnings.catch_warnings()
    ):  # an axis's loop over the whole drive may extrapolate: its sd says how far
        warnings.filterwarnings("ignore", message="a drive far beyond the model's range")
        value = np.asarray(q(unravel(flat)))
        G = np.asarray(jax.jacfwd(lambda x: q(unravel(x)))(flat))
    sd = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", G, C, G, optimize=True), 0.0))
    unmeasured = _unmeasured_loops(scans)
    quantities = [
        Quantity(d.key, d.name, v, s, d.unit, unmeasured.get(d.key, ""))
        for d, v, s in zip(defined, value.tolist(), sd.tolist())
    ]
    P = np.concatenate([g.reshape(-1, 2, g.shape[-1]) for g in _path_gradients(model, scans, PATH_SAMPLES)])
    variance = np.einsum("nij,jk,nik->ni", P, C, P, optimize=True)  # (N, 2) nm^2
    cross = np.einsum("nij,jk,qk->qni", P, C, G, optimize=True)  # the path's covariance with each quantity
    removed = np.sum(cross**2, axis=(1, 2)) / np.maximum(sd**2, 1e-300)
    shares = 100 * removed / max(float(np.sum(variance)), 1e-300)
    shares = dict(zip([d.key for d in defined], shares.tolist()))
    return Determination(quantities, np.sqrt(np.mean(variance, axis=0)), shares)


def _path_gradients(model: ScanModel, scans: tuple, samples: Optional[int] = None) -> list:
    """Per scan the tip path's gradient (2, lines, pixels, 2, k) in the model's raw parameters,
    trace and retrace, with the one rigid motion of the whole path that no image can see
    projected out of every column (a translation is the lattice's phase, a turn its angle); on
    about ``samples`` lines and pixels a line of each image (every one when None)."""
    raw, rebuild = model.free_parameters(scans[0])
    flat, unravel = jax.flatten_util.ravel_pytree(raw)

    def paths(x, scan):
        step = (
            [1, 1]
            if samples is None
            else [max(1, n // samples) for n in (scan.raster.lines, scan.raster.pixels)]
        )
        return jnp.stack(rebuild(unravel(x)).paths(scan))[:, :: step[0], :: step[1]]

    G = [np.asarray(jax.jacfwd(paths)(flat, scan)) for scan in scans]  # (2, lines, pixels, 2, k)
    shapes = [g.shape for g in G]
    G = np.concatenate([g.reshape(-1, 2, g.shape[-1]) for g in G])  # (N, 2, k)
    p = np.concatenate([np.asarray(paths(flat, scan)).reshape(-1, 2) for scan in scans])
    p = p - p.mean(axis=0)
    rigid = np.stack(
        [np.tile([1.0, 0.0], (len(p), 1)), np.tile([0.0, 1.0], (len(p), 1)), p @ [[0, 1], [-1, 0]]]
    )
    q, _ = np.linalg.qr(rigid.reshape(3, -1).T)  # (2N, 3) orthonormal rigid motions
    flatG = G.reshape(-1, G.shape[-1])
    G = (flatG - q @ (q.T @ flatG)).reshape(G.shape)
    return [
        g.reshape(shape)
        for g, shape in zip(np.split(G, np.cumsum([np.prod(s[:3]) for s in shapes])[:-1]), shapes)
    ]


def path_covariance(model: ScanModel, scans: tuple, chords: tuple) -> list:
    """How uncertain the fitted tip path is at every pixel, beyond the one rigid motion of the
    whole path that no image can see: per scan an array (2, lines, pixels, 2, 2) nm^2, trace and
    retrace, of ``G_p C G_p^T``, ``G_p`` the pixel's tip position's gradient (2, k) in the raw
    parameters with the rigid motions projected out (:func:`_path_gradients`), and ``C``
    :func:`chord_covariance` (the delta method, as for the quantities). Where the chords hold
    the path it is about their precision; where the model alone carries it (between the
    features and beyond their reach) it says how far the parameters the data leave open can
    move it."""
    model = model.as_float64()
    C = chord_covariance(model, scans, chords)
    return [np.einsum("...ij,jk,...lk->...il", g, C, g, optimize=True) for g in _path_gradients(model, scans)]


def path_sd(model: ScanModel, scans: tuple, chords: tuple) -> list:
    """The tip path's standard deviation (nm) at every pixel, ``sqrt`` of the trace of
    :func:`path_covariance`: per scan (2, lines, pixels)."""
    return [
        np.sqrt(np.maximum(np.trace(c, axis1=-2, axis2=-1), 0.0))
        for c in path_covariance(model, scans, chords)
    ]


# ---------------------------------------------------------------------------------------------
# Where the model puts a feature it did not train on, and how sure it is


def feature_points(chords: tuple, values: np.ndarray) -> tuple:
    """Per feature per image (a *point*), the mean of ``values`` (n, ...) over its chords along
    the lines and over those across them, for the rows of
    :func:`~jaxafm.identify.stages.chord_fit_residuals` over ``chords`` (their first, the
    midpoints' of :func:`~jaxafm.identify.stages.chord_residuals`; the lengths' left out):
    ``(keys, means)``, ``keys``
    (p, 3) the image's number (scan by scan, trace then retrace) and the feature's lattice
    indices, ``means`` (p, 2, ...). A chord's residual is its midpoint's offset from the
    feature's site along the chord, so the two means are how far the model misplaces the feature
    along each scan axis. Features with chords in one direction only (at an image's edge) are
    left out."""
    rows = [c for images in chords for c in images]
    image = np.concatenate([np.full(len(c.weight), i) for i, c in enumerate(rows)])
    along = np.concatenate([np.asarray(c.along, bool) for c in rows])
    real = np.concatenate([np.asarray(c.weight) > 0 for c in rows])
    midpoints = np.nan_to_num(feature_keys(chords))
    keys, point = np.unique(np.column_stack([image, midpoints])[real], axis=0, return_inverse=True)
    slot = 2 * point.ravel() + (~along[real])
    values = np.asarray(values)[: len(real)][real]  # the midpoints' rows
    count = np.bincount(slot, minlength=2 * len(keys)).reshape(-1, 2)
    sums = np.zeros((count.size,) + values.shape[1:])
    np.add.at(sums, slot, values)
    both = np.all(count > 0, axis=1)
    means = sums.reshape((-1, 2) + values.shape[1:]) / np.maximum(count, 1).reshape(
        (-1, 2) + (1,) * (values.ndim - 1)
    )
    return keys[both], means[both]


def feature_spread(model: ScanModel, scans: tuple, chords: tuple) -> np.ndarray:
    """The spread (2, 2) nm^2 of a feature's offsets (:func:`feature_points`, along and across
    the lines) about where the model puts it, beyond the parameters' error: the training points'
    offsets ``m`` as fitted, ``sum m m^T / p`` over the ``p`` points, with the degrees of freedom
    the fit took from them given back, ``N / (N - k)`` for the ``N = 2 p`` offsets and the ``k``
    parameters the data fix (:func:`~jaxafm.identify.held_out.fitted_parameters`; the unbiased
    ``RSS / (n - k)`` of least squares). It holds the chords' noise, the features' own
    irregularity and whatever of the model's error the training features show."""
    return _spread(chords, chord_linearisation(model, scans, chords), min(scans[0].pitch))


def _spread(chords: tuple, linearised: tuple, pitch: float) -> np.ndarray:
    """:func:`feature_spread` from the chords' linearisation ``(r, J, smooth)`` and the pitch (nm)
    its residuals are in."""
    m = feature_points(chords, linearised[0])[1] * pitch
    n, k = m.size, hat_trace(*linearised)
    return m.T @ m / len(m) * n / max(n - k, 1.0)


#: the levels of the predicted ellipses :func:`position_check` scores
LEVELS = (0.5, 0.9)


def ellipse_quantile(level: float) -> float:
    """The squared Mahalanobis radius that holds ``level`` of a 2-D Gaussian: ``-2 ln(1 - level)``
    (the chi-square quantile with two degrees of freedom)."""
    return -2.0 * np.log1p(-level)


class PointPredictions(NamedTuple):
    """Where the model puts features and how sure it is (:func:`point_predictions`): per point,
    its image and lattice indices ``keys`` (p, 3) (:func:`feature_points`), its ``offsets``
    (p, 2) nm along and across the lines, their predicted ``covariance`` (p, 2, 2) nm^2, and the
    parameters' part of it, ``parameters`` (p, 2, 2) nm^2."""

    keys: np.ndarray
    offsets: np.ndarray
    covariance: np.ndarray
    parameters: np.ndarray


def point_predictions(model: ScanModel, scans: tuple, train: tuple, test: tuple) -> PointPredictions:
    """Where the model puts the features of the chords ``test`` and how sure it is: each
    point's offset and its predicted covariance ``G C G^T + S``, ``G`` the offset's gradient in
    the raw parameters, ``C`` :func:`chord_covariance` and ``S`` :func:`feature_spread`, both
    from the training chords ``train`` (:func:`~jaxafm.identify.stages.chord_data`)."""
    pitch = min(scans[0].pitch)
    trained = chord_linearisation(model, scans, train)
    C, S = _covariance(train, trained), _spread(train, trained, pitch)
    r, J, _ = chord_linearisation(model, scans, test)
    keys, m = feature_points(test, r)
    G = feature_points(test, J)[1] * pitch
    parameters = np.einsum("pij,jk,plk->pil", G, C, G, optimize=True)
    return PointPredictions(keys, m * pitch, parameters + S, parameters)


def position_check(model: ScanModel, scans: tuple, train: tuple, test: tuple) -> dict:
    """How well the fit knows where it puts the features it did not train on: each held-out
    point's offset ``m`` against its predicted covariance ``S_m`` (:func:`point_predictions`
    of the held-out chords ``test`` from the training chords ``train``):

    - ``held_out_coverage_50_pct``, ``held_out_coverage_90_pct``: the held-out points inside
      their predicted 50 % and 90 % ellipses (``m^T S_m^-1 m`` at most
      :func:`ellipse_quantile`); a calibrated prediction holds 50 % and 90 %;
    - ``held_out_offsets_rms_nm``: the rms length of ``m``; ``held_out_predicted_rms_nm``: the
      rms length the prediction expects, ``sqrt(mean tr S_m)``;
    - ``held_out_parameters_share_pct``: the parameters' share of that expectation (the rest
      is :func:`feature_spread`: chords, features, the model's error)."""
    _, m, cov, parameters = point_predictions(model, scans, train, test)
    if not len(m):
        return {}
    d2 = np.einsum("pi,pij,pj->p", m, np.linalg.inv(cov), m)
    total = np.trace(cov, axis1=1, axis2=2)
    return {
        f"held_out_coverage_{round(100 * level)}_pct": float(100 * np.mean(d2 <= ellipse_quantile(level)))
        for level in LEVELS
    } | {
        "held_out_points": len(m),
        "held_out_offsets_rms_nm": float(np.sqrt(np.mean(np.sum(m**2, axis=1)))),
        "held_out_predicted_rms_nm": float(np.sqrt(np.mean(total))),
        "held_out_parameters_share_pct": float(
            100 * np.sum(np.trace(parameters, axis1=1, axis2=2)) / np.sum(total)
        ),
    }
