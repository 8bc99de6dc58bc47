"""The diagnosis core: typed results, one BIC, one ranking and verdict, one table of skip reasons.

A diagnosis fits a nominal model to the training part of some data, then the nominal model
plus each candidate effect, and compares them on the held-out part, which no fit saw. Every
kind of data -- an actuator record (:class:`~jaxafm.diagnose.record.ActuatorRecord`), one
grating image (:class:`~jaxafm.diagnose.image.GratingImage`), a set of trace/retrace scans
(:class:`~jaxafm.diagnose.scans.ScanSet`) -- is a :class:`DataKind`: it holds its data and
supplies its nominal fit, its candidate fits and its own analysis and figure panels. The rest
is here, the same for all:

- the gap is the held-out misfit in nm (each kind says how it measures it); a candidate's
  shrink is ``100 (1 - gap_after / gap_before)`` %;
- the Bayesian information criterion of a training fit with ``n`` residuals, residual sum of
  squares ``RSS`` and ``k`` free parameters is

      BIC = n ln(RSS / n) + k ln n;

- a candidate is significant when it shrinks the gap by at least ``Rules.min_shrink_pct`` %
  *and* lowers the BIC by at least ``Rules.min_delta_bic`` against the nominal model (Kass &
  Raftery: 10 is "very strong" evidence);
- an effect the data's held-out part cannot test is judged on the same data split otherwise
  (:meth:`DataKind.judged_on`: a record's drift on alternating blocks where it holds out its
  later part), against the nominal model and the shape found refitted on that split;
  the candidate says which split judged it;
- candidates are ranked by shrink, best first; the verdict is the top significant one, or none;
  where significant candidates were judged on different splits, their shrinks are not comparable:
  they are compared on one split, the one the others were judged on (:func:`_on_one_split`), and
  where their gaps there come within ``Rules.min_shrink_pct`` % of the best's, the held-out part
  cannot separate them and the lowest delta BIC decides, every fit's scored under the same
  noise model (:func:`by_evidence`, :attr:`Fit.evidence`);
- a candidate that cannot be tried on the data is skipped with its reason (:data:`NOT_TRIED`);
- before the effects, a kind may try richer hysteresis operators, one rung at a time
  (:attr:`DataKind.shapes`: symmetric PI -> twice the plays -> generalised PI -> Preisach for
  records), each started from the richest significant rung below it: a rung that is significant
  against that one replaces it, and the effects are then compared against
  the richest significant rung, so an effect is blamed only for what a richer hysteresis cannot
  explain. When a rung is found and no effect on top of it, each effect is also added to the
  nominal model: one that is significant there, with a training BIC and a held-out gap no worse
  than the rung's, explains the misfit more simply, and the effects are ranked on the nominal.
  When an effect is found with a rung, the rung is checked once more with the effect in both
  models; a rung that is no longer significant then is dropped from the finding (its misfit was
  the effect's).

The writer of ``diagnosis.json``, ``metrics.json``, ``report.md`` and ``residuals.png`` is
:func:`jaxafm.diagnose.report.write`. Units: nm, s, V (``docs/conventions.md``).
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar, Optional

import numpy as np

from ..config.names import check_effect_names
from ..identify.fit import NESTING_TOLERANCE, bic

#: Why an effect that is not in the nominal model cannot be tried: ``{kind name: {effect: reason}}``
#: (the kinds: ``record``, ``image``, ``scans``). Every kind also skips :data:`NOISE` and the
#: effects its nominal model has (:data:`IN_NOMINAL`).
IN_NOMINAL = "already in the nominal model"
NOISE = "white noise is what the residual should be; it is no candidate"
_IMAGING = "an imaging effect: it needs AFM images, not an actuator record"
_TWO_AXES = "needs a record with two axes (t, ux, uy, x, y)"
_REPEATED = "needs an actuator record or images repeated over minutes"
NOT_TRIED = {
    "record": {
        "feedback_lag": _IMAGING,
        "feedback_asymmetry": _IMAGING,
        "tip": _IMAGING,
        "coupling": _TWO_AXES,
        "bow": _TWO_AXES,
        "asymmetry": "a hysteresis shape, not an effect: tried on the shape ladder (symmetric PI -> "
        "twice the plays -> generalised PI -> Preisach), where a Preisach density holds its own asymmetry",
    },
    "image": {
        "drift": "in one image a steady x drift shifts each row in proportion to its time, the same column "
        "as coupling (skew): image twice, or in both slow-axis directions, to tell them apart",
        "asymmetry": "one image holds one branch of the loop; its shape is the nominal nonlinearity: needs "
        "trace and retrace",
        "rate_dependence": "needs images at two scan speeds",
        "feedback_lag": "its edge shift v tau is the same on every edge of one image and the edge phases "
        "absorb it: needs trace and retrace, or two scan speeds",
        "feedback_asymmetry": "in one image it moves every falling edge alike (by about v tau_fall) and the "
        "falling edges' phase absorbs it: needs trace and retrace (the slow side swaps) at two scan speeds",
        "tip": "its widening of the grooves is the same on every row and the two edge phases absorb it: "
        "needs a tip characteriser or a sample of known width",
    },
    "scans": {
        "asymmetry": "the nominal model fits the trace and retrace branches apart, asymmetric or not",
        "creep": _REPEATED,
        "drift": _REPEATED,
    },
}


#: The richer hysteresis operators a diagnosis may find, in words.
SHAPE_NAMES = {
    "finer": "finer (twice the plays)",
    "gpi": "asymmetric (generalised PI)",
    "preisach": "Preisach",
}


@dataclasses.dataclass(frozen=True)
class Rules:
    """When a candidate counts: the held-out gap shrinks by ``min_shrink_pct`` % and the training
    BIC falls by ``min_delta_bic``; iterative fits stop after ``max_steps`` solver steps."""

    min_shrink_pct: float = 5.0
    min_delta_bic: float = 10.0
    max_steps: int = 300


@dataclasses.dataclass(frozen=True, eq=False)
class Fit:
    """A model fitted to the training part of the data (a kind adds what it keeps of its model).

    Attributes:
        residual: measured - model (nm) at every datum, trained on and held out.
        parameters: free parameters ``k`` of the fit.
        train_rms_nm: ``sqrt(RSS / n)`` over the ``n`` training residuals (nm).
        heldout_gap_nm: the misfit on the held-out part (nm; each kind says how it measures it).
        bic: the training fit's :func:`bic`.
    """

    residual: np.ndarray
    parameters: int
    train_rms_nm: float
    heldout_gap_nm: float
    bic: float

    @staticmethod
    def scores(rss: float, n: int, k: int) -> dict:
        """``parameters``, ``train_rms_nm`` and ``bic`` of a training fit with ``n`` residuals,
        residual sum of squares ``rss`` (nm^2) and ``k`` free parameters."""
        return {"parameters": k, "train_rms_nm": float(np.sqrt(rss / n)), "bic": bic(rss, n, k)}

    @property
    def evidence(self) -> Optional[float]:
        """The training BIC under a noise model every fit of the kind shares, where the kind's
        fits score their BICs under different ones (a record's drift models the residual's
        colour); ``None``: :attr:`bic` is that already. :func:`by_evidence` weighs it."""
        return None

    def shown(self) -> dict:
        """What a candidate row of ``diagnosis.json`` shows of this fit beside the common numbers."""
        return {}

    def summary(self) -> dict:
        """The numbers of the ``nominal`` section of ``diagnosis.json``."""
        return {
            "train_rms_nm": self.train_rms_nm,
            "heldout_gap_nm": self.heldout_gap_nm,
            "parameters": self.parameters,
        }


@dataclasses.dataclass(frozen=True, eq=False)
class Candidate:
    """One candidate effect tried: the nominal model plus ``effect``, refitted and compared.

    Attributes:
        effect: the effect's name (``docs/conventions.md``).
        heldout_gap_before_nm: the nominal model's held-out gap (nm).
        heldout_gap_after_nm: the held-out gap with the candidate (nm).
        shrink_pct: ``100 (1 - after / before)`` %.
        train_rms_after_nm: the training rms with the candidate (nm).
        delta_bic: the training BIC with the candidate minus the nominal's.
        extra_parameters: the parameters the candidate adds.
        significant: whether it passes both :class:`Rules`.
        fit: the candidate's :class:`Fit`.
        trains_worse: a candidate effect trains worse than the model it was added to (by more
            than :data:`~jaxafm.identify.fit.NESTING_TOLERANCE`): started there, where it changes
            nothing, its best fit cannot, so its solver stopped short of it (a failure, not a
            finding).
        judged_on: the split it was judged on, where it is not the data's own
            (:meth:`DataKind.judged_on`), else ``""``.
        nominal_gap_nm: the nominal model's held-out gap on that split (nm).
        delta_evidence: the training :attr:`Fit.evidence` with the candidate minus the
            nominal's, where the kind has one, else ``None`` (:attr:`delta_bic` is that).
    """

    effect: str
    heldout_gap_before_nm: float
    heldout_gap_after_nm: float
    shrink_pct: float
    train_rms_after_nm: float
    delta_bic: float
    extra_parameters: int
    significant: bool
    fit: Fit
    trains_worse: bool = False
    judged_on: str = ""
    nominal_gap_nm: Optional[float] = None
    delta_evidence: Optional[float] = None

    @property
    def evidence(self) -> float:
        """The delta BIC :func:`by_evidence` weighs: :attr:`delta_evidence`, else :attr:`delta_bic`."""
        return self.delta_bic if self.delta_evidence is None else self.delta_evidence

    @classmethod
    def compare(
        cls, effect: str, nominal: Fit, fit: Fit, rules: Rules, nested: bool = True, split=None
    ) -> Candidate:
        """``fit`` (nominal + ``effect``) against ``nominal`` under ``rules``; ``nested``: ``fit``
        started from ``nominal``'s (a candidate effect), so that training worse is a failure (a
        hysteresis rung started afresh is not); ``split``: the :class:`_Split` it was judged
        on where that is not the data's own."""
        before, after = nominal.heldout_gap_nm, fit.heldout_gap_nm
        shrink, dbic = 100 * (1 - after / before), float(fit.bic - nominal.bic)
        shared = None if fit.evidence is None else float(fit.evidence - nominal.evidence)
        return cls(
            effect,
            before,
            after,
            shrink,
            fit.train_rms_nm,
            dbic,
            fit.parameters - nominal.parameters,
            bool(shrink >= rules.min_shrink_pct and dbic <= -rules.min_delta_bic),
            fit,
            nested and bool(fit.train_rms_nm > (1 + NESTING_TOLERANCE) * nominal.train_rms_nm),
            split.data.split_label if split else "",
            split.nominal.heldout_gap_nm if split else None,
            shared,
        )

    def to_json(self) -> dict:
        """The candidate's row of ``diagnosis.json``."""
        common = (
            "effect",
            "heldout_gap_before_nm",
            "heldout_gap_after_nm",
            "shrink_pct",
            "train_rms_after_nm",
            "delta_bic",
            "extra_parameters",
        )
        flags = {"significant": self.significant, "trains_worse_than_without": self.trains_worse}
        split = {"judged_on": self.judged_on} if self.judged_on else {}
        shared = {} if self.delta_evidence is None else {"delta_bic_coloured_noise": self.delta_evidence}
        return {k: getattr(self, k) for k in common} | shared | split | self.fit.shown() | flags

    def line(self) -> str:
        """The candidate's result, for the log."""
        return (
            f"  + {self.effect:16s} held-out gap {self.heldout_gap_after_nm:8.3g} nm "
            f"({self.shrink_pct:+6.1f} %), delta BIC {self.delta_bic:+9.1f}"
            + ("  significant" if self.significant else "")
            + (
                f"  (judged on {self.judged_on}: {self.heldout_gap_before_nm:.3g} nm before)"
                if self.judged_on
                else ""
            )
            + ("  trains worse than without it: the solver stopped short" if self.trains_worse else "")
        )


