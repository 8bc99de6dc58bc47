"""Step A's plausibility checks: what makes a fitted scanner unusable, in words.

:func:`implausible`: a tip that travels far more or less than the image, a falling hysteresis
branch, creep against the move, a loop wider than its travel. :func:`unvalidated`: held-out
features misplaced by more than :data:`MAX_HELD_OUT_PITCH` of the pitch, or placed worse by the
correction than by the raw image (their rms residual or the spread of their local pitch), or
features whose widths the correction makes less uniform than the raw image's (:func:`uneven_widths`).
:func:`undetermined`: an axis's loop the data leave open
(:class:`~jaxafm.identify.identifiability.Quantity`). :func:`unsettled`: a tip path the data
leave more open than both a held-out feature's place and the precision the task asks for.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from ..config.names import KNOWABLE
from ..model.hysteresis import AbstractHysteresis
from ..model.io import check_monotone
from ..model.scanner import Scanner
from .held_out import WIDTH_WAYS
from .scan_model import ScanModel

Array = jax.Array

#: how far (a fraction of the step) a fitted creep's step response may fall back or below the
#: step before the model counts as creeping against the move: 0.1 %, 3 nm after a 3 µm move,
#: under the calibration image's feature precision and 1/40 of the creep of 0.01 per decade
#: over the four decades of the bank
CREEP_FALL = 1e-3


def implausible(model: ScanModel, scans: tuple) -> list:
    """What makes a fitted model unusable, in words (empty: plausible): per scan, the tip's
    travel along the fast axis over the image outside 0.5 to 2 times the image's width; a
    hysteresis branch that falls (:func:`~jaxafm.model.io.check_monotone`); creep of the
    wrong sign (it must continue the move, :func:`creep_fall`); a loop wider than the travel."""
    failures = []
    for scan in scans:
        path = np.asarray(model.paths(scan)[0]).reshape(-1, 2)
        travel = float(np.ptp(path @ scan.raster.rotation[:, 0]))
        ratio = travel / scan.raster.size[0]
        if not 0.5 < ratio < 2:
            failures.append(
                f"{scan.name}: the tip travels {travel / 1e3:.4g} µm along the fast axis over a "
                f"{scan.raster.size[0] / 1e3:.4g} µm image ({ratio:.2f} times its width)"
            )
    try:
        check_monotone(model.scanner)
    except ValueError as e:
        failures.append(f"a hysteresis branch falls: {e}")
    for a in ("x", "y"):
        creep = getattr(model.scanner, a).creep
        fall = None if creep is None else creep_fall(creep)
        if fall is not None and fall > CREEP_FALL:
            failures.append(
                f"{a} creep runs against the move: after a step its response falls back by "
                f"{100 * fall:.2g} % of the step (allowed {100 * CREEP_FALL:g} %)"
            )
    failures += _loop_widths(model.scanner, scans)
    return failures


#: the largest held-out feature residual (rms, a fraction of the pitch) a usable model may leave:
#: beyond it a model cannot even tell the lattice's sites apart reliably
MAX_HELD_OUT_PITCH = 0.05


def unvalidated(validation: dict, pitch: float) -> list:
    """What the held-out features say against a fitted model, in words (empty: nothing):
    ``validation`` as :func:`~jaxafm.identify.held_out.validate` gives it, ``pitch`` nm."""
    if not validation.get("held_out_features"):
        return []
    out = []
    rms, raw = validation["held_out_rms_nm"], validation["held_out_raw_rms_nm"]
    if rms > MAX_HELD_OUT_PITCH * pitch:
        out.append(
            f"the held-out features are misplaced by {rms:.4g} nm rms, more than "
            f"{100 * MAX_HELD_OUT_PITCH:g} % of the {pitch:.4g} nm pitch"
        )
    if rms >= raw:
        out.append(
            f"the correction misplaces the held-out features more than the raw image ({rms:.4g} nm rms "
            f"against {raw:.4g} nm)"
        )
    spread = validation["held_out_pitch_std_corrected_pct"], validation["held_out_pitch_std_raw_pct"]
    if spread[0] > spread[1]:
        out.append(
            f"the correction makes the held-out features' local pitch less uniform ({spread[0]:.3g} % "
            f"spread against {spread[1]:.3g} % raw)"
        )
    return out + uneven_widths(validation)


#: the level of the one-sided F test by which :func:`uneven_widths` calls the corrected features'
#: widths less uniform than the raw ones
WIDTH_LEVEL = 0.99


def uneven_widths(validation: dict) -> list:
    """Where the correction makes the features' widths less uniform than the raw image, in words
    (:func:`~jaxafm.identify.held_out.feature_widths`, along the lines and across them): their
    corrected spread's square against the raw one's beyond the ``WIDTH_LEVEL`` quantile of the
    F distribution with ``n - 1`` and ``n - 1`` degrees of freedom for ``n`` widths (the test of
    two independent samples' spreads; the raw and corrected widths of a feature share its edges'
    noise, which brings their spreads closer, so chance alone refuses less often than the
    level says). A lattice's features are
    one shape: a path that runs too fast or too slow across some of them (one that slips a
    lattice row between features, say, while the chords' midpoints still fit) shows here."""
    out = []
    for way in WIDTH_WAYS:
        n = validation.get(f"feature_widths_{way}", 0)
        raw = validation.get(f"feature_width_spread_{way}_raw_pct")
        corrected = validation.get(f"feature_width_spread_{way}_corrected_pct")
        if n < 3 or not raw or not np.isfinite(raw) or not np.isfinite(corrected):
            continue
        allowed = float(np.sqrt(scipy.stats.f.ppf(WIDTH_LEVEL, n - 1, n - 1)))
        if corrected > allowed * raw:
            out.append(
                f"the correction makes the features' widths {way} the lines less uniform "
                f"({corrected:.3g} % spread against {raw:.3g} % raw over {n} widths, more than the "
                f"{allowed:.2f} times chance allows): the fitted path runs too fast or too slow "
                "across some features; solver.chord_lengths: true fits the chords' lengths too"
            )
    return out


def undetermined(quantities: list) -> list:
    """A scan's loop that the scans leave open, in words
    (:attr:`~jaxafm.identify.identifiability.Quantity.determined`): a model whose loop is a guess
    where it was measured cannot compensate it."""
    return [
        f"the scans do not determine the {q.name} ({q.value:.3g} +- {q.sd:.3g} {q.unit}): scan at more "
        "line rates or angles, or a lattice with more features along each line"
        for q in quantities
        if q.key.startswith("loop_scan") and not q.determined
    ]


#: the tip path's uncertainty (rms over the images, a fraction of the scans' finest pixel) step A
#: tolerates unless told (``solver.path_tolerance_nm``): a tenth of a pixel, the precision the
#: images can place a feature to and the tip path goal of docs/step_a.md
PATH_TOLERANCE_PX = 0.1


def path_tolerance_nm(scans: tuple, tolerance_nm=None) -> float:
    """The tip path uncertainty (nm) step A tolerates: ``tolerance_nm`` when given, else
    :data:`PATH_TOLERANCE_PX` of the finest pixel of ``scans``."""
    if tolerance_nm is not None:
        return float(tolerance_nm)
    return PATH_TOLERANCE_PX * min(min(s.raster.pixel_size) for s in scans)


#: how :func:`unsettled`'s reason begins
PATH_OPEN = "the scans leave the tip path open"


def path_open(path_nm: float, expected_nm: float, tolerance_nm: float) -> bool:
    """:func:`unsettled`'s rule: the path's sd ``path_nm`` exceeds both a held-out feature's
    predicted error ``expected_nm`` and the tolerance ``tolerance_nm`` (all nm rms)."""
    return path_nm > max(expected_nm, tolerance_nm)


def unsettled(determination, validation: dict, tolerance_nm: float) -> list:
    """A tip path the scans leave open, in words: the parameters the data do not fix move the
    path (rms over the images, :class:`~jaxafm.identify.identifiability.Determination`) by
    more than both the error the fit predicts for a held-out feature
    (``held_out_predicted_rms_nm``, :func:`~jaxafm.identify.identifiability.position_check`)
    and ``tolerance_nm``, the precision the task asks for (:func:`path_tolerance_nm`). The
    held-out features check the model where they are; between and beyond them it is the model
    alone that places the tip, and a path less certain there than a feature is placed has not
    been checked, unless it is still as certain as the task needs (a fit whose features sit to
    a nanometre need not fix its path to one). Names the quantity whose knowledge would settle
    most of it, and how to state it where the user may know it (a calibration model's
    ``known``, :data:`~jaxafm.config.names.KNOWABLE`)."""
    expected = validation.get("held_out_predicted_rms_nm")
    path = determination.path_rms_nm
    if expected is None or not path_open(path, expected, tolerance_nm):
        return []
    q, share = determination.settled_most
    x, y = determination.path_sd_nm
    return [
        f"{PATH_OPEN}: the parameters they do not fix move it by {path:.4g} nm "
        f"rms over the images (x {x:.4g}, y {y:.4g} nm), more than the {expected:.4g} nm a held-out "
        f"feature is predicted to be placed to and the {tolerance_nm:.4g} nm the path may be open "
        f"(solver.path_tolerance_nm); knowing the {q.name} ({q.value:.4g} +- {q.sd:.3g} {q.unit}) "
        f"would settle {share:.0f} % of it: {_state_it(q)}scan at more line rates or angles, or a "
        "lattice with more features"
    ]


def _state_it(q) -> str:
    """How to tell step A a quantity the user may know (:func:`unsettled`), or nothing."""
    if q.key not in KNOWABLE:
        return ""
    return f"state it if you know it (the model's known: {{{q.key}: [value, sd]}}), or "


def creep_fall(creep) -> float:
    """How far (a fraction of the step) the step response ``sum_k g_k (1 - exp(-t / tau_k))`` of
    ``creep`` falls below its running maximum or below zero, for t from tau_min / 10 to
    10 tau_max: 0 for creep that continues the move (every weight non-negative)."""
    taus, g = np.asarray(creep.taus), np.asarray(creep.weights)
    t = np.geomspace(taus.min() / 10, taus.max() * 10, 400)
    r = np.concatenate([[0.0], (g * (1 - np.exp(-t[:, None] / taus))).sum(axis=1)])
    return float(np.max(np.maximum.accumulate(r) - r))


@eqx.filter_jit
def _swept(h: AbstractHysteresis, u: Array, history: Array) -> Array:
    """``h(u, history)``, compiled once for both axes' operators (op by op it compiles each step)."""
    return h(u, history)


def _loop_widths(scanner: Scanner, scans: tuple) -> list:
    """A loop over the drive the scans used that is wider than its own travel, per axis."""
    u = np.concatenate([s.raster.wanted().reshape(-1, 2) / np.asarray(s.sensitivity) for s in scans])
    out = []
    for k, a in enumerate("xy"):
        lo, hi = u[:, k].min(), u[:, k].max()
        sweep = np.concatenate([np.linspace(lo, hi, 200), np.linspace(hi, lo, 200)])
        d = np.asarray(_swept(getattr(scanner, a).hysteresis, jnp.asarray(sweep), jnp.asarray([hi, lo])))
        up, down = d[:200], d[200:][::-1]
        travel, width = float(np.ptp(d)), float(np.max(np.abs(down - up)))
        if width > travel:
            out.append(f"the {a} loop is {width:.4g} nm wide over a travel of {travel:.4g} nm")
    return out
