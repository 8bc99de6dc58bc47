"""Step A on a scanner whose hysteresis loop is wide: the retrace indexed by the feature fit.
Its own module so that ``--dist loadfile`` can hand it to one worker and test_step_a to the other."""

import numpy as np
import pytest

from jaxafm.config import CalibrationLattice, SimulatedCalibration
from jaxafm.identify import staged_fit
from jaxafm.identify.calibration_scan import _retrace_matches, one_pitch_back
from jaxafm.identify.features import LatticeFeatures
from jaxafm.identify.scan_model import ScanModelSpec, nominal_scan_model, start_lattice, start_loop
from jaxafm.identify.staged_fit import identify
from jaxafm.identify.stages import FitPlan, StageFit
from jaxafm.identify.step_a import true_scan_model
from jaxafm.instrument.afm import default_afm
from jaxafm.jobs import calibrate


def reversal_lag(trace: LatticeFeatures, retrace: LatticeFeatures, pitch_px: tuple) -> float:
    """How much earlier along the line the retrace sees the pillars of the trace's last half
    pitch, under the matching of ``retrace``'s indices (:meth:`CalibrationScan.feature_matches`):
    the median over the pillars both show of the trace's column less the retrace's, in pitches
    (nan where the retrace shows none of them)."""
    turn = trace.rc[:, 1] > trace.rc[:, 1].max() - 0.5 * pitch_px[0]
    col = {tuple(ij): c for ij, c in zip(retrace.ij, retrace.rc[:, 1])}
    lags = [c - col[tuple(ij)] for ij, c in zip(trace.ij[turn], trace.rc[turn, 1]) if tuple(ij) in col]
    return float(np.median(lags) / pitch_px[0]) if lags else float("nan")


def test_a_wide_loop_retrace_is_indexed_by_the_feature_fit_not_its_nearest_feature():
    """A 17.7 % loop scanned with 10 % overscan (configs/study.yaml's scanner 3, at 64 px): near the line
    reversal the retrace sees each pillar about 0.9 pitch earlier along the line than the trace,
    so the retrace feature nearest a trace feature there is the next pillar. Through the true
    scanner, trace and retrace features must sit on the same lattice sites (one shift for
    both); the nearest match does not, one of the matchings tried does, and step A's feature
    fit keeps that one: its tip path is then within tens of nm of the truth, where the
    nearest match leaves it about half a pitch (500 nm rms) off."""
    afm = default_afm(loop_width=0.177, creep_gamma=0.01, coupling=0.0003, noise_std=0.2)
    spec = SimulatedCalibration(pixels=64, size_nm=8000, line_rate_hz=1.0, seed=0)
    (scan,), sim = calibrate.calibration_scans(spec, CalibrationLattice(pitch_nm=1000, rotation_deg=0), afm)
    trace, retraces = scan.feature_matches()
    true = true_scan_model(sim)

    def shifts(retrace):  # whole-pitch shift of trace and of retrace onto the true sites
        e = true.site_errors(scan, [(trace.rc, trace.ij), (retrace.rc, retrace.ij)])
        return [tuple(np.round(np.median(np.asarray(x), axis=0))) for x in e]

    agree = [len(set(shifts(r))) == 1 for r in retraces]
    assert agree[0] is False and True in agree  # the nearest match is wrong; another is right
    ident = identify(
        scan,
        plan=FitPlan(max_steps=30, blur_px=(), coarsen="auto", hold_out=False, select=False),
        log=lambda m: None,
    )
    assert "matched the other way" in ident.stages[0].message
    e = np.stack(
        [
            np.asarray(p) - np.asarray(getattr(sim.measured, k))
            for p, k in zip(ident.model.paths(scan), ("path_trace", "path_retrace"))
        ]
    )
    e = e - e.reshape(-1, 2).mean(axis=0)  # the lattice's absolute place is not observable
    assert np.sqrt(np.mean(e[..., 0] ** 2)) < 100.0  # nm; a pitch is 1000


