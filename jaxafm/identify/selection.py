"""The scanner model the data can support: a ladder of models climbed by an information criterion.

A calibration lattice shows its scanner at the features only: a few dozen points on each
branch. A model with more freedom than that (16 plays per axis, dead zones, creep, bow, lag)
fits the features it sees and swings between them, so a model that fits better is not one that
predicts better. Step A therefore climbs a ladder of models (:func:`select`) from the plainest
the configuration allows -- straight axes (a one-play PI operator), with the configured coupling
and feedback lag -- towards the configured one. At each step it tries every next rung: the plays
doubled or quadrupled (up to the configured number; Preisach levels likewise), or one more configured effect
(:data:`EFFECT_ORDER`), each started from the best model so far, and moves to the one with the
lowest score if that is lower than the best so far by :data:`MIN_GAIN` at least (forward stepwise
selection); it stops when no next rung lowers it that much. Models whose scores lie within 2 of
each other are about equally supported by the data (Burnham & Anderson 2002, section 2.6), and of
two such the plainer is kept: a richer rung that fits its training features no better than that
only swings more between them. An effect whose rung did not lower the best score at all at two
steps in a row is not tried again, to spare its fits (an effect may fail once, before the plays it needs, and
still be kept later).

The score is the small-sample Akaike information criterion of the training features
(:func:`aicc`): the features, not the chords, are the independent data (a feature's chords share
its shape irregularity), two coordinates each per image they show in, and a rung pays for each
parameter the data fix (its effective number, the trace of the fit's hat matrix), the more as
they approach the number of data.

Rate dependence needs scans at two line rates or more: one speed cannot tell a lag of the
scanner from a branch of its loop. Nor can any image tell a lag of the scanner from a delay of
the z signal (``feedback_lag``'s edge delay): both shift each edge by the tip's speed times the
delay. So the rate-dependence rung is tried only with several line rates and without
``feedback_lag``; otherwise it is not tried, and the reason is kept.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from .scan_model import ScanModelSpec, feature_reach

#: the effects after the plays, in the order the ladder tries them
EFFECT_ORDER = ("bow", "creep", "asymmetry", "drift", "rate_dependence")
#: effects the first rung keeps when configured: what any calibration pair shows first
BASE_EFFECTS = ("coupling", "feedback_lag")


@dataclasses.dataclass(frozen=True)
class Rung:
    """One model of the ladder and how it fared.

    Attributes:
        label: what the rung adds, in words.
        spec: the model.
        score: its information criterion (:func:`aicc`; NaN for a rung not tried).
        fit: how it fits, in words (the training features' rms residual, its parameters).
        kept: whether the ladder went on from it.
        reason: why it was kept or not, in words.
    """

    label: str
    spec: ScanModelSpec
    score: float
    fit: str
    kept: bool
    reason: str


@dataclasses.dataclass(frozen=True)
class RungFit:
    """What fitting one rung gives the ladder: the fitted ``model`` (whatever the caller fits),
    its ``score`` (lower is better, :func:`aicc`) and a ``note`` on how it fits."""

    model: object
    score: float
    note: str


def aicc(residuals_nm: np.ndarray, parameters: float) -> tuple:
    """``(score, note)``: Akaike's information criterion with its small-sample correction,
    ``n ln(RSS / n) + 2 k + 2 k (k + 1) / (n - k - 1)`` (Hurvich & Tsai 1989), of the training
    features' residuals (features, 2) nm, ``n`` their coordinates, ``k`` the ``parameters`` the
    data fix; infinite for ``k >= n - 1``; and the numbers in words."""
    e = np.asarray(residuals_nm, dtype=float).ravel()
    n, k, rss = e.size, float(parameters), float(np.sum(e**2))
    score = n * np.log(max(rss, 1e-300) / n) + 2 * k + 2 * k * (k + 1) / (n - k - 1) if k < n - 1 else np.inf
    return float(score), f"{n // 2} features {np.sqrt(rss / n * 2):.1f} nm rms, {k:.1f} parameters"


def supported_dead_zones(spec: ScanModelSpec, scans: tuple) -> tuple:
    """``(spec, note)``: ``spec`` with its dead zones inside the features' reach R from the centre
    (:func:`~jaxafm.identify.scan_model.feature_reach`), no more a side than they can hold, and
    why in words (empty when their number is unchanged). m a side sit ``R / (m + 1)`` apart; a
    stretch shorter than the pitch P may hold no feature, and a dead zone whose stretch holds
    none bends the axis between features where nothing shows it. So m is at most ``R / P - 1``
    on either axis (at least 1: the asymmetry rung needs one)."""
    if spec.kind != "gpi" or "asymmetry" not in spec.effects:
        return spec, ""
    spec = dataclasses.replace(spec, deadzone_reach=feature_reach(scans))
    pitch = min(scans[0].pitch)
    reach = min(min(-below, above) for below, above in spec.deadzone_reach)
    most = max(1, int(reach / pitch) - 1)
    if most >= spec.deadzones:
        return spec, ""
    note = (
        f"{most} dead zone{'s' * (most > 1)} a side, not {spec.deadzones}: the features reach "
        f"{reach:.4g} nm from the centre, {reach / pitch:.2g} pitches, and each dead zone's stretch "
        "must hold a pitch"
    )
    return dataclasses.replace(spec, deadzones=most), note


def base_spec(spec: ScanModelSpec) -> ScanModelSpec:
    """The ladder's first rung: straight axes (one play), with the configured base effects."""
    effects = tuple(e for e in spec.effects if e in BASE_EFFECTS)
    return dataclasses.replace(spec, kind="pi", effects=effects, operators=1)


#: the plays of the model that matches the retrace's lattice indices and aligns the scans
MATCHING_PLAYS = 4


def matching_spec(spec: ScanModelSpec) -> ScanModelSpec:
    """The model of step A's first chord stage when the ladder chooses the final one: the base
    rung with :data:`MATCHING_PLAYS` plays, loop enough to tell a retrace indexed a pitch off
    (whose loop would have to be a pitch wide near the reversals) from the right one, too little
    to fit such a loop as well (a model of many plays can)."""
    return dataclasses.replace(base_spec(spec), operators=min(MATCHING_PLAYS, max(spec.operators, 1)))


def _sizes(spec: ScanModelSpec) -> list:
    """The play counts (PI, generalised PI) or Preisach levels the ladder doubles through."""
    top = spec.levels if spec.kind == "preisach" else spec.operators
    sizes, n = [], 2
    while n < top:
        sizes.append(n)
        n *= 2
    return sizes + [top] if top > 1 else []


def _hysteresis(spec: ScanModelSpec, current: ScanModelSpec, n: int) -> ScanModelSpec:
    """``current`` with ``n`` plays (or Preisach levels, for a Preisach ``spec``)."""
    if spec.kind == "preisach":
        return dataclasses.replace(current, kind="preisach", levels=n)
    return dataclasses.replace(current, operators=n)


def select(spec: ScanModelSpec, fit: Callable, line_rates: Sequence[float], log: Callable = print) -> tuple:
    """Climb the ladder from :func:`base_spec` towards ``spec`` (module docstring).

    Arguments:
        spec: the richest model allowed (the configured one).
        fit: ``fit(rung_spec, start) -> RungFit``: the rung fitted from ``start`` (the best
            rung's fitted model so far, ``None`` for the first).
        line_rates: the scans' line rates (Hz).
        log: where each rung's line goes.

    Returns:
        ``(model, spec, rungs)``: the chosen rung's fitted model and spec, and every rung tried
        (:class:`Rung`) in order.
    """
    current = base_spec(spec)
    best = fit(current, None)
    rungs = [Rung("straight axes" + _with(current), current, best.score, best.note, True, "the first rung")]
    log(f"  model ladder: {rungs[0].label}: score {best.score:.1f} ({best.note})")
    reason = _rate_dependence(spec, line_rates)
    skipped = ["rate_dependence"] if reason else []
    strikes = {}
    if reason:
        rungs.append(Rung("+ rate_dependence", spec, float("nan"), "", False, reason))
        log(f"  model ladder: + rate_dependence: {reason}")
    while True:
        tried = [(label, cand, fit(cand, best.model)) for label, cand in _next(spec, current, skipped)]
        if not tried:
            break
        label, cand, new = min(tried, key=lambda t: t[2].score)
        kept = new.score <= best.score - MIN_GAIN
        for other, o_cand, o_new in tried:
            if other != label:
                note = "not kept (another rung scored lower)"
            else:
                note = (
                    f"kept ({best.score:.1f} -> {new.score:.1f})"
                    if kept
                    else f"not kept (not {MIN_GAIN:g} below {best.score:.1f})"
                )
            rungs.append(Rung(other, o_cand, o_new.score, o_new.note, kept and other == label, note))
            log(f"  model ladder: {other}: score {o_new.score:.1f} ({o_new.note}), {note}")
        for effect in _struck(tried, best.score, strikes):
            skipped.append(effect)
            log(
                f"  model ladder: + {effect}: not tried again (it lowered the score at neither of the last two steps)"
            )
        if not kept:
            break
        best, current = new, cand
    return best.model, current, rungs


#: how much a richer rung must lower the best score to be kept (module docstring)
MIN_GAIN = 2.0
#: how many steps in a row an effect's rung may fail to lower the best score at all before the
#: ladder stops trying it (a rung that lowers it by less than :data:`MIN_GAIN` is not kept, but
#: its effect is tried again: it may need plays still to come)
STRIKES = 2


def _struck(tried: list, best: float, strikes: dict) -> list:
    """The effects whose rungs have now failed to lower the ``best`` score :data:`STRIKES` steps in
    a row (``strikes``, per effect, counts them and is updated); play doublings are always tried."""
    out = []
    for label, _, new in tried:
        if not label.startswith("+ "):
            continue
        effect = label[2:]
        strikes[effect] = strikes.get(effect, 0) + 1 if new.score >= best else 0
        if strikes[effect] >= STRIKES:
            out.append(effect)
    return out


def _rate_dependence(spec: ScanModelSpec, line_rates: Sequence[float]) -> str:
    """Why the ladder does not try rate dependence (empty: it does)."""
    if "rate_dependence" not in spec.effects:
        return ""
    if len(set(line_rates)) < 2:
        return "not tried: one line rate cannot tell the scanner's lag from its loop; scan at two or more"
    if "feedback_lag" in spec.effects:
        return (
            "not tried: a lag of the scanner and the z signal's edge delay (feedback_lag) shift every edge "
            "alike, so the scans fix only their sum, the edge delay; leave feedback_lag out to give the lag "
            "to the scanner"
        )
    return ""


def _next(spec: ScanModelSpec, current: ScanModelSpec, skipped: list) -> list:
    """The rungs one step above ``current`` towards ``spec``: ``(label, spec)`` each."""
    now = current.levels if current.kind == "preisach" else current.operators
    what = "Preisach levels" if spec.kind == "preisach" else "plays"
    sizes = [n for n in _sizes(spec) if n > now][:2]  # two doublings ahead: one may not help where two do
    out = [(f"{n} {what} per axis", _hysteresis(spec, current, n)) for n in sizes]
    for effect in EFFECT_ORDER:
        if effect in spec.effects and effect not in current.effects and effect not in skipped:
            cand = dataclasses.replace(current, effects=current.effects + (effect,))
            if effect == "asymmetry":
                cand = dataclasses.replace(cand, kind=spec.kind)
            out.append((f"+ {effect}", cand))
    return out


def _with(spec: ScanModelSpec) -> str:
    return f" + {', '.join(spec.effects)}" if spec.effects else ""
