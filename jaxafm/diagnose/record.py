"""Diagnosis of an actuator record: where the nominal model misses, which effect is missing.

The nominal model (:class:`~jaxafm.diagnose.plant.Plant`) is fitted to the training part of a
record (the first ``train_fraction`` of it, after ``settle`` samples -- by default until every
drive has reversed once, :func:`first_reversal`; or, with ``blocks``, every other of that many
equal blocks in time); the richer hysteresis operators are tried (symmetric
PI -> twice the plays -> generalised PI -> Preisach: :data:`SHAPES`), then each candidate effect
is added -- the same module the simulator uses -- and the model refitted, warm-started from the
richest significant shape. The gap is the rms residual ``sqrt(mean((d - model)^2))`` (nm) on
the held-out part, which the fits never saw; BIC, significance, ranking and verdict are the
core's (:mod:`jaxafm.diagnose.core`).

What the split cannot test is said (:meth:`ActuatorRecord.warnings`): held-out inputs beyond the
training range (the fits extrapolate there) and a held-out part that is nearly a flat hold.

Where the nominal model misses: its residual by time (rms and mean), by input level on the
ascending and descending branch (the sign of ``du/dt``), by input rate; its whiteness and its
cross-correlation with the input (:func:`jaxafm.diagnose.report.residual_tests`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from scipy import signal

from ..config.common import MAX_OPERATORS
from ..instrument.records import Record
from ..model.effects import Vibration
from .core import DataKind, Diagnosis, Findings, Fit, Rules, diagnose
from .plant import (
    CREEP_TAU_MIN,
    Nominal,
    Plant,
    fit_plant,
    n_parameters,
    nominal_plant,
    sizes,
    title,
    with_effect,
)
from .report import MAX_LAG, above_floor, binned_rms, noise_floor_nm, residual_tests, rms
from .wander import NOISE_PARAMETERS_PER_OUTPUT, PARAMETERS_PER_OUTPUT, Wander, fit_wander

Array = jax.Array
#: Candidate effects for actuator records; the last two need two axes (asymmetry is a hysteresis
#: shape: :data:`SHAPES`).
RECORD_CANDIDATES = ("rate_dependence", "creep", "vibration", "drift", "coupling", "bow")
TWO_AXIS = ("coupling", "bow")
#: The richer hysteresis operators tried after each nominal kind, in order: ``finer`` is the
#: nominal's kind with twice the plays (a loop whose kinks fall between the nominal's play radii
#: leaves a slow misfit that creep or drift would otherwise take), ``gpi`` adds dead zones.
SHAPES = {"pi": ("finer", "gpi", "preisach"), "gpi": ("finer", "preisach"), "preisach": ()}
MIN_EXPLAINED = 0.5  # the nominal fit must explain this fraction of the output variance
BINS = 8  # input-level and input-rate bins of the residual decomposition
RANGE_WARN_PCT = 2.0  # held-out inputs beyond the training range by more than this % of it: warn
FLAT_WARN_PCT = 5.0  # held-out input span below this % of the training span: a flat hold
#: Effects judged on ``JUDGE_BLOCKS`` alternating blocks where the record's own split holds out
#: its later part: a drift that wanders cannot be extrapolated over the record's last part, but
#: can be interpolated between training blocks on both sides. Eleven blocks, not five: on a drive
#: whose amplitude follows a 10 s envelope, five blocks of a 20 s record held out the small loops
#: alone, and the wander's bridges between training blocks took 9-10 % off a control's hysteresis
#: misfit there. Creep stays on the later split: judged on blocks, a record cropped at its start
#: (creep of the cut in its first block, the settle capped at half a block) gave a creep rate 35 %
#: or more off the truth's, and with the whole settle the verdict went to rate dependence.
JUDGED_ON_BLOCKS = ("drift",)
#: The block counts tried, in order, for that split: the first whose training blocks reach every
#: held-out input (:func:`beyond_training`, within :data:`RANGE_WARN_PCT`) is used, else the first.
#: A held-out block that drives an axis beyond what the training blocks reached measures the
#: hysteresis model's extrapolation (a Preisach plane's unvisited relays: 84-110 nm rms on a 6 s
#: generator record whose training blocks of 11 stop 18 % of the span short on one axis, against
#: 3.5-5 nm in the others), which no time-dependent effect explains and which swamps the drift.
JUDGE_BLOCKS = (11, 13, 9, 15, 7, 17, 19, 21)
MIN_BLOCK_SAMPLES = 10  # the shortest block of a blocked split
WANDER_ROUNDS = 2  # a drift's plant and wander refitted to what the other leaves, this many times
VIBRATION_BAND = (10.0, 0.45)  # a mode is sought above 10 x the drive's frequency, below 0.45 x the rate


@dataclasses.dataclass(frozen=True, eq=False)
class RecordFit(Fit):
    """A :class:`~jaxafm.diagnose.core.Fit` of a record; ``residual`` (T, k) nm.

    Attributes:
        plant: the fitted :class:`~jaxafm.diagnose.plant.Plant`.
        solver_steps: the Levenberg-Marquardt steps it took.
        step_limit: the steps it was allowed (reaching them: stopped before converging).
        wander: a drift's wander on top of the plant (:mod:`~jaxafm.diagnose.wander`), or ``None``.
        evidence_bic: the training BIC with the residual's colour modelled (:attr:`evidence`).
    """

    plant: Plant
    solver_steps: int
    step_limit: int
    wander: Optional[Wander] = None
    evidence_bic: Optional[float] = None

    @property
    def evidence(self) -> Optional[float]:
        """The training BIC under one noise model for every fit of a record: a coloured term
        beside white noise (:func:`~jaxafm.diagnose.wander.fit_wander` with ``drift=False``),
        the drift's walk and rate on top for a fit with a drift (its own BIC). A drift's BIC
        models the residual's colour and a least-squares BIC does not, so between the two the
        colour would count as drift."""
        return self.evidence_bic

    @property
    def at_step_limit(self) -> bool:
        """Whether the fit stopped at its step limit rather than converging."""
        return self.solver_steps >= self.step_limit

    def shown(self) -> dict:
        fitted = sizes(self.plant)
        if self.wander is not None:
            fitted["drift_nm_per_s"] = self.wander.velocity.tolist()
            fitted["drift_wander_nm2_per_s"] = self.wander.diffusion.tolist()
            fitted["coloured_misfit_sd_nm"] = self.wander.coloured_sd.tolist()
            fitted["coloured_misfit_time_s"] = self.wander.coloured_time_s.tolist()
        return {
            "solver_steps": self.solver_steps,
            "stopped_at_step_limit": self.at_step_limit,
            "fitted": fitted,
        }

    def summary(self) -> dict:
        return super().summary() | self.shown()


def beyond_training(u: np.ndarray, train: np.ndarray, heldout: np.ndarray) -> np.ndarray:
    """How far the held-out inputs leave the training inputs' range, per input column of ``u``
    (T, k) V: ``max(lo - min(held), max(held) - hi, 0)`` in % of the training span ``hi - lo``."""
    u_train, u_held = u[train], u[heldout]
    lo, hi = u_train.min(0), u_train.max(0)
    beyond = np.maximum(np.maximum(lo - u_held.min(0), u_held.max(0) - hi), 0.0)
    return 100 * beyond / np.maximum(hi - lo, 1e-12)


def _columns(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a[:, None] if a.ndim == 1 else a


@dataclasses.dataclass(frozen=True, eq=False)
class ActuatorRecord(DataKind):
    """An actuator record (one or two axes) as a diagnosis's data.

    Attributes:
        record: the record; ``u`` (T,) or (T, k) V, ``d`` (T,) or (T, k) nm.
        spec: the nominal model.
        train: (T,) True on the training samples.
        heldout: (T,) True on the held-out samples.
        settle: samples at the start left out of the training loss and the analysis.
        history: inputs (H, k) V applied before ``t[0]``, or ``None``.
        max_steps: Levenberg-Marquardt steps per fit.
        blocks: the number of alternating blocks of a blocked split, 0 for a later held-out part.
        fitted: the nominal's fit, once made (:meth:`checked_against_pi`).
        notes: what the run must say beside the split's warnings (a nominal replaced, and why).
    """

    record: Record
    spec: Nominal
    train: np.ndarray
    heldout: np.ndarray
    settle: int = 0
    history: Optional[Array] = None
    max_steps: int = 300
    blocks: int = 0
    fitted: Optional[RecordFit] = None
    notes: tuple = ()

    name = "record"
    gap_label = "held-out gap (rms) [nm]"
    grid = (2, 3)
    figsize = (15, 8.5)

    @classmethod
    def split_off(
        cls,
        record: Record,
        spec: Nominal,
        train_fraction: float = 0.6,
        settle: int = 0,
        history=None,
        max_steps: int = 300,
        blocks: int = 0,
    ) -> ActuatorRecord:
        """``record`` with its first ``train_fraction`` (from sample ``settle`` on) to train on,
        or with ``blocks`` > 0, every other of ``blocks`` equal blocks in time (the first, third,
        ...: training; the others held out, each between two training blocks).

        Arguments:
            record: the record.
            spec: the nominal model.
            train_fraction: the training part, in (0, 1) (without ``blocks``).
            settle: samples at the start left out of training.
            history: inputs (H,) V applied before ``t[0]`` (the same on every axis), or ``None``.
            max_steps: Levenberg-Marquardt steps per fit.
            blocks: 0, or an odd number >= 3 of alternating blocks.

        Raises:
            ValueError: when either part would have fewer than 10 samples, or for an even
                ``blocks``.
        """
        n = len(record)
        if blocks:
            if blocks < 3 or blocks % 2 == 0 or n // blocks < MIN_BLOCK_SAMPLES:
                raise ValueError(
                    f"split blocks: {blocks} blocks of a {n}-sample record; an odd number >= 3 of "
                    f"blocks of at least {MIN_BLOCK_SAMPLES} samples each (training blocks at both ends)"
                )
            train = (np.arange(n) * blocks // n) % 2 == 0
        else:
            train = np.arange(n) < record.split(train_fraction)
        heldout = ~train
        train[:settle] = False
        k = _columns(record.u).shape[1]
        hist = (
            None
            if history is None
            else jnp.broadcast_to(jnp.asarray(history, dtype=float)[:, None], (len(history), k))
        )
        return cls(record, spec, train, heldout, settle, hist, max_steps, blocks)

    @property
    def split_label(self) -> str:
        return f"{self.blocks} alternating blocks" if self.blocks else "the later part"

    def judged_on(self, effect: str) -> ActuatorRecord:
        """The record split into alternating blocks (:attr:`blocked`) for the effects of
        :data:`JUDGED_ON_BLOCKS` where it holds out its later part; itself otherwise."""
        return self.blocked if effect in JUDGED_ON_BLOCKS and not self.blocks else self

    @functools.cached_property
    def blocked(self) -> ActuatorRecord:
        """The same record, nominal and settle (at most half a block) on alternating blocks: the
        first count of :data:`JUDGE_BLOCKS` whose training blocks reach every held-out input
        (counts whose blocks would be shorter than :data:`MIN_BLOCK_SAMPLES` are not tried)."""
        n, first = len(self.record), None
        for blocks in JUDGE_BLOCKS:
            if first is not None and n // blocks < MIN_BLOCK_SAMPLES:
                continue
            out = ActuatorRecord.split_off(
                self.record,
                self.spec,
                settle=min(self.settle, n // blocks // 2),
                max_steps=self.max_steps,
                blocks=blocks,
            )
            out = dataclasses.replace(out, history=self.history, notes=self.notes)
            first = first or out
            if np.max(beyond_training(out.u, out.train, out.heldout)) <= RANGE_WARN_PCT:
                return out
        return first

    @property
    def split_s(self) -> float:
        """Where the held-out part starts (s): its first sample's time."""
        return float(self.record.t[np.argmax(self.heldout)])

    @property
    def u(self) -> np.ndarray:
        """Drives (T, k) V."""
        return _columns(self.record.u)

    @property
    def d(self) -> np.ndarray:
        """Outputs (T, k) nm."""
        return _columns(self.record.d)

    @property
    def model(self) -> str:
        return title(self.spec)

    @property
    def label(self) -> str:
        return f"{self.spec.kind} + {', '.join(self.spec.effects)}"

    @property
    def tries(self) -> tuple:
        one_axis = self.d.shape[1] < 2
        return tuple(e for e in RECORD_CANDIDATES if not (e in TWO_AXIS and one_axis))

    @property
    def kind(self) -> str:
        """The nominal hysteresis operator's kind (a symmetric PI with asymmetry is a gpi)."""
        return "gpi" if self.spec.kind == "pi" and "asymmetry" in self.spec.effects else self.spec.kind

    @property
    def shapes(self) -> tuple:
        return SHAPES[self.kind]

    def nominal_effects(self, nominal: Fit) -> frozenset:
        return nominal.plant.effects | frozenset(self.spec.effects)

    def cannot(self, effect: str) -> Optional[str]:
        t = self.record.t
        if effect == "creep" and t[-1] - t[0] < 10 * CREEP_TAU_MIN:
            return (
                f"the record lasts {t[-1] - t[0]:.3g} s, less than one decade above the shortest creep "
                f"lag ({CREEP_TAU_MIN:g} s)"
            )
        if effect != "vibration":
            return None
        lo, hi = self.mode_band()
        if lo < hi:
            return None
        return (
            f"sampled at {1 / np.median(np.diff(t)):.3g} Hz: no band left for a mode between 10 x the "
            f"drive's frequency ({lo:.3g} Hz) and 0.45 x the sample rate ({hi:.3g} Hz)"
        )

    def mode_band(self) -> tuple:
        """Where a mechanical mode is sought (Hz): above ten times the drive's strongest frequency,
        below 0.45 times the sample rate."""
        fs = 1 / float(np.median(np.diff(self.record.t)))
        f, p = signal.welch(self.u - self.u.mean(0), fs, axis=0, nperseg=min(len(self.u), 4096))
        drive = float(f[1:][np.argmax(p[1:].sum(-1))])
        return VIBRATION_BAND[0] * drive, VIBRATION_BAND[1] * fs

    def _mode_start(self, base: RecordFit) -> tuple:
        """A vibration candidate's start per axis, frequency (Hz) and damping: the pair on a grid
        (40 log-spaced frequencies over :meth:`mode_band`, dampings 0.02-0.4) whose mode, put after
        the ``base`` model's output, best fits the training outputs (the other parameters held)."""
        lo, hi = self.mode_band()
        t = jnp.asarray(self.record.t)
        grid = jnp.asarray([(f, z) for f in np.geomspace(lo, hi, 40) for z in (0.02, 0.05, 0.1, 0.2, 0.4)])
        out = []
        for k in range(self.d.shape[1]):
            p = jnp.asarray(self.d[:, k] - base.residual[:, k])
            ringing = jax.vmap(lambda fz, p=p: Vibration(fz[0], fz[1])(p, t))(grid)
            loss = np.sum((np.asarray(ringing)[:, self.train] - self.d[self.train, k]) ** 2, axis=1)
            out.append(tuple(float(x) for x in grid[int(np.argmin(loss))]))
        return tuple(out)

    def _fit(self, plant: Plant, wander: Optional[Wander] = None) -> RecordFit:
        """Fit ``plant`` on the training samples; residuals ``d - model`` (T, k) nm, gaps and BIC.
        With a ``wander``, the plant is fitted to ``d`` less its level (:meth:`_with_wander`)."""
        u, d, t = self.u, self.d, self.record.t
        fitted, pred, steps = fit_plant(
            plant,
            jnp.asarray(u),
            jnp.asarray(t),
            jnp.asarray(d if wander is None else d - wander.level),
            jnp.asarray(self.train, dtype=float),
            self.history,
            self.max_steps,
        )
        r = d - np.asarray(pred)
        rss, k = float(np.sum(r[self.train] ** 2)), n_parameters(plant, u, t, d)
        noise = fit_wander(r, t, self.train, drift=False)
        return RecordFit(
            residual=r,
            heldout_gap_nm=float(np.sqrt(np.mean(r[self.heldout] ** 2))),
            plant=fitted,
            solver_steps=int(steps),
            step_limit=self.max_steps,
            evidence_bic=noise.bic(k + NOISE_PARAMETERS_PER_OUTPUT * d.shape[1]),
            **Fit.scores(rss, int(self.train.sum()) * d.shape[1], k),
        )

    def _with_wander(self, fit: RecordFit, rounds: int = WANDER_ROUNDS) -> RecordFit:
        """``fit`` (a plant without drift) plus a drift as a random process, a rate and a wander
        (:func:`fit_wander` on its training residual); the plant refitted to the output less the
        drift and the drift to what the plant leaves, ``rounds`` times. The residual is
        ``d - plant - drift``: on the held-out part the drift the training samples around it
        predict (interpolated across a held-out block, extrapolated across a held-out end). The
        BIC is the drift's likelihood's (:meth:`Wander.bic`, from its one-step predictions,
        which pays for the start and the rate itself), the wander's ratio, the coloured term's
        variance and time constant and the noise variance per output four more parameters. The
        coloured term stays in the residual: it is the plant's short-memory misfit, which the
        walk would otherwise follow."""
        for _ in range(rounds):
            fit = self._fit(fit.plant, fit_wander(fit.residual, self.record.t, self.train))
        wander = fit_wander(fit.residual, self.record.t, self.train)
        r = fit.residual - wander.level
        k = fit.parameters + PARAMETERS_PER_OUTPUT * r.shape[1]
        bic = wander.bic(k)  # its likelihood models the colour: its own BIC is its evidence too
        return dataclasses.replace(
            fit,
            residual=r,
            heldout_gap_nm=float(np.sqrt(np.mean(r[self.heldout] ** 2))),
            wander=wander,
            parameters=k,
            train_rms_nm=float(np.sqrt(np.mean(r[self.train] ** 2))),
            bic=bic,
            evidence_bic=bic,
        )

    def fit_nominal(self) -> RecordFit:
        """The nominal model, started by :func:`~jaxafm.diagnose.plant.nominal_plant` and fitted
        (:meth:`_nominal_fit`; the fit :meth:`checked_against_pi` made, where it made one).

        Raises:
            ValueError: when it explains less than :data:`MIN_EXPLAINED` of the output variance.
        """
        fit = self.fitted or self._nominal_fit(self.spec)
        r, d = fit.residual[self.train], self.d[self.train]
        explained = 1 - np.sum(r**2) / np.sum((d - d.mean(0)) ** 2)
        if not np.isfinite(explained) or explained < MIN_EXPLAINED:
            raise ValueError(
                f"the nominal model ({self.spec.kind}) cannot be fitted to this record: it explains "
                f"{100 * explained:.0f} % of the output variance (at least {100 * MIN_EXPLAINED:.0f} % needed); "
                "check that the input and output columns belong together (data.input_columns, "
                "data.output_columns) and that the output follows the input"
            )
        return fit

    def _nominal_fit(self, spec: Nominal) -> RecordFit:
        """The nominal ``spec`` fitted. A generalised PI holds the PI of the same plays (its dead
        zones at the identity): it is started from that PI's fit, with dead zones that change
        nothing, so it never ends worse than the PI (a fit from the straight line can stall far
        above it)."""
        if spec.kind != "gpi":
            return self._fit(nominal_plant(spec, self.u, self.d, self.record.t, self.train, self.history))
        pi = spec.model_copy(update={"kind": "pi"})
        pi_fit = self._fit(nominal_plant(pi, self.u, self.d, self.record.t, self.train, self.history))
        plant = with_effect(
            pi_fit.plant, "asymmetry", self.u, self.d, self.record.t, deadzones=spec.deadzones
        )
        return self._fit(plant)

    def checked_against_pi(self) -> ActuatorRecord:
        """This record with a Preisach nominal checked against the PI of as many plays: the
        factorised Preisach density does not hold a PI exactly, so it cannot start from the PI's
        fit as a generalised PI does, and its own start (alternating least squares on the plane)
        can stall where the PI fits well. Where the Preisach trains worse than the PI, its fit
        has failed: the diagnosis goes on from the PI, and :meth:`warnings` says so with both
        training errors. Other nominals are returned as they are (unfitted)."""
        if self.spec.kind != "preisach":
            return self
        fits = {k: self._nominal_fit(self.spec.model_copy(update={"kind": k})) for k in ("preisach", "pi")}
        if fits["preisach"].train_rms_nm <= fits["pi"].train_rms_nm:
            return dataclasses.replace(self, fitted=fits["preisach"])
        note = (
            f"the Preisach nominal ({self.spec.levels} levels) trains worse than a PI of "
            f"{self.spec.operators} plays on the same record ({fits['preisach'].train_rms_nm:.3g} nm against "
            f"{fits['pi'].train_rms_nm:.3g} nm rms): its fit failed, and the diagnosis starts from the PI"
        )
        pi = self.spec.model_copy(update={"kind": "pi"})
        return dataclasses.replace(self, spec=pi, fitted=fits["pi"], notes=self.notes + (note,))

    def fit_shape(self, kind: str, base: RecordFit) -> RecordFit:
        """The nominal model with a richer hysteresis: ``finer`` starts afresh with twice the plays,
        ``gpi`` adds dead zones to the ``base`` fit's PI (started where they change nothing),
        ``preisach`` starts afresh from a Preisach plane of ``spec.levels`` levels; the nominal's
        other effects kept."""
        if kind == "gpi":
            return self._fit(with_effect(base.plant, "asymmetry", self.u, self.d, self.record.t))
        if kind == "finer":
            spec = self.spec.model_copy(update={"operators": min(2 * self.spec.operators, MAX_OPERATORS)})
        else:
            spec = self.spec.model_copy(update={"kind": kind})
        return self._fit(nominal_plant(spec, self.u, self.d, self.record.t, self.train, self.history))

    def fit_candidate(self, effect: str, nominal: RecordFit) -> RecordFit:
        mode = self._mode_start(nominal) if effect == "vibration" else None
        if effect == "drift":
            return self._with_wander(nominal)
        plant = with_effect(
            nominal.plant, effect, self.u[self.train], self.d[self.train], self.record.t, mode
        )
        return self._fit(plant)

    def warnings(self) -> list:
        """Held-out inputs beyond the training range (by how much), and a held-out part that is
        nearly a flat hold, per input, each with the split that fixes it; then the :attr:`notes`."""
        out = []
        u_train, u_held = self.u[self.train], self.u[self.heldout]
        fix = "a blocked split (split: blocked) puts training data on both sides of every held-out block"
        beyond = beyond_training(self.u, self.train, self.heldout)
        for i in range(self.u.shape[1]):
            lo, hi = u_train[:, i].min(), u_train[:, i].max()
            span = max(hi - lo, 1e-12)
            if beyond[i] > RANGE_WARN_PCT:
                out.append(
                    f"input {i + 1}: the held-out inputs leave the training range [{lo:.3g}, {hi:.3g}] V by "
                    f"up to {beyond[i] * span / 100:.3g} V ({beyond[i]:.0f} % of it): the fits extrapolate "
                    f"there; {fix}"
                )
            held_span = np.ptp(u_held[:, i])
            if 100 * held_span / span < FLAT_WARN_PCT:
                out.append(
                    f"input {i + 1}: the held-out part is nearly a flat hold (its input spans {held_span:.3g} V, "
                    f"{100 * held_span / span:.1f} % of the training span): it tests creep and drift, not the "
                    f"hysteresis; {fix}"
                )
        return out + list(self.notes)

    def describe(self) -> dict:
        return {
            "source": self.record.meta["source"],
            "samples": len(self.record),
            "outputs": self.d.shape[1],
            "train_samples": int(self.train.sum()),
            "heldout_samples": int(self.heldout.sum()),
            "split": f"blocked, {self.blocks} blocks" if self.blocks else "later",
            "judged_on_other_split": (
                {e: self.blocked.split_label for e in JUDGED_ON_BLOCKS} if not self.blocks else {}
            ),
            "settle_samples": self.settle,
            "settle_s": float(self.record.t[self.settle] - self.record.t[0]),
            "heldout_from_s": self.split_s,
            "duration_s": float(self.record.t[-1] - self.record.t[0]),
            "counts": "samples",
            "heldout_where": "every other block in time" if self.blocks else "later in time",
            "units": "nm (gaps, residuals), V, s",
        }

    def findings(self, diagnosis: Diagnosis) -> Findings:
        """The nominal residual (after ``settle``) decomposed, its tests and their sentences."""
        s = self.settle
        r, u, t = diagnosis.nominal.residual[s:], self.u[s:], self.record.t[s:]
        test, dec = residual_tests(r, u, t), decompose(r, u, t)
        m = test["metrics"]
        metrics = {"train_samples": int(self.train.sum()), "heldout_samples": int(self.heldout.sum())}
        floor = noise_floor_nm(self.d[self.heldout])
        gap = diagnosis.final.heldout_gap_nm
        metrics |= {
            "noise_floor_nm": floor,
            "final_heldout_gap_above_floor_nm": above_floor(gap, floor),
            "nominal_heldout_gap_above_floor_nm": above_floor(diagnosis.nominal.heldout_gap_nm, floor),
        }
        notes = [
            f"- Noise floor: the held-out output's white noise, from its second differences, is "
            f"{floor:.3g} nm rms; the final model's held-out gap {gap:.3g} nm is "
            f"{above_floor(gap, floor):.3g} nm above it (the nominal's "
            f"{above_floor(diagnosis.nominal.heldout_gap_nm, floor):.3g} nm), in quadrature.",
            f"- Whiteness: lag-1 autocorrelation {m['residual_acf_lag1']:.2f}, "
            f"{m['residual_acf_outside_band_pct']:.0f} % of lags 1-{MAX_LAG} outside the 95 % band "
            f"(+-{m['correlation_band_95']:.3f}); Ljung-Box p = {m['ljung_box_p']:.2g}.",
            f"- Input cross-correlation: max |rho| {m['input_ccf_max_abs']:.2f} with u, "
            f"{m['input_rate_ccf_max_abs']:.2f} with du/dt (band +-{m['correlation_band_95']:.3f}).",
        ]
        return Findings(
            metrics | m | concentration(dec),
            where(dec, self.split_s),
            notes,
            dec,
            {"test": test, "dec": dec},
        )

    def panels(self, axes: list, diagnosis: Diagnosis, findings: Findings) -> None:
        """Residual against time, by input level and branch, by input rate; its autocorrelation
        and input cross-correlation with their 95 % bands."""
        s, top = self.settle, diagnosis.top
        t, r = self.record.t[s:], diagnosis.nominal.residual[s:]
        test, dec = findings.plots["test"], findings.plots["dec"]
        a = axes[0]
        for i in range(r.shape[1]):
            a.plot(t, r[:, i], lw=0.6, label=f"nominal, output {i + 1}")
        if top is not None:
            a.plot(
                t, top.fit.residual[s:, 0], lw=0.6, color="k", alpha=0.7, label=f"with {top.effect}, output 1"
            )
        held = self.heldout[s:]
        starts = np.flatnonzero(np.diff(np.r_[0, held.astype(int)]) == 1)
        ends = np.flatnonzero(np.diff(np.r_[held.astype(int), 0]) == -1)
        for i, (a0, a1) in enumerate(zip(starts, ends)):
            a.axvspan(t[a0], t[a1], color="0.9", zorder=0, label="held out" if i == 0 else None)
        a.set(xlabel="time [s]", ylabel="residual measured - model [nm]", title="residual against time")
        a.legend(fontsize=7)
        a = axes[1]
        e = np.array(dec["edges"]["input_v"])
        mid = 0.5 * (e[1:] + e[:-1])
        for branch, m in (("ascending", "^-"), ("descending", "v-")):
            a.plot(mid, dec["rms_nm"][f"input_v_{branch}"], m, label=branch)
        a.set(xlabel="input u [V]", ylabel="rms residual [nm]", title="by input level and branch")
        a.legend(fontsize=8)
        a = axes[2]
        e = np.array(dec["edges"]["input_rate_v_per_s"])
        a.plot(0.5 * (e[1:] + e[:-1]), dec["rms_nm"]["input_rate_v_per_s"], "o-")
        a.set(xlabel="|du/dt| [V/s]", ylabel="rms residual [nm]", title="by input rate (equal-count bins)")
        a.set_xscale("log")
        a = axes[3]
        for i, acf in enumerate(test["acf"]):
            a.plot(np.arange(1, acf.size + 1), acf, lw=1, label=f"output {i + 1}")
        a.axhspan(-test["band"], test["band"], color="0.85", label="95 % band (white)")
        a.set(xlabel="lag [samples]", ylabel="autocorrelation", title="whiteness of the nominal residual")
        a.legend(fontsize=8)
        a = axes[4]
        lags = np.arange(-(test["ccf_u"][0].size // 2), test["ccf_u"][0].size // 2 + 1)
        for i, (cu, cr) in enumerate(zip(test["ccf_u"], test["ccf_rate"])):
            a.plot(lags, cu, lw=1, label=f"with u, output {i + 1}")
            a.plot(lags, cr, lw=1, ls=":", label=f"with du/dt, output {i + 1}")
        a.axhspan(-test["band"], test["band"], color="0.85", label="95 % band")
        a.set(xlabel="lag [samples]", ylabel="cross-correlation", title="residual against the input")
        a.legend(fontsize=7)


def diagnose_record(
    record: Record,
    spec: Nominal,
    candidates,
    train_fraction: float = 0.6,
    settle: Optional[int] = None,
    history=None,
    rules: Rules = Rules(),
    log=print,
    blocks: int = 0,
) -> Diagnosis:
    """Fit the nominal model to ``record``, then nominal + each candidate; rank the candidates.

    Arguments:
        record: the actuator record.
        spec: the nominal model.
        candidates: effect names to try (those a record cannot show are skipped with the reason).
        train_fraction: the first part of the record (in time) the fits train on.
        settle: samples at the start left out of training; ``None``: :func:`auto_settle`.
        history: inputs (H,) V applied before ``t[0]``, or ``None``.
        rules: when a candidate is significant, and the solver's step limit.
        log: called with a line per fit.
        blocks: 0 (hold out the later part), or an odd number of alternating blocks
            (:meth:`ActuatorRecord.split_off`).

    Returns:
        The :class:`~jaxafm.diagnose.core.Diagnosis`; its ``data`` is an :class:`ActuatorRecord`,
        its fits are :class:`RecordFit` s.
    """
    if settle is None:
        settle = auto_settle(record, train_fraction, history, blocks)
    data = ActuatorRecord.split_off(record, spec, train_fraction, settle, history, rules.max_steps, blocks)
    return diagnose(data.checked_against_pi(), candidates, rules, log)


#: A drive has reversed once it is this fraction of its range away from both its running maximum
#: and its running minimum since the record's start (a margin well above command noise).
REVERSAL_FRACTION = 0.05
#: The automatic settle takes at most this fraction of the training part.
MAX_SETTLE_FRACTION = 0.25
#: A drive that stays within this fraction of its range of its first value over the first
#: :data:`REST_SPAN` of the record (at least 10 samples) starts at rest.
REST_FRACTION = 0.005
REST_SPAN = 0.01


def first_reversal(u, fraction: float = REVERSAL_FRACTION) -> int:
    """The first sample by which every input column of ``u`` (T,) or (T, k) has reversed once:
    is at least ``fraction`` of its range away from both its running maximum and its running
    minimum since ``t[0]``; 0 for a column that never reverses (a ramp, a step and hold).

    Before a drive's first reversal the model's memory -- which plays are engaged and where,
    the creep stages' levels -- is what the motion before the record left, which the record
    does not hold; the nominal model starts it at rest. A reversal of size ``s`` puts every play
    of threshold up to ``s / 2`` in the state the record's own motion gives it (the wiping-out
    property), whatever came before; larger plays and creep stages slower than the time elapsed
    still carry the unknown start."""
    out = 0
    for col in _columns(np.asarray(u, dtype=float)).T:
        margin = fraction * np.ptp(col)
        if margin == 0:
            continue
        away = np.minimum(np.maximum.accumulate(col) - col, col - np.minimum.accumulate(col))
        hit = np.flatnonzero(away >= margin)
        out = max(out, int(hit[0]) if hit.size else 0)
    return out


def starts_at_rest(u) -> bool:
    """Whether every input column of ``u`` (T,) or (T, k) holds still at the record's start:
    within :data:`REST_FRACTION` of its range of its first value over the first
    :data:`REST_SPAN` of the samples (at least 10)."""
    u = _columns(np.asarray(u, dtype=float))
    head = u[: max(10, int(REST_SPAN * len(u)))]
    return bool(np.all(np.abs(head - u[0]) <= REST_FRACTION * np.ptp(u, axis=0)))


def auto_settle(record: Record, train_fraction: float = 0.6, history=None, blocks: int = 0) -> int:
    """The default ``settle``: 0 where the start state is known -- the inputs before the record
    are given (``history``), or the drive starts at rest (:func:`starts_at_rest`, the nominal
    model's start) -- else :func:`first_reversal` of the record's drive, at most
    :data:`MAX_SETTLE_FRACTION` of the training part (the first block of a blocked split)."""
    if history is not None or starts_at_rest(record.u):
        return 0
    n = len(record)
    train = n // blocks if blocks else record.split(train_fraction)
    return min(first_reversal(record.u), int(MAX_SETTLE_FRACTION * train))


def decompose(r: np.ndarray, u: np.ndarray, t: np.ndarray) -> dict:
    """rms residual (nm) by time (and its mean), by input level on each branch, and by input rate.

    Arguments:
        r: residuals (T, k) nm.
        u: drives (T, k) V.
        t: times (T,) s.

    Returns:
        ``edges`` and ``rms_nm`` per bin (all axes together) and ``overall_rms_nm``; branches
        split at the sign of ``du/dt`` (ascending: > 0); rate bins hold equal numbers of samples.
    """
    rate = np.gradient(u, t, axis=0)
    tt = np.repeat(t[:, None], u.shape[1], 1)
    r_, u_, v_, t_ = np.ravel(r), np.ravel(u), np.ravel(rate), np.ravel(tt)
    out = {
        "time_s": np.linspace(t[0], t[-1], 11),
        "input_v": np.linspace(u_.min(), u_.max(), BINS + 1),
        # by quantiles: a step's rate would otherwise put every other sample in the first bin
        "input_rate_v_per_s": np.unique(np.quantile(np.abs(v_), np.linspace(0, 1, BINS + 1))),
    }
    idx = np.clip(np.digitize(t_, out["time_s"][1:-1]), 0, 9)
    table = {
        "time_s": binned_rms(t_, r_, out["time_s"]),
        "time_s_mean": [float(np.mean(r_[idx == b])) for b in range(10)],
        "input_rate_v_per_s": binned_rms(np.abs(v_), r_, out["input_rate_v_per_s"]),
    }
    for name, sel in (("ascending", v_ > 0), ("descending", v_ <= 0)):
        table[f"input_v_{name}"] = binned_rms(u_[sel], r_[sel], out["input_v"])
    return {"edges": {k: v.tolist() for k, v in out.items()}, "rms_nm": table, "overall_rms_nm": rms(r_)}


def where(dec: dict, split_s: float) -> list:
    """Sentences that say where the residual of :func:`decompose` is concentrated, with the
    numbers; the held-out part starts at ``split_s`` s."""
    e, tab, overall = dec["edges"], dec["rms_nm"], dec["overall_rms_nm"]
    lines = []
    time = np.array(tab["time_s"])
    lines.append(
        f"Over time the rms residual goes from {time[0]:.3g} nm (first tenth) to {time[-1]:.3g} nm "
        f"(last tenth), {time[-1] / time[0]:.2f}x, and its mean from {tab['time_s_mean'][0]:+.3g} nm to "
        f"{tab['time_s_mean'][-1]:+.3g} nm; the held-out part starts at {split_s:.3g} s."
    )
    best = None
    for branch in ("ascending", "descending"):
        vals = np.array(tab[f"input_v_{branch}"], dtype=float)
        if np.all(np.isnan(vals)):
            continue
        b = int(np.nanargmax(vals))
        if best is None or vals[b] > best[0]:
            best = (vals[b], branch, e["input_v"][b], e["input_v"][b + 1])
    lines.append(
        f"By input level, it is largest on the {best[1]} branch between {best[2]:.3g} and {best[3]:.3g} V: "
        f"{best[0]:.3g} nm rms against {overall:.3g} nm overall ({best[0] / overall:.2f}x)."
    )
    rate = np.array(tab["input_rate_v_per_s"], dtype=float)
    lo, hi = rate[0], rate[~np.isnan(rate)][-1]
    lines.append(
        f"By input rate, it is {lo:.3g} nm rms at the slowest and {hi:.3g} nm rms at the fastest "
        f"({hi / lo:.2f}x)."
    )
    return lines


def concentration(dec: dict) -> dict:
    """Flat metrics of :func:`decompose`: the largest bin of each decomposition over the overall rms."""
    overall = dec["overall_rms_nm"]
    tab = dec["rms_nm"]
    by_level = np.nanmax(np.r_[tab["input_v_ascending"], tab["input_v_descending"]])
    return {
        "residual_rms_nm": overall,
        "residual_time_last_over_first": tab["time_s"][-1] / tab["time_s"][0],
        "residual_mean_change_nm": tab["time_s_mean"][-1] - tab["time_s_mean"][0],
        "residual_level_max_over_overall": float(by_level / overall),
        "residual_rate_fast_over_slow": float(
            np.nanmax(tab["input_rate_v_per_s"][-2:]) / tab["input_rate_v_per_s"][0]
        ),
    }