def _grid(columns, first_index):
    """Features at ``columns`` (px) on 7 rows 16 px apart, indexed from ``first_index`` along the line."""
    rows = 8.0 + 16.0 * np.arange(7)
    rc = np.array([(r, c) for r in rows for c in columns])
    ij = np.array([(first_index + k, i) for i in range(7) for k in range(len(columns))])
    return LatticeFeatures(rc, ij)


@pytest.mark.parametrize("displacement", [3.0, 12.0, 26.0])  # px; a pitch is 16
def test_a_retrace_more_than_a_pitch_behind_is_matched_only_with_wide_loop(displacement):
    """Pillars J = 0, 1, ... 16 px apart; the trace sees J = 0-6 at columns 10 + 16 J, the retrace
    each pillar ``displacement`` px earlier (those inside columns 0-111), each image indexing its
    own features from 0. The retrace feature of pillar J must get the trace's index J under one
    of the matchings: within a pitch (3, 12 px) under the two the line reversal gives; 1.6
    pitches behind (26 px: the nearest retrace feature to the last trace column is pillar J + 1's,
    and none lies beyond it) only under ``wide_loop``'s pitch-back matching, whose
    ``reversal_lag`` is then the displacement."""
    pillars = np.arange(9)
    trace = _grid(10.0 + 16.0 * pillars[:7], 0)
    seen = [j for j in pillars if 0 <= 10.0 + 16.0 * j - displacement <= 111]
    retrace = _grid(10.0 + 16.0 * np.array(seen) - displacement, 0)
    true_shift = (seen[0], 0)  # trace index minus the retrace's own, for the same pillar
    plain = [tuple(m.ij[0] - retrace.ij[0]) for m in _retrace_matches(trace, retrace, (16.0, 16.0))]
    back = one_pitch_back(trace, _retrace_matches(trace, retrace, (16.0, 16.0))[0], (16.0, 16.0))
    assert (true_shift in plain) == (displacement < 16.0)
    if displacement > 16.0:
        assert tuple(back.ij[0] - retrace.ij[0]) == true_shift
        assert reversal_lag(trace, back, (16.0, 16.0)) == pytest.approx(displacement / 16.0)


def test_wide_loop_puts_a_25_percent_loop_on_its_lattice_in_both_scans_of_a_0_90_pair():
    """A 25 % loop (configs/study_wide.yaml's widest) imaged at 0° and 90° with 10 % overscan: near
    the reversal each retrace sees the pillars about 1.7 pitches behind the trace, beyond every
    matching the reversal alone gives (so no model fits the first scan's retrace indexed by
    them). With ``wide_loop`` each scan's retrace is matched the way whose trace and retrace
    features lie on the same true lattice sites (one shift for both, through the true scanner),
    the later scan's in the chord stage over both scans, and the tip path over the 0° scan is
    within a tenth of a pitch of the truth on both axes."""
    afm = default_afm(loop_width=0.25, creep_gamma=0.01, coupling=0.02, noise_std=0.2)
    spec = SimulatedCalibration(pixels=64, size_nm=8000, line_rate_hz=1.0, angles_deg=[0, 90], seed=0)
    scans, sims = [], []
    for angle in (0, 90):
        (scan,), sim = calibrate.calibration_scans(
            spec.model_copy(update={"angles_deg": [angle]}),
            CalibrationLattice(pitch_nm=1000, rotation_deg=0),
            afm,
        )
        scans.append(scan)
        sims.append(sim)
    true = true_scan_model(sims[0])

    def on_true_sites(scan, trace, retrace):
        e = true.site_errors(scan, [(trace.rc, trace.ij), (retrace.rc, retrace.ij)])
        return len({tuple(np.round(np.median(np.asarray(x), axis=0))) for x in e}) == 1

    for wide in (False, True):  # the first scan's right matching is the pitch-back one alone
        trace, retraces = scans[0].feature_matches(wide)
        assert (True in [on_true_sites(scans[0], trace, r) for r in retraces]) is wide
    plan = FitPlan(
        max_steps=(30, 30), blur_px=(), coarsen="auto", hold_out=False, select=False, wide_loop=True
    )
    ident = identify(scans, plan=plan, log=lambda m: None)
    assert "matched the pitch-back way" in ident.stages[0].message
    assert "90 degree scan" in ident.stages[1].message and "matched the" in ident.stages[1].message
    paths = zip(ident.model.paths(scans[0]), ("path_trace", "path_retrace"))
    e = np.stack([np.asarray(p) - np.asarray(getattr(sims[0].measured, k)) for p, k in paths])
    e = e - e.reshape(-1, 2).mean(axis=0)  # the lattice's absolute place is not observable
    rms = np.sqrt(np.mean(e.reshape(-1, 2) ** 2, axis=0))
    assert np.all(rms < 100.0), rms  # nm; a pitch is 1000


