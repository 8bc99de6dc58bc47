"""Chords whose midpoints lie off their features' lines (``grating.off_line_chords_sd``) on the
real lattices.

The three shipped Nanosurf lattices (jaxafm/data/real/README.md), each identified as its
``configs/calibrate_nanosurf_NAME.yaml`` says, with every chord (the default) and with
``grating.off_line_chords_sd: 5``, every chord whose midpoint lies more than 5 robust sds off its
feature's line of midpoints left out (:func:`jaxafm.identify.chords._on_line`: a turned square's
chords that meet its top or bottom side). Beside each, the committed run of the configuration as
it is (``experiments/results/calibrate_nanosurf_NAME/metrics.json``). For each: how many chords
the images give, the held-out features' residual (nm) raw and corrected, the error the fit
predicts for them (nm) and how many lie inside their 90 % ellipses, their local pitch spread and
largest distance error (%), the model the ladder kept and the fit's time. The held-out features
are placed by their own chords, so dropping chords moves them too: each run is judged on its
own chords. No truth is known here.

    python experiments/step_a_off_line_chords.py [--lattices square_pits round_pits round_pillars]

writes experiments/results/step_a_off_line_chords/metrics.json (a table of docs/step_a.md).
"""

from __future__ import annotations

import numpy as np
from step_a_real_classes import MODEL_KEPT, ROOT, committed, identified, run_lattices

from jaxafm.identify.chords import find_chords
from jaxafm.identify.stages import chord_residuals

OUT = ROOT / "experiments" / "results" / "step_a_off_line_chords"
#: how far off its feature's line a chord's midpoint may lie, robust sds
SDS = 5.0
#: what the table keeps of each identification (``identification_metrics``' keys)
KEPT = (
    "held_out_rms_nm",
    "held_out_raw_rms_nm",
    "held_out_predicted_rms_nm",
    "held_out_coverage_90_pct",
    "held_out_pitch_std_corrected_pct",
    "held_out_distance_error_max_corrected_pct",
) + MODEL_KEPT


def chords_at_fit(ident, scans: tuple) -> dict:
    """How many chords the ``scans``' images give (every image of every scan, read as the scans
    say), and the training chords' midpoints off their features' lines at the fit (nm rms,
    :func:`~jaxafm.identify.stages.chord_residuals`), all and along the lines."""
    images = [(np.asarray(getattr(s, k)), s) for s in scans for k in ("trace", "retrace")]
    count = sum(len(find_chords(z, s.pits, off_line_sd=s.off_line_sd).feature) for z, s in images)
    r = np.asarray(
        chord_residuals(ident.model.free_parameters(scans[0])[0], (ident.model, scans, ident.chords))
    )
    w = np.concatenate([np.asarray(w) for images in ident.chords for *_, w in images])
    along = np.concatenate([np.asarray(a) for images in ident.chords for *_, a, _ in images]) > 0
    real = w > 0
    nm = min(scans[0].pitch) * r[real] / w[real]
    return {
        "chords": int(count),
        "midpoint_rms_nm": float(np.sqrt(np.mean(nm**2))),
        "midpoint_along_rms_nm": float(np.sqrt(np.mean(nm[along[real]] ** 2))),
    }


def run(lattice: str, sds) -> dict:
    """The lattice identified with every chord (``sds`` None: the configuration as it is, its
    metrics as committed) or with ``grating.off_line_chords_sd`` at ``sds``: the ``KEPT``
    metrics and :func:`chords_at_fit`."""
    grating = None if sds is None else {"off_line_chords_sd": sds}
    out = identified(lattice, KEPT, grating=grating, more=chords_at_fit)
    if sds is None:  # the same fit as the committed run's: its metrics as committed
        out |= committed(lattice, KEPT)
    return out


def _line(lattice: str, name: str, r: dict) -> str:
    return (
        f"{lattice} {name}: {r['chords']} chords, midpoints {r['midpoint_rms_nm']:.1f} nm rms at the fit "
        f"({r['midpoint_along_rms_nm']:.1f} nm along the lines); held-out features "
        f"{r['held_out_raw_rms_nm']:.1f} nm raw -> "
        f"{r['held_out_rms_nm']:.1f} nm (predicted {r['held_out_predicted_rms_nm']:.1f} nm, "
        f"{r['held_out_coverage_90_pct']:.0f} % in their 90 % ellipses); pitch spread "
        f"{r['held_out_pitch_std_corrected_pct']:.2f} %; distances "
        f"{r['held_out_distance_error_max_corrected_pct']:.2f} % at most; kept {r['model_kind']} "
        f"{r['model_operators']} + {', '.join(r['model_effects'])}; {r['fit_s']:.0f} s"
    )


def main() -> None:
    run_lattices(
        OUT,
        __doc__,
        lambda lattice: {"every chord": run(lattice, None), "on their lines": run(lattice, SDS)},
        _line,
    )


if __name__ == "__main__":
    main()
