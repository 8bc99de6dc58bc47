"""The chords' lengths (``solver.chord_lengths``) on the real lattices.

The three shipped Nanosurf lattices (jaxafm/data/real/README.md), each identified as its
``configs/calibrate_nanosurf_NAME.yaml`` says but with ``solver.chord_lengths: true``: the
chord stages fit each chord's length against its features' common length as well as its
midpoint (:func:`jaxafm.identify.stages.width_misfits`). Beside each, the committed run of the
configuration as it is (``experiments/results/calibrate_nanosurf_NAME/metrics.json``): the
held-out features' residual (nm), their local pitch spread (%), the largest error of a distance
between them (%), the features' widths' spread along the lines after the correction (%), the
model the ladder kept and the fit's time. No truth is known here: the held-out features are
the check.

    python experiments/step_a_chord_lengths_real.py [--lattices square_pits round_pits round_pillars]

writes experiments/results/step_a_chord_lengths_real/metrics.json (a table of docs/step_a.md).
"""

from __future__ import annotations

from step_a_real_classes import MODEL_KEPT, ROOT, committed, identified, run_lattices

OUT = ROOT / "experiments" / "results" / "step_a_chord_lengths_real"
#: what the table keeps of each identification (``identification_metrics``' keys)
KEPT = (
    "held_out_rms_nm",
    "held_out_coverage_90_pct",
    "held_out_pitch_std_corrected_pct",
    "held_out_distance_error_max_corrected_pct",
    "feature_width_spread_along_raw_pct",
    "feature_width_spread_along_corrected_pct",
) + MODEL_KEPT


def _line(lattice: str, name: str, r: dict) -> str:
    return (
        f"{lattice} {name}: held-out features {r['held_out_rms_nm']:.1f} nm "
        f"({r['held_out_coverage_90_pct']:.0f} % in their 90 % ellipses); pitch spread "
        f"{r['held_out_pitch_std_corrected_pct']:.2f} %; distances "
        f"{r['held_out_distance_error_max_corrected_pct']:.2f} % at most; widths along "
        f"{r['feature_width_spread_along_corrected_pct']:.2f} %; kept {r['model_kind']} "
        f"{r['model_operators']} + {', '.join(r['model_effects'])}; {r['fit_s']:.0f} s"
    )


def main() -> None:
    run_lattices(
        OUT,
        __doc__,
        lambda lattice: {
            "midpoints": committed(lattice, KEPT),
            "lengths": identified(lattice, KEPT, solver={"chord_lengths": True}),
        },
        _line,
    )


if __name__ == "__main__":
    main()