def test_the_loop_start_puts_a_wide_loops_tip_path_within_a_quarter_pitch():
    """A 25 % loop imaged at 0°: the nominal model (a narrow loop) on the right (pitch-back)
    matching puts the tip path more than half a pitch from the truth along x, outside the chord
    fit's valley (half a pitch either way); a uniform loop scaled to that matching's features
    (``start_loop``) starts it well inside: within a quarter pitch rms."""
    afm = default_afm(loop_width=0.25, creep_gamma=0.01, coupling=0.02, noise_std=0.2)
    spec = SimulatedCalibration(pixels=64, size_nm=8000, line_rate_hz=1.0, seed=0)
    (scan,), sim = calibrate.calibration_scans(spec, CalibrationLattice(pitch_nm=1000, rotation_deg=0), afm)
    trace, retraces = scan.feature_matches(wide_loop=True)
    right = retraces[-1]  # the pitch-back matching (the test above: the right one on this scanner)
    assert reversal_lag(trace, right, scan.pitch_px) > 1.0
    nominal = start_lattice(nominal_scan_model(scan, ScanModelSpec()).as_float64(), scan, (trace, right))

    def x_rms(model) -> float:
        paths = zip(model.paths(scan), ("path_trace", "path_retrace"))
        e = np.stack([np.asarray(p) - np.asarray(getattr(sim.measured, k)) for p, k in paths])
        e = e - e.reshape(-1, 2).mean(axis=0)
        return float(np.sqrt(np.mean(e[..., 0] ** 2)))

    assert x_rms(nominal) > 500.0  # nm; a pitch is 1000
    assert x_rms(start_loop(nominal, scan, trace, right)) < 250.0


def test_wide_loop_adds_the_pitch_back_matching_and_leaves_the_reversals_own_as_they_were(monkeypatch):
    """A 24 % loop (configs/study_wide.yaml's scanner 3, at 64 px) whose right matching is the
    line reversal's nearest, with the retrace 1.25 pitches behind the trace there. ``wide_loop``
    adds the pitch-back matching (2.6 pitches behind), which alone starts from a loop scaled to
    its features; the nearest one starts from the nominal model as without ``wide_loop`` (started
    from the scaled loop instead, this scanner's tip path ended 2.0 nm rms off along x at 128 px,
    against 0.27 nm), is kept, and puts the tip path within a tenth of a pitch of the truth."""
    afm = default_afm(loop_width=0.2426, creep_gamma=0.0134, coupling=-0.059, noise_std=0.26)
    spec = SimulatedCalibration(pixels=64, size_nm=8000, line_rate_hz=1.0, seed=0)
    (scan,), sim = calibrate.calibration_scans(spec, CalibrationLattice(pitch_nm=1000, rotation_deg=0), afm)
    trace, retraces = scan.feature_matches(wide_loop=True)
    assert len(retraces) == 2 and reversal_lag(trace, retraces[0], scan.pitch_px) > 1.0
    started = []

    def spy(model, scan, trace, retrace):
        started.append(retrace.ij)
        return start_loop(model, scan, trace, retrace)

    monkeypatch.setattr(staged_fit, "start_loop", spy)
    plan = FitPlan(max_steps=30, blur_px=(), coarsen="auto", hold_out=False, select=False, wide_loop=True)
    ident = identify(scan, plan=plan, log=lambda m: None)
    assert len(started) == 1 and np.array_equal(started[0], retraces[1].ij)  # the pitch-back one alone
    assert "matched the nearer way" in ident.stages[0].message
    paths = zip(ident.model.paths(scan), ("path_trace", "path_retrace"))
    e = np.stack([np.asarray(p) - np.asarray(getattr(sim.measured, k)) for p, k in paths])
    e = e - e.reshape(-1, 2).mean(axis=0)  # the lattice's absolute place is not observable
    assert np.all(np.sqrt(np.mean(e.reshape(-1, 2) ** 2, axis=0)) < 100.0)  # nm; a pitch is 1000


