"""Step A on a scanner whose hysteresis loop is wide: the retrace indexed by the feature fit.
Its own module so that ``--dist loadfile`` can hand it to whichever worker is free at the end."""

import numpy as np

from jaxafm.config import CalibrationLattice, SimulatedCalibration
from jaxafm.identify.scan_model import ScanModel
from jaxafm.identify.staged_fit import identify
from jaxafm.identify.stages import FitPlan
from jaxafm.instrument.afm import default_afm
from jaxafm.jobs import calibrate


def _true_model(sim):
    return ScanModel(sim.afm.scanner.without("noise"), sim.afm.feedback, sim.lattice, rotation_free=True)


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
    true = _true_model(sim)

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
