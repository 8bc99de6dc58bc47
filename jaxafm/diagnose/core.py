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
- candidates are ranked by shrink, best first; the verdict is the top significant one, or none;
- a candidate that cannot be tried on the data is skipped with its reason (:data:`NOT_TRIED`).

The writer of ``diagnosis.json``, ``metrics.json``, ``report.md`` and ``residuals.png`` is
:func:`jaxafm.diagnose.report.write`. Units: nm, s, V (``docs/conventions.md``).
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar, Optional

import numpy as np

from ..config.names import check_effect_names
from ..identify.fit import bic

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
        "tip": _IMAGING,
        "coupling": _TWO_AXES,
        "bow": _TWO_AXES,
        "asymmetry": "a Preisach density holds its own asymmetry",
    },
    "image": {
        "drift": "in one image a steady x drift shifts each row in proportion to its time, the same column "
        "as coupling (skew): image twice, or in both slow-axis directions, to tell them apart",
        "asymmetry": "one image holds one branch of the loop; its shape is the nominal nonlinearity: needs "
        "trace and retrace",
        "rate_dependence": "needs images at two scan speeds",
        "feedback_lag": "its edge shift v tau is the same on every edge of one image and the edge phases "
        "absorb it: needs trace and retrace, or two scan speeds",
        "tip": "its widening of the grooves is the same on every row and the two edge phases absorb it: "
        "needs a tip characteriser or a sample of known width",
    },
    "scans": {
        "asymmetry": "the nominal model fits the trace and retrace branches apart, asymmetric or not",
        "creep": _REPEATED,
        "drift": _REPEATED,
    },
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

    @classmethod
    def compare(cls, effect: str, nominal: Fit, fit: Fit, rules: Rules) -> Candidate:
        """``fit`` (nominal + ``effect``) against ``nominal`` under ``rules``."""
        before, after = nominal.heldout_gap_nm, fit.heldout_gap_nm
        shrink, dbic = 100 * (1 - after / before), float(fit.bic - nominal.bic)
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
        return {k: getattr(self, k) for k in common} | self.fit.shown() | {"significant": self.significant}

    def line(self) -> str:
        """The candidate's result, for the log."""
        return (
            f"  + {self.effect:16s} held-out gap {self.heldout_gap_after_nm:8.3g} nm "
            f"({self.shrink_pct:+6.1f} %), delta BIC {self.delta_bic:+9.1f}"
            + ("  significant" if self.significant else "")
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

    def nominal_effects(self, nominal: Fit) -> frozenset:
        """The effects the fitted ``nominal`` model has (default: hysteresis alone)."""
        return frozenset({"hysteresis"})

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
    """

    data: DataKind
    nominal: Fit
    candidates: tuple
    skipped: dict
    verdict: Optional[str]
    rules: Rules

    @property
    def kind(self) -> str:
        """The data kind's name."""
        return self.data.name

    @property
    def top(self) -> Optional[Candidate]:
        """The verdict's candidate, or ``None``."""
        return next((c for c in self.candidates if c.effect == self.verdict), None)

    def verdict_json(self) -> dict:
        """The ``verdict`` section of ``diagnosis.json``: effect, text and, if any, its gaps."""
        top = self.top
        gaps = ("heldout_gap_before_nm", "heldout_gap_after_nm", "shrink_pct")
        return {
            "effect": self.verdict,
            "text": self.verdict or "no significant unmodelled effect",
            **({k: getattr(top, k) for k in gaps} if top else {}),
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
            "verdict_shrink_pct": top.shrink_pct if top else 0.0,
            "verdict_heldout_gap_after_nm": top.heldout_gap_after_nm if top else nominal.heldout_gap_nm,
        }
        for c in self.candidates:
            for k in ("heldout_gap_after_nm", "shrink_pct", "delta_bic"):
                out[f"{c.effect}_{k}"] = getattr(c, k)
        return out


def skip_reason(data: DataKind, effect: str, nominal: Fit) -> Optional[str]:
    """Why ``effect`` cannot be tried on ``data`` with the fitted ``nominal`` model, or ``None``."""
    if effect in data.nominal_effects(nominal):
        return IN_NOMINAL
    if effect in data.tries:
        return None
    if effect == "noise":
        return NOISE
    return NOT_TRIED[data.name].get(effect, f"no candidate model of it for a {data.name}")


def rank(candidates) -> tuple:
    """The candidates by shrink, best first (ties keep their order), and the verdict: the top
    significant one's effect, or ``None``."""
    ranked = tuple(sorted(candidates, key=lambda c: -c.shrink_pct))
    return ranked, next((c.effect for c in ranked if c.significant), None)


def diagnose(data: DataKind, candidates, rules: Rules = Rules(), log=None) -> Diagnosis:
    """Fit the nominal model, then nominal + each candidate that can be tried; rank them.

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
    nominal = data.fit_nominal()
    log(
        f"nominal ({data.label}): train rms {nominal.train_rms_nm:.3g} nm, "
        f"held-out gap {nominal.heldout_gap_nm:.3g} nm"
    )
    tried, skipped = [], {}
    for effect in candidates:
        why = skip_reason(data, effect, nominal)
        if why:
            skipped[effect] = why
            continue
        tried.append(Candidate.compare(effect, nominal, data.fit_candidate(effect, nominal), rules))
        log(tried[-1].line())
    ranked, verdict = rank(tried)
    return Diagnosis(data, nominal, ranked, skipped, verdict, rules)