def _lm_fit(start: float, floor: float, rate: float, steps: int):
    """A stand-in for a chord stage's fit whose loss falls from ``start`` towards ``floor``
    geometrically (by ``rate`` a step), as a Levenberg-Marquardt fit does near its optimum,
    after ``steps`` steps; converged once within 1 % of its floor. Its ``model`` is the pair
    ``(floor, rate)`` that the next fit goes on from."""
    loss = floor + (start - floor) * rate**steps
    return StageFit((floor, rate, loss), steps, loss < 1.01 * floor, loss)


def _go_on(fit, data, limit=30):
    """Another ``limit`` steps of ``fit`` (the ``more`` of ``_confirmed_choice``)."""
    floor, rate, loss = fit.model
    return _lm_fit(loss, floor, rate, limit)


def _matchings(*fits, own=(False, True)):
    """The matchings tried, in order: the first from the model so far, the next from its own start."""
    return [staged_fit._Matching(fit, None, [], [], None, o) for fit, o in zip(fits, own)]


def test_a_matching_from_its_own_start_replaces_the_first_only_on_fits_gone_on_long_enough():
    """The case of study_wide_0_90_wide_loop.yaml's scanners 3 and 6: the first (right) matching
    descends from far off (2.3e-3 after 30 steps) to its floor 5e-5; the pitch-back one, started
    near its own optimum, sits at 7.8e-4 with its floor 7e-4. After one step limit it leads by
    three times (more than ``MATCH_RATIO``): compared then, it would be kept. Gone on, the first
    leads, and is kept; the fits the stage keeps are those of its step limit."""
    tried = _matchings(_lm_fit(1.0, 5e-5, 0.9, 30), _lm_fit(1e-3, 7e-4, 0.9, 30))
    assert tried[1].fit.loss * staged_fit.MATCH_RATIO < tried[0].fit.loss  # one step limit's verdict
    best, note = staged_fit._confirmed_choice(tried, _go_on)
    assert best == 0 and "to confirm the lead" in note
    assert [t.fit.steps for t in tried] == [30, 30]


def test_a_matching_that_fits_far_better_on_converged_fits_is_kept():
    """The pitch-back matching truly fits better (floor 1e-5 against 1e-3): it leads after one
    step limit and still leads once both fits have converged, so it replaces the first; fits
    that had converged at the first comparison are not gone on with (no note), and no fit goes
    on for more than ``CONFIRM_ROUNDS`` step limits."""
    tried = _matchings(_lm_fit(1.0, 1e-3, 0.5, 30), _lm_fit(1.0, 1e-5, 0.5, 30))
    assert staged_fit._confirmed_choice(tried, _go_on) == (1, "")  # converged at once: compared as they are
    calls = []
    slow = _matchings(_lm_fit(1.0, 1e-3, 0.9, 30), _lm_fit(1.0, 1e-5, 0.8, 30))
    best, note = staged_fit._confirmed_choice(slow, lambda fit, data: calls.append(fit) or _go_on(fit, data))
    assert best == 1 and "to confirm the lead" in note
    assert 0 < len(calls) <= 2 * (staged_fit.CONFIRM_ROUNDS - 1)
    assert max(fit.steps for fit in calls) < 30 * staged_fit.CONFIRM_ROUNDS  # each goes on from below the cap


