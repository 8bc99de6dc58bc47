"""Step A: identify the scanner end to end from trace/retrace images of a calibration lattice.

The paper (section III-A) turns feature points of one image pair into (voltage, true position)
pairs and fits a polynomial per branch (the baseline:
:mod:`~jaxafm.identify.polynomial_baseline`). Here the scanner model itself is fitted: the
simulated AFM images the known lattice through the candidate model along the same drive, and the
solver matches the two images, trace and retrace together (:func:`identify`).

A periodic lattice makes the image loss many-valleyed. The fit stays in the right valley in three
ways: (1) the features carry lattice indices, and trace and retrace columns are matched at
the line reversal, where the tip is continuous, so they cannot slip by a pitch
(:mod:`~jaxafm.identify.calibration_scan`); (2) the model is first fitted to the features'
chords (:mod:`~jaxafm.identify.chords`), a smooth problem with one valley, on the model the data
support (:mod:`~jaxafm.identify.selection`); (3) the image fit then starts from there on Gaussian-blurred
images (both blurred alike), whose basin is as wide as the blur, and sharpens in stages
(:mod:`~jaxafm.identify.stages`). Held-out features judge every stage
(:mod:`~jaxafm.identify.held_out`) and the result is checked for plausibility
(:mod:`~jaxafm.identify.plausibility`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Optional

import jax.numpy as jnp
import numpy as np

from .calibration_scan import CalibrationScan, check_scan_set, drive_range, one_pitch_back
from .features import LatticeFeatures
from .fit import FitResult
from .held_out import (
    fitted_parameters,
    held_out_errors,
    held_out_image,
    held_out_rms,
    holds_features,
    judge_stage,
    split_chords,
    split_masks,
    validate,
)
from .identifiability import identifiability, position_check
from .plausibility import implausible, path_tolerance_nm, undetermined, unsettled, unvalidated
from .scan_model import ScanModel, ScanModelSpec, nominal_scan_model, start_lattice, start_loop, transplant
from .selection import RungFit, aicc, matching_spec, select, supported_dead_zones
from .stages import (
    FitPlan,
    Stage,
    StageFit,
    StageKind,
    check_plan,
    chord_data,
    coarse_ends,
    coarse_factor,
    fit_stage,
    plan_stages,
    refit_edges,
)


@dataclasses.dataclass(frozen=True)
class Identification:
    """What :func:`identify` returns.

    Attributes:
        model: the fitted :class:`~jaxafm.identify.scan_model.ScanModel` (the last accepted
            stage's).
        stages: one :class:`~jaxafm.identify.fit.FitResult` per stage (chords, then
            each blur), in order.
        seconds: the whole identification's wall time (s).
        accepted: per stage, whether its result was kept (an image stage that worsens the
            held-out features, or the training features when no site is held out, is not,
            :func:`~jaxafm.identify.held_out.judge_stage`).
        held_out_nm: per stage, the held-out features' rms residual (nm) after it
            (:func:`~jaxafm.identify.held_out.held_out_rms`); NaN when no feature is held out.
        validation: the held-out features' summary (:func:`~jaxafm.identify.held_out.validate`)
            and how well the fit predicts their errors
            (:func:`~jaxafm.identify.identifiability.position_check`).
        failures: what failed the plausibility checks
            (:func:`~jaxafm.identify.plausibility.implausible`); empty if none.
        spec: the model fitted (the ladder's choice, or the configured one).
        rungs: the model ladder's rungs (:class:`~jaxafm.identify.selection.Rung`), if climbed.
        quantities: the fitted model's physical quantities with their standard deviations
            (:func:`~jaxafm.identify.identifiability.identifiability`).
        kinds: per stage, its :class:`~jaxafm.identify.stages.StageKind`.
        chords: the training chords the quantities' standard deviations come from
            (:func:`~jaxafm.identify.stages.chord_data` at full resolution): what any other
            uncertainty of the model needs (:func:`~jaxafm.identify.identifiability.path_covariance`).
    """

    model: ScanModel
    stages: tuple
    seconds: float
    accepted: tuple = ()
    held_out_nm: tuple = ()
    validation: dict = dataclasses.field(default_factory=dict)
    failures: tuple = ()
    spec: ScanModelSpec = ScanModelSpec()
    rungs: tuple = ()
    quantities: tuple = ()
    kinds: tuple = ()
    chords: tuple = ()

    @property
    def image_rms_pct(self) -> Optional[float]:
        """The last kept image stage's rms image residual, % of the depth; None without one."""
        kept = [s for s, k, ok in zip(self.stages, self.kinds, self.accepted) if ok and k is StageKind.IMAGES]
        return 100 * float(np.sqrt(kept[-1].loss)) if kept else None

    @property
    def converged(self) -> bool:
        return all(
            s.converged for s, ok in zip(self.stages, self.accepted or [True] * len(self.stages)) if ok
        )

    @property
    def plausible(self) -> bool:
        return not self.failures


def identify(
    scans,
    spec: ScanModelSpec = ScanModelSpec(),
    plan: FitPlan = FitPlan(),
    start: Optional[ScanModel] = None,
    log: Callable = print,
) -> Identification:
    """Fit the scanner end to end: to the features' chords (with ``plan.select``, the model the
    data support, :mod:`~jaxafm.identify.selection`), then to the images at each blur.

    Several scans (e.g. at scan angles 0 and 90 degrees, or one angle at several line rates)
    are fitted together; the first one's chord fit fixes how the others' lattice indices line
    up with its own (:meth:`_StagedFit.align`). Half the lattice's sites are held out
    (``plan.hold_out``, :mod:`~jaxafm.identify.held_out`), and an image stage is kept only if it
    does not worsen the held-out features' residual beyond its uncertainty (the training
    features' when none is held out): a slip by a pitch shows there first. The chord stages fit
    scans with up to ``plan.coarsen`` pixels of a line averaged into one
    (:meth:`~jaxafm.identify.calibration_scan.CalibrationScan.coarse`), the image stages the whole
    scans. Never returns a silently bad fit: each stage's convergence, acceptance and loss are in
    the result, a stage whose loss is not finite raises, and the fitted model is checked
    (:func:`~jaxafm.identify.plausibility.implausible`).

    Arguments:
        scans: a :class:`~jaxafm.identify.calibration_scan.CalibrationScan` or several, of one
            lattice and one instrument.
        spec: the model to fit (:class:`~jaxafm.identify.scan_model.ScanModelSpec`).
        plan: how to fit it (:class:`~jaxafm.identify.stages.FitPlan`).
        start: the model to start from instead of ``spec``'s nominal one
            (:func:`~jaxafm.identify.scan_model.nominal_scan_model`).
        log: where each stage's one-line summary goes.

    Returns:
        An :class:`Identification`.

    Raises:
        ValueError: for scans of different lattices or instruments, a bad plan (blur, step
            limits, solver, tolerances, coarsening) or spec, or images whose features cannot be
            found or matched.
    """
    scans = (scans,) if isinstance(scans, CalibrationScan) else tuple(scans)
    check_scan_set(scans)
    stages = plan_stages(len(scans), plan.blur_px)
    limits = check_plan(plan, stages)
    factor = coarse_factor(scans, plan.coarsen)
    began = time.perf_counter()
    matches = [scan.feature_matches(plan.wide_loop) for scan in scans]
    found = [(trace, retraces[0]) for trace, retraces in matches]
    nominal_scan_model(
        scans[0], spec, scans
    )  # the configured kind, effects and plays: refused before any work
    if plan.select:
        spec, note = supported_dead_zones(spec, scans)
        if note:
            log(f"  model: {note}")
    first = matching_spec(spec) if plan.select else spec
    model = nominal_scan_model(scans[0], first, scans) if start is None else start
    model = start_lattice(model.as_float64(), scans[0], found[0])  # float64 leaves: one compilation each
    train, test = split_chords(found, plan.hold_out)  # the first stage may change the first retrace
    fit = _StagedFit(scans, plan, factor, [r for _, r in matches], log, model, found, train, test, spec)
    for i, (stage, limit) in enumerate(zip(stages, limits)):
        if i == 1 and len(scans) > 1:
            fit.align()
        fit.run(stage, limit, i, len(stages))
    failures = fit.fall_back()
    validation = validate(fit.model, scans, fit.train, fit.test)
    chords = chord_data(fit.train, scans, 1)
    if validation.get("held_out_features"):
        validation |= position_check(fit.model, scans, chords, chord_data(fit.test, scans, 1))
    determination = identifiability(fit.model, scans, chords, drive_range(scans))
    quantities = determination.quantities
    validation |= _path_summary(determination)
    tolerance = path_tolerance_nm(scans, plan.path_tolerance_nm)
    validation["path_tolerance_nm"] = tolerance
    failures += unvalidated(validation, min(scans[0].pitch)) + unsettled(determination, validation, tolerance)
    return Identification(
        fit.model,
        tuple(fit.results),
        time.perf_counter() - began,
        tuple(fit.accepted),
        tuple(fit.held_nm),
        validation,
        tuple(failures + undetermined(quantities)),
        fit.spec,
        tuple(fit.rungs),
        tuple(quantities),
        tuple(fit.kinds),
        chords,
    )


def _path_summary(determination) -> dict:
    """The tip path's uncertainty for ``metrics.json``: its sd (nm, rms over the images) in
    all and along x and y, and the quantity whose knowledge would settle most of it, with that
    share (%) (:class:`~jaxafm.identify.identifiability.Determination`)."""
    q, share = determination.settled_most
    x, y = determination.path_sd_nm
    return {
        "path_sd_rms_nm": determination.path_rms_nm,
        "path_sd_x_rms_nm": float(x),
        "path_sd_y_rms_nm": float(y),
        "path_settled_most_by": q.key,
        "path_settled_most_pct": share,
    }


@dataclasses.dataclass
class _StagedFit:
    """:func:`identify`'s stages as they run: the scans, the plan, the coarse factor and each
    scan's retrace matches; the model so far (the last kept stage's), the features (a chord
    stage may re-match a scan's retrace) and their split, each scan's lattice index shift onto
    the first's (:meth:`align`), the image masks (made at the first image stage), and per stage
    its result, acceptance and held-out residual."""

    scans: tuple
    plan: FitPlan
    factor: int
    retraces: list  # per scan, its retrace's matchings (CalibrationScan.feature_matches)
    log: Callable
    model: ScanModel
    found: list
    train: list
    test: list
    spec: ScanModelSpec
    shifts: Optional[list] = None
    masks: Optional[tuple] = None
    rungs: list = dataclasses.field(default_factory=list)
    results: list = dataclasses.field(default_factory=list)
    kinds: list = dataclasses.field(default_factory=list)
    accepted: list = dataclasses.field(default_factory=list)
    held_nm: list = dataclasses.field(default_factory=list)
    comparable: list = dataclasses.field(default_factory=list)  # judged residual of stages on every scan

    def run(self, stage: Stage, limit: int, i: int, total: int) -> None:
        """Stage ``i`` of ``total``: fit it from the model so far, judge it, log and record it."""
        images = stage.kind is StageKind.IMAGES
        fitted = stage.scans(self.scans)
        k = 1 if images else self.factor  # the chords on the coarse scans, the images whole
        level = tuple(scan.coarse(k) for scan in fitted)
        name = stage.label + (f", {level[0].raster.pixels} px a line" if k > 1 else "")
        self.log(f"  stage {i + 1}/{total} {name} ...")
        began = time.perf_counter()
        last = stage.kind is StageKind.CHORDS and not stage.first_scan_only
        rematch = range(1, len(self.scans)) if i == 1 and last and self.plan.wide_loop else ()
        matching = range(1) if i == 0 else rematch
        fit, kernel, matched = self._fit(stage, level, limit, matching, ladder=last and self.plan.select)
        if last and k > 1 and not self.plan.blur_px:  # no image stage will fit the whole scans
            level = fitted
            fit = fit_stage(stage, fit.model, level, chord_data(self.train, self.scans, 1), self.plan, limit)
            matched += ", then on the whole scans"
        if images:  # the edges the image stage's scanner and feedback lag imply
            train = chord_data(self.train[: len(fitted)], fitted, 1)
            fit = dataclasses.replace(fit, model=refit_edges(fit.model, fitted, train))
        solver = self.plan.solver
        passes = f" over {fit.passes} passes (the stated quantities weighed anew)" if fit.passes > 1 else ""
        message = (
            f"{solver}: converged in {fit.steps} steps{passes}, loss {fit.loss:.3e}"
            if fit.converged
            else f"{solver}: did NOT converge in {fit.steps} steps{passes} (max_steps={limit}"
            f"{' a pass' if passes else ''}); last loss {fit.loss:.3e}"
        ) + matched
        which, features = ("held-out", self.test) if holds_features(self.test) else ("training", self.train)
        judged = held_out_rms(fit.model, fitted, features[: len(fitted)])
        error = judged if features is self.test else float("nan")
        pixel_nm = max(max(scan.raster.pixel_size) for scan in fitted)
        keep, verdict = (
            judge_stage(self.comparable, judged, features, which, pixel_nm) if images else (True, "")
        )
        if not np.isnan(judged):
            message += f", {which} features {judged:.2f} nm" + verdict
        if images and self.masks[1] is not None:
            held = held_out_image(fit.model, level, kernel, self.masks[1])
            message += f", held-out image {held:.3f} % of depth"
        self.model = fit.model if keep else self.model
        seconds = time.perf_counter() - began
        self.results.append(
            FitResult(fit.model, solver, fit.converged, fit.steps, fit.loss, seconds, message)
        )
        self.accepted.append(keep)
        self.kinds.append(stage.kind)
        self.held_nm.append(error)
        if len(fitted) == len(self.scans):
            self.comparable.append(judged)
        self.log(f"  stage {i + 1}/{total} {name}: {message}, {seconds:.1f} s")

    def fall_back(self) -> list:
        """What makes the model so far implausible (:func:`~jaxafm.identify.plausibility.implausible`;
        empty: nothing). Where image stages left it so and an earlier kept stage's model is
        plausible, the latest such model is taken instead and the stages after it are rejected,
        saying so: stages that wandered into an impossible scanner do not cost the fit the
        plausible one they started from."""
        failures = implausible(self.model, self.scans)
        kept = [i for i, ok in enumerate(self.accepted) if ok]
        if not failures or self.kinds[kept[-1]] is not StageKind.IMAGES:
            return failures
        for i in reversed(kept[:-1]):
            if not implausible(self.results[i].model, self.scans):
                later = kept[kept.index(i) + 1 :]
                for j in later:
                    self.accepted[j] = False
                names = ", ".join(str(j + 1) for j in later)
                names = (
                    f"stages {names}: the scanner they"
                    if len(later) > 1
                    else f"stage {names}: the scanner it"
                )
                self.log(
                    f"  REJECTED {names} left is implausible ({failures[0]}); the model of stage {i + 1} is kept"
                )
                self.model = self.results[i].model
                return []
        return failures

    def _fit(self, stage: Stage, level: tuple, limit: int, matching: range, ladder: bool) -> tuple:
        """``(fit, kernel, note)``: the stage fitted on the scans ``level`` (an image stage's
        blur kernel, else ``None``; a note for its message), its retrace matchings chosen first
        for the scans ``matching`` (:meth:`_matched`); with ``ladder``, the model ladder climbed
        from there (:meth:`_ladder`). An image stage that starts from a chord stage's model starts
        from the feedback lag its edge delay implies (:meth:`~jaxafm.identify.scan_model.ScanModel.lag_from_edges`)."""
        if stage.kind is StageKind.IMAGES:
            self.masks = self.masks or self._masks(level)
            kernel = jnp.asarray(stage.kernel())
            kept = [kind for kind, ok in zip(self.kinds, self.accepted) if ok]
            start = self.model
            if kept[-1] is StageKind.CHORDS and start.feedback is not None:
                start = start.lag_from_edges()
                self.log(
                    f"    the chords' edge delay {1e3 * float(start.edge_delay):.2f} ms: the feedback "
                    f"lag starts at {1e3 * float(start.feedback.tau):.2f} ms"
                )
            return fit_stage(stage, start, level, (kernel, self.masks[0]), self.plan, limit), kernel, ""
        notes = []
        for k in matching:
            fit, note = self._matched(stage, level, limit, k)
            notes.append(note)
            self.model = fit.model
        if matching and not ladder:
            return fit, None, "".join(notes)
        data = chord_data(self.train, self.scans, self.factor)
        if ladder:
            return self._ladder(stage, level, data, limit), None, "".join(notes)
        return fit_stage(stage, self.model, level, data, self.plan, limit), None, ""

    def _masks(self, level: tuple) -> tuple:
        """The image stages' training and held-out masks (:func:`~jaxafm.identify.held_out.split_masks`)
        without the images' outliers (spikes, clipped pixels: :mod:`~jaxafm.identify.chords`)."""
        train, held = split_masks(self.model, level, self.plan.hold_out)
        keep = [jnp.asarray([~f.chords.image.outliers for f in images], dtype=float) for images in self.found]
        train = tuple(m * k for m, k in zip(train, keep))
        return train, (None if held is None else tuple(m * k for m, k in zip(held, keep)))

    def _ladder(self, stage: Stage, level: tuple, data: tuple, limit: int):
        """The model ladder (:func:`~jaxafm.identify.selection.select`) on the chord stage: each
        rung's nominal model, started from the best so far
        (:func:`~jaxafm.identify.scan_model.transplant`; the first rung from its nominal lattice on
        the features, as the first stage's fit of the configured model may hold its lattice where
        a straight scanner cannot follow), fitted, and scored by the information
        criterion of its training features (:func:`~jaxafm.identify.selection.aicc`, the parameters
        :func:`~jaxafm.identify.held_out.fitted_parameters`). Returns the chosen rung's fit; the
        chosen spec and the rungs are kept."""

        def fit_rung(spec: ScanModelSpec, start) -> RungFit:
            model = nominal_scan_model(self.scans[0], spec, self.scans).as_float64()
            if start is None:  # the first rung from the nominal lattice: a richer fit's may not suit it
                model = start_lattice(model, self.scans[0], self.found[0])
            else:
                model = transplant(start.model, model)
            fit = fit_stage(stage, model, level, data, self.plan, limit)
            train = [[(coarse_ends(e, self.factor), ij, a) for e, ij, a in images] for images in self.train]
            residuals = held_out_errors(fit.model, level, train)  # the training features', on ``level``
            return RungFit(fit, *aicc(residuals, fitted_parameters(fit.model, level, data)))

        rates = [scan.raster.line_rate for scan in self.scans]
        fit, self.spec, self.rungs = select(self.spec, fit_rung, rates, self.log)
        return fit

    def _matched(self, stage: Stage, level: tuple, limit: int, k: int) -> tuple:
        """Scan ``k``'s chord stage, fitted once for each way of matching its retrace's indices to
        its trace's (:meth:`~jaxafm.identify.calibration_scan.CalibrationScan.feature_matches`);
        the first matching is kept unless another fits ``MATCH_RATIO`` times better (one started
        from a model of its own: once their fits have converged, :func:`_confirmed_choice`), and
        its features and their split with it: a retrace indexed a pitch off asks the hysteresis
        loop for a branch separation a pitch off near the reversal, where the loop closes, which
        no scanner model fits (on scanner 3 of configs/study.yaml its loss is 150 times the
        right match's). Scan 0 is fitted alone (the first stage), a later scan with the scans
        before it in their kept matchings (a scan not yet matched would bring its first matching,
        right or not), its indices shifted onto the first scan's (:meth:`align`). With
        ``plan.wide_loop`` the pitch-back matching (the retrace a pitch further behind the trace
        at the reversal than the first matching) starts from a uniform loop scaled to its features
        (:func:`~jaxafm.identify.scan_model.start_loop`): from the nominal model's narrow loop
        the chord fit does not reach it. The line reversal's own matchings start from the
        nominal model, so ``wide_loop`` adds a matching and changes no other. Returns the fit
        and a note for the stage's message (empty with one match)."""
        trace, scan = self.found[k][0], self.scans[k]
        shift = 0 if self.shifts is None else self.shifts[k]
        back = one_pitch_back(trace, self.retraces[k][0], scan.pitch_px).ij if self.plan.wide_loop else None
        tried = []
        for retrace in self.retraces[k]:
            start, own = self.model, back is not None and np.array_equal(retrace.ij, back)
            if own:
                start = start_loop(
                    start, scan, *(dataclasses.replace(f, ij=f.ij + shift) for f in (trace, retrace))
                )
            train, test = (
                _shifted(part[0], shift) for part in split_chords([(trace, retrace)], self.plan.hold_out)
            )
            data = chord_data([*self.train[:k], train], self.scans, self.factor)
            fit = fit_stage(stage, start, level[: k + 1], data, self.plan, limit)
            tried.append(_Matching(fit, retrace, train, test, data, own))
        best, confirmed = _confirmed_choice(
            tried, lambda fit, data: fit_stage(stage, fit.model, level[: k + 1], data, self.plan, limit)
        )
        losses = [t.fit.loss for t in tried]
        others = ", ".join(f"{v:.3e}" for j, v in enumerate(losses) if j != best)
        which = "pitch-back" if tried[best].own_start else ("nearer", "other")[min(best, 1)]
        name = "retrace" if k == 0 else f"{scan.name}'s retrace"
        note = (
            f"; {name} indices matched the {which} way at the line reversal "
            f"(loss {losses[best]:.3e}; {others} the other way{'s' if len(tried) > 2 else ''}{confirmed})"
            if len(tried) > 1
            else ""
        )
        chosen = tried[best]
        self.train[k], self.test[k], self.found[k] = chosen.train, chosen.test, (trace, chosen.retrace)
        return chosen.fit, note

    def align(self) -> None:
        """Shift each later scan's lattice indices onto the first scan's, through the model
        fitted to the first scan's features (:func:`_lattice_shifts`)."""
        self.shifts = _lattice_shifts(self.model, self.scans, self.found)
        self.train = [_shifted(part, shift) for part, shift in zip(self.train, self.shifts)]
        self.test = [_shifted(part, shift) for part, shift in zip(self.test, self.shifts)]


def _shifted(part: list, shift) -> list:
    """One scan's chords ``[(ends, ij, along_lines), ...]`` with their lattice indices shifted."""
    return [(ends, ij + np.asarray(shift).astype(int), along) for ends, ij, along in part]


#: how many times better another retrace matching must fit than the first one to be taken
MATCH_RATIO = 2.0

#: how many times its stage's step limit a retrace matching's fit from a start of its own may take
#: to confirm that it fits ``MATCH_RATIO`` times better than the first matching
CONFIRM_ROUNDS = 4


def _choice(losses: list) -> int:
    """The retrace matching kept on these losses: the first, unless another fits
    ``MATCH_RATIO`` times better (then the best)."""
    best = int(np.argmin(losses))
    return best if losses[best] * MATCH_RATIO <= losses[0] else 0


@dataclasses.dataclass
class _Matching:
    """One retrace matching's chord stage (:meth:`_StagedFit._matched`): its ``fit``
    (:class:`~jaxafm.identify.stages.StageFit`), the ``retrace`` features so indexed, their
    ``train`` and ``test`` chords, the stage's chord ``data`` with them, and whether the fit
    started from a model of its own (``own_start``: ``wide_loop``'s pitch-back matching, from a
    loop scaled to its features) rather than from the model so far as the others do."""

    fit: StageFit
    retrace: LatticeFeatures
    train: list
    test: list
    data: tuple
    own_start: bool


def _confirmed_choice(tried: list, more: Callable) -> tuple:
    """:func:`_choice` over the :class:`_Matching` s ``tried``, where another matching that
    started from a model of its own replaces the first only on fits that have converged: while
    the choice is such a matching and its fit or the first's has not, each of the two that has
    not goes on from where it stopped (``more(fit, data)``, another step limit's worth), up to
    ``CONFIRM_ROUNDS`` step limits in all, and the choice is made again on those fits.
    Matchings fitted from one start for one step limit race fairly; from different starts
    their losses compare the starts as much as the matchings: ``wide_loop``'s pitch-back
    matching, started from a loop scaled to its features, led the right one by 2.4 and 3 times
    after 30 steps and trailed it by 12 after 120 (the 90° scans of
    study_wide_0_90_wide_loop.yaml's scanners 3 and 6, experiments/results/step_a_study_log).
    The fits gone on with decide the matching only; the stage keeps its fit at the step limit,
    as the plan asks: a chord fit of one coarse scan converged further can fit its chords
    better and the features worse (study_wide_0_90_wide_loop.yaml's scanner 8: its 0° scan's
    pitch-back fit after 30 steps, loss 4.2e-5, training features 42 nm; converged at 102
    steps, loss 3.9e-5, 185 nm). Returns the chosen index and a note for the stage's message
    (empty when no fit went on): the losses compared, in the order tried, and after how many
    steps."""
    fits = [t.fit for t in tried]
    best, rounds = _choice([f.loss for f in fits]), 1

    def unsettled(best: int) -> bool:
        started_apart = tried[best].own_start != tried[0].own_start
        return started_apart and not (fits[0].converged and fits[best].converged)

    while best and rounds < CONFIRM_ROUNDS and unsettled(best):
        for j in {0, best}:
            if not fits[j].converged:
                fit = more(fits[j], tried[j].data)
                fits[j] = dataclasses.replace(fit, steps=fits[j].steps + fit.steps)
        rounds += 1
        best = _choice([f.loss for f in fits])
    if rounds == 1:
        return best, ""
    losses = ", ".join(f"{f.loss:.3e} after {f.steps} steps" for f in fits)
    return best, f"; chosen on fits gone on to confirm the lead: {losses}"


def _lattice_shifts(model: ScanModel, scans: tuple, found: list) -> list:
    """Each scan's whole lattice index shift onto the first scan's (zero for the first). Through
    ``model`` (fitted to the first scan's features) a later scan's trace features land near
    whole lattice coordinates: its rising fast axis follows the branch that the first scan's
    slow axis traced, while its retrace follows a branch no earlier image showed (its retrace
    indices follow the trace's,
    :meth:`~jaxafm.identify.calibration_scan.CalibrationScan.feature_matches`). The shift is the
    nearest whole number of their median (:func:`_index_shift`); unless four in five trace
    features round to that same shift, the scans are unmatchable (an error naming the scan)."""
    shifts = [np.zeros(2, int)]
    for k in range(1, len(scans)):
        trace = found[k][0]
        d = np.asarray(model.site_errors(scans[k], [(trace.rc, trace.ij)])[0])
        shift, agree = _index_shift(d, trace.ij)
        if agree < 0.8:
            raise ValueError(
                f"{scans[k].name}: only {100 * agree:.0f} % of its trace features lie nearest the same "
                f"lattice sites through the model fitted to {scans[0].name}: the scans do not image one "
                "lattice with one scanner (check the scan angles, sizes and centres), or that fit is too "
                "loose (raise solver.max_steps)"
            )
        shifts.append(shift.astype(int))
    return shifts


def _index_shift(d: np.ndarray, ij: np.ndarray) -> tuple:
    """``(shift, agree)``: the whole lattice shift (2,) of a scan's features whose offsets from
    their sites are ``d`` (n, 2) pitches at its indices ``ij`` (n, 2), and the fraction of features
    that round to it. The first scan's model is loose on the axis that scan swept slowly (its
    loop there unseen): its error may grow across the lattice, so where the offsets themselves
    do not agree, their trend along the indices (a plane, least squares after dropping the
    features more than half a pitch off it) is taken out first: that trend is the model's, a
    wrong shift is the same whole number everywhere."""
    shift = np.round(np.median(d, axis=0))
    agree = float(np.mean(np.all(np.round(d) == shift, axis=1)))
    if agree >= 0.8 or len(d) < 6:
        return shift, agree
    X = np.column_stack([np.ones(len(d)), ij - np.median(ij, axis=0)])
    keep = np.ones(len(d), bool)
    for _ in range(3):
        coef = np.linalg.lstsq(X[keep], d[keep], rcond=None)[0]
        keep = np.all(np.abs(d - X @ coef) < 0.5, axis=1)
        if keep.sum() < 3:
            return shift, agree
    flat = d - X[:, 1:] @ coef[1:]
    shift = np.round(np.median(flat, axis=0))
    return shift, float(np.mean(np.all(np.round(flat) == shift, axis=1)))