@dataclasses.dataclass(frozen=True)
class Findings:
    """What a kind's own analysis of the nominal residual found, for the report.

    Attributes:
        metrics: flat ``metrics.json`` entries beside the common ones.
        where: sentences that say where the nominal model misses, with the numbers.
        notes: Markdown lines after the candidate table and those sentences.
        decomposition: tables of the residual for ``diagnosis.json``, or ``None``.
        plots: what the kind's figure panels draw (the kind's own; :meth:`DataKind.panels`).
    """

    metrics: dict
    where: list
    notes: list
    decomposition: Optional[dict] = None
    plots: Any = None


class DataKind(abc.ABC):
    """A kind of data a diagnosis runs on: it holds the data and its split into training and
    held-out parts, fits the nominal model and the candidates, and analyses and draws its
    nominal residual. The core (:func:`diagnose`, :func:`jaxafm.diagnose.report.write`) does
    the comparison, the ranking, the verdict and the files.

    Class attributes:
        name: the kind's entry in :data:`NOT_TRIED` (``record``, ``image``, ``scans``).
        gap_label: the candidate bar chart's axis label (what the gap is, with its unit).
        grid: rows and columns of the figure's panels; the last one is the bar chart.
        figsize: the figure's size in inches.
    """

    name: ClassVar[str]
    gap_label: ClassVar[str]
    grid: ClassVar[tuple] = (2, 2)
    figsize: ClassVar[tuple] = (12, 8.5)

    @property
    @abc.abstractmethod
    def model(self) -> str:
        """The nominal model, in words (``diagnosis.json``)."""

    @property
    @abc.abstractmethod
    def label(self) -> str:
        """The nominal model in a few words, for the log."""

    @property
    @abc.abstractmethod
    def tries(self) -> tuple:
        """The effects that can be tried on this data (the others: :data:`NOT_TRIED`)."""

    #: Richer hysteresis operators to try before the effects, in order (none by default).
    shapes: ClassVar[tuple] = ()

    def nominal_effects(self, nominal: Fit) -> frozenset:
        """The effects the fitted ``nominal`` model has (default: hysteresis alone)."""
        return frozenset({"hysteresis"})

    def fit_shape(self, kind: str, base: Fit) -> Fit:
        """The nominal model with the richer hysteresis operator ``kind`` (one of :attr:`shapes`),
        started from ``base`` (the richest significant rung so far) where it can, fitted to the
        training part."""
        raise NotImplementedError(f"{self.name} data have no hysteresis shapes to try")

    def warnings(self) -> list:
        """Sentences on what the split cannot test (default: none)."""
        return []

    def cannot(self, effect: str) -> Optional[str]:
        """Why ``effect`` (one of :attr:`tries`) cannot be tried on these particular data, or
        ``None`` (default: it can)."""
        return None

    def judged_on(self, effect: str) -> DataKind:
        """The data ``effect`` is judged on: these, or the same data split otherwise, where the
        held-out part these data keep cannot test it (default: these)."""
        return self

    @property
    def split_label(self) -> str:
        """The split in a few words (where :meth:`judged_on` gives other data)."""
        return "the data's split"

    @abc.abstractmethod
    def fit_nominal(self) -> Fit:
        """The nominal model fitted to the training part."""

    @abc.abstractmethod
    def fit_candidate(self, effect: str, nominal: Fit) -> Fit:
        """The nominal model plus ``effect`` (one of :attr:`tries`), fitted to the training part."""

    @abc.abstractmethod
    def describe(self) -> dict:
        """The ``data`` section of ``diagnosis.json``: source, sizes, the split, units."""

    @abc.abstractmethod
    def findings(self, diagnosis: Diagnosis) -> Findings:
        """Where the nominal model misses: metrics, sentences, tables, report lines, plots."""

    @abc.abstractmethod
    def panels(self, axes: list, diagnosis: Diagnosis, findings: Findings) -> None:
        """Draw the kind's own panels on ``axes`` (all of the figure's but the last)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Diagnosis:
    """The result of a diagnosis.

    Attributes:
        data: the :class:`DataKind` diagnosed (its data, split and what it computed of them).
        nominal: the nominal model's :class:`Fit`.
        candidates: the candidates tried, ranked by shrink (best first).
        skipped: the candidates not tried, with the reason.
        verdict: the top significant candidate's effect, or ``None``.
        rules: the :class:`Rules` applied.
        shapes: the hysteresis rungs tried (:class:`Candidate` s named by the operator's kind),
            each against the rung below it, and the recheck of the rung found, if any.
        shape: the richer hysteresis operator the data need (its kind), or ``None``.
        base: the fit the effects were compared against (the nominal, or the rung found).
        warnings: sentences on what the split cannot test.
        contest: where significant candidates were judged on different splits, each refitted
            on the split the others were not judged on and compared there
            (:func:`_on_one_split`), the verdict the best of them; else empty.
    """

    data: DataKind
    nominal: Fit
    candidates: tuple
    skipped: dict
    verdict: Optional[str]
    rules: Rules
    shapes: tuple = ()
    shape: Optional[str] = None
    base: Optional[Fit] = None
    warnings: tuple = ()
    contest: tuple = ()

    @property
    def kind(self) -> str:
        """The data kind's name."""
        return self.data.name

    @property
    def top(self) -> Optional[Candidate]:
        """The verdict's candidate, or ``None``."""
        return next((c for c in self.candidates if c.effect == self.verdict), None)

    @property
    def text(self) -> str:
        """The verdict in words: the effect (or none) and the hysteresis shape found, if any."""
        text = self.verdict or "no significant unmodelled effect"
        if self.shape:
            text += f"; hysteresis shape: {SHAPE_NAMES[self.shape]} instead of the nominal's"
        return text

    @property
    def final(self) -> Fit:
        """The diagnosis's final model: the verdict's fit, else the rung found, else the nominal."""
        return self.top.fit if self.top else (self.base or self.nominal)

    @property
    def evidence_decided(self) -> tuple:
        """The candidates compared on one split whose held-out gaps could not separate them
        (:func:`tied`), where there are several: the training evidence chose between them
        (:func:`by_evidence`); else empty."""
        found = tied(self.contest, rank(self.contest, self.rules)[1], self.rules) if self.contest else []
        return tuple(found) if len(found) > 1 else ()

    def verdict_json(self) -> dict:
        """The ``verdict`` section of ``diagnosis.json``: effect, shape, text and, if any, the
        effect's gaps (against the model it was added to), the split that judged it where it is
        not the data's own, and the gap left against the nominal's on the same split."""
        top = self.top
        gaps = ("heldout_gap_before_nm", "heldout_gap_after_nm", "shrink_pct")
        nominal = top.nominal_gap_nm if top and top.judged_on else self.nominal.heldout_gap_nm
        return {
            "effect": self.verdict,
            "hysteresis_shape": self.shape,
            "text": self.text,
            **({k: getattr(top, k) for k in gaps} if top else {}),
            **({"judged_on": top.judged_on} if top and top.judged_on else {}),
            "total_shrink_pct": 100 * (1 - self.final.heldout_gap_nm / nominal),
        }

    def metrics(self) -> dict:
        """The ``metrics.json`` entries every diagnosis writes: the nominal fit, the verdict and
        each candidate's gap, shrink and delta BIC."""
        top, nominal = self.top, self.nominal
        out = {
            "nominal_train_rms_nm": nominal.train_rms_nm,
            "nominal_heldout_gap_nm": nominal.heldout_gap_nm,
            "nominal_parameters": nominal.parameters,
            "verdict": self.verdict or "no significant unmodelled effect",
            "hysteresis_shape": self.shape or "nominal",
            "verdict_shrink_pct": top.shrink_pct if top else 0.0,
            "verdict_heldout_gap_after_nm": top.heldout_gap_after_nm if top else nominal.heldout_gap_nm,
        }
        for prefix, rows in (("", self.candidates), ("shape_", self.shapes)):
            for c in rows:
                for k in ("heldout_gap_after_nm", "shrink_pct", "delta_bic"):
                    out[f"{prefix}{c.effect}_{k}"] = getattr(c, k)
        return out


def skip_reason(data: DataKind, effect: str, nominal: Fit) -> Optional[str]:
    """Why ``effect`` cannot be tried on ``data`` with the fitted ``nominal`` model, or ``None``."""
    if effect in data.nominal_effects(nominal):
        return IN_NOMINAL
    if effect in data.tries:
        return data.cannot(effect)
    if effect == "noise":
        return NOISE
    return NOT_TRIED[data.name].get(effect, f"no candidate model of it for a {data.name}")


def rank(candidates, rules: Rules = Rules()) -> tuple:
    """The candidates by shrink, best first (ties keep their order), and the verdict: the top
    significant one's effect, or ``None`` -- unless a significant candidate with fewer extra
    parameters comes within ``rules.min_shrink_pct`` % of its held-out gap: the richer one is
    then not significant against the simpler one, and the simpler one is the verdict (a heavily
    damped mode, two parameters per axis, can follow a first-order lag as well as the lag does)."""
    ranked = tuple(sorted(candidates, key=lambda c: -c.shrink_pct))
    significant = [c for c in ranked if c.significant]
    if not significant:
        return ranked, None
    top = significant[0]
    for c in significant[1:]:
        shrink = 100 * (1 - top.heldout_gap_after_nm / c.heldout_gap_after_nm)
        if c.extra_parameters < top.extra_parameters and shrink < rules.min_shrink_pct:
            top = c
    return ranked, top.effect


def diagnose(data: DataKind, candidates, rules: Rules = Rules(), log=None) -> Diagnosis:
    """Fit the nominal model, climb the hysteresis shapes, then add each candidate effect that
    can be tried to the richest significant shape; rank them (module docstring).

    Arguments:
        data: the data, as a :class:`DataKind`.
        candidates: effect names to try (``docs/conventions.md``), in the order of the report.
        rules: when a candidate is significant.
        log: called with a line per fit (``None``: quiet).

    Returns:
        The :class:`Diagnosis`.

    Raises:
        ValueError: for an unknown effect name, or what the kind raises for data it cannot fit.
    """
    check_effect_names(candidates, "candidates")
    log = log or (lambda _: None)
    warnings = tuple(data.warnings())
    for w in warnings:
        log(f"warning: {w}")
    nominal = data.fit_nominal()
    log(
        f"nominal ({data.label}): train rms {nominal.train_rms_nm:.3g} nm, "
        f"held-out gap {nominal.heldout_gap_nm:.3g} nm"
    )
    base, shape, shapes = _climb(data, nominal, rules, log)
    splits = _Splits(data, nominal, base, tuple(c.effect for c in shapes if c.significant))
    tried, skipped = [], {}
    for effect in candidates:
        why = skip_reason(data, effect, nominal)
        if why:
            skipped[effect] = why
            continue
        tried.append(splits.of(effect).judge(effect, rules))
        log(tried[-1].line())
    ranked, verdict = rank(tried, rules)
    contest, verdict = _on_one_split(splits, ranked, verdict, rules, log)
    with_shape = {c.effect: c.fit for c in ranked}
    if shape and not verdict and tried:
        ranked, verdict, base = _simpler(splits, base, ranked, verdict, rules, log)
        if base is nominal:
            contest, verdict = _on_one_split(splits, ranked, verdict, rules, log, on_nominal=True)
    if verdict and shape:  # is the richer shape still needed once the effect is in?
        split = splits.of(verdict)
        plain = next((c.fit for c in ranked if c.effect == verdict and base is nominal), None)
        plain = plain or split.data.fit_candidate(verdict, split.nominal)
        recheck = Candidate.compare(shape, plain, with_shape[verdict], rules, nested=False, split=split.other)
        shapes.append(dataclasses.replace(recheck, effect=f"{shape} (with {verdict})"))
        log(shapes[-1].line().replace("+ ", "hysteresis ", 1))
        if not recheck.significant:
            shape = None
            if base is not nominal:
                ranked, verdict = _on_nominal(splits, ranked, {verdict: plain}, rules, log)
                contest, verdict = _on_one_split(splits, ranked, verdict, rules, log, on_nominal=True)
                base = nominal
    return Diagnosis(
        data, nominal, ranked, skipped, verdict, rules, tuple(shapes), shape, base, warnings, contest
    )


@dataclasses.dataclass(frozen=True)
class _Split:
    """A split candidates are judged on: its data, nominal fit and base (the rungs found, on it);
    ``other``: itself where it is not the diagnosed data's own split, else ``None``."""

    data: DataKind
    nominal: Fit
    base: Fit
    own: bool

    @property
    def other(self) -> Optional[_Split]:
        return None if self.own else self

    def judge(
        self, effect: str, rules: Rules, on_nominal: bool = False, fit: Optional[Fit] = None
    ) -> Candidate:
        """``effect`` added to this split's base (its nominal ``on_nominal``) and compared with
        it; ``fit``: that fit where it was made already."""
        base = self.nominal if on_nominal else self.base
        fit = fit or self.data.fit_candidate(effect, base)
        return Candidate.compare(effect, base, fit, rules, split=self.other)


class _Splits:
    """The splits a diagnosis judges on: the data's own, and each other one an effect asks for
    (:meth:`DataKind.judged_on`), its nominal refitted there and the rungs found climbed again."""

    def __init__(self, data: DataKind, nominal: Fit, base: Fit, rungs: tuple):
        self.data, self.rungs = data, rungs
        self._made = {id(data): _Split(data, nominal, base, True)}

    @property
    def own(self) -> _Split:
        """The diagnosed data's own split."""
        return self._made[id(self.data)]

    def of(self, effect: str) -> _Split:
        """The split ``effect`` is judged on, fitted the first time it is asked for."""
        data = self.data.judged_on(effect)
        if id(data) not in self._made:
            nominal = base = data.fit_nominal()
            for kind in self.rungs:
                base = data.fit_shape(kind, base)
            self._made[id(data)] = _Split(data, nominal, base, False)
        return self._made[id(data)]


def _on_one_split(splits: _Splits, ranked, verdict, rules: Rules, log, on_nominal: bool = False) -> tuple:
    """Significant candidates judged on different splits (a record's drift on alternating blocks,
    the others on its later part) cannot be ranked by their shrinks, each against another held-out
    part: those judged on the data's own split are refitted on the other one (on its base, or its
    nominal ``on_nominal``) and all compared there. Returns ``(the candidates compared there,
    the verdict)``: the best there (:func:`rank`, then :func:`by_evidence`), or ``((), verdict)``
    when the significant candidates share one split."""
    significant = [c for c in ranked if c.significant]
    elsewhere = [c for c in significant if c.judged_on]
    if not elsewhere or len(elsewhere) == len(significant):
        return (), verdict
    split = splits.of(elsewhere[0].effect)
    contest = list(elsewhere)
    for c in significant:
        if not c.judged_on:
            contest.append(split.judge(c.effect, rules, on_nominal))
            log(contest[-1].line().replace("+ ", f"+ (against {elsewhere[0].effect}) ", 1))
    contest, best = rank(contest, rules)
    return contest, by_evidence(contest, best, rules) or verdict


def tied(ranked, verdict: Optional[str], rules: Rules = Rules()) -> list:
    """The significant candidates of ``ranked`` whose held-out gap is within
    ``rules.min_shrink_pct`` % of the ``verdict``'s (the resolution the shrink rule itself takes,
    so that the held-out part cannot separate them), the verdict's own among them; empty without
    a verdict."""
    top = next((c for c in ranked if c.effect == verdict), None)
    if top is None:
        return []
    return [
        c
        for c in ranked
        if c.significant
        and 100 * (1 - top.heldout_gap_after_nm / c.heldout_gap_after_nm) < rules.min_shrink_pct
    ]


def by_evidence(ranked, verdict: Optional[str], rules: Rules = Rules()) -> Optional[str]:
    """Where the held-out gaps cannot separate significant candidates (:func:`tied`), the
    training evidence does: of those, the one of lowest delta BIC under the noise model they
    share (:attr:`Candidate.evidence`). Returns its effect, or ``None`` without a verdict."""
    candidates = tied(ranked, verdict, rules)
    return min(candidates, key=lambda c: c.evidence).effect if candidates else None


def _on_nominal(splits: _Splits, ranked, fitted: dict, rules: Rules, log) -> tuple:
    """The recheck dropped the rung the effects were added to: every effect compared on the
    nominal model of its split instead (``fitted``: effect -> its fit on that nominal, where one
    was made), so that the verdict and its numbers are those of the model it names. Returns
    ``(ranked, verdict)`` (:func:`rank`)."""
    plain = []
    for c in ranked:
        plain.append(splits.of(c.effect).judge(c.effect, rules, on_nominal=True, fit=fitted.get(c.effect)))
        log(plain[-1].line().replace("+ ", "+ (on the nominal) ", 1))
    return rank(plain, rules)


def _climb(data: DataKind, nominal: Fit, rules: Rules, log) -> tuple:
    """The hysteresis rungs of ``data.shapes``, each against the richest significant one below
    it: ``(that richest fit, its kind or None, the rungs tried)``."""
    base, shape, shapes = nominal, None, []
    for kind in data.shapes:
        shapes.append(Candidate.compare(kind, base, data.fit_shape(kind, base), rules, nested=False))
        log(shapes[-1].line().replace("+ ", "hysteresis ", 1))
        if shapes[-1].significant:
            base, shape = shapes[-1].fit, kind
    return base, shape, shapes


def _simpler(splits: _Splits, rung: Fit, ranked, verdict, rules: Rules, log) -> tuple:
    """A rung was found and no effect on top of it: each effect is added to the nominal model
    (of the split it is judged on) instead. One that is significant there with a training BIC
    and a held-out gap no worse than the rung's (on that split) explains the misfit more simply;
    the effects are then ranked on the nominal. Returns ``(ranked, verdict, base)``, unchanged
    when no effect does."""
    plain, rivals = [], []
    for c in ranked:
        split = splits.of(c.effect)
        plain.append(split.judge(c.effect, rules, on_nominal=True))
        log(plain[-1].line().replace("+ ", "+ (on the nominal) ", 1))
        fit = plain[-1].fit
        if (
            plain[-1].significant
            and fit.bic <= split.base.bic
            and fit.heldout_gap_nm <= split.base.heldout_gap_nm
        ):
            rivals.append(plain[-1])
    if not rivals:
        return ranked, verdict, rung
    return rank(plain, rules)[0], rank(rivals, rules)[1], splits.own.nominal