def test_matchings_from_one_start_and_a_first_that_leads_are_compared_as_they_stand():
    """Matchings fitted from the same model for the same steps race fairly: the one that leads
    by ``MATCH_RATIO`` is kept at once, unconverged (the other way of configs/study.yaml's
    scanner 3). And when the first leads, or another by less than ``MATCH_RATIO``, nothing is
    fitted again: the rule costs no time where the first matching is kept."""
    never = lambda fit, data: pytest.fail("fitted again")
    fair = _matchings(_lm_fit(1.0, 5e-5, 0.9, 30), _lm_fit(1e-3, 7e-4, 0.9, 30), own=(False, False))
    assert staged_fit._confirmed_choice(fair, never) == (1, "")
    close = _matchings(_lm_fit(1.0, 1e-3, 0.95, 30), _lm_fit(1.0, 8e-4, 0.95, 30))
    assert staged_fit._confirmed_choice(close, never) == (0, "")


def test_a_later_scans_matchings_are_judged_beside_the_scans_matched_before_it_alone(monkeypatch):
    """Three scans of a 25 % loop (0° and 90° at 1 Hz, 0° at 2 Hz) with ``wide_loop``: the chord
    stage over all scans matches scans 1 and 2 in turn, each matching's fit on that scan and the
    scans before it in their kept matchings, never beside a later scan, which would bring its
    first matching, right or not (configs/study_classes_speed.yaml's Preisach scanner 5, four
    scans: its model 276 nm off along y so, 3.9 nm matched beside the scans before it alone).
    The fits are stood in for by one that records what it was given; every matching then fits
    equally well and the first is kept."""
    afm = default_afm(loop_width=0.25, creep_gamma=0.01, coupling=0.02, noise_std=0.2)
    spec = SimulatedCalibration(pixels=64, size_nm=8000, line_rate_hz=1.0, seed=0)
    lattice = CalibrationLattice(pitch_nm=1000, rotation_deg=0)
    scans = [
        calibrate.calibration_scans(
            spec.model_copy(update={"angles_deg": [a], "line_rate_hz": r}), lattice, afm
        )[0][0]
        for a, r in ((0, 1.0), (90, 1.0), (0, 2.0))
    ]
    seen, kept = [], {}

    def fit_stage(stage, model, level, data, plan, max_steps):
        if not stage.first_scan_only:
            seen.append((len(level), [[np.asarray(chords[1]) for chords in images] for images in data]))
        return StageFit(model, 1, True, 1.0)

    align = staged_fit._StagedFit.align

    def aligned(self):  # each scan's training chords' lattice indices per image, first matchings
        align(self)
        kept["train"] = [[np.asarray(ij) for _, ij, _ in part] for part in self.train]

    monkeypatch.setattr(staged_fit, "fit_stage", fit_stage)
    monkeypatch.setattr(staged_fit._StagedFit, "align", aligned)
    plan = FitPlan(max_steps=(2, 2), blur_px=(), coarsen="auto", hold_out=False, select=False, wide_loop=True)
    identify(scans, plan=plan, log=lambda m: None)
    tried = [len(scan.feature_matches(True)[1]) for scan in scans[1:]]
    matching = seen[: sum(tried)]
    assert [n for n, _ in matching] == [k + 1 for k, t in enumerate(tried, 1) for _ in range(t)]
    for n, indices in matching:  # the scans before it, in their kept matching (here the first)
        for before, given in zip(kept["train"][: n - 1], indices[: n - 1]):
            assert all(np.array_equal(a, b[: len(a)]) for a, b in zip(before, given))
