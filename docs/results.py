"""The results tables of the README and the docs, generated from the committed results.

Every number that a page quotes from a run comes from a file under ``experiments/results/``
through this script: each table sits on its page between ``<!-- results:NAME -->`` and
``<!-- /results -->``, and says which file it comes from and which command makes that file.

    python docs/results.py            # write every table into README.md and docs/**/*.md
    python docs/results.py --check    # exit status 1 naming each stale table and cell

``--check`` (run by ``.ci/run``) also fails on a table that no page shows, a marker naming no
table, and a sentence that narrates when a number was measured ("this round", "earlier",
"N min N s"): the pages say what is, the git log says what was. It needs the standard library
alone, not jaxafm or JAX.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import statistics
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

from jaxafm.identify.plausibility import PATH_OPEN, PATH_TOLERANCE_PX, path_open

ROOT = Path(__file__).resolve().parents[1]
RESULTS = "experiments/results"
PAGES = ("README.md", "docs/*.md", "docs/guides/*.md")
BEGIN = re.compile(r"<!-- results:([a-z0-9_]+) -->")
END = "<!-- /results -->"
#: Phrases that narrate when or how often something was measured; the git log keeps that.
NARRATION = re.compile(
    r"\b(this round|round before|sessions?|previously|no longer|used to|earlier|before this|until now|now|"
    r"\d+ min \d+(\.\d+)? s)\b",
    re.IGNORECASE,
)


# --- runs and values -----------------------------------------------------------------------


@dataclass(frozen=True)
class Run:
    """A committed result file (under ``experiments/results/``) and the command that makes it."""

    path: str
    command: str

    @property
    def file(self) -> str:
        """The file's path from the repository root."""
        return f"{RESULTS}/{self.path}"


class Results:
    """The committed result files under ``root``, each read once."""

    def __init__(self, root: Path):
        self.root = root
        self._loaded: dict[str, Any] = {}

    def __call__(self, run: Run) -> Any:
        """The parsed JSON of ``run``'s file (a ``.csv`` file: its rows, each a dict of strings)."""
        if run.path not in self._loaded:
            path = self.root / run.file
            try:
                text = path.read_text()
                self._loaded[run.path] = (
                    list(csv.DictReader(text.splitlines())) if path.suffix == ".csv" else json.loads(text)
                )
            except (OSError, ValueError) as e:
                raise SystemExit(f"{path}: cannot read the results of `{run.command}`: {e}") from e
        return self._loaded[run.path]


def _unit(text: str, unit: str) -> str:
    """``text`` followed by ``unit`` (``×`` and ``°`` without a space)."""
    if not unit:
        return text
    return f"{text}{unit}" if unit in ("×", "°") else f"{text} {unit}"


def q(value: Any, unit: str = "", digits: int = 1, tiny: bool = False) -> str:
    """A number as the pages print it: ``digits`` decimals, thousands separated, then its unit.
    ``None`` is a dash. With ``tiny``, a non-zero value too small for ``digits`` decimals is
    written in powers of ten (a round-off error, say) instead of as zero."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    v = float(value)
    if tiny and v and abs(v) < 0.5 * 10**-digits:
        text = f"{v:.1e}"
    else:
        text = f"{v:,.{digits}f}"
        text = text.lstrip("-") if not text.strip("-0.,") else text
    return _unit(text.replace("-", "−"), unit)


def count(value: Any) -> str:
    """A whole number, thousands separated."""
    return "–" if value is None else f"{int(value):,}"


def span(values: Sequence[float], unit: str = "", digits: int = 1) -> str:
    """The range of ``values``, ``lo–hi unit`` (``lo to hi`` where ``lo`` is negative; one value
    where both ends print alike)."""
    lo, hi = q(min(values), "", digits), q(max(values), "", digits)
    return _unit(lo if lo == hi else f"{lo} to {hi}" if min(values) < 0 else f"{lo}–{hi}", unit)


def verdict(met: Optional[bool]) -> str:
    """A goal's verdict cell."""
    return "measured" if met is None else "met" if met else "**not met**"


# --- tables ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Link:
    """A cell that links ``target`` (from the repository root, with an optional ``#anchor``)."""

    text: str
    target: str


def source(run: Run) -> Link:
    """The command that makes ``run``, linked to the file it writes."""
    return Link(f"`{run.command}`", run.file)


Cell = Union[str, Link, tuple]  # a tuple: several links, one after the other


@dataclass
class Table:
    """A results table: its header, its rows of formatted cells, the runs its numbers come from,
    and a short note printed after them (no numbers of its own)."""

    header: list[str]
    rows: list[list[Cell]]
    runs: list[Run]
    note: str = ""


TABLES: dict[str, Callable[[Results], Table]] = {}


def table(name: str):
    """Register a function ``Results -> Table`` as the table ``name`` of the pages' markers."""

    def register(make):
        TABLES[name] = make
        return make

    return register


def relative(target: str, page: str) -> str:
    """``target`` (from the repository root, with an optional ``#anchor``) as a link from ``page``."""
    path, _, anchor = target.partition("#")
    rel = os.path.relpath(path, os.path.dirname(page) or ".").replace(os.sep, "/")
    return rel + (f"#{anchor}" if anchor else "")


def cell(c: Cell, page: str) -> str:
    """A cell's Markdown on ``page``."""
    if isinstance(c, tuple):
        return "; ".join(cell(link, page) for link in c)
    return c if isinstance(c, str) else f"[{c.text}]({relative(c.target, page)})"


def render(made: Table, page: str) -> list[str]:
    """The Markdown lines of a table on ``page``: the table, then where its numbers come from."""
    lines = ["| " + " | ".join(made.header) + " |", "|" + "---|" * len(made.header)]
    lines += ["| " + " | ".join(cell(c, page) for c in row) + " |" for row in made.rows]
    runs = list(dict.fromkeys(made.runs))
    if runs:
        sources = "; ".join(cell(source(r), page) for r in runs)
        lines += ["", f"From {sources}." + (f" {made.note}" if made.note else "")]
    return lines


# --- the committed runs ------------------------------------------------------------------

STEP_A_SIM = Run("step_a_simulated/metrics.json", "jaxafm calibrate configs/step_a_simulated.yaml")
STEP_A_ABL = Run("step_a_ablation/metrics.json", "jaxafm calibrate configs/step_a_ablation.yaml")
STEP_A_ANGLES = Run("step_a_angles/metrics.json", "python experiments/step_a_angles.py")
STEP_A_LATTICES = Run("step_a_lattices/metrics.json", "python experiments/step_a_lattices.py")
BENCH_STEP_A = Run("bench_step_a/metrics.json", "python experiments/bench_step_a.py --pixels 256")
GPU_STEP_A = Run(
    "gpu_h200/bench_step_a_gpu.json",
    "python experiments/bench_step_a.py --pixels 256 --runs geodesic --seeds 1 --profile 0",
)
GPU_HOST_STEP_A = Run(
    "gpu_h200/bench_step_a_cpu.json",
    "JAX_PLATFORMS=cpu taskset -c 0,1 python experiments/bench_step_a.py --pixels 256 --runs geodesic --seeds 1 "
    "--profile 0",
)
PAPER = Run("paper/metrics.json", "jaxafm run configs/paper.yaml")
PAPER_TRUE = Run(
    "paper_true_model/metrics.json", "python experiments/paper_true_model.py --config configs/paper.yaml"
)
PAPER_CONVERGED = Run("paper_converged/metrics.json", "jaxafm run configs/paper_converged.yaml")
PUSH_STUDY = Run("push_study/metrics.json", "python experiments/push_study.py --fields 4")
PUSH_0_90 = Run(
    "push_study_0_90/metrics.json",
    "python experiments/push_study.py --fields 4 --model experiments/results/step_a_simulated/model_gpi.json "
    "--out experiments/results/push_study_0_90",
)
PUSH_TRUE = Run(
    "push_study_true_model/metrics.json",
    "python experiments/push_study.py --fields 4 --model experiments/results/paper_true_model/true_scanner.json "
    "--out experiments/results/push_study_true_model",
)
MINOR_LOOPS = Run("minor_loops.json", "python experiments/minor_loops.py")
DRIFT_TRACKING = Run("drift_tracking/results.json", "python experiments/drift_tracking.py")
STUDY = Run("study/metrics.json", "jaxafm study configs/study.yaml")
STUDY_WIDE = Run("study_wide/metrics.json", "jaxafm study configs/study_wide.yaml")
STUDY_0_90 = Run("study_0_90/metrics.json", "jaxafm study configs/study_0_90.yaml")
STUDY_0_90_CY = Run("study_0_90_condition_y/metrics.json", "jaxafm study configs/study_0_90_condition_y.yaml")
STUDY_WIDE_0_90_CY = Run(
    "study_wide_0_90_condition_y/metrics.json", "jaxafm study configs/study_wide_0_90_condition_y.yaml"
)
STUDY_WIDE_LOOP = Run(
    "study_wide_0_90_wide_loop/metrics.json", "jaxafm study configs/study_wide_0_90_wide_loop.yaml"
)
STUDY_CLASSES = Run("study_classes/metrics.json", "jaxafm study configs/study_classes.yaml")
STUDY_CLASSES_0_90_CY = Run(
    "study_classes_0_90_condition_y/metrics.json", "jaxafm study configs/study_classes_0_90_condition_y.yaml"
)
STUDY_CLASSES_WIDE_LOOP = Run(
    "study_classes_0_90_wide_loop/metrics.json", "jaxafm study configs/study_classes_0_90_wide_loop.yaml"
)
STUDY_CLASSES_SPEED = Run("study_classes_speed/metrics.json", "jaxafm study configs/study_classes_speed.yaml")
STUDY_SPEED = Run("study_speed/metrics.json", "jaxafm study configs/study_speed.yaml")
STUDY_PUSHES = Run("study_push_learning/metrics.json", "jaxafm study configs/study_push_learning.yaml")
STUDY_LEAD_IN = Run("study_push_lead_in/metrics.json", "jaxafm study configs/study_push_lead_in.yaml")
STUDY_NO_LEARNING = Run("study_no_learning/metrics.json", "jaxafm study configs/study_no_learning.yaml")
STUDY_GATE = Run("study_push_gate/metrics.json", "jaxafm study configs/study_push_gate.yaml")
PUSH_SHORTFALL = Run("push_shortfall/shortfall.json", "python experiments/push_shortfall.py")
BENCH_STUDY = Run("bench_study/bench.json", "python experiments/bench_study.py")
GPU_STUDY = Run(
    "gpu_h100/bench_study.json",
    "python experiments/bench_study.py --batches 1024 4096 --calls 2 --loop 2 --full 0",
)
BENCH_HYSTERESIS = Run("bench_hysteresis.json", "python experiments/bench_hysteresis.py")
BENCH_PREISACH_FIT = Run("bench_preisach_fit.json", "python experiments/bench_preisach_fit.py")
BENCH_SCAN = Run("bench_scan.json", "python experiments/bench_scan.py")
BENCH_RENDER = Run("bench_render/metrics.json", "python experiments/bench_render.py")
GRATING_SCAN = Run("simulated_grating_scan/metrics.json", "python experiments/simulated_grating_scan.py")
PIEZO_FIT = Run("piezo_sine_1hz/metrics.json", "jaxafm fit configs/piezo_sine_1hz.yaml")
BENCH_BAND = Run("bench_band/bench.json", "python experiments/bench_band.py")
BENCH_BLAS = Run("bench_blas_threads/bench.json", "python experiments/bench_blas_threads.py")
BENCH_SUITE = Run("bench_suite/suite.json", "python experiments/bench_suite.py")
BENCH_SUITE_TRIAL = Run("bench_suite/trial.json", "python experiments/bench_suite.py --trial")
BENCH_SUITE_FLAGS = Run("bench_suite/flags.json", "python experiments/bench_suite.py --flags")
CROSS_RECORD = Run("cross_record/metrics.json", "python experiments/cross_record.py")
PREDICT = Run("predict_piezo/metrics.json", "jaxafm predict configs/predict_piezo.yaml")
COMPENSATE = Run("compensate_piezo/metrics.json", "jaxafm compensate configs/compensate_piezo.yaml")
REAL_GRATING = Run("real_grating/metrics.json", "python experiments/real_grating.py")
REAL_LATTICE = Run("real_lattice/metrics.json", "python experiments/real_lattice.py")
WITHHELD = Run("withheld_effects/summary.json", "python experiments/withheld_effects.py")
WITHHELD_CASES = Run("withheld_effects/cases.json", "python experiments/withheld_effects.py")
RECORDS = Run(
    "withheld_records_rerun/summary.json",
    "python experiments/withheld_effects.py --kind record --out experiments/results/withheld_records_rerun",
)
RECORDS_CASES = Run("withheld_records_rerun/cases.json", RECORDS.command)
INDEPENDENT = Run("independent_check/summary.json", "python experiments/independent_check.py")
WANDERING_COMMAND = "python experiments/independent_check.py --wandering"
WANDERING = Run("independent_check_wandering/summary.json", WANDERING_COMMAND)
REPORTED = Run(
    "independent_check_wandering/reported.json", "python experiments/independent_check.py --reported"
)
WANDERING_NODES7 = Run(
    "independent_check_wandering_nodes7/summary.json",
    "python experiments/independent_check.py --wandering --truth preisach --effects drift creep "
    "--profile-nodes 7 --shard 1/2 --out experiments/results/independent_check_wandering_nodes7 "
    "(and --shard 2/2; then --effects control, --shard 1/2 and 2/2)",
)
PREISACH_RUNG = Run(
    "independent_check_wandering/preisach_rung.json", "python experiments/preisach_rung.py --nodes 5 7 9 13"
)
STABILITY = Run("stability/summary.json", "python experiments/stability.py")
STABILITY_ROWS = (
    Run("stability/rows-1-of-2.json", "python experiments/stability.py --shard 1/2"),
    Run("stability/rows-2-of-2.json", "python experiments/stability.py --shard 2/2"),
)


def diagnosis_run(folder: str, config: str) -> Run:
    """The ``diagnosis.json`` of a ``jaxafm diagnose`` run."""
    return Run(f"{folder}/diagnosis.json", f"jaxafm diagnose configs/{config}.yaml")


DIAGNOSE_SIMULATED = diagnosis_run("diagnose_simulated", "diagnose_simulated")
DIAGNOSE_SCANS = diagnosis_run("diagnose_scans", "diagnose_scans")
DIAGNOSE_SCANS_LATTICE = diagnosis_run("diagnose_scans_lattice", "diagnose_scans_lattice")
#: The real data's diagnoses: (case as the table names it, run).
DIAGNOSE_REAL = (
    ("piezo, symmetric PI nominal", diagnosis_run("diagnose_real/piezo_pi", "diagnose_piezo_pi")),
    ("piezo, generalised PI nominal", diagnosis_run("diagnose_real/piezo_gpi", "diagnose_piezo_gpi")),
    ("piezo, Preisach nominal", diagnosis_run("diagnose_real/piezo_preisach", "diagnose_piezo_preisach")),
    (
        "second piezo record (step, then sine)",
        diagnosis_run("diagnose_real/piezo_step", "diagnose_piezo_step"),
    ),
    ("1-D grating image", diagnosis_run("diagnose_real/grating", "diagnose_grating")),
    (
        "2-D lattice image, square pits, trace",
        diagnosis_run("diagnose_real/lattice", "diagnose_real_lattice"),
    ),
)


# --- the goals (docs/index.md, README.md) ----------------------------------------------------


@dataclass(frozen=True)
class Goal:
    """One goal checked on one run (or a tuple of runs, whose files the result and the verdict
    then take as a tuple): its wording, the page that explains it, the result as a sentence of
    formatted numbers, and whether it is met (``None``: measured, no goal)."""

    name: str
    goal: str
    run: Union[Run, tuple]
    page: str
    result: Callable[[Any], str]
    met: Callable[[Any], Optional[bool]] = field(default=lambda m: None)


def _bench_runs(m: dict) -> dict:
    """The step A benchmark's runs (name: result) in its metrics, without its settings, machine
    and profile."""
    return {k: v for k, v in m.items() if isinstance(v, dict) and "seconds" in v}


def _geodesic(m: dict) -> dict:
    """The geodesic solver's run in the step A benchmark's metrics, whatever its step limits."""
    return m[f"jaxafm geodesic LM, steps {','.join(map(str, m['steps']))}"]


def _linearity(m, prefix):
    return m[f"{prefix}_linearity_error_trace_pct"], m[f"{prefix}_linearity_error_retrace_pct"]


def _lattice_errors(rows):
    return [abs(r["rotation_error_deg"]) for r in rows]


UNCERTAINTY = Run("uncertainty_coverage/metrics.json", "python experiments/uncertainty_coverage.py")
POSTERIOR_CHECK = Run("posterior_check/metrics.json", "python experiments/posterior_check.py")
UNCERTAINTY_MODELS = {"pi": "PI", "gpi": "generalised PI", "gpi_creep": "generalised PI + creep"}
UNCERTAINTY_RECORDS = {"sine": "sine", "ramped": "ramped sine", "step": "step + sine (5 kHz)"}


def _in_record(m: dict) -> list:
    """The real records' own held-out rows (not the cross-record ones) of the coverage run."""
    return [(k, v) for k, v in m["real"].items() if "->" not in k]


def _coverage_goal(m: dict) -> str:
    """The default (AR(1)) 90 % coverage on the real records' held-out parts and the generator's."""
    own = [v["ar1_coverage_90_pct"] for _, v in _in_record(m)]
    cross = [v["ar1_coverage_90_pct"] for k, v in m["real"].items() if "->" in k]
    gen = m["generator_summary"]
    return (
        f"real records, own held-out part: {span(own, '%')} ({sum(85 <= c <= 95 for c in own)} of {len(own)} "
        f"fits in 85–95 %); across records: {span(cross, '%')}; independent generator: "
        + "; ".join(
            f"{UNCERTAINTY_MODELS[kind]} median {q(gen[f'generator/{kind}/ar1']['median_coverage_90_pct'], '%')}"
            for kind in ("pi", "gpi_creep")
        )
    )


STEP_A_INDEPENDENT = Run(
    "step_a_independent/summary.json", "python experiments/step_a_independent.py --cases 20 --pixels 64"
)
#: the generator's cases run again (``--seeds``), each with the tip path's coverage: per run its
#: seeds, the latest run first
STEP_A_RERUNS = {
    Run(
        STEP_A_INDEPENDENT.path, "python experiments/step_a_independent.py --pixels 64 --seeds " + seeds
    ): seeds
    for seeds in (
        "101 103 104 107 109 110 112 113 115 118 119 900 901",
        "100 106 116",
        "114 105 102 108 111 117",
        "102 108 111 117",
        "100 101 103 104 106 107 109 110 112 113 115 116 118 119 901",
        "114 105 900 901",
        "102 103 107 109 110 112 113 115 116 118 119",
    )
}
#: all, one after the other: what the summary's coverage medians come from
STEP_A_COVERAGE = Run(STEP_A_INDEPENDENT.path, " && ".join(run.command for run in reversed(STEP_A_RERUNS)))


def _run_of(seed: int, run: Run, reruns: dict = STEP_A_RERUNS, study: Run = STEP_A_INDEPENDENT) -> Run:
    """``run``'s file with the command that last wrote the generator's case ``seed`` into it: the
    latest of ``reruns`` (``--seeds`` runs) that had it, else the ``study``'s own."""
    latest = next((r for r, seeds in reruns.items() if str(seed) in seeds.split()), study)
    return Run(run.path, latest.command)


def _scans_label(r: dict) -> str:
    """A generator case's scans in words: a speed series, a 0° + 90° pair, one 0° scan of a
    3 × 3 lattice, or one 0° scan."""
    if len(r["rates_hz"]) > 1:
        return "speed series"
    if len(r["angles_deg"]) > 1:
        return "0° + 90°"
    return "3 × 3 lattice" if r.get("unidentifiable") and "3 x 3" in r["unidentifiable"] else "one 0° scan"


NANOSURF = tuple(
    (
        label,
        Run(
            f"calibrate_nanosurf_{name}/metrics.json",
            f"jaxafm calibrate configs/calibrate_nanosurf_{name}.yaml",
        ),
    )
    for label, name in (
        ("square pits", "square_pits"),
        ("round pits", "round_pits"),
        ("round pillars", "round_pillars"),
    )
)


def _learning_result(m: dict) -> str:
    """A study's A+B learning (``AB_learning``) as a sentence."""
    never = len(m["unlearnt_scanners"])
    return (
        f"{q(m['learnt_median_nm'], 'nm')} against {q(m['first_round_median_nm'], 'nm')} "
        f"(ratio {q(m['learnt_ratio'], '', 2)}) on the {count(len(m['learnt_scanners']))} scanners that reached "
        f"10 finds" + (f"; {count(never)} never did" if never else "")
    )


def _largest_gap(bins: list) -> float:
    """The largest |observed − predicted| (points) over the reliability bins with ≥ 100 trials."""
    return max(
        (abs(b["observed_pct"] - b["predicted_pct"]) for b in bins if b["trials"] >= 100),
        default=float("nan"),
    )


def _model_kept(m: dict) -> str:
    """The model step A kept: its operator, plays per axis and effects."""
    kind = {"pi": "PI", "gpi": "generalised PI", "preisach": "Preisach"}[m["gpi_model_kind"]]
    return f"{kind}, {m['gpi_model_operators']} plays + " + ", ".join(m["gpi_model_effects"])


def _pixel(m: dict) -> float:
    """A calibration run's pixel (nm)."""
    return m["calibration_size_nm"] / m["pixels"]


def _raw_to(m: dict, raw: str, corrected: str, unit: str, digits: int = 1) -> str:
    """``raw → corrected`` of two metrics."""
    return f"{q(m[raw], unit, digits)} → {q(m[corrected], unit, digits)}"


def _covered(m: dict, which: str, level: float) -> float:
    """A study's true A+B errors within the predicted radius of ``level`` (%), over ``which`` trials."""
    c = m["AB_position_coverage"]
    return c["true"][which]["covered_pct"][c["levels"].index(level)]


def noise_ceiling(m: dict) -> str:
    """A study's A+B+C ceiling that its scanners' white position noise sets, where it says."""
    if "ABC_noise_ceiling_pct" not in m:
        return ""
    return f" (the tip's position noise allows at most {q(m['ABC_noise_ceiling_pct'], '%')} A+B+C)"


def study_result(m: dict, misses: bool = True) -> str:
    """A study's goal cell: its A+B+C, push and ran shares (``misses``: and the A+B median and p95)
    and the A+B+C ceiling its position noise sets."""
    text = (
        f"A+B+C {q(m['ABC_success_pct'], '%')}, push {q(m['push_success_pct'], '%')}, "
        f"ran {q(m['ABC_ran_pct'], '%')}"
    )
    if misses:
        text += f"; A+B median {q(m['AB_error_median_nm'], 'nm')}, p95 {q(m['AB_error_p95_nm'], 'nm')}"
    return text + noise_ceiling(m)


def classes_result(m: dict) -> str:
    """A truth-class study's goal cell: A+B+C and push success over all trials and per class, and
    the A+B+C ceiling its position noise sets."""
    per_class = ", ".join(
        f"{c} {q(v['ABC_success_pct'], '%')} / {q(v['push_success_pct'], '%')}"
        for c, v in m["truth_classes"].items()
    )
    text = (
        f"A+B+C {q(m['ABC_success_pct'], '%')}, push {q(m['push_success_pct'], '%')}; per class {per_class}"
    )
    return text + noise_ceiling(m)


GOALS = [
    Goal(
        "step_a_linearity",
        "step A: linearity < 0.5 % after compensation",
        STEP_A_SIM,
        "docs/step_a.md",
        lambda m: (
            f"{q(m['gpi_analytic_linearity_error_trace_pct'], '%', 2)} trace, "
            f"{q(m['gpi_analytic_linearity_error_retrace_pct'], '%', 2)} retrace from a 0° + 90° pair at 1 and 2 Hz "
            f"(uncompensated {span(_linearity(m, 'uncompensated'), '%')}, "
            f"the paper's inverse {span(_linearity(m, 'paper'), '%')})"
        ),
        lambda m: max(_linearity(m, "gpi_analytic")) < 0.5,
    ),
    Goal(
        "step_a_small_loops",
        "step A from 0° + 90°: y small loops within 1 % (±0.1…±3 V)",
        STEP_A_ANGLES,
        "docs/step_a.md",
        lambda m: (
            f"y {q(m['0 + 90 deg']['minor_loop_max_error_pct'][1], '%', 2)}, "
            f"x {q(m['0 + 90 deg']['minor_loop_max_error_pct'][0], '%', 2)} "
            f"(from 0° alone: y {q(m['0 deg']['minor_loop_max_error_pct'][1], '%')})"
        ),
        lambda m: max(m["0 + 90 deg"]["minor_loop_max_error_pct"]) < 1,
    ),
    Goal(
        "step_a_both_axes",
        "step A from 0° + 90°: linearity < 0.25 % on both axes",
        STEP_A_ANGLES,
        "docs/step_a.md",
        lambda m: (
            f"x {q(m['0 + 90 deg']['linearity_x_at_0deg']['compensated_pct'], '%', 2)}, "
            f"y {q(m['0 + 90 deg']['linearity_y_at_90deg']['compensated_pct'], '%', 2)} "
            f"(from 0° alone: y {_linearity_cell(m['0 deg']['linearity_y_at_90deg'])})"
        ),
        lambda m: (
            max(
                m["0 + 90 deg"]["linearity_x_at_0deg"]["compensated_pct"],
                m["0 + 90 deg"]["linearity_y_at_90deg"]["compensated_pct"],
            )
            < 0.25
        ),
    ),
    Goal(
        "step_a_rotation",
        "step A on turned lattices (pits, pillars, 0–3°): rotation within 0.05°",
        STEP_A_LATTICES,
        "docs/step_a.md",
        lambda rows: f"within {q(max(_lattice_errors(rows)), '°', 3)} in all {len(rows)}",
        lambda rows: max(_lattice_errors(rows)) < 0.05,
    ),
    Goal(
        "step_a_held_out",
        "step A on turned lattices: held-out residual < 2 nm",
        STEP_A_LATTICES,
        "docs/step_a.md",
        lambda rows: (
            f"{span([r['held_out_rms_nm'] for r in rows], 'nm', 2)}; under 2 nm in "
            f"{sum(r['held_out_rms_nm'] < 2 for r in rows)} of {len(rows)} (the simulator's own tip path: "
            f"{span([r['held_out_floor_nm'] for r in rows], 'nm', 2)} on the same measure)"
        ),
        lambda rows: all(r["held_out_rms_nm"] < 2 for r in rows),
    ),
    Goal(
        "step_a_speed",
        "step A: 256² identification ≤ 30 s, compiling included",
        BENCH_STEP_A,
        "docs/step_a.md",
        lambda m: (
            f"{q(_geodesic(m)['seconds'], 's')} ({q(_geodesic(m)['compile_s'], 's')} compiling); tip path "
            f"{q(statistics.median(_geodesic(m)['path_x_rms_nm_by_seed']), 'nm', 2)} "
            f"rms, median over {m['seeds']} scans"
        ),
        lambda m: _geodesic(m)["seconds"] <= 30,
    ),
    Goal(
        "after_b",
        "after B: < 20 nm (p95)",
        PAPER,
        "docs/positioning.md",
        lambda m: (
            f"median {q(m['AB_polynomial_error_median_nm'], 'nm')}, p95 "
            f"{q(m['AB_polynomial_error_p95_nm'], 'nm')}, worst {q(m['AB_polynomial_error_max_nm'], 'nm')} "
            f"over {count(m['AB_polynomial_error_targets'])} targets"
        ),
        lambda m: m["AB_polynomial_error_p95_nm"] < 20,
    ),
    Goal(
        "after_c",
        "after C: < 0.1 R for every target",
        PAPER,
        "docs/positioning.md",
        lambda m: (
            f"{q(m['ABC_within_0p1R_pct'], '%')} of {count(m['ABC_polynomial_error_targets'])} "
            f"targets, worst {q(m['ABC_error_over_radius_max'], 'R', 3)}"
        ),
        lambda m: m["ABC_within_0p1R_pct"] == 100,
    ),
    Goal(
        "after_c_fields",
        "after C, over four more particle fields: < 0.1 R for every target",
        PUSH_STUDY,
        "docs/positioning.md",
        lambda m: (
            f"{q(m['ABC_within_0p1R_pct'], '%')} of {count(m['push_trials'])}, "
            f"worst {q(m['ABC_error_over_radius_max'], 'R', 3)}"
        ),
        lambda m: m["ABC_within_0p1R_pct"] == 100,
    ),
    Goal(
        "push",
        "push success ≥ 99 %",
        PAPER,
        "docs/positioning.md",
        lambda m: (
            f"{q(m['push_success_pct'], '%')} of {count(m['push_trials'])} pushes "
            f"({q(m['push_first_success_pct'], '%')} at the first push)"
        ),
        lambda m: m["push_success_pct"] >= 99,
    ),
    Goal(
        "push_fields",
        "push success ≥ 99 %, over four more particle fields",
        PUSH_STUDY,
        "docs/positioning.md",
        lambda m: (
            f"{q(m['push_success_pct'], '%')} ({count(m['push_successes'])} of {count(m['push_trials'])})"
        ),
        lambda m: m["push_success_pct"] >= 99,
    ),
    Goal(
        "fields_0_90",
        "over the four particle fields with step A from a 0° + 90° pair: A+B+C within 0.1 R ≥ 99.5 % and "
        "push success ≥ 99.5 %",
        PUSH_0_90,
        "docs/positioning.md",
        lambda m: (
            f"A+B+C {q(m['ABC_within_0p1R_pct'], '%')} of {count(m['push_trials'])} "
            f"(worst {q(m['ABC_error_over_radius_max'], 'R', 3)}), push {q(m['push_success_pct'], '%')} "
            f"({count(m['push_successes'])} of {count(m['push_trials'])})"
        ),
        lambda m: m["push_trials"] >= 256 and min(m["ABC_within_0p1R_pct"], m["push_success_pct"]) >= 99.5,
    ),
    Goal(
        "study",
        "study across 16 scanners (4096 trials): A+B+C within 0.1 R ≥ 99 %, push ≥ 99 %, ran 100 %",
        STUDY,
        "docs/study.md",
        study_result,
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"]) >= 99 and m["ABC_ran_pct"] == 100,
    ),
    Goal(
        "study_0_90_condition_y",
        "the same study with step A from a 0° + 90° pair and the local scan's conditioning line along y "
        "(study_0_90_condition_y.yaml): A+B+C within 0.1 R ≥ 99 %, push ≥ 99 %, ran 100 %",
        STUDY_0_90_CY,
        "docs/study.md#step-a-from-a-0-90-pair",
        study_result,
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"]) >= 99 and m["ABC_ran_pct"] == 100,
    ),
    Goal(
        "study_wide_0_90_wide_loop",
        "the wider family with step A from a 0° + 90° pair told of wide loops and the conditioning line "
        "along y (study_wide_0_90_wide_loop.yaml): A+B+C within 0.1 R ≥ 99 %, push ≥ 99 %, ran ≥ 99 %",
        STUDY_WIDE_LOOP,
        "docs/study.md#the-wider-family-from-a-0-90-pair",
        lambda m: study_result(m, misses=False),
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"], m["ABC_ran_pct"]) >= 99,
    ),
    Goal(
        "study_wide",
        "wider scanner family (study_wide.yaml): ≥ 95 %",
        STUDY_WIDE,
        "docs/study.md",
        lambda m: (
            f"A+B+C {q(m['ABC_success_pct'], '%')}, push {q(m['push_success_pct'], '%')}, "
            f"ran {q(m['ABC_ran_pct'], '%')}"
        ),
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"], m["ABC_ran_pct"]) >= 95,
    ),
    Goal(
        "study_position_coverage",
        "positions after A+B (study.yaml, ≥ 4096 trials): the predicted 90 % radius holds 85–95 % of the true errors",
        STUDY,
        "docs/study.md#the-spread-the-tracker-predicts-for-an-ab-move",
        lambda m: (
            f"{q(_covered(m, 'all', 0.9), '%')} within the 90 % radius, {q(_covered(m, 'all', 0.5), '%')} within "
            f"the 50 % over {count(m['AB_position_coverage']['true']['all']['trials'])} trials; "
            "aimed by 10 finds or more "
            f"{q(_covered(m, 'learnt', 0.9), '%')} and {q(_covered(m, 'learnt', 0.5), '%')} "
            "(after A alone: no prediction)"
        ),
        lambda m: (
            m["AB_position_coverage"]["true"]["all"]["trials"] >= 4096 and 85 <= _covered(m, "all", 0.9) <= 95
        ),
    ),
    Goal(
        "study_classes",
        "true scanners of classes the fitted model cannot describe (study_classes.yaml): A+B+C and push ≥ 98 %",
        STUDY_CLASSES,
        "docs/study.md#true-scanners-of-other-model-classes",
        classes_result,
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"]) >= 98,
    ),
    Goal(
        "study_classes_0_90_condition_y",
        "the same with step A from a 0° + 90° pair and the local scan's conditioning line along y "
        "(study_classes_0_90_condition_y.yaml): A+B+C and push ≥ 98 %",
        STUDY_CLASSES_0_90_CY,
        "docs/study.md#step-a-from-a-0-90-pair-on-the-other-classes",
        classes_result,
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"]) >= 98,
    ),
    Goal(
        "study_classes_0_90_wide_loop",
        "the same with step A also told of wide loops (study_classes_0_90_wide_loop.yaml): A+B+C and push ≥ 98 %",
        STUDY_CLASSES_WIDE_LOOP,
        "docs/study.md#step-a-from-a-0-90-pair-on-the-other-classes",
        classes_result,
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"]) >= 98,
    ),
    Goal(
        "study_classes_speed",
        "the same calibrated at the study's two line rates with the lag in step A's model "
        "(study_classes_speed.yaml): A+B+C and push ≥ 98 %",
        STUDY_CLASSES_SPEED,
        "docs/study.md#calibrated-at-the-surveys-line-rate",
        classes_result,
        lambda m: min(m["ABC_success_pct"], m["push_success_pct"]) >= 98,
    ),
    Goal(
        "study_rate",
        "study: 30,000 B+C trials/min on 2 CPU cores",
        BENCH_STUDY,
        "docs/study.md",
        lambda m: (
            f"{count(m['best']['trials_per_min'])} per minute at a batch of "
            f"{count(m['best']['batch'])} on {devices(m['best']['devices'])} "
            f"({q(m['best']['trials_per_min'] / m['python_loop']['trials_per_min'], '×')} a Python loop)"
        ),
        lambda m: m["best"]["trials_per_min"] >= 30_000,
    ),
    Goal(
        "study_gpu",
        "study bench on one GPU (NVIDIA H100)",
        GPU_STUDY,
        "docs/study.md",
        lambda m: (
            f"{count(m['best']['trials_per_min'])} B+C trials per minute at a batch of "
            f"{count(m['best']['batch'])}"
        ),
    ),
    Goal(
        "study_speed",
        "study with step A per scanner: 64 scanners × 64 trials < 30 min on 2 cores",
        STUDY_SPEED,
        "docs/study.md",
        lambda m: (
            f"{q(m['wall_s'] / 60, 'min')} ({count(m['scanners'])} scanners, {count(m['trials'])} trials)"
        ),
        lambda m: m["wall_s"] < 30 * 60,
    ),
    Goal(
        "preisach_speed",
        "Preisach 50× faster than a NumPy loop (50 levels)",
        BENCH_HYSTERESIS,
        "docs/model.md#speed-python-experimentsbench_hysteresispy",
        lambda m: (
            f"{q(m['models'][0]['speedup_hard_vs_play_loop'], '×')} against a NumPy loop over the "
            f"same O(n) plays; {q(m['models'][0]['speedup_hard_vs_relay_grid'], '×')} against the O(n²) relay grid"
        ),
        lambda m: m["models"][0]["speedup_hard_vs_play_loop"] >= 50,
    ),
    Goal(
        "preisach_fit",
        "Preisach fit (50 levels, 20,000 samples): ≤ 1 s once compiled, peak memory ≤ 0.5 GB (10⁹ bytes)",
        BENCH_PREISACH_FIT,
        "docs/model.md#exact-fits-of-pi-and-preisach-weights-python-experimentsbench_preisach_fitpy",
        lambda m: (
            f"{q(_exact_fit(m)['compiled_s'], 's', 2)} ({q(_exact_fit(m)['calls'][0]['seconds'], 's', 1)} "
            f"compiling included); peak {q(_gb(_exact_fit(m)['calls'][0]['peak_mb']), 'GB', 2)} after "
            f"one fit, {q(_gb(_peak_mb(_exact_fit(m))), 'GB', 2)} after {len(_exact_fit(m)['calls'])} in "
            f"one process, {q(_gb(_exact_fit(m)['peak_before_mb']), 'GB', 2)} of it before the fits (BFGS: "
            f"{q(_run(m, 'optimistix.bfgs')['compiled_s'], 's', 1)}, "
            f"{q(_gb(_peak_mb(_run(m, 'optimistix.bfgs'))), 'GB', 1)})"
        ),
        lambda m: _exact_fit(m)["compiled_s"] <= 1.0 and _gb(_peak_mb(_exact_fit(m))) <= 0.5,
    ),
    Goal(
        "real_actuator",
        "real actuator: held-out error below the published differentiable Preisach fit (4.3 % rms)",
        PIEZO_FIT,
        "docs/real_data.md",
        lambda m: (
            f"Preisach {q(m['preisach_heldout_rms_error_pct'], '%', 2)}, generalised PI + creep "
            f"{q(m['gpi_creep_heldout_rms_error_pct'], '%', 2)} held-out rms"
        ),
        lambda m: max(m["preisach_heldout_rms_error_pct"], m["gpi_creep_heldout_rms_error_pct"]) < 4.3,
    ),
    Goal(
        "predict",
        "`jaxafm predict` reproduces the fit's held-out error",
        PREDICT,
        "docs/model.md",
        lambda m: (
            f"{q(m['rms_error_pct'], '%', 3)} rms, {q(m['max_error_pct'], '%', 3)} max "
            "(the fit table's generalised PI row)"
        ),
    ),
    Goal(
        "compensate",
        "`jaxafm compensate` then the model: tracking < 0.05 % of range",
        COMPENSATE,
        "docs/model.md",
        lambda m: f"{q(m['tracking_rms_error_pct'], '%', 3, tiny=True)} rms through the model it inverts",
        lambda m: m["tracking_max_error_pct"] < 0.05,
    ),
    Goal(
        "minor_loops",
        "models fitted on one major loop, scored on minor loops (second real record)",
        CROSS_RECORD,
        "docs/real_data.md",
        lambda m: (
            f"generalised PI {q(m['gpi_on_sine_scored_on_ramped_minor_rms_error_pct'], '%', 2)} rms "
            f"({q(m['gpi_on_ramped_scored_on_ramped_minor_rms_error_pct'], '%', 2)} fitted on them); "
            f"generalised PI + creep {q(m['gpi_creep_on_sine_scored_on_ramped_minor_rms_error_pct'], '%', 2)}"
        ),
    ),
    Goal(
        "real_grating",
        "real 1-D grating: pitch and distortion from one image",
        REAL_GRATING,
        "docs/real_data.md",
        lambda m: (
            f"pitch {q(m['pitch_nm'], 'nm')} ± {q(m['pitch_se_nm'], 'nm')}; local pitch spread "
            f"{q(m['raw_pitch_std_pct'], '%', 2)} raw, {q(m['corrected_pitch_std_pct'], '%', 2)} corrected"
        ),
    ),
    Goal(
        "diagnosis_top1",
        "diagnosis (own simulator): top-1 ≥ 90 % at the middle magnitude",
        WITHHELD,
        "docs/diagnosis.md#checked-on-withheld-effects-python-experimentswithheld_effectspy",
        lambda m: (
            f"scan sets {q(m['scans']['top1_accuracy_middle_pct'], '%', 0)}, 2-D lattice scan sets "
            f"{q(m['lattice']['top1_accuracy_middle_pct'], '%', 0)}"
        ),
        lambda m: min(m["scans"]["top1_accuracy_middle_pct"], m["lattice"]["top1_accuracy_middle_pct"]) >= 90,
    ),
    Goal(
        "diagnosis_records_top1",
        "diagnosis of records (own simulator): top-1 ≥ 90 % at the middle magnitude",
        RECORDS,
        "docs/diagnosis.md#checked-on-withheld-effects-python-experimentswithheld_effectspy",
        lambda m: q(m["record"]["top1_accuracy_middle_pct"], "%", 0),
        lambda m: m["record"]["top1_accuracy_middle_pct"] >= 90,
    ),
    Goal(
        "diagnosis_controls",
        "diagnosis (own simulator): ≤ 1 false alarm in 20 controls",
        WITHHELD,
        "docs/diagnosis.md#checked-on-withheld-effects-python-experimentswithheld_effectspy",
        lambda m: f"{count(m['controls_flagged'])} of {count(m['controls'])} (records, scan sets, lattices)",
        lambda m: m["controls_flagged"] <= m["controls"] / 20,
    ),
    Goal(
        "diagnosis_records_controls",
        "diagnosis of records (own simulator): ≤ 1 false alarm in 20 controls",
        RECORDS,
        "docs/diagnosis.md#checked-on-withheld-effects-python-experimentswithheld_effectspy",
        lambda m: f"{count(m['record']['controls_flagged'])} of {count(m['record']['controls'])}",
        lambda m: m["record"]["controls_flagged"] <= m["record"]["controls"] / 20,
    ),
    *(
        Goal(
            f"step_a_real_{label.replace(' ', '_')}",
            f"step A on a real lattice (Nanosurf {label}): held-out residual ≤ 0.3 px and ≤ ⅓ of the "
            "raw one, local pitch spread smaller corrected than raw",
            run,
            "docs/step_a.md#real-lattices-the-three-nanosurf-images",
            lambda m: (
                f"{q(m['gpi_held_out_rms_nm'], 'nm')} ({q(m['gpi_held_out_rms_nm'] / _pixel(m), 'px', 2)}) "
                f"of {q(m['gpi_held_out_raw_rms_nm'], 'nm')} raw; spread "
                f"{_raw_to(m, 'gpi_held_out_pitch_std_raw_pct', 'gpi_held_out_pitch_std_corrected_pct', '%', 2)}"
            ),
            lambda m: (
                m["gpi_plausible"]
                and m["gpi_held_out_rms_nm"] <= min(0.3 * _pixel(m), m["gpi_held_out_raw_rms_nm"] / 3)
                and m["gpi_held_out_pitch_std_corrected_pct"] < m["gpi_held_out_pitch_std_raw_pct"]
            ),
        )
        for label, run in NANOSURF
    ),
    Goal(
        "step_a_independent",
        "step A on an independent generator's lattices, ≥ 20 cases: tip path ≤ 0.1 px, held-out "
        "features ≤ 0.15 px, held-out distances ≤ 0.2 % (worst case)",
        STEP_A_INDEPENDENT,
        "docs/step_a.md#lattices-jaxafm-did-not-make-python-experimentsstep_a_independentpy",
        lambda m: (
            f"{count(m['saved'])} of {count(m['cases'])} cases saved; worst tip path "
            f"{q(m['tip_path_rms_px_max'], 'px', 2)}, held-out {q(m['held_out_rms_px_max'], 'px', 2)}, "
            f"distances {q(m['held_out_distance_error_max_pct_max'], '%', 2)}"
        ),
        lambda m: (
            m["cases"] >= 20
            and m["saved"] == m["cases"]
            and m["tip_path_rms_px_max"] <= 0.1
            and m["held_out_rms_px_max"] <= 0.15
            and m["held_out_distance_error_max_pct_max"] <= 0.2
        ),
    ),
    Goal(
        "step_a_speed_series",
        "step A from a speed series (independent generator): fitted rate lag within 10 % of the truth",
        STEP_A_INDEPENDENT,
        "docs/step_a.md#lattices-jaxafm-did-not-make-python-experimentsstep_a_independentpy",
        lambda m: (
            ", ".join("not kept" if v is None else f"{v:+.0f} %" for v in m["rate_lag_relative_error_pct"])
            or "no speed series"
        ),
        lambda m: (
            bool(m["rate_lag_relative_error_pct"])
            and all(v is not None and abs(v) <= 10 for v in m["rate_lag_relative_error_pct"])
        ),
    ),
    Goal(
        "diagnosis_shrink",
        "diagnosis (own simulator): median shrink of the held-out gap ≥ 80 %",
        WITHHELD,
        "docs/diagnosis.md#checked-on-withheld-effects-python-experimentswithheld_effectspy",
        lambda m: (
            f"scan sets {q(m['scans']['median_shrink_pct'], '%')}, 2-D lattice scan sets "
            f"{q(m['lattice']['median_shrink_pct'], '%')}"
        ),
        lambda m: min(m["scans"]["median_shrink_pct"], m["lattice"]["median_shrink_pct"]) >= 80,
    ),
    Goal(
        "diagnosis_records_shrink",
        "diagnosis of records (own simulator): median shrink ≥ 80 %",
        RECORDS,
        "docs/diagnosis.md#checked-on-withheld-effects-python-experimentswithheld_effectspy",
        lambda m: q(m["record"]["median_shrink_pct"], "%"),
        lambda m: m["record"]["median_shrink_pct"] >= 80,
    ),
    Goal(
        "diagnosis_records_shrink_above_noise",
        "diagnosis of records (own simulator): median shrink above the records' 2 nm white noise ≥ 80 %",
        RECORDS,
        "docs/diagnosis.md#checked-on-withheld-effects-python-experimentswithheld_effectspy",
        lambda m: q(m["record"]["median_shrink_above_noise_pct"], "%"),
        lambda m: m["record"]["median_shrink_above_noise_pct"] >= 80,
    ),
    Goal(
        "independent_top1",
        "diagnosis on an independent generator (half with the wrong hysteresis class): "
        "top-1 ≥ 90 % at the middle magnitude",
        INDEPENDENT,
        "docs/diagnosis.md#checked-on-records-jaxafm-did-not-make-python-experimentsindependent_checkpy",
        lambda m: f"{q(m['all']['top1_middle_pct'], '%')} of {count(m['all']['cases_middle'])}",
        lambda m: m["all"]["top1_middle_pct"] >= 90,
    ),
    Goal(
        "independent_controls",
        "diagnosis on an independent generator: ≤ 1 false alarm in 20 controls",
        INDEPENDENT,
        "docs/diagnosis.md#checked-on-records-jaxafm-did-not-make-python-experimentsindependent_checkpy",
        lambda m: f"{count(m['all']['controls_flagged'])} of {count(m['all']['controls'])}",
        lambda m: m["all"]["controls_flagged"] <= m["all"]["controls"] / 20,
    ),
    Goal(
        "wandering_cases",
        "diagnosis of drifts that wander and of creep: ≥ 100 cases at three magnitudes and ≥ 20 "
        "controls, half with the other hysteresis class",
        WANDERING,
        "docs/diagnosis.md#drifts-that-wander-and-creep-python-experimentsindependent_checkpy-wandering",
        lambda m: (
            f"{count(m['all']['cases'] - m['all']['controls'])} cases "
            f"({count(m['all'].get('cases_low', 0))} low, {count(m['all'].get('cases_middle', 0))} middle, "
            f"{count(m['all'].get('cases_high', 0))} high) and {count(m['all']['controls'])} controls; "
            f"{count(m['different']['cases'])} of {count(m['all']['cases'])} with the other class"
        ),
        lambda m: (
            m["all"]["cases"] - m["all"]["controls"] >= 100
            and m["all"]["controls"] >= 20
            and min(m["all"].get(f"cases_{lv}", 0) for lv in ("low", "middle", "high")) > 0
            and 2 * m["different"]["cases"] >= m["all"]["cases"]
        ),
    ),
    Goal(
        "wandering_top1",
        "diagnosis of drifts that wander and of creep (independent generator, half the other "
        "hysteresis class): top-1 ≥ 95 % at the middle magnitude",
        WANDERING,
        "docs/diagnosis.md#drifts-that-wander-and-creep-python-experimentsindependent_checkpy-wandering",
        lambda m: f"{q(m['all']['top1_middle_pct'], '%')} of {count(m['all']['cases_middle'])}",
        lambda m: m["all"]["top1_middle_pct"] >= 95,
    ),
    Goal(
        "wandering_controls",
        "diagnosis of drifts that wander and of creep: ≤ 1 false alarm in 20 controls",
        WANDERING,
        "docs/diagnosis.md#drifts-that-wander-and-creep-python-experimentsindependent_checkpy-wandering",
        lambda m: f"{count(m['all']['controls_flagged'])} of {count(m['all']['controls'])}",
        lambda m: m["all"]["controls_flagged"] <= m["all"]["controls"] / 20,
    ),
    Goal(
        "wandering_shrink",
        "diagnosis of drifts that wander and of creep: median shrink above the noise floor ≥ 80 % "
        "of the correctly named",
        WANDERING,
        "docs/diagnosis.md#drifts-that-wander-and-creep-python-experimentsindependent_checkpy-wandering",
        lambda m: (
            f"{q(m['all']['median_shrink_above_floor_correct_pct'], '%')} (an exact model of the "
            f"actuator: {q(m['all']['median_shrink_above_floor_ceiling_correct_pct'], '%')}); above the "
            f"generator's floor with a Preisach truth's switching roughness "
            f"{q(m['all']['median_shrink_above_generator_floor_correct_pct'], '%')} (an exact model: "
            f"{q(m['all']['median_shrink_above_generator_floor_ceiling_correct_pct'], '%')})"
        ),
        lambda m: m["all"]["median_shrink_above_floor_correct_pct"] >= 80,
    ),
    Goal(
        "independent_shrink",
        "diagnosis on an independent generator: median shrink ≥ 80 %",
        INDEPENDENT,
        "docs/diagnosis.md#checked-on-records-jaxafm-did-not-make-python-experimentsindependent_checkpy",
        lambda m: (
            f"{q(m['all']['median_shrink_correct_pct'], '%')}; the generator's noise caps it at "
            f"{q(m['all']['median_shrink_ceiling_correct_pct'], '%')} for any model"
        ),
        lambda m: m["all"]["median_shrink_correct_pct"] >= 80,
    ),
    Goal(
        "stability",
        "diagnosis: the verdict stays when a record is cropped by 10 % at either end or decimated by 2",
        STABILITY,
        "docs/diagnosis.md#the-verdict-on-a-record-cropped-or-decimated-python-experimentsstabilitypy",
        lambda m: (
            f"{count(m['verdict_flips'])} verdict and {count(m['shape_flips'])} shape flips in "
            f"{count(m['cases'] * m['variants_per_case'])} variants of {count(m['cases'])} records"
        ),
        lambda m: m["verdict_flips"] == 0,
    ),
]
GOALS.append(
    Goal(
        "uncertainty_coverage",
        "actuator fits: held-out samples inside the 90 % band in 85–95 % (each real record, cross-record, generator)",
        UNCERTAINTY,
        "docs/uncertainty.md",
        _coverage_goal,
        lambda m: all(85 <= v["ar1_coverage_90_pct"] <= 95 for v in m["real"].values()),
    )
)
GOALS.append(
    Goal(
        "posterior_vs_nuts",
        "Laplace posterior within 20 % of NUTS (means and sds, per parameter)",
        POSTERIOR_CHECK,
        "docs/uncertainty.md#the-laplace-approximation-against-nuts",
        lambda m: "; ".join(
            f"{case}: mean gap ≤ {q(c['mode']['max_mean_gap_over_nuts_sd'], 'sd', 2)}, "
            f"sd error ≤ {q(100 * c['mode']['max_sd_error'], '%')}"
            for case, c in m.items()
        ),
        lambda m: all(
            c["mode"]["max_mean_gap_over_nuts_sd"] <= 0.2 and c["mode"]["max_sd_error"] <= 0.2
            for c in m.values()
        ),
    )
)
GOALS += [
    Goal(
        f"step_a_real_{label.replace(' ', '_')}_coverage",
        f"step A on a real lattice (Nanosurf {label}): held-out features inside the 90 % ellipse the fit "
        "predicts for them in 85–95 %",
        run,
        "docs/uncertainty.md#step-a-how-sure-the-fit-is-of-where-it-puts-the-tip",
        lambda m: (
            f"{q(m['gpi_held_out_coverage_90_pct'], '%', 0)} of {count(m['gpi_held_out_points'])} "
            f"(50 % ellipse: {q(m['gpi_held_out_coverage_50_pct'], '%', 0)}); predicted "
            f"{q(m['gpi_held_out_predicted_rms_nm'], 'nm')} rms, found {q(m['gpi_held_out_offsets_rms_nm'], 'nm')}"
        ),
        lambda m: 85 <= m["gpi_held_out_coverage_90_pct"] <= 95,
    )
    for label, run in NANOSURF
]
GOALS += [
    Goal(
        "posterior_cost",
        "the posterior adds at most 20 % to a fit's time (each model of jaxafm fit configs/piezo_sine_1hz.yaml)",
        PIEZO_FIT,
        "docs/uncertainty.md#what-it-costs-python-experimentsbench_bandpy",
        lambda m: "; ".join(f"{BAND_MODELS[n]} {q(_posterior_share(m, n), '%', 0)}" for n in BAND_MODELS),
        lambda m: all(_posterior_share(m, n) <= 20 for n in BAND_MODELS),
    ),
    Goal(
        "band_cost",
        "a 90 % band over a 20,000-sample prediction in under a second on 2 cores, compiling included",
        BENCH_BAND,
        "docs/uncertainty.md#what-it-costs-python-experimentsbench_bandpy",
        lambda m: "; ".join(
            f"{BAND_MODELS[n]} {q(r['first_call_s'], 's', 2)}" for n, r in m["models"].items()
        ),
        lambda m: m["samples"] >= 20_000 and all(r["first_call_s"] < 1 for r in m["models"].values()),
    ),
]
GOALS += [
    Goal(
        name,
        f"{label}: predicted first-push success within 5 points of the observed in every tenth with ≥ 100 "
        "trials, Brier score better than the overall rate's",
        run,
        "docs/uncertainty.md#before-a-push-its-odds",
        lambda m: (
            f"largest gap {q(_largest_gap(m['push_first_reliability']), 'points')} over "
            f"{count(sum(b['trials'] >= 100 for b in m['push_first_reliability']))} tenths with ≥ 100 trials; "
            f"Brier {m['push_first_brier']:.4f} against {m['push_first_brier_base_rate']:.4f}"
        ),
        lambda m: (
            _largest_gap(m["push_first_reliability"]) <= 5
            and m["push_first_brier"] < m["push_first_brier_base_rate"]
        ),
    )
    for name, label, run in (
        ("push_odds", "study", STUDY),
        ("push_odds_learning", "study with pushes that learn (study_push_learning.yaml)", STUDY_PUSHES),
    )
]
GOALS.append(
    Goal(
        "step_a_independent_coverage",
        "step A on an independent generator's lattices: the true tip path inside the 90 % ellipse the fit "
        "predicts at 85–95 % of the pixels (median over the cases)",
        STEP_A_COVERAGE,
        "docs/uncertainty.md#step-a-how-sure-the-fit-is-of-where-it-puts-the-tip",
        lambda m: (
            f"{q(m['tip_path_coverage_90_pct_median'], '%', 0)} from the parameters, "
            f"{q(m['tip_path_coverage_90_with_spread_pct_median'], '%', 0)} with a feature's spread added, "
            f"over {count(m['coverage_cases'])} cases (held-out features: "
            f"{q(m['held_out_coverage_90_pct_median'], '%', 0)})"
        ),
        lambda m: 85 <= m["tip_path_coverage_90_with_spread_pct_median"] <= 95,
    )
)
GOALS.append(
    Goal(
        "study_wide_learning",
        "study_wide: the A+B error once learnt from ten or more of step C's finds at most half that of the "
        "first round",
        STUDY_WIDE,
        "docs/study.md#learning-while-positioning",
        lambda m: _learning_result(m["AB_learning"]),
        lambda m: m["AB_learning"]["learnt_ratio"] <= 0.5,
    )
)
GOALS.append(
    Goal(
        "study_learning_cost",
        "learning while positioning adds at most 20 % to a study's time (study.yaml against "
        "study_no_learning.yaml, the same study without it, run one after the other)",
        (STUDY, STUDY_NO_LEARNING),
        "docs/study.md#what-learning-costs",
        lambda m: (
            f"{q(m[0]['wall_s'] / 60, 'min')} with learning against {q(m[1]['wall_s'] / 60, 'min')} without "
            f"({q(100 * (m[0]['wall_s'] / m[1]['wall_s'] - 1), '%')}); the trials alone "
            f"{q(m[0]['trials_s'], 's', 0)} against {q(m[1]['trials_s'], 's', 0)}"
        ),
        lambda m: m[0]["wall_s"] <= 1.2 * m[1]["wall_s"],
    )
)
#: The README's short table: the positioning goals and the real data.
README_GOALS = (
    "step_a_linearity",
    "step_a_real_square_pits",
    "after_b",
    "after_c",
    "push",
    "study",
    "study_0_90_condition_y",
    "real_actuator",
    "independent_top1",
)


PAGE_TITLES = {
    "step_a": "step A",
    "positioning": "positioning",
    "study": "study",
    "model": "model",
    "real_data": "real data",
    "diagnosis": "diagnosis",
    "uncertainty": "uncertainty",
}


def goals_table(names: Optional[Sequence[str]]) -> Callable[[Results], Table]:
    """The goals named (all when ``None``), a row each: goal, result, verdict, run, page."""

    def make(results: Results) -> Table:
        rows = []
        for g in GOALS:
            if names is None or g.name in names:
                runs = g.run if isinstance(g.run, tuple) else (g.run,)
                data = tuple(map(results, runs)) if isinstance(g.run, tuple) else results(g.run)
                page = Link(PAGE_TITLES[Path(g.page.partition("#")[0]).stem], g.page)
                links = tuple(map(source, runs))
                rows.append([g.goal, g.result(data), verdict(g.met(data)), links, page])
        return Table(["goal", "result", "", "run", "page"], rows, [])

    return make


TABLES["goals"] = goals_table(None)
TABLES["readme"] = goals_table(README_GOALS)


# --- tables of the form label x column, from one flat file ----------------------------------


@dataclass(frozen=True)
class Col:
    """A column of a grid table: its header and the key that follows each row's prefix."""

    header: str
    key: str
    unit: str = ""
    digits: int = 1


def grid(data: dict, rows: Sequence[tuple[str, str]], cols: Sequence[Col]) -> list[list[Cell]]:
    """One row per ``(label, prefix)``, the value of ``prefix + col.key`` in each column."""
    return [[label] + [q(data[prefix + c.key], c.unit, c.digits) for c in cols] for label, prefix in rows]


def facts(rows: Sequence[tuple[str, str]]) -> list[list[Cell]]:
    """A two-column table of ``(quantity, formatted value)``."""
    return [[label, value] for label, value in rows]


# --- step A (docs/step_a.md) -----------------------------------------------------------------

COMPENSATED = (
    Col("linearity trace", "linearity_error_trace_pct", "%", 2),
    Col("linearity retrace", "linearity_error_retrace_pct", "%", 2),
    Col("x rms", "x_rms_error_nm", "nm"),
    Col("y max", "y_max_error_nm", "nm"),
    Col("pitch std (trace)", "pitch_std_trace_pct", "%", 2),
)


@table("step_a_simulated")
def step_a_simulated(results: Results) -> Table:
    m = results(STEP_A_SIM)
    drives = [
        ("uncompensated (nominal)", "uncompensated_"),
        ("the paper's polynomial + network (0° pair)", "paper_"),
        ("end to end + analytic inverse", "gpi_analytic_"),
        ("end to end + numerical inverse", "gpi_numerical_"),
    ]
    rows = grid(m, drives, COMPENSATED)
    for row, (_, prefix) in zip(rows, drives):
        row += [q(m[prefix + "fit_s"] or None, "s"), q(m[prefix + "inverse_s"] or None, "s")]
    return Table(["drive"] + [c.header for c in COMPENSATED] + ["fit", "inverse"], rows, [STEP_A_SIM])


@table("step_a_simulated_held_out")
def step_a_simulated_held_out(results: Results) -> Table:
    m = results(STEP_A_SIM)
    rows = [
        ("held-out lattice sites", count(m["gpi_held_out_features"])),
        (
            "held-out residual after each stage",
            " · ".join(q(v, "nm", 2) for v in m["gpi_held_out_nm_by_stage"]),
        ),
        ("stages kept", f"{sum(m['gpi_stages_accepted'])} of {len(m['gpi_stages_accepted'])}"),
        (
            "held-out local pitch spread, raw → corrected",
            f"{q(m['gpi_held_out_pitch_std_raw_pct'], '%')} → {q(m['gpi_held_out_pitch_std_corrected_pct'], '%', 2)}",
        ),
        ("image residual, rms of the depth", q(m["gpi_image_rms_pct"], "%", 2)),
        ("plausible", q(m["gpi_plausible"])),
    ]
    return Table(["", "end to end (gpi)"], facts(rows), [STEP_A_SIM])


def _parameter(name: str, value: float) -> str:
    """A fitted scanner parameter in the unit its name gives."""
    if name.endswith("_per_nm"):
        return f"{value:.3g} /nm".replace("-", "−")
    if name.endswith("_tau_s"):
        return q(1e3 * value, "ms", 3)
    if "creep_per_decade" in name:
        return q(100 * value, "%/decade", 2)
    return q(value, "", 4)


PARAMETERS = (
    ("coupling x from y", "coupling_xy"),
    ("coupling y from x", "coupling_yx"),
    ("bow x", "bow_x_per_nm"),
    ("bow y", "bow_y_per_nm"),
    ("feedback lag", "feedback_tau_s"),
    ("creep x", "creep_per_decade_x"),
    ("creep y", "creep_per_decade_y"),
)


@table("step_a_simulated_parameters")
def step_a_simulated_parameters(results: Results) -> Table:
    m = results(STEP_A_SIM)
    rows = [
        [label, _parameter(k, m[f"gpi_true_{k}"]), _parameter(k, m[f"gpi_fit_{k}"])]
        for label, k in PARAMETERS
    ]
    return Table(["parameter", "true", "fitted"], rows, [STEP_A_SIM])


@table("step_a_nanosurf")
def step_a_nanosurf(results: Results) -> Table:
    rows = []
    for label, run in NANOSURF:
        m = results(run)
        pixel = _pixel(m)
        rows.append(
            [
                label,
                _model_kept(m),
                count(m["gpi_held_out_features"]),
                _raw_to(m, "gpi_held_out_raw_rms_nm", "gpi_held_out_rms_nm", "nm")
                + f" ({q(m['gpi_held_out_rms_nm'] / pixel, 'px', 2)})",
                _raw_to(m, "gpi_held_out_pitch_std_raw_pct", "gpi_held_out_pitch_std_corrected_pct", "%", 2),
                _raw_to(
                    m,
                    "gpi_held_out_distance_error_max_raw_pct",
                    "gpi_held_out_distance_error_max_corrected_pct",
                    "%",
                    2,
                ),
                " / ".join(
                    _raw_to(
                        m,
                        f"gpi_feature_width_spread_{way}_raw_pct",
                        f"gpi_feature_width_spread_{way}_corrected_pct",
                        "%",
                        2,
                    )
                    for way in ("along", "across")
                ),
                q(m["gpi_plausible"]),
                q(m["gpi_fit_s"], "s", 0),
            ]
        )
    header = [
        "lattice",
        "model kept",
        "held-out features",
        "held-out residual, raw → corrected",
        "local pitch spread",
        "largest distance error",
        "feature widths' spread, along / across the lines",
        "saved",
        "fit",
    ]
    return Table(header, rows, [run for _, run in NANOSURF])


def _quantity(m: dict, key: str, unit: str, digits: int, scale: float = 1.0) -> str:
    """A fitted quantity ± its standard deviation; a dash where the model lacks it."""
    if m.get(key) is None:
        return "–"
    sd = m.get(f"{key}_sd")
    return q(scale * m[key], "", digits) + (
        f" ± {q(scale * sd, unit, digits)}" if sd is not None else f" {unit}"
    )


NANOSURF_QUANTITIES = (
    ("x gain", "gpi_x_gain_nm_per_v", "nm/V", 0, 1.0),
    ("y gain", "gpi_y_gain_nm_per_v", "nm/V", 0, 1.0),
    ("x loop at mid-drive", "gpi_x_loop_pct_of_travel", "% of travel", 2, 1.0),
    ("y loop at mid-drive", "gpi_y_loop_pct_of_travel", "% of travel", 2, 1.0),
    ("coupling x from y", "gpi_coupling_xy", "", 4, 1.0),
    ("edge delay (z signal)", "gpi_edge_delay_s", "ms", 2, 1e3),
    ("lattice angle", "gpi_lattice_angle_deg", "°", 2, 1.0),
)


@table("step_a_nanosurf_quantities")
def step_a_nanosurf_quantities(results: Results) -> Table:
    rows = [
        [label] + [_quantity(results(run), key, unit, digits, scale) for _, run in NANOSURF]
        for label, key, unit, digits, scale in NANOSURF_QUANTITIES
    ]
    return Table(["quantity"] + [label for label, _ in NANOSURF], rows, [run for _, run in NANOSURF])


@table("step_a_independent")
def step_a_independent(results: Results) -> Table:
    m = results(STEP_A_INDEPENDENT)
    both = lambda key, unit, digits: (
        f"{q(m[key + '_median'], unit, digits)} ({q(m[key + '_max'], unit, digits)})"
    )
    rows = [
        ("drawn cases, saved as plausible", f"{count(m['saved'])} of {count(m['cases'])}"),
        ("tip path rms, all scans (goal ≤ 0.1 px)", both("tip_path_rms_px", "px", 2)),
        ("tip path rms, worst scan alone", both("tip_path_worst_scan_rms_px", "px", 2)),
        ("held-out features, raw", both("held_out_raw_rms_px", "px", 2)),
        ("held-out features, corrected (goal ≤ 0.15 px)", both("held_out_rms_px", "px", 2)),
        (
            "largest held-out distance error, raw → corrected (goal ≤ 0.2 %)",
            f"{both('held_out_distance_error_max_raw_pct', '%', 2)} → "
            f"{both('held_out_distance_error_max_pct', '%', 2)}",
        ),
        (
            "speed series: fitted rate lag, relative error against the truth (goal within 10 %)",
            ", ".join("not kept" if v is None else f"{v:+.0f} %" for v in m["rate_lag_relative_error_pct"])
            or "–",
        ),
    ]
    rows += [(f"unidentifiable: {u['case'].replace('_', ' ')}", u["outcome"]) for u in m["unidentifiable"]]
    return Table(["", "median (worst) over the saved cases"], facts(rows), [STEP_A_INDEPENDENT])


STEP_A_FEW = Run("step_a_few_features/seed7.json", "python experiments/step_a_few_features.py")
STEP_A_FEW_IMAGES = Run(
    "step_a_few_features/seed7_blur2_1.json", "python experiments/step_a_few_features.py --blur-px 2 1"
)


def _stage_times(log: list) -> list:
    """Each stage's wall time (s) as its log line ends: ``..., 803.4 s``."""
    done = [line for line in log if line.startswith("  stage ") and not line.endswith("...")]
    return [float(line.rsplit(", ", 1)[1].removesuffix(" s")) for line in done]


@table("step_a_few_features")
def step_a_few_features(results: Results) -> Table:
    r = results(STEP_A_FEW)
    m, px = r["metrics"], lambda v: q(v, "px", 2)
    nm_px = lambda key: f"{q(m[key], 'nm', 0)} ({px(m[key] / r['pixel_nm'])})"
    rates = ", ".join(f"{v:g}" for v in r["rates_hz"])
    rows = [
        (
            "images",
            f"3 × 3 square pits, 0° at {rates} Hz, {r['pixels']} px ({q(r['pixel_nm'], 'nm', 0)} a pixel), "
            "trace and retrace, TIFF",
        ),
        ("image stages (the default on measured images)", ", ".join(map(str, r["image_blurs_px"])) or "none"),
        ("model the ladder kept", r["kept"]),
        (
            "held-out features, raw → corrected",
            f"{nm_px('held_out_raw_rms_nm')} → {nm_px('held_out_rms_nm')}",
        ),
        (
            "their local pitch spread, raw → corrected",
            _raw_to(m, "held_out_pitch_std_raw_pct", "held_out_pitch_std_corrected_pct", "%", 3),
        ),
        (
            "largest held-out distance error, raw → corrected",
            _raw_to(
                m, "held_out_distance_error_max_raw_pct", "held_out_distance_error_max_corrected_pct", "%", 2
            ),
        ),
        (
            "the tip path's sd over the images (step A's check) against a held-out feature's predicted error",
            f"{nm_px('path_sd_rms_nm')} against {nm_px('held_out_predicted_rms_nm')}; knowing "
            f"`{m['path_settled_most_by']}` would settle {q(m['path_settled_most_pct'], '%', 0)} of it",
        ),
        ("outcome", "saved" if r["plausible"] else "refused: " + "; ".join(r["failures"])),
        (
            "true tip path, rms: all pixels (x / y)",
            f"{px(r['tip_path_rms_px'])} ({' / '.join(map(px, r['tip_path_xy_rms_px']))})",
        ),
        (
            "true tip path, rms: inside / outside the features' reach",
            f"{px(r['tip_path_inside_reach_rms_px'])} / {px(r['tip_path_outside_reach_rms_px'])} "
            f"({q(100 * r['inside_reach_share'], '%', 0)} of the pixels inside)",
        ),
        (
            "its sd as the fit predicts it: inside / outside the reach",
            f"{px(r['path_sd_inside_reach_px'])} / {px(r['path_sd_outside_reach_px'])}",
        ),
        ("step A's time on 2 cores", q(r["seconds"], "s", 0)),
    ]
    b = results(STEP_A_FEW_IMAGES)
    held = b["metrics"]["held_out_nm_by_stage"]
    stages = ", ".join(
        f"{q(h, 'nm', 0)} ({'kept' if ok else 'rejected'}, {q(t, 's', 0)})"
        for h, ok, t in zip(held, b["metrics"]["stages_accepted"], _stage_times(b["log"]))
    )
    rows += [
        ("with image stages (`--blur-px 2 1`): held-out features after each stage", stages),
        ("the same: outcome", "saved" if b["plausible"] else "refused: " + "; ".join(b["failures"])),
    ]
    note = (
        "Seed 7 of the independent generator; the tip path after the rigid motion no image can see. "
        "Times from one run of each on 2 cores."
    )
    return Table(
        ["", "step A as `jaxafm calibrate` runs it"], facts(rows), [STEP_A_FEW, STEP_A_FEW_IMAGES], note
    )


STEP_A_FEW_KNOWN = (
    Run(
        "step_a_few_features/seed7_known_y_10pct.json",
        "python experiments/step_a_few_features.py --known y --sd-pct 10",
    ),
    Run(
        "step_a_few_features/seed7_known_y_2pct.json",
        "python experiments/step_a_few_features.py --known y --sd-pct 2",
    ),
    Run(
        "step_a_few_features/seed7_known_xy_2pct.json",
        "python experiments/step_a_few_features.py --known x y --sd-pct 2",
    ),
    Run(
        "step_a_few_features/seed7_known_y_2pct_lag.json",
        "python experiments/step_a_few_features.py --known y --sd-pct 2 --lag",
    ),
)


def _reasons(failures: list) -> str:
    """A refusal's reasons, each up to its first colon or semicolon (the rest is the numbers' detail)."""
    short = [f.split(": ")[0].split("; ")[0].split(" (")[0] for f in failures]
    return "refused: " + "; ".join(short) if short else "saved"


def _tip_path_rows(runs: list, px) -> list:
    """Two rows of a few-features table: the true tip path's rms over all pixels (x / y), and
    inside / outside the features' reach, per run (``px`` writes a number of pixels)."""
    return [
        ["true tip path, rms: all pixels (x / y)"]
        + [f"{px(r['tip_path_rms_px'])} ({' / '.join(map(px, r['tip_path_xy_rms_px']))})" for r in runs],
        ["true tip path, rms: inside / outside the features' reach"]
        + [
            f"{px(r['tip_path_inside_reach_rms_px'])} / {px(r['tip_path_outside_reach_rms_px'])}"
            for r in runs
        ],
    ]


@table("step_a_few_features_known")
def step_a_few_features_known(results: Results) -> Table:
    runs = [results(STEP_A_FEW)] + [results(r) for r in STEP_A_FEW_KNOWN]
    true = runs[1]["true_gains_nm_per_v"]
    px = lambda v: q(v, "px", 2)

    def gain(r, a):
        m = r["metrics"]
        return f"{q(m[f'{a}_gain_nm_per_v'], 'nm/V', 0)} ± {q(m[f'{a}_gain_nm_per_v_sd'], 'nm/V', 0)}"

    stated = lambda r: (
        ", ".join(
            f"{k[0]} {q(v, 'nm/V', 0)} ± {q(sd, 'nm/V', 0)}" for k, (v, sd) in r.get("known", {}).items()
        )
        or "nothing"
    )
    rows = [
        ["stated (`known`)"] + [stated(r) for r in runs],
        [f"x gain, fitted (the generator's: {q(true['x_gain_nm_per_v'], 'nm/V', 0)})"]
        + [gain(r, "x") for r in runs],
        [f"y gain, fitted (the generator's: {q(true['y_gain_nm_per_v'], 'nm/V', 0)})"]
        + [gain(r, "y") for r in runs],
        ["model the ladder kept"] + [r["kept"] for r in runs],
        ["held-out features, corrected"] + [q(r["metrics"]["held_out_rms_nm"], "nm", 0) for r in runs],
        ["the tip path's sd over the images (step A's check)"]
        + [
            f"{q(r['metrics']['path_sd_rms_nm'], 'nm', 0)}; knowing `{r['metrics']['path_settled_most_by']}` "
            f"would settle {q(r['metrics']['path_settled_most_pct'], '%', 0)} of it"
            for r in runs
        ],
        ["outcome"] + [_reasons(r["failures"]) for r in runs],
        *_tip_path_rows(runs, px),
        ["step A's time on 2 cores"] + [q(r["seconds"], "s", 0) for r in runs],
    ]
    note = (
        "Seed 7 of the independent generator, as in the table above; a gain stated is the generator's own "
        "(the ascending branch's mean slope over the drive the scans cover, from its relays) with an sd of "
        "10 % or 2 % of it. The last column's model has `rate_dependence` in place of `feedback_lag` (`--lag`; "
        "at one angle step A fits one of the two). The tip path after the rigid motion no image can see."
    )
    header = [
        "",
        "nothing stated",
        "y gain ± 10 %",
        "y gain ± 2 %",
        "x and y gains ± 2 %",
        "y gain ± 2 %, the scanner's lag in place of the edge delay",
    ]
    return Table(header, rows, [STEP_A_FEW, *STEP_A_FEW_KNOWN], note)


@table("step_a_few_features_where")
def step_a_few_features_where(results: Results) -> Table:
    run = STEP_A_FEW_KNOWN[1]  # the y gain stated at 2 %
    r = results(run)
    px = lambda v: q(v, "px", 2)
    rows = [
        [f"{q(s['line_rate_hz'], 'Hz', 1)}, {s['direction']}"]
        + [px(s["rms_xy_px"][0]), px(s["mean_xy_px"][0]), px(s["rms_xy_px"][1])]
        for s in r["error_by_scan"]
    ]
    bands = lambda key: " · ".join(q(v, "", 1) for v in r[key]) + " px"
    note = (
        "Seed 7 of the independent generator, the y gain stated at 2 % (the third column of the table above); "
        "the tip path's error at every pixel after the one rigid motion. Along x by the nominal x position, in "
        f"eight bands from left to right: {bands('x_error_by_x_band_px')}; along x by the nominal y position, "
        f"from the first line to the last: {bands('x_error_by_y_band_px')} (their means "
        f"{bands('mean_x_error_by_y_band_px')}); along y by y: {bands('y_error_by_y_band_px')}. Each scan "
        "after its own rigid motion: " + ", ".join(px(v) for v in r["tip_path_per_scan_own_rigid_px"]) + "."
    )
    header = ["scan", "x: rms", "x: mean", "y: rms"]
    return Table(header, rows, [run], note)


STEP_A_FEW_LENGTHS = Run(
    "step_a_few_features/seed7_known_y_2pct_lengths.json",
    "python experiments/step_a_few_features.py --known y --sd-pct 2 --chord-lengths",
)


@table("step_a_chord_lengths")
def step_a_chord_lengths(results: Results) -> Table:
    """The small lattice (the y gain stated at 2 %) fitted on the chords' midpoints alone and on
    their lengths too, against the generator's truth."""
    runs = [results(STEP_A_FEW_KNOWN[1]), results(STEP_A_FEW_LENGTHS)]
    true, loops = runs[1]["true_gains_nm_per_v"], runs[1]["true_loops_nm"]
    px = lambda v: q(v, "px", 2)
    m = lambda key: [r["metrics"][key] for r in runs]
    rows = [
        ["model the ladder kept"] + [r["kept"] for r in runs],
        [f"x gain, fitted (the generator's: {q(true['x_gain_nm_per_v'], 'nm/V', 0)})"]
        + [
            f"{q(v, 'nm/V', 0)} ± {q(sd, 'nm/V', 0)}"
            for v, sd in zip(m("x_gain_nm_per_v"), m("x_gain_nm_per_v_sd"))
        ],
        [f"loop in the 0.5 Hz scan, fitted (the generator's: {q(loops[0], 'nm', 0)})"]
        + [f"{q(v, 'nm', 0)} ± {q(sd, 'nm', 0)}" for v, sd in zip(m("loop_scan0_nm"), m("loop_scan0_nm_sd"))],
        ["held-out features, corrected"] + [q(v, "nm", 0) for v in m("held_out_rms_nm")],
        ["features' widths along the lines, spread raw → corrected"]
        + [
            _raw_to(
                r["metrics"],
                "feature_width_spread_along_raw_pct",
                "feature_width_spread_along_corrected_pct",
                "%",
                3,
            )
            for r in runs
        ],
        ["the tip path's sd over the images (step A's check)"] + [q(v, "nm", 0) for v in m("path_sd_rms_nm")],
        ["outcome"] + [_reasons(r["failures"]) for r in runs],
        *_tip_path_rows(runs, px),
        ["x error in eight bands of x, left to right"]
        + [" · ".join(q(v, "", 1) for v in r["x_error_by_x_band_px"]) + " px" for r in runs],
        ["true tip path inside the predicted 90 % ellipses (with a feature's spread)"]
        + [q(r["tip_path_coverage_90_with_spread_pct"], "%", 0) for r in runs],
        ["step A's time on 2 cores"] + [q(r["seconds"], "s", 0) for r in runs],
    ]
    note = (
        "Seed 7 of the independent generator, the y gain stated at 2 % (as in the tables above). The tip "
        "path after the rigid motion no image can see; a loop is how far the retrace lies behind the trace "
        "in the middle column, on average over the lines."
    )
    header = ["", "midpoints (the default)", "midpoints and lengths (`solver.chord_lengths: true`)"]
    return Table(header, rows, [STEP_A_FEW_KNOWN[1], STEP_A_FEW_LENGTHS], note)


STEP_A_LENGTHS_REAL = Run(
    "step_a_chord_lengths_real/metrics.json", "python experiments/step_a_chord_lengths_real.py"
)


@table("step_a_chord_lengths_real")
def step_a_chord_lengths_real(results: Results) -> Table:
    """Each Nanosurf lattice fitted on the chords' midpoints alone and on their lengths too."""
    ways = {"midpoints": "midpoints (committed run)", "lengths": "midpoints and lengths"}
    rows = []
    for lattice, by_way in results(STEP_A_LENGTHS_REAL).items():
        for name, r in by_way.items():
            kept = f"{r['model_kind']} {r['model_operators']} plays + " + ", ".join(r["model_effects"])
            rows.append(
                [lattice.replace("_", " "), ways[name], q(r["held_out_rms_nm"], "nm")]
                + [q(r["held_out_coverage_90_pct"], "%", 0), q(r["held_out_pitch_std_corrected_pct"], "%", 2)]
                + [q(r["held_out_distance_error_max_corrected_pct"], "%", 2)]
                + [
                    f"{q(r['feature_width_spread_along_raw_pct'], '%', 2)} → "
                    f"{q(r['feature_width_spread_along_corrected_pct'], '%', 2)}"
                ]
                + [kept, q(r["plausible"]), q(r["fit_s"], "s", 0)]
            )
    header = ["lattice", "the chords' fit", "held-out features", "inside their 90 % ellipses"]
    header += [
        "their local pitch spread",
        "largest distance error",
        "widths along the lines, raw → corrected",
    ]
    header += ["model the ladder kept", "saved as plausible", "step A's time"]
    note = "The held-out features as `jaxafm calibrate` gives them, corrected; times on 2 cores."
    return Table(header, rows, [STEP_A_LENGTHS_REAL], note)


STEP_A_OFF_LINE_REAL = Run(
    "step_a_off_line_chords/metrics.json", "python experiments/step_a_off_line_chords.py"
)


@table("step_a_off_line_chords")
def step_a_off_line_chords(results: Results) -> Table:
    """Each Nanosurf lattice fitted with every chord and without those off their features' lines."""
    ways = {"every chord": "every chord (committed run)", "on their lines": "`off_line_chords_sd: 5`"}
    rows = []
    for lattice, by_way in results(STEP_A_OFF_LINE_REAL).items():
        for name, r in by_way.items():
            kept = f"{r['model_kind']} {r['model_operators']} plays + " + ", ".join(r["model_effects"])
            rows.append(
                [lattice.replace("_", " "), ways[name], count(r["chords"])]
                + [f"{q(r['midpoint_rms_nm'], 'nm')} ({q(r['midpoint_along_rms_nm'], 'nm')})"]
                + [f"{q(r['held_out_raw_rms_nm'], 'nm')} → {q(r['held_out_rms_nm'], 'nm')}"]
                + [q(r["held_out_predicted_rms_nm"], "nm"), q(r["held_out_coverage_90_pct"], "%", 0)]
                + [q(r["held_out_pitch_std_corrected_pct"], "%", 2)]
                + [q(r["held_out_distance_error_max_corrected_pct"], "%", 2), kept, q(r["plausible"])]
            )
    header = [
        "lattice",
        "chords read",
        "chords in all images",
        "midpoints off their lines at the fit (along the lines)",
    ]
    header += ["held-out features, raw → corrected", "predicted for them", "inside their 90 % ellipses"]
    header += [
        "their local pitch spread",
        "largest distance error",
        "model the ladder kept",
        "saved as plausible",
    ]
    note = (
        "The held-out features as `jaxafm calibrate` gives them, each run placing them by its own "
        "chords; the midpoints rms over the training chords at the fit."
    )
    return Table(header, rows, [STEP_A_OFF_LINE_REAL], note)


STEP_A_FLOOR = Run(
    "step_a_independent/floor.json", "python experiments/step_a_floor.py --seeds 100 106 111 114 116"
)


@table("step_a_floor")
def step_a_floor(results: Results) -> Table:
    px = lambda v: "–" if v is None else q(v, "px", 2)
    rows = []
    for r in results(STEP_A_FLOOR):
        a, floor, alone = r["step_a"], r["floor"], r["floor_hysteresis_only"]
        scans = _scans_label(r)
        rows.append(
            [f"{r['seed']} ({scans})", q(100 * a["inside_share"], "%", 0)]
            + [px(a[k]) for k in ("all_px", "inside_px", "outside_px")]
            + [px(floor[k]) for k in ("all_px", "inside_px", "outside_px")]
            + [px(alone["all_px"]), _lags(r)]
        )
    header = ["case", "pixels inside the reach", "step A: all pixels", "inside", "outside"]
    header += ["floor: all pixels", "inside", "outside", "floor, hysteresis alone"]
    header += ["x lag: generator / step A / floor"]
    return Table(header, rows, [STEP_A_FLOOR], "Tip path rms against the truth after the rigid motion.")


def _lags(row: dict, suffix: str = "") -> str:
    """A speed series' x rate lags: the generator's, step A's and the floor's (ms), of the model
    class whose keys end in ``suffix``."""
    fitted = [row["step_a" + suffix].get("x_rate_lag_s"), row["floor" + suffix].get("x_rate_lag_s")]
    if len(row["rates_hz"]) < 2 or None in fitted or "true_rate_lag_s" not in row:
        return "–"
    return " / ".join(q(1e3 * v, "ms", 2) for v in [row["true_rate_lag_s"]] + fitted)


STEP_A_CREEP_ONSET = Run(
    "step_a_independent_creep_onset/cases-rerun.json",
    "python experiments/step_a_independent.py --pixels 64 --creep-onset --seeds 102 105 108 111 114 117 && "
    "python experiments/step_a_independent.py --pixels 64 --creep-onset --seeds 114",
)
STEP_A_FLOOR_ONSET = Run(
    "step_a_independent/floor.json",
    "python experiments/step_a_floor.py --seeds 111 --classes preisach --creep-onset",
)


def _onset(onset: Optional[float]) -> str:
    """A fitted creep onset (ms), or how far below a millisecond it ran (to 0: the bank's fastest
    lag, 10 ms, then sets the shape)."""
    if onset is None:
        return "–"
    return q(1e3 * onset, "ms", 0) if onset >= 1e-3 else f"≈ 0 ({onset:.1e} s)".replace("-", "−")


def _lag_error(fitted: Optional[float], true: float) -> str:
    """A fitted lag (ms) and its relative error against the generator's ``true`` one."""
    if fitted is None:
        return "not kept"
    return f"{q(1e3 * fitted, 'ms', 2)} ({q(100 * (fitted / true - 1), '%', 0)})"


@table("step_a_creep_onset_floor")
def step_a_creep_onset_floor(results: Results) -> Table:
    rows, cases = [], [r for r in results(STEP_A_FLOOR_ONSET) if "floor_preisach_creep_onset" in r]
    for r in cases:
        true = r["true_rate_lag_s"]
        fits = [
            ("floor, creep of fixed shape", r["floor_preisach"]),
            ("floor, the case drawn without creep", r["floor_preisach_no_creep"]),
            ("floor, creep's onset fitted", r["floor_preisach_creep_onset"]),
            ("step A, creep of fixed shape", r["step_a_preisach"]),
            ("step A, creep's onset fitted", r["step_a_preisach_creep_onset"]),
        ]
        for name, f in fits:
            onset = f.get("x_creep_onset_s")
            rows.append(
                [f"{r['seed']}: {name}", q(f["all_px"], "px", 3), _lag_error(f["x_rate_lag_s"], true)]
                + [q(100 * f["x_creep_per_decade"], "%", 2) if "x_creep_per_decade" in f else "–"]
                + [_onset(onset), f"{q(f['plausible'])}: {f['model']}" if "plausible" in f else "–"]
            )
    header = ["case: fit", "tip path", "x lag (error)", "x creep per decade", "creep onset"]
    header += ["step A: saved, model kept"]
    note = (
        "Preisach class: the floor 16 levels with every effect, step A its ladder. The generator: "
        "drive lag "
        + ", ".join(q(1e3 * r["true_rate_lag_s"], "ms", 2) for r in cases)
        + ", creep per decade "
        + ", ".join(q(100 * r["true_creep_per_decade"], "%", 2) for r in cases)
        + " from an onset of 0.1 s. Fitted creep is the x axis'; the floor's creep of fixed shape "
        "predates its report (–)."
    )
    return Table(header, rows, [STEP_A_FLOOR_ONSET, STEP_A_FLOOR_PREISACH], note)


def _with_study(results: Results, run: Run) -> tuple:
    """``(pairs, runs)``: each case of ``run`` after the generalised PI study's fit of its seed,
    ``(study's, run's)``, and the runs they come from."""
    study = _gpi_cases(results)
    pairs = [(study[r["seed"]][0], r) for r in results(run)]
    return pairs, list(dict.fromkeys([run] + [study[r["seed"]][1] for r in results(run)]))


@table("step_a_creep_onset")
def step_a_creep_onset(results: Results) -> Table:
    rows, (pairs, runs) = [], _with_study(results, STEP_A_CREEP_ONSET)
    for fixed, r in pairs:
        true = r["true_rate_lag_s"]
        onset = r.get("gpi_x_creep_onset_s")
        rows.append(
            [f"{r['seed']} ({r['feature'].replace('_', ' ')})"]
            + [_tip_path_cell(c["gpi_plausible"], c["tip_path_rms_px"]) for c in (fixed, r)]
            + [_lag_error(c.get("gpi_x_rate_lag_s"), true) for c in (fixed, r)]
            + [q(100 * c["gpi_x_creep_per_decade"], "%", 2) for c in (fixed, r)]
            + [_onset(onset)]
        )
    header = ["case", "tip path: fixed shape", "onset fitted", "x lag (error): fixed shape", "onset fitted"]
    header += ["x creep per decade: fixed shape", "onset fitted", "x creep onset"]
    note = (
        "Generalised PI class, speed series at 0.5, 1 and 2 Hz at 0°. The generator's creep is "
        "1–2 % per decade from an onset of 0.1 s on both axes."
    )
    return Table(header, rows, runs, note)


#: the generator's cases with ``solver.chord_lengths``, per ``--seeds`` run (each seed in one)
STEP_A_LENGTHS_RUNS = {
    Run(
        "step_a_independent_lengths/cases-rerun.json",
        f"python experiments/step_a_independent.py --pixels 64 --chord-lengths --seeds {seeds}",
    ): seeds
    for seeds in ("102 105 108 111 114 117", "100 101 103 104 106 107 109 110 112 113 115 116 118 119")
}
STEP_A_LENGTHS = next(iter(STEP_A_LENGTHS_RUNS))


@table("step_a_independent_lengths")
def step_a_independent_lengths(results: Results) -> Table:
    rows, (pairs, study_runs) = [], _with_study(results, STEP_A_LENGTHS)
    runs = [_run_of(r["seed"], STEP_A_LENGTHS, STEP_A_LENGTHS_RUNS, STEP_A_LENGTHS) for _, r in pairs]
    for pair in pairs:
        r = pair[1]
        one_rate = len(r["rates_hz"]) == 1
        rows.append(
            [f"{r['seed']} ({_scans_label(r)}, {r['feature'].replace('_', ' ')})"]
            + [_tip_path_cell(c["gpi_plausible"], c["tip_path_rms_px"]) for c in pair]
            + [q(c["gpi_held_out_rms_nm"] / c["pixel_nm"], "px", 2) for c in pair]
            + ["–" if one_rate else _lag_error(c.get("gpi_x_rate_lag_s"), r["true_rate_lag_s"]) for c in pair]
            + [q(c["gpi_feature_width_spread_across_corrected_pct"], "%", 1) for c in pair]
            + [q(c["tip_path_coverage_90_with_spread_pct"], "%", 0) for c in pair]
            + [f"{q(c['gpi_fit_s'], 's', 0)}" for c in pair]
        )
    both = [p for p in pairs if all(c["gpi_plausible"] for c in p)]
    median = [f"median of the {len(both)} saved by both"]
    median += [q(statistics.median(c["tip_path_rms_px"] for c in way), "px", 2) for way in zip(*both)]
    rows.append(median + [""] * (len(rows[0]) - len(median)))
    header = ["case", "tip path: midpoints", "lengths", "held-out features: midpoints", "lengths"]
    header += ["x lag (error): midpoints", "lengths", "widths across the lines: midpoints", "lengths"]
    header += ["true path in the 90 % ellipses: midpoints", "lengths", "step A's time: midpoints", "lengths"]
    note = (
        "Generalised PI class; speed series at 0.5, 1 and 2 Hz at 0°, pairs at 0° and 90° at 1 Hz "
        "(no lag fitted: –). The midpoints are the study's fits (the default), the lengths "
        "`solver.chord_lengths: true`. Widths across the lines: their spread after the correction. "
        "The true path in the predicted 90 % ellipses with a feature's spread. Times on 2 cores."
    )
    return Table(header, rows, list(dict.fromkeys(runs + study_runs[1:])), note)


STEP_A_OFF_LINE = Run(
    "step_a_independent_off_line/cases-rerun.json",
    "python experiments/step_a_independent.py --pixels 64 --off-line-chords 5 --seeds 107 113 116",
)


@table("step_a_independent_off_line")
def step_a_independent_off_line(results: Results) -> Table:
    """The generator's square-pit cases read with every chord (the study's fits) and without the
    chords off their features' lines."""
    rows, (pairs, runs) = [], _with_study(results, STEP_A_OFF_LINE)
    for pair in pairs:
        r = pair[1]
        rows.append(
            [f"{r['seed']} ({_scans_label(r)}, {r['feature'].replace('_', ' ')})"]
            + [_tip_path_cell(c["gpi_plausible"], c["tip_path_rms_px"]) for c in pair]
            + [q(c["gpi_held_out_rms_nm"] / c["pixel_nm"], "px", 2) for c in pair]
            + [q(c["gpi_held_out_distance_error_max_corrected_pct"], "%", 2) for c in pair]
            + [q(c["tip_path_coverage_90_with_spread_pct"], "%", 0) for c in pair]
        )
    ways = ("every chord", "`off_line_chords_sd: 5`")
    header = ["case"] + [
        f"{what}: {way}" if k == 0 else way
        for what in (
            "tip path",
            "held-out features",
            "largest held-out distance error",
            "true path in the 90 % ellipses",
        )
        for k, way in enumerate(ways)
    ]
    note = (
        "Generalised PI class; every chord: the study's fits (the default). The true path in the "
        "predicted 90 % ellipses with a feature's spread."
    )
    return Table(header, rows, runs, note)


STEP_A_FLOOR_PREISACH = Run(
    "step_a_independent/floor.json",
    "python experiments/step_a_floor.py --seeds 100 111 114 --classes preisach",
)
#: step A's Preisach fits re-run without their floors (``--no-floor``): the run and its seeds
STEP_A_FLOOR_PREISACH_RERUNS = {
    Run(
        STEP_A_FLOOR_PREISACH.path,
        f"python experiments/step_a_floor.py --seeds {seeds} --classes preisach --no-floor",
    ): seeds
    for seeds in ("100",)
}
#: the study's cases, per shard file (each seed in one): step A's generalised PI held-out features
STEP_A_CASES = tuple(
    Run(f"step_a_independent/cases-{part}.json", STEP_A_INDEPENDENT.command)
    for part in ("1-of-1", "1-of-2", "2-of-2", "rerun")
)


def _gpi_cases(results: Results) -> dict:
    """The generalised PI study's cases by seed: each its latest row and the run that wrote it."""
    return {r["seed"]: (r, _run_of(r["seed"], run)) for run in STEP_A_CASES for r in results(run)}


def _preisach_run(seed: int) -> Run:
    """The Preisach study's file with the command that last wrote case ``seed`` into it."""
    return _run_of(seed, STEP_A_PREISACH, STEP_A_PREISACH_RERUNS, STEP_A_PREISACH)


def _tip_path_cell(saved: bool, rms_px: float, inside_px=None, outside_px=None) -> str:
    """A tip path's rms (px), with its split inside / outside the features' reach where the run
    made it, marked ``refused:`` for a fit step A refused or judged not plausible."""
    px = lambda v: "–" if v is None else q(v, "px", 2)
    split = "" if inside_px is None else f" ({px(inside_px)} / {px(outside_px)})"
    return ("" if saved else "refused: ") + px(rms_px) + split


@table("step_a_floor_preisach")
def step_a_floor_preisach(results: Results) -> Table:
    px = lambda v: "–" if v is None else q(v, "px", 2)
    path = lambda a, saved: _tip_path_cell(saved, a["all_px"], a["inside_px"], a["outside_px"])
    study = _gpi_cases(results)
    rows, runs = [], [STEP_A_FLOOR_PREISACH]
    for r in results(STEP_A_FLOOR_PREISACH):
        if "step_a_preisach" not in r:
            continue
        gpi, pre = r["step_a"], r["step_a_preisach"]
        case, run = study[r["seed"]]
        own = _run_of(r["seed"], STEP_A_FLOOR_PREISACH, STEP_A_FLOOR_PREISACH_RERUNS, STEP_A_FLOOR_PREISACH)
        runs += [x for x in (run, own) if x not in runs]
        scans = _scans_label(r)
        rows.append(
            [f"{r['seed']} ({scans})", path(gpi, "refused" not in case and case["gpi_plausible"])]
            + [px(case["gpi_held_out_rms_nm"] / case["pixel_nm"]), px(r["floor"]["all_px"])]
            + [path(pre, pre["plausible"])]
            + [px(pre["held_out_px"]), px(r["floor_preisach"]["all_px"]), pre["model"]]
            + [_lags(r, "_preisach")]
        )
    header = ["case", "generalised PI: step A (inside / outside the reach)", "held-out features", "floor"]
    header += ["Preisach: step A (inside / outside the reach)", "held-out features", "floor"]
    header += ["Preisach model the ladder kept", "x lag: generator / Preisach step A / floor"]
    note = (
        "Tip path rms against the truth after the rigid motion; held-out features as `jaxafm calibrate` "
        "gives them; refused: the fit step A refused or judged not plausible."
    )
    return Table(header, rows, runs, note)


STEP_A_PREISACH = Run(
    "step_a_independent_preisach/cases-1-of-1.json",
    "python experiments/step_a_independent.py --cases 20 --pixels 64 --model preisach",
)
#: the Preisach study's cases run again, as :data:`STEP_A_RERUNS`
STEP_A_PREISACH_RERUNS = {
    Run(
        STEP_A_PREISACH.path,
        f"{STEP_A_PREISACH.command.split(' --cases')[0]} --pixels 64 --model preisach --seeds {seeds}",
    ): seeds
    for seeds in (
        "900",
        "104 106 109 110 119 114",
        "111 119 106 104 101 109 103 118 115 107 112 117 102 105 108",
        "100 110 113 116 901",
    )
}


@table("step_a_independent_preisach")
def step_a_independent_preisach(results: Results) -> Table:
    """The study's cases run with each model class: tip path, held-out features, the Preisach
    plane kept, its lag."""
    px = lambda v: "–" if v is None else q(v, "px", 2)
    saved = lambda r, name: "refused" not in r and r.get(f"{name}_plausible")
    gpi = _gpi_cases(results)
    rows, runs, pairs = [], [], []
    for p in results(STEP_A_PREISACH):
        g, run = gpi[p["seed"]]
        own = _preisach_run(p["seed"])
        runs += [r for r in (own, run) if r not in runs]
        scans = _scans_label(p)
        cells = [f"{p['seed']} ({scans}, {p['feature'].replace('_', ' ')})"]
        for r, name in ((g, "gpi"), (p, "preisach")):
            if r.get("tip_path_rms_px") is None:
                cells += ["not saved", "–"]
                continue
            inside, outside = r.get("tip_path_inside_reach_rms_px"), r.get("tip_path_outside_reach_rms_px")
            cells += [
                _tip_path_cell(saved(r, name), r["tip_path_rms_px"], inside, outside),
                px(r[f"{name}_held_out_rms_nm"] / r["pixel_nm"]),
            ]
        kept = "–"
        if saved(p, "preisach"):
            kept = f"{p['preisach_model_operators']} levels + " + ", ".join(p["preisach_model_effects"])
        lag = p.get("preisach_x_rate_lag_s")
        error = (
            "–"
            if lag is None or len(p["rates_hz"]) < 2
            else f"{100 * (lag / p['true_rate_lag_s'] - 1):+.0f} %"
        )
        rows.append(cells + [kept, error])
        if saved(p, "preisach") and saved(g, "gpi"):
            pairs.append((g["tip_path_rms_px"], p["tip_path_rms_px"]))
    if pairs:
        med = [statistics.median(v) for v in zip(*pairs)]
        rows.append([f"median of the {len(pairs)} saved by both", px(med[0]), "", px(med[1]), "", "", ""])
    header = ["case", "generalised PI: tip path (inside / outside the reach)", "held-out features"]
    header += ["Preisach: tip path (inside / outside the reach)", "held-out features"]
    header += ["Preisach model the ladder kept", "x lag against the generator's"]
    note = (
        "Tip path rms against the truth after the rigid motion (inside / outside the features' reach where "
        "the run split it); held-out features as `jaxafm calibrate` gives them; refused: the fit step A "
        "refused or judged not plausible; not saved: none scored."
    )
    return Table(header, rows, runs, note)


@table("step_a_feature_widths")
def step_a_feature_widths(results: Results) -> Table:
    """The generator's cases whose runs measured the features' widths (generalised PI, with the
    fixed creep shape and with its onset fitted): tip path, held-out features, the widths'
    spread along and across the lines raw and corrected, and what step A refused them for."""
    px = lambda v: q(v, "px", 2)
    gpi = _gpi_cases(results)
    found = [(row, run, "") for row, run in gpi.values()]
    found += [(row, STEP_A_CREEP_ONSET, ", creep onset fitted") for row in results(STEP_A_CREEP_ONSET)]
    rows, runs = [], []
    for r, run, how in sorted(found, key=lambda f: (f[0]["seed"], f[2])):
        if "gpi_feature_widths_across" not in r:
            continue
        runs += [run] if run not in runs else []
        spread = lambda way: (
            f"{q(r[f'gpi_feature_width_spread_{way}_raw_pct'], '%', 1)} → "
            f"{q(r[f'gpi_feature_width_spread_{way}_corrected_pct'], '%', 1)}"
        )
        why = [
            reason
            for reason, words in (
                ("widths", "widths"),
                ("path open", "leave the tip path open"),
                ("local pitch", "local pitch"),
            )
            if any(words in f for f in r.get("gpi_failures", []))
        ]
        rows.append(
            [
                f"{r['seed']} ({_scans_label(r)}{how})",
                px(r["tip_path_rms_px"]),
                px(r["gpi_held_out_rms_nm"] / r["pixel_nm"]),
                spread("along"),
                spread("across"),
                "saved" if r.get("gpi_plausible") else "refused: " + ", ".join(why or ["another check"]),
            ]
        )
    header = ["case", "tip path", "held-out features", "widths' spread along the lines, raw → corrected"]
    header += ["across the lines", "step A"]
    note = (
        "Tip path rms against the truth after the rigid motion; the widths' spread over every feature of "
        "every image, % of their mean; refused: the checks that refused the fit (widths: the feature "
        "width check; path open: the path check; local pitch: the held-out local pitch check)."
    )
    return Table(header, rows, runs, note)


#: the path tolerances (px) :func:`step_a_path_tolerance` re-applies the path check at
PATH_TOLERANCES_PX = (0.05, PATH_TOLERANCE_PX, 0.2, 0.4)


@table("step_a_path_tolerance")
def step_a_path_tolerance(results: Results) -> Table:
    """How the path check sorts each class's fits of the generator's cases by their true tip
    path, at several tolerances: the check (:func:`jaxafm.identify.plausibility.path_open`)
    re-applied to each case's recorded path sd and predicted held-out error."""
    px = lambda v: q(v, "px", 2)
    spread = lambda v, end: "–" if not v else f"{px(statistics.median(v))} / {px(end(v))}"
    gpi = _gpi_cases(results)
    preisach = {r["seed"]: (r, _preisach_run(r["seed"])) for r in results(STEP_A_PREISACH)}
    rows, runs = [], []
    for label, name, cases in (("generalised PI", "gpi", gpi), ("Preisach", "preisach", preisach)):
        checked = [(r, run) for r, run in cases.values() if r.get(f"{name}_path_sd_rms_nm") is not None]
        runs += [run for _, run in checked if run not in runs]
        for tolerance in PATH_TOLERANCES_PX:
            saved, refused = [], []
            for r, _ in checked:
                others = [f for f in r[f"{name}_failures"] if not f.startswith(PATH_OPEN)]
                opened = path_open(
                    r[f"{name}_path_sd_rms_nm"],
                    r[f"{name}_held_out_predicted_rms_nm"],
                    tolerance * r["pixel_nm"],
                )
                (refused if others or opened else saved).append(r["tip_path_rms_px"])
            default = " (the default)" if tolerance == PATH_TOLERANCE_PX else ""
            rows.append(
                [label, px(tolerance) + default, f"{len(saved)} of {len(checked)}", spread(saved, max)]
                + [spread(refused, min)]
            )
    header = ["class", "path tolerance", "saved", "saved: tip path median / max", "refused: median / min"]
    note = (
        "The generator's cases whose files hold the path check's numbers. The check re-applied to each "
        "case's recorded path sd and predicted held-out error with the tolerance in px of its pixel; a "
        "case refused for another reason stays refused. Tip path rms against the truth after the rigid motion."
    )
    return Table(header, rows, runs, note)


def _ellipses(r: dict, key: str) -> str:
    """The 90 % and 50 % ellipses' coverage of ``key`` (``..._{level}..._pct``) in ``r``."""
    return f"{q(r[key.format(90)], '%', 0)} / {q(r[key.format(50)], '%', 0)}"


@table("step_a_coverage")
def step_a_coverage(results: Results) -> Table:
    """Step A's predicted position errors against the held-out features (real lattices and the
    generator) and against the generator's true tip path."""
    rows = []
    lattices = [(f"{label} (real)", run) for label, run in NANOSURF] + [
        ("jaxafm's simulated AFM", STEP_A_SIM)
    ]
    for label, run in lattices:
        m = results(run)
        rows.append(
            [label, count(m["gpi_held_out_points"])]
            + [f"{q(m['gpi_held_out_offsets_rms_nm'], 'nm')} / {q(m['gpi_held_out_predicted_rms_nm'], 'nm')}"]
            + [
                _ellipses(m, "gpi_held_out_coverage_{}_pct"),
                q(m["gpi_held_out_parameters_share_pct"], "%", 0),
            ]
            + ["–"] * 3
        )
    runs = [run for _, run in lattices]
    cases = [(r, run) for run in STEP_A_CASES for r in results(run) if "tip_path_coverage_90_pct" in r]
    for r, run in sorted(cases, key=lambda c: c[0]["seed"]):
        rerun = _run_of(r["seed"], run)
        runs += [rerun] if rerun not in runs else []
        scans = _scans_label(r)
        px = r["pixel_nm"]
        rows.append(
            [f"{r['seed']} ({scans}, generator)", count(r["gpi_held_out_points"])]
            + [f"{q(r['gpi_held_out_offsets_rms_nm'], 'nm')} / {q(r['gpi_held_out_predicted_rms_nm'], 'nm')}"]
            + [
                _ellipses(r, "gpi_held_out_coverage_{}_pct"),
                q(r["gpi_held_out_parameters_share_pct"], "%", 0),
            ]
            + [
                f"{q(r['tip_path_rms_px'] * px, 'nm')} / {q(r['tip_path_predicted_rms_px'] * px, 'nm')} / "
                f"{q(r['tip_path_predicted_rms_with_spread_px'] * px, 'nm')}",
                _ellipses(r, "tip_path_coverage_{}_pct"),
                _ellipses(r, "tip_path_coverage_{}_with_spread_pct")
                + f" ({q(r['tip_path_coverage_90_with_spread_inside_reach_pct'], '%', 0)} inside, "
                f"{q(r['tip_path_coverage_90_with_spread_outside_reach_pct'], '%', 0)} beyond)",
            ]
        )
    header = ["lattice or case", "held-out points", "their offsets / predicted, rms"]
    header += ["inside the 90 % / 50 % ellipses", "parameters' share of the prediction"]
    header += ["true tip path: error / predicted (parameters) / predicted (+ spread), rms"]
    header += ["inside the 90 % / 50 % ellipses, parameters"]
    header += ["the same, + spread (90 %: inside the features' reach, beyond it)"]
    note = (
        "A point is one feature in one image; its offset, how far the model misplaces it along each scan axis; "
        "the tip path, every pixel of every scan after the one rigid motion no image can see."
    )
    return Table(header, rows, runs, note)


@table("push_odds")
def push_odds(results: Results) -> Table:
    """The study's first pushes: predicted success against observed, per tenth of prediction."""
    m = results(STUDY)
    rows = [
        [
            f"{q(100 * b['lo'], '%', 0)}–{q(100 * b['hi'], '%', 0)}",
            count(b["trials"]),
            q(b["predicted_pct"], "%"),
            q(b["observed_pct"], "%"),
            q(b["observed_pct"] - b["predicted_pct"], "points"),
        ]
        for b in m["push_first_reliability"]
    ]
    header = ["predicted success", "trials", "mean prediction", "observed success", "observed − predicted"]
    note = (
        f"{count(m['push_first_trials'])} of {count(m['trials'])} trials given odds; Brier score "
        f"{m['push_first_brier']:.4f} against {m['push_first_brier_base_rate']:.4f} for predicting every push by "
        f"the overall rate ({q(m['push_first_success_pct'], '%')} of first pushes within "
        f"{m['push_tolerance_radii']:g} R)."
    )
    return Table(header, rows, [STUDY], note)


PUSH_ODDS_MODELS = Run("push_odds_models/metrics.json", "python experiments/push_odds_models.py")


@table("push_odds_models")
def push_odds_models(results: Results) -> Table:
    """Committed studies' first pushes scored with two models of a push's miss."""
    m = results(PUSH_ODDS_MODELS)
    labels = {
        "distance": "along and across, each a line in the push's distance",
        "affine": "affine (jaxafm's)",
    }
    rows = []
    for study, scores in m.items():
        for name, label in labels.items():
            score = scores[name]
            big = [b for b in score["bins"] if b["trials"] >= 100]
            rows.append(
                [
                    f"{study}.yaml",
                    label,
                    count(score["trials"]),
                    f"{score['brier']:.4f} / {score['brier_base_rate']:.4f}",
                    ", ".join(
                        f"{q(100 * b['lo'], '%', 0)}–{q(100 * b['hi'], '%', 0)}: "
                        f"{q(b['observed_pct'] - b['predicted_pct'], 'points')}"
                        for b in big
                    ),
                    q(_largest_gap(score["bins"]), "points"),
                    q(statistics.median(score["residual_sd_nm"]), "nm"),
                ]
            )
    header = [
        "study",
        "model of the miss",
        "trials given odds",
        "Brier score / the overall rate's",
        "observed − predicted, tenths with ≥ 100 trials",
        "largest gap there",
        "scatter about the model, median over the scanners",
    ]
    note = (
        "The same trials, in the same order, for both models. Scatter: each scanner's rms residual per component of "
        "its touching first pushes' misses about the model fitted to all of them."
    )
    return Table(header, rows, [PUSH_ODDS_MODELS], note)


STEP_A_REAL_CLASSES = Run("step_a_real_classes/metrics.json", "python experiments/step_a_real_classes.py")


@table("step_a_real_classes")
def step_a_real_classes(results: Results) -> Table:
    """Each Nanosurf lattice identified with each model class."""
    classes = {"gpi": "generalised PI (committed run)", "preisach": "Preisach plane"}
    kinds = {"pi": "PI", "gpi": "generalised PI", "preisach": "Preisach"}
    rows = []
    for lattice, by_class in results(STEP_A_REAL_CLASSES).items():
        for name, r in by_class.items():
            size = "levels" if r["model_kind"] == "preisach" else "plays"
            shape = f"{kinds[r['model_kind']]}, {r['model_operators']} {size}"
            shape = "straight axes" if r["model_kind"] == "pi" and r["model_operators"] == 1 else shape
            kept = f"{shape} + " + ", ".join(r["model_effects"])
            rows.append(
                [lattice.replace("_", " "), classes[name]]
                + [f"{q(r['held_out_raw_rms_nm'], 'nm')} → {q(r['held_out_rms_nm'], 'nm')}"]
                + [
                    f"{q(r['held_out_pitch_std_raw_pct'], '%', 2)} → {q(r['held_out_pitch_std_corrected_pct'], '%', 2)}"
                ]
                + [q(r["held_out_distance_error_max_corrected_pct"], "%", 2), kept, q(r["plausible"])]
            )
    header = ["lattice", "richest model", "held-out features: raw → corrected", "their local pitch spread"]
    header += ["largest distance error, corrected", "model the ladder kept", "saved as plausible"]
    return Table(
        header, rows, [STEP_A_REAL_CLASSES], "The held-out features as `jaxafm calibrate` gives them."
    )


REAL_LATTICE_ARTEFACTS = Run(
    "real_lattice_artefacts/metrics.json", "python experiments/real_lattice_artefacts.py"
)


@table("real_lattice_artefacts")
def real_lattice_artefacts(results: Results) -> Table:
    """Two Nanosurf lattices with scars and dust added, with the outlier handling and without."""
    off = {
        "none": "all on",
        "scars": "scars not looked for",
        "dust": "height from the 99.5th percentile only (no mode check)",
        "dust_mask": "dust not masked",
        "one_side": "chords left on one side of a feature kept",
    }
    rows = []
    for r in results(REAL_LATTICE_ARTEFACTS)["rows"]:
        handling = off[r["handling_off"]] if "handling_off" in r else "–"
        if "refused" in r:
            outcome = ["–", "–", "–", f"refused: {r['refused'].split(': ', 1)[1]}"]
        else:
            held = f"{q(r['held_out_raw_rms_nm'], 'nm')} → {q(r['held_out_rms_nm'], 'nm')}"
            saved = "saved as plausible" if r["plausible"] else "refused"
            found = "–"
            if "features_found" in r:
                found = f"{r['features_found']} / {r['features_with_chords']}"
            outcome = [
                held,
                q(r["held_out_pitch_std_corrected_pct"], "%", 2),
                found,
                saved,
            ]
        rows.append([r["lattice"].replace("_", " "), r["images"], handling, *outcome])
    header = ["lattice", "images", "outlier handling", "held-out features: raw → corrected"]
    header += ["their local pitch spread, corrected", "trace: features found / with chords", "step A"]
    return Table(
        header, rows, [REAL_LATTICE_ARTEFACTS], "The clean rows are the committed `jaxafm calibrate` runs."
    )


PREISACH_LEVELS = {
    100: Run("step_a_independent/preisach_levels_100.json", "python experiments/step_a_preisach_levels.py"),
    111: Run(
        "step_a_independent/preisach_levels_111.json",
        "python experiments/step_a_preisach_levels.py --seed 111 --runs 4 8 16 "
        "--effects coupling rate_dependence creep",
    ),
}


@table("real_lattice_artefacts_breakdown")
def real_lattice_artefacts_breakdown(results: Results) -> Table:
    """Where the loss with scars and dust lies: each model on each image's held-out chords."""
    rows = [
        [
            b["lattice"].replace("_", " "),
            q(b["model_dirty_chords_dirty_nm"], "nm"),
            q(b["model_dirty_chords_clean_nm"], "nm"),
            q(b["model_clean_chords_dirty_nm"], "nm"),
            q(b["model_clean_chords_clean_nm"], "nm"),
            ", ".join(
                f"{tuple(ij)} {image.split()[-1]} {q(nm, 'nm', 0)}" for image, ij, nm in b["worst_held_out"]
            ),
            "; ".join(
                f"{image.split()[-1]} {', '.join(str(tuple(ij)) for ij in sites) or 'none'}"
                for image, sites in b["training_sites_lost"].items()
            ),
        ]
        for b in results(REAL_LATTICE_ARTEFACTS)["breakdown"]
    ]
    header = ["lattice", "fitted with scars and dust: on their held-out chords", "on the clean image's"]
    header += [
        "fitted to the clean images: on the held-out chords with scars and dust",
        "on the clean image's",
        "fitted with scars and dust: its worst held-out features on the clean chords (i, j)",
        "training sites (i + j even) left without chords by scars and dust",
    ]
    return Table(
        header,
        rows,
        [REAL_LATTICE_ARTEFACTS],
        "Held-out features' rms residual; all outlier handling on. The clean fit is identified again.",
    )


@table("real_lattice_artefacts_predicted")
def real_lattice_artefacts_predicted(results: Results) -> Table:
    """How far the fit with scars and dust itself predicts its held-out features' errors."""
    rows = [
        [
            b["lattice"].replace("_", " "),
            q(b["predicted_sd_median_nm"], "nm", 0),
            "; ".join(
                f"{tuple(ij)} {image.split()[-1]}: {q(nm, 'nm', 0)} off, predicted {q(sd, 'nm', 0)}, d² {d2:.1f}"
                for image, ij, nm, sd, d2 in b["predicted_worst"]
            ),
            f"{b['predicted_bound_d2']:.1f}",
        ]
        for b in results(REAL_LATTICE_ARTEFACTS)["breakdown"]
    ]
    header = [
        "lattice",
        "a held-out feature's predicted error, median",
        "the held-out features furthest out by their predicted covariance (i, j)",
        "the bound on the largest d² (99 %)",
    ]
    return Table(
        header,
        rows,
        [REAL_LATTICE_ARTEFACTS],
        "The model fitted with scars and dust, all outlier handling on; each held-out feature's error on "
        "its own chords and its predicted covariance from the training chords, as step A's validation "
        "gives them; predicted error: the root of the covariance's trace (both axes); d² the squared "
        "Mahalanobis distance; the bound: the chi-square quantile of two degrees of freedom at "
        "1 - 0.01 / n for n held-out features (Bonferroni: the largest of n exceeds it in at most 1 % of "
        "lattices).",
    )


def preisach_levels(seed: int) -> Callable[[Results], Table]:
    """The table of ``experiments/step_a_preisach_levels.py`` on case ``seed``."""

    def make(results: Results) -> Table:
        run = PREISACH_LEVELS[seed]
        m = results(run)
        px = lambda v: q(v, "px", 2)
        spread = lambda v: "none" if v is None else q(v, "mean relay weights", 2)
        refused = lambda r: (
            [count(r["levels"]), spread(r["prior_spread"])]
            + ["refused: " + ": ".join(r["refused"].split(": ")[:2])]
            + ["–"] * 8
        )
        rows = [
            refused(r)
            if "refused" in r
            else [count(r["levels"]), spread(r["prior_spread"]), px(r["held_out_px"]), px(r["all_px"])]
            + [px(r["inside_px"]), px(r["x_margins_px"]), px(r["y_margins_px"])]
            + [f"{px(r['sd_inside_px'])} / {px(r['sd_outside_px'])}", q(r["plausible"])]
            + [f"{q(r['aicc'], '', 1)} ({q(r['fitted_parameters'], '', 1)})"]
            + [" / ".join(q(r[f"centres_{k}_px"], "px", 3) for k in ("fitted", "left_out", "half_out"))]
            for r in m["rows"]
        ]
        header = ["levels", "density prior's spread", "held-out features", "tip path: all pixels"]
        header += [
            "inside the reach",
            "x margins",
            "y margins",
            "its predicted sd: inside / outside the reach",
        ]
        header += ["saved as plausible", "AICc of the training features (parameters the data fix)"]
        header += ["training features' centres: fitted / each left out / half left out"]
        note = (
            f"Case {m['seed']}, the ladder off, with {', '.join(m['effects'])}; tip path rms after the rigid "
            "motion; its sd as the fit predicts it (`path_sd`), rms over the pixels."
        )
        return Table(header, rows, [run], note)

    return make


table("step_a_preisach_levels")(preisach_levels(100))
table("step_a_preisach_levels_111")(preisach_levels(111))


RATE_LAG = Run("rate_lag_discretisation/metrics.json", "python experiments/rate_lag_discretisation.py")


@table("rate_lag_discretisation")
def rate_lag_discretisation(results: Results) -> Table:
    rows = []
    for r in results(RATE_LAG)["rows"]:
        rate = "0.5, 1 and 2 Hz at once" if r["line_rate_hz"] == "all" else q(r["line_rate_hz"], "Hz", 1)
        closed = q(1e3 * r["closed_form_lag_s"], "ms", 2) if "closed_form_lag_s" in r else "–"
        rows.append(
            [q(1e3 * r["true_lag_s"], "ms", 1), rate]
            + [q(1e3 * r["fitted_lag_s"], "ms", 2), closed, q(r["relative_error_pct"], "%", 0)]
            + [q(1e3 * r["fitted_lag_linear_s"], "ms", 2), q(r["relative_error_linear_pct"], "%", 1)]
        )
    header = ["generator's lag", "line rate", "zero hold: jaxafm's lag that reproduces it", "closed form"]
    header += ["relative error", "linear hold: jaxafm's lag", "relative error"]
    return Table(header, rows, [RATE_LAG], "64 px lines, one sample a pixel; the lag stage alone.")


@table("rate_lag_order")
def rate_lag_order(results: Results) -> Table:
    rows = [
        [str(r["seed"]), q(r["loop_pct"], "%", 1), q(1e3 * r["true_lag_s"], "ms", 2)]
        + [q(1e3 * r["after_lag_s"], "ms", 3), q(r["relative_error_pct"], "%", 1)]
        for r in results(RATE_LAG)["order"]
    ]
    header = ["generator scanner", "loop", "drive lag before the Preisach", "the same as a lag after it"]
    header += ["relative error"]
    return Table(header, rows, [RATE_LAG], "x axis, hysteresis only; +-8 V triangles at 0.5, 1 and 2 Hz.")


@table("rate_lag_truth")
def rate_lag_truth(results: Results) -> Table:
    ms = lambda seconds: q(1e3 * seconds, "ms", 2)
    rows = [
        [str(r["scanner"]), ms(r["true_lag_s"]), ms(r["linear_hold_equivalent_s"]), ms(r["step_a_lag_s"])]
        + [ms(r["step_a_lag_s"] - r["linear_hold_equivalent_s"])]
        for r in results(RATE_LAG)["truth"]
    ]
    header = ["scanner", "true lag (zero hold)", "the same through the linear hold"]
    header += ["step A's lag (linear hold)", "step A's less the same"]
    note = "x axis; the lag stage alone, fitted to the truth's lag over 128 px lines (10 % over-scan) at 1 and 2 Hz."
    return Table(header, rows, [RATE_LAG], note)


@table("step_a_ablation")
def step_a_ablation(results: Results) -> Table:
    m = results(STEP_A_ABL)
    models = [
        ("full (gpi + creep + coupling + bow + lag)", "full"),
        ("no creep", "no_creep"),
        ("no asymmetry (symmetric PI)", "no_asymmetry"),
        ("no coupling", "no_coupling"),
    ]
    rows = []
    for label, name in models:
        why = (
            "; ".join(m[f"{name}_failures"])
            if not m[f"{name}_plausible"]
            else m.get(f"{name}_analytic_refused")  # the inverse refused the compensated scan's drive
        )
        if why:
            rows.append([label, f"refused: {why}"] + ["–"] * (len(COMPENSATED) - 1))
        else:
            rows += grid(m, [(label, f"{name}_analytic_")], COMPENSATED)
    return Table(["model"] + [c.header for c in COMPENSATED], rows, [STEP_A_ABL])


@table("step_a_angles")
def step_a_angles(results: Results) -> Table:
    m = results(STEP_A_ANGLES)
    rows = []
    for label, key in (("0°", "0 deg"), ("0° + 90°", "0 + 90 deg")):
        r = m[key]
        loops = r["minor_loop_max_error_pct"]
        rows.append(
            [
                label,
                q(loops[0], "%", 2),
                q(loops[1], "%", 2),
                _linearity_cell(r["linearity_x_at_0deg"]),
                _linearity_cell(r["linearity_y_at_90deg"]),
                f"{q(r['held_out_rms_nm'], 'nm', 2)} ({count(r['held_out_features'])})",
                q(r["held_out_floor_nm"], "nm", 2),
                " / ".join(q(v, "", 2) for v in r["tip_path_rms_nm"]) + " nm",
                q(r["plausible"]),
                q(r["fit_s"], "s", 0),
            ]
        )
    header = ["scans", "small loops x: worst \\|fit/true − 1\\|", "small loops y", "linearity x (0°)"]
    header += ["linearity y (90°)", "held-out sites", "their floor (true tip path)", "tip path x / y"]
    header += ["plausible", "fit"]
    return Table(header, rows, [STEP_A_ANGLES])


def _linearity_cell(r: dict) -> str:
    """A re-imaged raster's compensated linearity error, or why the inverse refused it (a drive
    beyond the range the model was fitted over, ``experiments/step_a_angles.py``)."""
    return "refused: a drive beyond the fitted range" if "refused" in r else q(r["compensated_pct"], "%", 2)


#: The triangle amplitudes of ``experiments/step_a_angles.py`` (``AMPLITUDES_V``).
SMALL_LOOPS_V = (0.1, 0.2, 0.5, 1.0, 3.0)


@table("step_a_small_loops")
def step_a_small_loops(results: Results) -> Table:
    m = results(STEP_A_ANGLES)
    series = [
        (f"{axis} from {label}", m[key][f"minor_loop_ratio_{axis}"])
        for key, label in (("0 deg", "0°"), ("0 + 90 deg", "0° + 90°"))
        for axis in ("x", "y")
    ]
    rows = [[name] + [q(v, "", 3) for v in ratios] for name, ratios in series]
    header = ["fitted / true travel"] + [f"±{a:g} V" for a in SMALL_LOOPS_V]
    return Table(header, rows, [STEP_A_ANGLES])


@table("step_a_lattices")
def step_a_lattices(results: Results) -> Table:
    rows = [
        [
            r["lattice"],
            q(r["rotation_deg"], "°"),
            q(r["true_rotation_from_x_axis_deg"], "°", 3),
            q(r["fit_rotation_deg"], "°", 3),
            q(r["rotation_error_deg"], "°", 3),
            q(r["held_out_rms_nm"], "nm", 2),
            q(r["held_out_floor_nm"], "nm", 2),
            " / ".join(q(v, "", 2) for v in r["tip_path_rms_nm"]) + " nm",
            f"{q(r['held_out_pitch_std_raw_pct'], '%', 2)} → {q(r['held_out_pitch_std_corrected_pct'], '%', 2)}",
            q(all(r["stages_accepted"]) and r["plausible"]),
        ]
        for r in results(STEP_A_LATTICES)
    ]
    header = ["lattice", "turned on the stage", "true angle from x", "fitted", "error", "held-out residual"]
    header += ["its floor (true tip path)", "tip path x / y"]
    return Table(
        header + ["held-out pitch spread raw → corrected", "all stages kept, plausible"],
        rows,
        [STEP_A_LATTICES],
    )


def _timing_cells(r: dict, stages: str) -> list:
    """A step A benchmark run's total, compiling and compiled times, and its stages' (``stages``:
    ``"stage_seconds"`` of the first identification or ``"stage_seconds_compiled"``)."""
    times = [q(r[k], "s") for k in ("seconds", "compile_s", "seconds_compiled")]
    return times + [" · ".join(q(v, "", 1) for v in r[stages]) + " s"]


@table("bench_step_a")
def bench_step_a(results: Results) -> Table:
    m = results(BENCH_STEP_A)
    rows = []
    for name, r in _bench_runs(m).items():
        by_seed = r["path_x_rms_nm_by_seed"]
        rows.append(
            [
                name,
                *_timing_cells(r, "stage_seconds"),
                f"{q(statistics.median(by_seed), '', 2)} ({q(max(by_seed), '', 2)}) nm",
                " · ".join(q(v, "", 1) for v in r["stage_path_x_rms_nm"]) + " nm",
            ]
        )
    header = [
        "run",
        "total (first)",
        "compiling",
        "compiled",
        "stages",
        "tip path x rms: median (max) over scans",
    ]
    return Table(header + ["after each stage (first scan)"], rows, [BENCH_STEP_A])


@table("bench_step_a_jacobian")
def bench_step_a_jacobian(results: Results) -> Table:
    profile = results(BENCH_STEP_A)["jacobian_profile"]
    cpu = profile["parts"]
    rows = [[part, q(cpu[part]["median_s"], "s", 2), q(cpu[part]["compile_s"], "s")] for part in cpu]
    repeats = next(iter(cpu.values()))["repeats"]
    size = f"{count(profile['parameters'])} parameters, {count(profile['samples'])} samples; medians of {repeats}."
    return Table(["one forward-mode Jacobian of", "2-core CPU", "compiling"], rows, [BENCH_STEP_A], size)


@table("bench_step_a_gpu")
def bench_step_a_gpu(results: Results) -> Table:
    rows = []
    for run, device in (
        (GPU_STEP_A, "one NVIDIA H200"),
        (GPU_HOST_STEP_A, "2 CPU cores of the same machine"),
    ):
        (r,) = _bench_runs(results(run)).values()
        rows.append([device, *_timing_cells(r, "stage_seconds_compiled"), q(r["path_x_rms_nm"], "nm", 2)])
    header = ["device", "total (first)", "compiling", "compiled", "stages, compiled", "tip path x rms"]
    return Table(header, rows, [GPU_STEP_A, GPU_HOST_STEP_A])


# --- positioning (docs/positioning.md) -------------------------------------------------------

STAGE_COLS = (
    Col("targets", "_error_targets", "", 0),
    Col("median", "_error_median_nm", "nm"),
    Col("p95", "_error_p95_nm", "nm"),
    Col("worst", "_error_max_nm", "nm"),
    Col("scanning", "_scan_time_s", "s", 0),
)
STAGES = (
    ("open loop", "open_loop"),
    ("A", "A"),
    ("B without A (polynomial)", "B_polynomial"),
    ("B without A (pairwise, eq. 4-5 variant)", "B_pairwise"),
    ("A+B (polynomial)", "AB_polynomial"),
    ("A+B (pairwise, eq. 4-5 variant)", "AB_pairwise"),
    ("A+B+C", "ABC_polynomial"),
)


def stages_table(run: Run) -> Callable[[Results], Table]:
    """The ablation table of a ``jaxafm run``: errors per stage, true tip to true centre."""

    def make(results: Results) -> Table:
        rows = grid(results(run), STAGES, STAGE_COLS)
        return Table(["stage"] + [c.header for c in STAGE_COLS], rows, [run])

    return make


TABLES["paper_stages"] = stages_table(PAPER)
TABLES["paper_true_model_stages"] = stages_table(PAPER_TRUE)


def run_summary(run: Run) -> Callable[[Results], Table]:
    """Step C and the push of a ``jaxafm run``, and what step A and B cost."""

    def make(results: Results) -> Table:
        m = results(run)
        rows = [
            ("A+B+C within 0.1 R", q(m["ABC_within_0p1R_pct"], "%")),
            (
                "A+B+C error / R: median, worst",
                f"{q(m['ABC_error_over_radius_median'], '', 3)}, {q(m['ABC_error_over_radius_max'], '', 3)}",
            ),
            ("local scans verified", q(m["ABC_found_pct"], "%")),
            ("local scan lines, mean", q(m["ABC_lines_mean"], "", 2)),
            ("local scan time, mean", q(m["ABC_local_scan_s_mean"], "s")),
            ("push success (within 1 R of the goal)", q(m["push_success_pct"], "%")),
            ("push success after the first push", q(m.get("push_first_success_pct"), "%")),
            ("corrective pushes per particle", q(m.get("push_corrections_mean"), "", 2)),
            (
                "push miss: median, worst",
                f"{q(m['push_error_median_nm'], 'nm')}, {q(m['push_error_max_nm'], 'nm')}",
            ),
            (
                "landmarks found (B, A+B)",
                f"{count(m['B_landmarks_found'])}, {count(m['AB_landmarks_found'])} of "
                f"{count(m['landmarks_n'] ** 2)}",
            ),
            ("step A's identification", q(m["step_a_fit_s"] or None, "s")),
        ]
        return Table(["", "value"], facts(rows), [run])

    return make


TABLES["paper_summary"] = run_summary(PAPER)
TABLES["paper_true_model_summary"] = run_summary(PAPER_TRUE)


@table("paper_converged")
def paper_converged(results: Results) -> Table:
    """The paper run with step A stopped at its step limits, run until it converges, and with the
    true scanner as the model: what each puts where."""
    runs = (PAPER, PAPER_CONVERGED, PAPER_TRUE)
    m = [results(run) for run in runs]
    nm = lambda key: [q(r[key], "nm") for r in m]
    rows = [
        ["A: median", *nm("A_error_median_nm")],
        ["A: worst", *nm("A_error_max_nm")],
        ["A+B (polynomial): median", *nm("AB_polynomial_error_median_nm")],
        ["A+B (polynomial): worst", *nm("AB_polynomial_error_max_nm")],
        ["A+B+C error / R: worst", *[q(r["ABC_error_over_radius_max"], "", 3) for r in m]],
        ["push miss: median", *nm("push_error_median_nm")],
        ["push miss: worst", *nm("push_error_max_nm")],
        ["step A's identification", *[q(r["step_a_fit_s"] or None, "s") for r in m]],
    ]
    header = ["", "step A stopped at 30 · 60 · 100 steps", "step A converged", "the true scanner"]
    note = "Errors: true tip to true particle centre; times as each run recorded them (the converged run on one core)."
    return Table(header, rows, list(runs), note)


def push_fields(run: Run, folder: str) -> Callable[[Results], Table]:
    """``experiments/push_study.py``: A+B, step C and the push per particle field, then all."""

    def make(results: Results) -> Table:
        total = results(run)
        fields = [Run(f"{folder}/field_{i}/metrics.json", run.command) for i in range(total["fields"])]
        rows = []
        for i, f in enumerate(fields):
            m = results(f)
            rows.append(
                [
                    f"field {i}",
                    q(m["AB_polynomial_error_median_nm"], "nm"),
                    q(m["AB_polynomial_error_max_nm"], "nm"),
                    q(m["ABC_within_0p1R_pct"], "%"),
                    q(m["ABC_error_over_radius_max"], "R", 3),
                    q(m["push_success_pct"], "%"),
                    q(m["push_error_max_nm"], "nm"),
                ]
            )
        rows.append(
            [
                f"all {count(total['push_trials'])} targets",
                "–",
                q(total["AB_polynomial_error_max_nm"], "nm"),
                q(total["ABC_within_0p1R_pct"], "%"),
                q(total["ABC_error_over_radius_max"], "R", 3),
                q(total["push_success_pct"], "%"),
                q(total["push_error_max_nm"], "nm"),
            ]
        )
        header = [
            "particles",
            "A+B median",
            "A+B worst",
            "A+B+C within 0.1 R",
            "worst",
            "push success",
            "worst miss",
        ]
        return Table(header, rows, [run])

    return make


TABLES["push_study"] = push_fields(PUSH_STUDY, "push_study")
TABLES["push_study_0_90"] = push_fields(PUSH_0_90, "push_study_0_90")
TABLES["push_study_true_model"] = push_fields(PUSH_TRUE, "push_study_true_model")


@table("minor_loops")
def minor_loops(results: Results) -> Table:
    rows = [
        [q(r["sweep_v"], "V")]
        + [
            f"{q(r['true_nm'][a], '', 0)} / {q(r['fit_nm'][a], '', 0)} nm ({q(r['ratio'][a], '', 3)})"
            for a in (0, 1)
        ]
        for r in results(MINOR_LOOPS)
    ]
    return Table(["sweep", "x: true / fitted (ratio)", "y: true / fitted (ratio)"], rows, [MINOR_LOOPS])


@table("drift_tracking")
def drift_tracking(results: Results) -> Table:
    r = results(DRIFT_TRACKING)
    methods = ("none", "static field", "tracker with drift")
    rows = []
    for truth in ("generalised_pi", "preisach"):
        for method in methods:
            m = r[truth][method]
            miss = m["miss_nm"]
            rows.append(
                [
                    truth,
                    method,
                    q(statistics.median(miss[:10]), "nm"),
                    q(statistics.median(miss[10:]), "nm"),
                    q(max(miss[10:]), "nm"),
                    q(m.get("miss_over_sd_rms_after_10"), "", 2) if method != "none" else "–",
                    ", ".join(q(v, "", 3) for v in m["velocity_nm_s"]) + " nm/s"
                    if "velocity_nm_s" in m
                    else "–",
                ]
            )
    header = [
        "true scanner",
        "refinement",
        "moves 1–10",
        "moves 11–100",
        "worst 11–100",
        "rms miss / sd",
        "drift found",
    ]
    note = (
        f"Median and worst miss of the true tip over {r['moves']} moves; the truth drifts at "
        f"({q(r['velocity_truth_nm_s'][0], '', 1)}, {q(r['velocity_truth_nm_s'][1], '', 1)}) nm/s, in the "
        f"commands' units ({q(r['velocity_commands_need_nm_s'][0], '', 2)}, "
        f"{q(r['velocity_commands_need_nm_s'][1], '', 2)}) nm/s for the model's x gain {r['gain']}."
    )
    return Table(header, rows, [DRIFT_TRACKING], note)


# --- studies (docs/study.md) -----------------------------------------------------------------

STUDY_COLS = (
    Col("ran", "_ran_pct", "%"),
    Col("median", "_error_median_nm", "nm"),
    Col("p95", "_error_p95_nm", "nm"),
    Col("p99", "_error_p99_nm", "nm"),
    Col("worst", "_error_max_nm", "nm"),
    Col("success", "_success_pct", "%"),
    Col("scanning", "_scan_time_s", "s", 0),
)


def study_stages(run: Run) -> Callable[[Results], Table]:
    """A study's table per stage: errors over the trials that ran, success over all trials."""

    def make(results: Results) -> Table:
        rows = grid(results(run), (("A+B", "AB"), ("A+B+C", "ABC"), ("push", "push")), STUDY_COLS)
        return Table(["stage"] + [c.header for c in STUDY_COLS], rows, [run])

    return make


def study_summary(run: Run, wall: bool = True) -> Callable[[Results], Table]:
    """A study's size, time, and what its step C and push did beyond the stage table. ``wall``:
    whether the file's ``wall_s`` is the study's own (not that of a call that only summarised
    its stored chunks)."""

    def make(results: Results) -> Table:
        m = results(run)
        rows = [
            (
                "trials, scanners",
                f"{count(m['trials'])} on {count(m['scanners'])} ({count(m['trials_per_scanner'])} each)",
            ),
            ("wall time of the command", q(m["wall_s"] / 60, "min") if wall else "–"),
            ("local scans verified", q(m["ABC_found_pct"], "%")),
            *(
                [
                    (
                        "A+B+C within 0.1 R that the tip's position noise allows",
                        q(m["ABC_noise_ceiling_pct"], "%"),
                    )
                ]
                if "ABC_noise_ceiling_pct" in m
                else []
            ),
            ("local scan lines, mean", q(m["ABC_lines_mean"], "", 2)),
            ("push success after the first push", q(m["push_first_success_pct"], "%")),
            ("corrective pushes per trial", q(m["push_corrections_mean"], "", 2)),
        ]
        return Table(["", "value"], facts(rows), [run])

    return make


def failure_modes(run: Run) -> Callable[[Results], Table]:
    """Why a study's trials failed, stage by stage (a stage's reasons exclusive)."""

    def make(results: Results) -> Table:
        m = results(run)
        rows = [
            [stage, reason, f"{count(n)} ({q(100 * n / m['trials'], '%')})"]
            for stage, reasons in m["failure_modes"].items()
            for reason, n in reasons.items()
            if n
        ]
        return Table(["stage", "failure", "trials"], rows, [run], "Reasons that no trial met are left out.")

    return make


def study_learning(run: Run) -> Callable[[Results], Table]:
    """A study's A+B error (median) per scanner before its moves learnt from step C's finds and after."""

    def make(results: Results) -> Table:
        m = results(run)["AB_learning"]
        learnt = m["per_scanner_learnt"]
        rows = [
            [s, q(e[0], "nm")]
            + ([q(learnt[s], "nm"), q(learnt[s] / e[0], "", 2)] if math.isfinite(learnt[s]) else ["–", "–"])
            for s, e in m["per_scanner"].items()
        ]
        never = m["unlearnt_scanners"]
        note = (
            f"Rounds of {m['round_trials']} trials; learnt: the trials aimed by 10 finds or more. Over the "
            f"{count(len(m['learnt_scanners']))} scanners that reached 10 finds: "
            f"{q(m['first_round_median_nm'], 'nm')} median in their first rounds (no finds), "
            f"{q(m['learnt_median_nm'], 'nm')} once learnt (ratio {q(m['learnt_ratio'], '', 2)})"
            + (f"; never reached 10 finds: scanner {', '.join(map(str, never))}." if never else ".")
        )
        return Table(["scanner", "A+B first round", "A+B learnt", "ratio"], rows, [run], note)

    return make


def study_truth_classes(run: Run) -> Callable[[Results], Table]:
    """A study's success per stage on the scanners of each truth class."""

    def make(results: Results) -> Table:
        m = results(run)["truth_classes"]
        rows = [
            [c, count(v["trials"])] + [q(v[f"{k}_success_pct"], "%") for k in ("AB", "ABC", "push")]
            for c, v in m.items()
        ]
        return Table(
            ["truth class", "trials", "A+B", "A+B+C", "push"], rows, [run], "Success over every trial."
        )

    return make


TABLES["study_classes_per_class"] = study_truth_classes(STUDY_CLASSES)
TABLES["study_classes_0_90_condition_y_per_class"] = study_truth_classes(STUDY_CLASSES_0_90_CY)
TABLES["study_classes_0_90_wide_loop_per_class"] = study_truth_classes(STUDY_CLASSES_WIDE_LOOP)
TABLES["study_classes_speed_per_class"] = study_truth_classes(STUDY_CLASSES_SPEED)
for _name, _run, _wall in (
    ("study", STUDY, True),
    ("study_wide", STUDY_WIDE, True),
    ("study_classes", STUDY_CLASSES, True),
    ("study_classes_0_90_condition_y", STUDY_CLASSES_0_90_CY, True),
    ("study_classes_0_90_wide_loop", STUDY_CLASSES_WIDE_LOOP, True),
    ("study_classes_speed", STUDY_CLASSES_SPEED, True),
    ("study_speed", STUDY_SPEED, True),
):
    TABLES[f"{_name}_stages"] = study_stages(_run)
    TABLES[f"{_name}_summary"] = study_summary(_run, _wall)
    TABLES[f"{_name}_failures"] = failure_modes(_run)
for _name, _run in (("study", STUDY), ("study_wide", STUDY_WIDE)):
    TABLES[f"{_name}_learning"] = study_learning(_run)


def study_pushes(other: Run, header: str) -> Callable[[Results], Table]:
    """study.yaml beside ``other``, a study that differs in its pushes alone: what the push did."""

    def make(results: Results) -> Table:
        runs = (STUDY, other)
        return Table(
            ["", "pushes as commanded (study.yaml)", header],
            _push_rows([results(r) for r in runs]),
            list(runs),
        )

    return make


def _push_rows(m: list) -> list:
    """What the pushes of the studies ``m`` (their metrics) did, one column a study."""
    fails = [f["failure_modes"]["push"] for f in m]
    rows = [
        ["first push within 1 R"] + [q(f["push_first_success_pct"], "%") for f in m],
        ["within 1 R after the checks"] + [q(f["push_success_pct"], "%") for f in m],
        ["corrective pushes per trial"] + [q(f["push_corrections_mean"], "", 2) for f in m],
        ["push error, median"] + [q(f["push_error_median_nm"], "nm") for f in m],
        ["push error, p95"] + [q(f["push_error_p95_nm"], "nm") for f in m],
    ]
    return rows + [
        [f"failed: {k}"] + [count(f.get(k, 0)) for f in fails]
        for k in fails[0]
        if any(f.get(k) for f in fails)
    ]


TABLES["study_push_learning"] = study_pushes(STUDY_PUSHES, "pushes that learn")
TABLES["study_push_lead_in"] = study_pushes(STUDY_LEAD_IN, "pushes through a 500 nm lead-in")


@table("study_learning_cost")
def study_learning_cost(results: Results) -> Table:
    """study_no_learning.yaml beside study.yaml, run one after the other: what learning while
    positioning costs in time and what it changes."""
    runs = (STUDY_NO_LEARNING, STUDY)
    m = [results(r) for r in runs]
    rows = [
        ["wall time of the command"] + [q(f["wall_s"] / 60, "min") for f in m],
        [f"of it, step A and the surveys of the {count(m[0]['scanners'])} scanners"]
        + [q(f["step_a_and_surveys_s"], "s", 0) for f in m],
        ["of it, the trials"] + [q(f["trials_s"], "s", 0) for f in m],
        ["A+B median"] + [q(f["AB_error_median_nm"], "nm") for f in m],
        ["A+B p95"] + [q(f["AB_error_p95_nm"], "nm") for f in m],
        ["A+B within 0.1 R"] + [q(f["AB_success_pct"], "%") for f in m],
        ["A+B+C within 0.1 R"] + [q(f["ABC_success_pct"], "%") for f in m],
        ["local scan lines, mean"] + [q(f["ABC_lines_mean"], "", 2) for f in m],
        ["push within 1 R after the checks"] + [q(f["push_success_pct"], "%") for f in m],
    ]
    return Table(["", "without learning", "learning from step C's finds (study.yaml)"], rows, list(runs))


def position_coverage(run: Run) -> Callable[[Results], Table]:
    """A study's A+B misses against the spread its tracker predicted: coverage at 50 and 90 %."""

    def make(results: Results) -> Table:
        c = results(run)["AB_position_coverage"]
        at = {level: i for i, level in enumerate(c["levels"])}
        what = {"true": "the true A+B error", "find": "step C's find about the aim (software's frame)"}
        trials = {"all": "every trial", "learnt": "aimed by 10 finds or more"}
        rows = [
            [
                what[kind],
                trials[name],
                count(v["trials"]),
                q(v["sd_median_nm"], "nm"),
                q(v["miss_over_sd_median"], "", 2),
                q(v["covered_pct"][at[0.5]], "%"),
                q(v["covered_pct"][at[0.9]], "%"),
            ]
            for kind in what
            for name in trials
            for v in [c[kind][name]]
        ]
        header = [
            "miss",
            "trials",
            "n",
            "predicted sd, median",
            "miss / sd, median",
            "within 50 %",
            "within 90 %",
        ]
        return Table(header, rows, [run], "Calibrated: 50 % and 90 %; miss / sd 1.18 at the median.")

    return make


TABLES["study_position_coverage"] = position_coverage(STUDY)


def _paths_run(folder: str, line_rate: Optional[float] = None) -> Run:
    """``experiments/step_a_study_paths.py``'s file for the study ``folder`` (at ``line_rate`` Hz on
    the 0° scan instead of the study's own first scan)."""
    suffix, option = (
        ("", "") if line_rate is None else (f"_0deg_{line_rate:g}Hz", f" --line-rate {line_rate:g}")
    )
    return Run(
        f"step_a_study_paths/{folder}{suffix}.json",
        f"python experiments/step_a_study_paths.py experiments/results/{folder}{option}",
    )


def step_a_paths(folder: str, config: str) -> Callable[[Results], Table]:
    """Each scanner's step A model in the study ``folder`` against the simulated true tip path."""
    paths = _paths_run(folder)
    info = Run(f"{folder}/scanners.json", f"jaxafm study configs/{config}")

    def make(results: Results) -> Table:
        scanners = results(info)
        rows = [
            [
                str(row["scanner"]),
                q(100 * scanners[str(row["scanner"])]["loop_width"], "%"),
                q(100 * scanners[str(row["scanner"])]["coupling"], "%", 2),
            ]
            + ([q(v, "nm", 2) for v in row["path_rms_nm"]] if row["path_rms_nm"] else ["refused", "refused"])
            + [row["right_matching"]]
            for row in results(paths)["scanners"]
        ]
        note = (
            "Tip path of step A's model less the simulator's true one over the calibration scan (trace and "
            "retrace), rms after the one rigid shift no image sees. Loop width: % of the range; coupling: x "
            "from y (y from x is −0.6 of it). Right matching: which of the matchings of the retrace's lattice "
            "indices that step A tries at the line reversal, in its order, puts trace and retrace on the same "
            "true sites (none: none of them)."
        )
        head = ["scanner", "loop width", "coupling", "x", "y", "right matching"]
        return Table(head, rows, [paths, info], note)

    return make


TABLES["study_step_a_paths"] = step_a_paths("study", "study.yaml")
TABLES["study_wide_step_a_paths"] = step_a_paths("study_wide", "study_wide.yaml")
TABLES["study_0_90_stages"] = study_stages(STUDY_0_90)
TABLES["study_0_90_condition_y_stages"] = study_stages(STUDY_0_90_CY)
TABLES["study_0_90_condition_y_summary"] = study_summary(STUDY_0_90_CY)
TABLES["study_0_90_condition_y_failures"] = failure_modes(STUDY_0_90_CY)
TABLES["study_wide_0_90_condition_y_stages"] = study_stages(STUDY_WIDE_0_90_CY)
TABLES["study_wide_0_90_wide_loop_stages"] = study_stages(STUDY_WIDE_LOOP)
TABLES["study_wide_0_90_wide_loop_summary"] = study_summary(STUDY_WIDE_LOOP)
TABLES["study_wide_0_90_wide_loop_failures"] = failure_modes(STUDY_WIDE_LOOP)


def _trials(run: Run) -> Run:
    """The ``trials.csv`` beside a study's ``metrics.json``."""
    return Run(run.path.replace("metrics.json", "trials.csv"), run.command)


def _scanner_success(rows: list, scanner: str, tolerance_radii: float) -> tuple:
    """``(A+B+C, push)`` success (%) over one scanner's trials in a study's ``trials.csv`` rows: the
    error within 0.1 R, the push within ``tolerance_radii`` R (a trial without a result fails)."""
    mine = [r for r in rows if r["scanner"] == scanner]

    def within(key: str, radii: float) -> float:
        ok = [float(r[key]) <= radii * float(r["radius_nm"]) for r in mine if r[key] not in ("", "nan")]
        return 100 * sum(ok) / len(mine)

    return within("ABC_error_nm", 0.1), within("push_error_nm", tolerance_radii)


#: particle radius bands (nm) of :func:`pushes_by_class`
RADIUS_BANDS_NM = ((5.0, 10.0), (10.0, 20.0), (20.0, 50.0))


def pushes_by_class(run: Run) -> Callable[[Results], Table]:
    """A study's pushes per truth class, from its ``trials.csv`` and ``scanners.json``: the first
    push's miss along its direction (median, nm and % of the push), what the check at the goal saw
    of it (the particle's seen move along the push less the push, median), and the pushes within
    their tolerance per band of particle radius (:data:`RADIUS_BANDS_NM`)."""
    info = Run(run.path.replace("metrics.json", "scanners.json"), run.command)

    def make(results: Results) -> Table:
        rows, truth = results(_trials(run)), {k: v["truth_class"] for k, v in results(info).items()}
        tol = results(run)["push_tolerance_radii"]
        out = []
        for c in dict.fromkeys(truth.values()):
            mine = [_push_row(r, tol) for r in rows if truth[r["scanner"]] == c]
            seen = [p for p in mine if math.isfinite(p["checked"])]
            bands = []
            for lo, hi in RADIUS_BANDS_NM:
                band = [p["ok"] for p in mine if lo <= p["radius"] < hi]
                bands.append(f"{q(100 * sum(band) / len(band), '%')} ({count(len(band))})" if band else "–")
            out.append(
                [c, count(len(mine)), q(statistics.median(p["along"] for p in mine), "nm")]
                + [q(100 * statistics.median(p["along"] / p["push"] for p in mine), "%", 2)]
                + [q(statistics.median(p["checked"] for p in seen), "nm"), *bands]
            )
        head = ["truth class", "pushes", "first push: miss along it", "of the push", "the check saw"]
        head += [f"within tolerance, R {lo:g}–{hi:g} nm" for lo, hi in RADIUS_BANDS_NM]
        note = (
            "Medians over each class's first pushes (trials.csv); a miss along the push is positive when long; the "
            "check saw the particle's move along the push less the push, where it found the particle. Within "
            "tolerance: the push's final error within 1 R, by the particle's radius (the pushes in the band)."
        )
        return Table(head, out, [run], note)

    return make


def _push_row(r: dict, tolerance_radii: float) -> dict:
    """One ``trials.csv`` row's push: its distance, the first push's miss along it, what the check
    saw of that miss (NaN where it found nothing), the particle's radius and whether the push
    ended within ``tolerance_radii`` R."""
    num = lambda k: float(r[k]) if r[k] not in ("", "nan") else math.nan
    dx, dy, push = num("push_dx"), num("push_dy"), num("push_distance_nm")
    norm = math.hypot(dx, dy)
    seen = (num("push_seen_moved_x_nm") * dx + num("push_seen_moved_y_nm") * dy) / norm
    radius = num("radius_nm")
    ok = r["push_contact"] == "1" and num("push_error_nm") <= tolerance_radii * radius
    return {
        "push": push,
        "along": num("push_first_along_nm"),
        "checked": seen - push,
        "radius": radius,
        "ok": ok,
    }


TABLES["study_classes_speed_pushes"] = pushes_by_class(STUDY_CLASSES_SPEED)


def per_scanner_0_90(
    runs: tuple, names: tuple, path_folders: tuple, classes: bool = False, path_names: Optional[tuple] = None
) -> Callable[[Results], Table]:
    """Studies of one scanner family side by side, scanner by scanner: each of ``path_folders``'
    step A tip path (``experiments/step_a_study_paths.py``; a folder's name, or its file's
    ``Run``) and each of ``runs``' A+B+C and push success, the columns named by ``names`` (the
    paths' by ``path_names`` if given; the first of each group with its stage's name); with
    ``classes``, each scanner's truth class (the first run's ``scanners.json``)."""
    path_runs = [f if isinstance(f, Run) else _paths_run(f) for f in path_folders]
    info = Run(runs[0].path.replace("metrics.json", "scanners.json"), runs[0].command)

    def make(results: Results) -> Table:
        rows = [results(_trials(r)) for r in runs]
        paths = [{str(p["scanner"]): p["path_rms_nm"] for p in results(r)["scanners"]} for r in path_runs]
        truth = {s: v["truth_class"] for s, v in results(info).items()} if classes else {}
        out = []
        for s in sorted({r["scanner"] for r in rows[0]}, key=int):
            success = [
                _scanner_success(r, s, results(run)["push_tolerance_radii"]) for r, run in zip(rows, runs)
            ]
            out.append(
                [s]
                + ([truth[s]] if classes else [])
                + [q(max(p[s]), "nm") if p[s] else "refused" for p in paths]
                + [q(v[0], "%") for v in success]
                + [q(v[1], "%") for v in success]
            )
        group = lambda stage, labels: [f"{stage}, {labels[0]}", *labels[1:]]
        head = [
            "scanner",
            *(["truth class"] if classes else []),
            *group("step A path", path_names or names[: len(path_runs)]),
            *group("A+B+C", names),
            *group("push", names),
        ]
        note = (
            "Step A path: the larger of x and y rms of step A's tip path less the true one over the 0° calibration "
            "scan (runs from one step A config share their step A models). Success over each scanner's trials in "
            "the runs' trials.csv: A+B+C within 0.1 R, push within its tolerance (1 R)."
        )
        return Table(head, out, [*runs, *path_runs], note)

    return make


TABLES["study_0_90_per_scanner"] = per_scanner_0_90(
    (STUDY, STUDY_0_90, STUDY_0_90_CY),
    ("0°", "0° + 90°", "+ condition_y"),
    ("study", "study_0_90"),
)
TABLES["study_wide_0_90_per_scanner"] = per_scanner_0_90(
    (STUDY_WIDE, STUDY_WIDE_0_90_CY, STUDY_WIDE_LOOP),
    ("0°, wide_loop", "0° + 90°", "0° + 90°, wide_loop"),
    ("study_wide", "study_wide_0_90_condition_y", "study_wide_0_90_wide_loop"),
)
TABLES["study_classes_0_90_per_scanner"] = per_scanner_0_90(
    (STUDY_CLASSES, STUDY_CLASSES_0_90_CY, STUDY_CLASSES_WIDE_LOOP),
    ("0°", "0° + 90°", "+ wide_loop"),
    (
        "study_classes",
        _paths_run("study_classes", 2.0),
        "study_classes_0_90_condition_y",
        _paths_run("study_classes_0_90_condition_y", 2.0),
        "study_classes_0_90_wide_loop",
        _paths_run("study_classes_0_90_wide_loop", 2.0),
    ),
    classes=True,
    path_names=("0°, 1 Hz", "2 Hz", "0° + 90°, 1 Hz", "2 Hz", "+ wide_loop, 1 Hz", "2 Hz"),
)
TABLES["study_classes_speed_per_scanner"] = per_scanner_0_90(
    (STUDY_CLASSES_WIDE_LOOP, STUDY_CLASSES_SPEED),
    ("1 Hz", "1 and 2 Hz"),
    (
        "study_classes_0_90_wide_loop",
        _paths_run("study_classes_0_90_wide_loop", 2.0),
        "study_classes_speed",
        _paths_run("study_classes_speed", 2.0),
    ),
    classes=True,
    path_names=("1 Hz, on the 1 Hz scan", "2 Hz scan", "1 and 2 Hz, on the 1 Hz scan", "2 Hz scan"),
)


STEP_C_CONDITIONING = Run(
    "step_c_conditioning/study_0_90_scanner_14.json", "python experiments/step_c_conditioning.py"
)


@table("step_c_conditioning")
def step_c_conditioning(results: Results) -> Table:
    """Step C's miss on one scanner with step A's model replaced part by part by the truth."""
    m = results(STEP_C_CONDITIONING)
    rows = [
        [name, q(v["within_0p1R_pct"], "%"), q(v["lines_mean"], "", 2)]
        + [q(x, "nm", 2) for x in v["all"]["mean_nm"] + v["all"]["rms_nm"]]
        + [count(v["three_lines"]["trials"])]
        for name, v in m["variants"].items()
    ]
    setup = m["setup"]
    note = (
        f"Scanner {setup['scanner']}'s first {setup['trials']} trials of {setup['study']}, A+B+C as the study runs "
        "them; the models without drift and noise, which no model knows. Miss: the true tip after step C less "
        "the particle's true centre."
    )
    head = ["step A's model", "within 0.1 R", "lines", "mean x", "mean y", "rms x", "rms y", "in 3 lines"]
    return Table(head, rows, [STEP_C_CONDITIONING], note)


@table("study_push_gate")
def study_push_gate(results: Results) -> Table:
    """The pushes gated by their odds: read from study.yaml's pushes (all made), and the gated run."""
    plain, gated = results(STUDY), results(STUDY_GATE)
    rows = [
        [
            f"study.yaml's pushes, withheld below {q(100 * g['min_odds'], '%', 0)}",
            q(g["made_pct"], "%"),
            q(g["success_of_made_pct"], "%"),
            "–",
        ]
        for g in plain["push_gate"]
    ]
    rows.append(
        [
            "study.yaml, every push made",
            "100.0 %",
            q(plain["push_success_pct"], "%"),
            q(plain["push_success_pct"], "%"),
        ]
    )
    rows.append(
        [
            f"study_push_gate.yaml: withheld below {q(100 * gated['push_gate_min_odds'], '%', 0)} in the study",
            q(100 - gated["push_withheld_pct"], "%"),
            q(gated["push_success_of_made_pct"], "%"),
            q(gated["push_success_pct"], "%"),
        ]
    )
    header = ["pushes", "made", "success of those made", "success over every trial"]
    return Table(header, rows, [STUDY, STUDY_GATE])


#: the truth class of each scanner of the study of record
STUDY_CLASSES_SPEED_SCANNERS = Run("study_classes_speed/scanners.json", STUDY_CLASSES_SPEED.command)
PUSH_SHORTFALL_CLASSES = Run(
    "push_shortfall/shortfall_study_classes_speed_scanners_0_1_2_3_5_9_13.json",
    "python experiments/push_shortfall.py --config configs/study_classes_speed.yaml --scanners 0 1 2 3 5 9 13",
)


def push_shortfall(run: Run, classes: Optional[Run] = None) -> Callable[[Results], Table]:
    """Each study scanner's push-like move (``experiments/push_shortfall.py``): the true travel's
    error per direction, and what a check arriving at the goal sees of it; with ``classes`` (a
    study's ``scanners.json``), each scanner's truth class."""

    def make(results: Results) -> Table:
        m = results(run)
        truth = {k: v["truth_class"] for k, v in results(classes).items()} if classes else {}
        ways = ("+x", "-x", "+y", "-y")
        rows = [
            [s]
            + ([truth[s]] if classes else [])
            + [q(100 * r[w]["travel_error"], "%") for w in ways]
            + [q(r[w]["seen_short_nm"], "nm") for w in ways]
            for s, r in m["scanners"].items()
        ]
        header = ["scanner"] + (["truth class"] if classes else [])
        header += [f"travel {w}" for w in ways] + [f"seen short {w}" for w in ways]
        return Table(header, rows, [run])

    return make


TABLES["push_shortfall"] = push_shortfall(PUSH_SHORTFALL)
TABLES["push_shortfall_truth_model"] = push_shortfall(
    Run(
        "push_shortfall/shortfall_study_classes_speed_scanners_0_1_2_3_5_9_13_truth_model.json",
        PUSH_SHORTFALL_CLASSES.command + " --truth-model",
    ),
    STUDY_CLASSES_SPEED_SCANNERS,
)
PUSH_LEAD_IN = Run(
    "push_shortfall/shortfall_lead_in_500.json", "python experiments/push_shortfall.py --lead-in 500"
)


@table("push_lead_in")
def push_lead_in(results: Results) -> Table:
    """study.yaml's scanners' push-like moves, the start backed straight from the place (as the
    study's push backs from the particle) or reached through a 500 nm lead-in along the move: per
    direction, medians over the scanners of the travel's error and of where the move truly
    starts and ends against where it should, from the tip's true place (the frame a particle
    there is found in)."""
    runs = (PUSH_SHORTFALL, PUSH_LEAD_IN)
    rows = []
    for w in ("+x", "-x", "+y", "-y"):
        for run, how in zip(runs, ("backed straight", "500 nm lead-in")):
            r = [v[w] for v in results(run)["scanners"].values()]
            med = lambda k: statistics.median(x[k] for x in r)
            worst = max((x["end_error_nm"] for x in r), key=abs)
            rows.append(
                [
                    w,
                    how,
                    q(100 * med("travel_error"), "%"),
                    q(med("start_error_nm"), "nm"),
                    q(med("end_error_nm"), "nm"),
                    q(worst, "nm"),
                ]
            )
    header = ["push", "start reached", "travel error, median", "start, median", "end, median", "end, worst"]
    return Table(header, rows, list(runs))


TABLES["push_shortfall_classes_speed"] = push_shortfall(PUSH_SHORTFALL_CLASSES, STUDY_CLASSES_SPEED_SCANNERS)


@table("bench_study")
def bench_study(results: Results) -> Table:
    m = results(BENCH_STUDY)
    rate = {(r["batch"], r["devices"]): r["trials_per_min"] for r in m["bc_fixed_model"]}
    batches = sorted({b for b, _ in rate})
    rows = [[count(b), count(rate.get((b, 1))), count(rate.get((b, 2)))] for b in batches]
    return Table(["batch", "1 device", "2 host devices"], rows, [BENCH_STUDY], "Trials per minute.")


def devices(n: int) -> str:
    """``n`` host devices, in words."""
    return f"{n} device" + ("s" if n > 1 else "")


#: The bench's names of its parts, where they need words.
PARTS = {"before: inverse per sample + twin run": "step A's inverse sample by sample, the twin run again"}


def bench_extras(run: Run) -> Callable[[Results], Table]:
    """The study bench beside its batches: the loop, the inverse sample by sample, the costs."""

    def make(results: Results) -> Table:
        m = results(run)
        split = m["batch_split"]
        rows = [
            (
                "best batch",
                f"{count(m['best']['trials_per_min'])} trials/min (batch {count(m['best']['batch'])}, "
                f"{devices(m['best']['devices'])})",
            ),
            ("one trial per call, Python loop", f"{count(m['python_loop']['trials_per_min'])} trials/min"),
            (
                "best batch, step A's inverse sample by sample",
                f"{count(m['old_inverse']['trials_per_min'])} trials/min",
            ),
            ("warm-up of the best batch (compiling)", q(m["best"]["warm_up_s"], "s", 0)),
            (
                "local scan lines, mean; trials that search again",
                f"{q(m['best']['lines_mean'], '', 2)}; {q(m['best']['second_pass_pct'], '%')}",
            ),
            (
                f"one batch of {count(split['batch'])}: first pass, second pass, rest",
                f"{q(split['first_pass_s'], 's', 2)}, {q(split['second_pass_s'], 's', 2)}, "
                f"{q(split['total_s'] - split['first_pass_s'] - split['second_pass_s'], 's', 2)}",
            ),
            (
                "where each particle shows in the survey: coarse to fine, every pixel",
                f"{q(split['image_position_s'], 's', 3)}, {q(split['image_position_every_pixel_s'], 's', 3)} "
                f"(positions equal to {q(split['image_position_max_difference_nm'], 'nm')})",
            ),
        ]
        rows += [
            (f"per drive sample and trial: {PARTS.get(part, part)}", q(v["us"], "µs", 3, tiny=True))
            for part, v in m["us_per_sample"].items()
        ]
        if "full_pipeline" in m:
            full = m["full_pipeline"]
            rows.append(
                (
                    f"a new scanner: step A, surveys, then {count(full['trials'])} trials",
                    f"{q(full['prepare_s'], 's', 0)} (step A {q(full['step_a_fit_s'], 's', 0)}) + "
                    f"{q(full['trials_s'], 's', 0)}: {count(full['trials_per_min'])} trials/min",
                )
            )
        return Table(["", "value"], facts(rows), [run])

    return make


TABLES["bench_study_extras"] = bench_extras(BENCH_STUDY)
TABLES["bench_study_gpu"] = bench_extras(GPU_STUDY)


# --- diagnosis (docs/diagnosis.md, docs/real_data.md) ----------------------------------------


UNITS = (  # a fitted size's name ends in its unit: (ending, how it prints)
    ("_per_nm", lambda v: f"{v:.2g} /nm".replace("-", "−")),
    ("_nm_per_s", lambda v: q(v, "nm/s", 3)),
    ("_nm2_per_s", lambda v: f"{v:.3g} nm²/s".replace("-", "−")),
    ("_per_decade", lambda v: q(100 * v, "%/decade", 2)),
    ("_hz", lambda v: q(v, "Hz", 0)),
    ("_s", lambda v: q(1e3 * v, "ms", 3) if abs(v) < 1 else q(v, "s", 2)),
    ("_nm", lambda v: q(v, "nm", 1)),
    ("", lambda v: f"{v:.3g}".replace("-", "−")),
)


def _fitted(fitted: dict, nominal: dict) -> str:
    """The sizes a candidate's fit adds to the nominal's, in the units their names give."""

    def one(name: str, v: float) -> str:
        return next(show(v) for end, show in UNITS if name.endswith(end))

    parts = []
    for name, v in fitted.items():
        if name in nominal:
            continue
        values = v if isinstance(v, list) else [v]
        label = re.sub(r"_(per_nm|nm_per_s|nm2_per_s|per_decade|hz|s|nm)$", "", name).replace("_", " ")
        parts.append(f"{label} {' / '.join(one(name, x) for x in values)}")
    return "; ".join(parts)


def _candidate(c: dict, kind: str, nominal: dict) -> list[Cell]:
    return [
        f"{kind} {c['effect']}" + (f" (on {s})" if (s := c.get("judged_on")) else ""),
        q(c["heldout_gap_after_nm"], "nm", 2),
        q(c["shrink_pct"], "%"),
        q(c["delta_bic"], "", 0),
        q(c["significant"]),
        _fitted(c["fitted"], nominal["fitted"]) or "–",
    ]


def diagnosis_table(run: Run) -> Callable[[Results], Table]:
    """One diagnosis: the nominal model, the shapes tried, each candidate effect, the verdict."""

    def make(results: Results) -> Table:
        d = results(run)
        nominal = d["nominal"]
        rows: list[list[Cell]] = [
            [f"nominal: {nominal['model']}", q(nominal["heldout_gap_nm"], "nm", 2), "–", "–", "–", "–"]
        ]
        rows += [_candidate(c, "shape", nominal) for c in d.get("hysteresis_shapes", [])]
        rows += [_candidate(c, "effect", nominal) for c in d["candidates"]]
        v = d["verdict"]
        rows.append(
            [
                f"**verdict: {v['text'] or 'no significant unmodelled effect'}**",
                q(v["heldout_gap_after_nm"], "nm", 2),
                q(v["total_shrink_pct"], "%"),
                "",
                "",
                "",
            ]
        )
        header = ["model", "held-out gap", "shrink", "ΔBIC", "significant", "fitted"]
        return Table(
            header,
            rows,
            [run],
            "The shrink is against the model each row was added to; the verdict's, from the nominal.",
        )

    return make


TABLES["diagnose_simulated"] = diagnosis_table(DIAGNOSE_SIMULATED)
TABLES["diagnose_scans"] = diagnosis_table(DIAGNOSE_SCANS)
TABLES["diagnose_scans_lattice"] = diagnosis_table(DIAGNOSE_SCANS_LATTICE)
for _name, _run in DIAGNOSE_REAL:
    TABLES["diagnose_" + _run.path.split("/")[1]] = diagnosis_table(_run)


@table("diagnose_real")
def diagnose_real(results: Results) -> Table:
    rows = []
    for case, run in DIAGNOSE_REAL:
        d = results(run)
        shapes = [c for c in d.get("hysteresis_shapes", []) if c["significant"]]
        effects = [c for c in d["candidates"] if c["significant"]]
        rows.append(
            [
                case,
                q(d["nominal"]["heldout_gap_nm"], "nm", 0),
                "; ".join(
                    f"{c['effect']} {q(c['heldout_gap_after_nm'], 'nm', 0)} ({q(c['shrink_pct'], '%')})"
                    for c in shapes
                )
                or "–",
                "; ".join(
                    f"{c['effect']} {q(c['heldout_gap_after_nm'], 'nm', 0)} ({q(c['shrink_pct'], '%')})"
                    for c in effects
                )
                or "–",
                f"**{d['verdict']['text'] or 'none'}**",
            ]
        )
    header = [
        "data, nominal model",
        "nominal held-out gap",
        "significant shapes",
        "significant effects on it",
    ]
    return Table(header + ["verdict"], rows, [run for _, run in DIAGNOSE_REAL])


@table("diagnose_real_noise")
def diagnose_real_noise(results: Results) -> Table:
    rows = []
    for case, run in DIAGNOSE_REAL[:4]:
        m = results(Run(run.path.replace("diagnosis.json", "metrics.json"), run.command))
        rows.append(
            [
                case,
                q(m["noise_floor_nm"], "nm"),
                q(m["nominal_heldout_gap_above_floor_nm"], "nm", 0),
                q(m["final_heldout_gap_above_floor_nm"], "nm", 0),
            ]
        )
    header = ["record, nominal model", "noise floor", "nominal gap above it", "final gap above it"]
    return Table(
        header,
        rows,
        [Run(r.path.replace("diagnosis.json", "metrics.json"), r.command) for _, r in DIAGNOSE_REAL[:4]],
    )


def _cases(results: Results, run: Run, kind: str) -> list:
    return [r for r in results(run) if r.get("data", "record") == kind]


def withheld_table(cases_run: Run, summary_run: Run, kind: str) -> Callable[[Results], Table]:
    """Per withheld effect of one kind of data: magnitudes, top-1 and median shrink per level."""

    def make(results: Results) -> Table:
        summary = results(summary_run)
        cases = _cases(results, cases_run, kind)
        levels = ("low", "middle", "high")
        rows = []
        for effect, mags in summary["magnitudes"][kind].items():
            unit = summary["units"][kind][effect]
            per = [[c for c in cases if c["truth"] == effect and c["level"] == lv] for lv in levels]
            rows.append(
                [
                    effect.replace("_", " "),
                    " / ".join(f"{m:g}" for m in mags) + f" {unit}",
                    ", ".join(f"{sum(c['verdict'] == effect for c in sel)}/{len(sel)}" for sel in per),
                    " / ".join(
                        q(statistics.median(c["verdict_shrink_pct"] for c in sel), "", 0) for sel in per
                    )
                    + " %",
                ]
            )
        controls = [c for c in cases if c["truth"] is None]
        largest = max(max((r[1] for r in c["ranking"]), default=0.0) for c in controls)
        rows.append(
            [
                "none (controls)",
                "–",
                f"{sum(c['verdict'] is None for c in controls)}/{len(controls)} no significant effect",
                f"largest shrink of any candidate {q(largest, '%')}",
            ]
        )
        header = ["withheld effect", "low / middle / high magnitude", "top-1 (low, middle, high)"]
        return Table(header + ["median shrink (low / middle / high)"], rows, [cases_run])

    return make


TABLES["withheld_record"] = withheld_table(RECORDS_CASES, RECORDS, "record")
TABLES["withheld_scans"] = withheld_table(WITHHELD_CASES, WITHHELD, "scans")
TABLES["withheld_lattice"] = withheld_table(WITHHELD_CASES, WITHHELD, "lattice")


@table("withheld_summary")
def withheld_summary(results: Results) -> Table:
    rows = []
    for label, run, kind in (
        ("records", RECORDS, "record"),
        ("scan sets", WITHHELD, "scans"),
        ("2-D lattice scan sets", WITHHELD, "lattice"),
    ):
        s = results(run)[kind]
        rows.append(
            [
                label,
                q(s["top1_accuracy_middle_pct"], "%", 0),
                f"{count(s['controls_flagged'])} of {count(s['controls'])}",
                q(s["median_shrink_pct"], "%"),
                q(s["median_shrink_middle_pct"], "%"),
                q(s.get("median_shrink_above_noise_pct"), "%"),
                q(s.get("median_rms_shrink_pct"), "%"),
                q(s["seconds_per_case_median"], "s"),
            ]
        )
    header = [
        "data",
        "top-1, middle magnitude",
        "controls flagged",
        "median shrink",
        "at the middle magnitude",
    ]
    note = (
        "Median shrink: of the held-out gap, the verdict's (0 where none), over the cases with a withheld "
        "effect; above the noise: the same on the gaps' parts above the records' white noise (its standard "
        "deviation per axis, taken off in quadrature)."
    )
    return Table(
        header + ["above the noise", "per crossing, noise included", "per case"],
        rows,
        [RECORDS, WITHHELD],
        note,
    )


def _wrong(confusion: dict, labels: list) -> int:
    """Cases given an effect other than their own (a miss, "none", is not wrong)."""
    none = labels.index("none")
    return sum(
        n
        for m in confusion.values()
        for i, row in enumerate(m)
        for j, n in enumerate(row)
        if j not in (i, none)
    )


def _share(pct: float, n: int) -> str:
    """``k/n (pct %)`` for a percentage of ``n`` cases."""
    return f"{round(pct * n / 100)}/{n} ({q(pct, '%', 0)})"


@table("independent_check")
def independent_check(results: Results) -> Table:
    m = results(INDEPENDENT)
    rows = []
    for label, key in (
        ("nominal class = truth's", "same"),
        ("nominal class ≠ truth's", "different"),
        ("all", "all"),
    ):
        s = m[key]
        top1 = [_share(s[f"top1_{lv}_pct"], s[f"cases_{lv}"]) for lv in ("low", "middle", "high")]
        rows.append(
            [
                label,
                *top1,
                f"{s['controls_flagged']}/{s['controls']}",
                count(_wrong(s["confusion"], m["labels"])),
            ]
        )
    header = ["", "top-1 low", "top-1 middle", "top-1 high", "controls flagged", "cases given a wrong effect"]
    return Table(header, rows, [INDEPENDENT])


@table("independent_shrink")
def independent_shrink(results: Results) -> Table:
    m = results(INDEPENDENT)["all"]
    by_level = m["median_shrink_and_ceiling_by_level_pct"]
    rows = [
        ("each effect's own shrink, median over the correctly named", q(m["median_shrink_correct_pct"], "%")),
        (
            "from the nominal to the final model (shape and effect)",
            q(m["median_total_shrink_correct_pct"], "%"),
        ),
        ("own shrink above the noise floor", q(m["median_shrink_above_floor_correct_pct"], "%")),
        ("nominal to final, above the noise floor", q(m["median_total_shrink_above_floor_correct_pct"], "%")),
        (
            "the most any model could shrink (the generator's noise)",
            q(m["median_shrink_ceiling_correct_pct"], "%"),
        ),
        (
            "own shrink above the generator's floor (its noise and a Preisach truth's switching roughness)",
            f"{q(m['median_shrink_above_generator_floor_correct_pct'], '%')} (PI truths "
            f"{q(m['median_shrink_above_generator_floor_by_truth_pct']['pi'], '%')}, Preisach truths "
            f"{q(m['median_shrink_above_generator_floor_by_truth_pct']['preisach'], '%')})",
        ),
        (
            "a Preisach truth's switching roughness on the judged held-out part, median",
            q(m["median_relay_roughness_nm"], "nm", 2),
        ),
        (
            "own shrink / its ceiling, low · middle · high",
            " · ".join(
                f"{q(a, '', 1)} / {q(b, '', 1)} %"
                for a, b in (by_level[lv] for lv in ("low", "middle", "high"))
            ),
        ),
        ("noise floor estimated from the held-out output, median", q(m["median_noise_floor_nm"], "nm", 2)),
        (
            "shapes found (none, generalised PI, Preisach)",
            ", ".join(count(m["shape_findings"].get(k, 0)) for k in ("None", "gpi", "preisach")),
        ),
        ("time per case, median", q(m["seconds_per_case_median"], "s", 0)),
    ]
    return Table(["median over the correctly named cases", "value"], facts(rows), [INDEPENDENT])


@table("independent_by_effect")
def independent_by_effect(results: Results) -> Table:
    m = results(INDEPENDENT)["all"]
    rows = []
    for effect, shrinks in m["median_shrink_by_effect_pct"].items():
        right = m["correct_by_effect_and_level"][effect]
        named = [f"{sum(right[lv])}/{len(right[lv])}" for lv in ("low", "middle", "high")]
        rows.append(
            [effect.replace("_", " "), ", ".join(named), " / ".join(q(v, "", 0) for v in shrinks) + " %"]
        )
    header = ["effect", "named (low, middle, high)", "own shrink, median (low / middle / high)"]
    return Table(header, rows, [INDEPENDENT], "An asymmetry counts as named when the shape found holds it.")


@table("independent_wandering")
def independent_wandering(results: Results) -> Table:
    m = results(WANDERING)
    levels = ("low", "middle", "high")
    rows = []
    for kind, right in m["wanders"]["by_wander"].items():
        rows.append([kind, *(f"{k}/{n}" if n else "–" for k, n in (right[lv] for lv in levels)), "–"])
    s = m["all"]
    top1 = [_share(s[f"top1_{lv}_pct"], s[f"cases_{lv}"]) if f"cases_{lv}" in s else "–" for lv in levels]
    rows.append(["all", *top1, f"{s['controls_flagged']}/{s['controls']}"])
    header = ["truth", "named low", "named middle", "named high", "controls flagged"]
    note = (
        f"Median shrink of the correctly named, own / above the noise floor: "
        f"{q(s['median_shrink_correct_pct'], '%')} / {q(s['median_shrink_above_floor_correct_pct'], '%')} "
        f"(an exact model of the actuator, its wander predicted at best across the held-out blocks: "
        f"{q(s['median_shrink_above_floor_ceiling_correct_pct'], '%')}); above the generator's floor, "
        f"its noise and a Preisach truth's switching roughness ("
        f"{q(s['median_relay_roughness_nm'], 'nm', 2)} median): "
        f"{q(s['median_shrink_above_generator_floor_correct_pct'], '%')} (PI truths "
        f"{q(s['median_shrink_above_generator_floor_by_truth_pct']['pi'], '%')}, Preisach truths "
        f"{q(s['median_shrink_above_generator_floor_by_truth_pct']['preisach'], '%')}; an exact model "
        f"{q(s['median_shrink_above_generator_floor_ceiling_correct_pct'], '%')}); "
        f"wrong verdicts: {count(_wrong(s['confusion'], m['labels']))}."
    )
    return Table(header, rows, [WANDERING], note)


@table("independent_preisach_rung")
def independent_preisach_rung(results: Results) -> Table:
    m = results(PREISACH_RUNG)
    versions = ("record", "relays", "continuous")
    rows = [
        [
            label,
            *(f"{q(r[f'{v}_gap_nm'], 'nm', 2)} ({q(r[f'{v}_floor_nm'], 'nm', 2)})" for v in versions),
            q(r["roughness_nm"], "nm", 2),
        ]
        for label, r in [*((str(c["seed"]), c) for c in m["cases"]), ("median", m["median"])]
    ]
    header = [
        "control (seed)",
        "the record: held-out gap (floor estimated)",
        "less the noise: the relays alone",
        "the density continuous, no noise",
        "the relays' switching roughness",
    ]
    note = "The diagnosis's Preisach rung, 20 levels, fitted on the first 60 % and scored on the rest, both axes."
    return Table(header, rows, [PREISACH_RUNG], note)


@table("independent_preisach_rung_nodes")
def independent_preisach_rung_nodes(results: Results) -> Table:
    m = results(PREISACH_RUNG)
    rows = [
        [
            f"{nodes} (the diagnosis's)" if int(nodes) == m["nodes"] else nodes,
            *(q(r[f"{v}_gap_nm"], "nm", 2) for v in ("record", "relays", "continuous")),
        ]
        for nodes, r in m["by_nodes"].items()
    ]
    header = ["profile nodes", "the record", "less the noise", "the density continuous, no noise"]
    return Table(header, rows, [PREISACH_RUNG], "Held-out gaps, median over the same controls.")


@table("independent_wandering_nodes")
def independent_wandering_nodes(results: Results) -> Table:
    rows = []
    for label, run in (("5 (the diagnosis's)", WANDERING), ("7", WANDERING_NODES7)):
        s = results(run)["different"]  # the symmetric PI nominal on the Preisach truths
        rows.append(
            [
                label,
                *(_share(s[f"top1_{lv}_pct"], s[f"cases_{lv}"]) for lv in ("low", "middle", "high")),
                f"{s['controls_flagged']}/{s['controls']}",
                q(s["median_shrink_above_floor_correct_pct"], "%"),
                q(s["median_shrink_above_generator_floor_correct_pct"], "%"),
            ]
        )
    header = [
        "profile nodes",
        "named low",
        "named middle",
        "named high",
        "controls flagged",
        "median shrink above the estimated floor",
        "above the generator's floor",
    ]
    ceiling = results(WANDERING)["different"]["median_shrink_above_generator_floor_ceiling_correct_pct"]
    note = (
        "The wandering check's 64 Preisach-truth cases (54 drifts and creeps, 10 controls); median "
        "shrink of the correctly named, their own step (an exact model of the actuator, above the "
        f"generator's floor: {q(ceiling, '%')})."
    )
    return Table(header, rows, [WANDERING, WANDERING_NODES7], note)


@table("independent_reported")
def independent_reported(results: Results) -> Table:
    rows = []
    for case in results(REPORTED):
        top = next((c for c in case["candidates"] if c["effect"] == case["verdict"]), None)
        gaps = (
            f"{q(top['heldout_gap_before_nm'], 'nm')} → {q(top['heldout_gap_after_nm'], 'nm')} "
            f"({q(top['shrink_pct'], '%')})"
            if top
            else "–"
        )
        rows.append(
            [
                case["case"],
                f"{case['verdict'] or 'none'} ({case['shape'] or 'nominal'} shape)",
                gaps,
                (top or {}).get("judged_on", "the later part") if top else "–",
            ]
        )
    header = ["case", "verdict (shape)", "held-out gap of the verdict", "judged on"]
    return Table(header, rows, [REPORTED])


@table("stability")
def stability(results: Results) -> Table:
    rows = []
    for run in STABILITY_ROWS:
        for case in results(run):
            name = f"{case['effect'] or 'control'}, {case['truth_hysteresis']} truth, {case['nominal_kind']} nominal"
            rows.append(
                [name] + [f"{v['verdict'] or '–'} ({v['shape'] or 'nominal'})" for v in case["variants"]]
            )
    header = ["case (middle magnitude)"] + [v["variant"] for v in results(STABILITY_ROWS[0])[0]["variants"]]
    return Table(header, rows, list(STABILITY_ROWS), "Each cell: the verdict (the hysteresis shape found).")


@table("stability_summary")
def stability_summary(results: Results) -> Table:
    m = results(STABILITY)
    rows = [
        [variant, count(v["verdict_flips"]), count(v["shape_flips"])]
        for variant, v in m["per_variant"].items()
    ]
    rows.append(
        [
            f"all {count(m['cases'] * m['variants_per_case'])} variants",
            count(m["verdict_flips"]),
            count(m["shape_flips"]),
        ]
    )
    return Table(
        ["variant", "verdict flips", "shape flips"],
        rows,
        [STABILITY],
        f"Right on the whole record: {m['right_whole']} of {m['cases']}; in every variant: "
        f"{m['right_all_variants']} of {m['cases']}.",
    )


# --- real data (docs/real_data.md) -----------------------------------------------------------

FIT_COLS = (
    Col("train rms", "_train_rms_error_pct", "%", 2),
    Col("held-out rms", "_heldout_rms_error_pct", "%", 2),
    Col("held-out max", "_heldout_max_error_pct", "%", 2),
    Col("fit time", "_fit_s", "s"),
    Col("solver steps", "_solver_steps", "", 0),
)
PIEZO_MODELS = (
    ("straight line (optimistix LM)", "line"),
    ("PI, 20 plays (optimistix LM)", "pi"),
    ("PI, 20 plays (jaxopt L-BFGS)", "pi_jaxopt"),
    ("generalised PI, 20 plays + 3+3 dead zones (optimistix LM)", "gpi"),
    ("generalised PI (jaxopt LM)", "gpi_jaxopt"),
    ("Preisach, 30 levels (jaxafm nnls, exact)", "preisach"),
    ("generalised PI + creep (optimistix LM)", "gpi_creep"),
    ("generalised PI + lag + creep (optimistix LM)", "gpi_lag_creep"),
)


# --- uncertainty (docs/uncertainty.md) -------------------------------------------------------

#: the models of ``jaxafm fit configs/piezo_sine_1hz.yaml`` whose band ``bench_band.py`` times:
#: the fit table's, its jaxopt rows left out, named without their solver
BAND_MODELS = {name: label.split(" (")[0] for label, name in PIEZO_MODELS if "jaxopt" not in name}


def _posterior_share(fit: dict, name: str) -> float:
    """What the posterior added to a model's fit in ``jaxafm fit`` (% of the fit's time)."""
    return 100 * fit[f"{name}_posterior_s"] / fit[f"{name}_fit_s"]


@table("posterior_cost")
def posterior_cost(results: Results) -> Table:
    """What a posterior and a band cost: ``jaxafm fit``'s times, and a 20,000-sample band."""
    fit, bench = results(PIEZO_FIT), results(BENCH_BAND)
    rows = [
        [
            label,
            count(b["parameters"]),
            q(fit[f"{name}_fit_s"], "s", 2),
            q(fit[f"{name}_posterior_s"], "s", 2),
            q(_posterior_share(fit, name), "%", 0),
            q(b["first_call_s"], "s", 2),
            f"{q(b['trace_s'], 's', 2)} + {q(b['compile_s'], 's', 2)}",
            q(1e3 * b["later_call_median_s"], "ms", 0),
            f"{q(b['compile_default_level_s'], 's', 2)}; {q(1e3 * b['run_default_level_s'], 'ms', 0)} "
            f"against {q(1e3 * b['run_s'], 'ms', 0)}",
        ]
        for name, label in BAND_MODELS.items()
        for b in [bench["models"][name]]
    ]
    large = results(BENCH_PREISACH_FIT)
    exact = _exact_fit(large)
    rows.append(
        [
            f"Preisach, {large['levels']} levels, {count(large['samples'])} training samples (simulated)",
            count(exact["posterior"]["parameters"]),
            q(exact["calls"][0]["seconds"], "s", 2),
            q(exact["posterior"]["seconds"], "s", 2),
            q(100 * exact["posterior"]["seconds"] / exact["calls"][0]["seconds"], "%", 0),
            "–",
            "–",
            "–",
            "–",
        ]
    )
    header = [
        "model",
        "parameters",
        "fit",
        "posterior (and the record's band)",
        "posterior / fit",
        f"band over {count(bench['samples'])} samples: first call",
        "of it, the linearisation's tracing + compiling",
        "later calls, median",
        "the linearisation at XLA's default level instead: compiling; a run against level 0's",
    ]
    note = (
        "Fit and posterior: the wall times `jaxafm fit` records (`<name>_fit_s`, `<name>_posterior_s`), "
        "compiling included (run with `JAXAFM_CACHE_DIR=off`); the band: each model's first call (compiling "
        "included), its linearisation traced and compiled again apart, and the median of five later calls on "
        "other drives of the same length, in one process; the linearisation compiles at XLA's backend "
        "optimisation level 0, the last column the same lowered program compiled at the default level (3), "
        "and the median of five runs of each. The last row: the exact fit's first call and its posterior as "
        "`jaxafm fit` makes it, in one process, on the simulated actuator's record of `bench_preisach_fit.py`."
    )
    return Table(header, rows, [PIEZO_FIT, BENCH_BAND, BENCH_PREISACH_FIT], note)


#: the suite's modules listed one by one (the longest); the rest share a row
SUITE_ROWS = 12


def _compiling(m: dict) -> float:
    """A test module's (or the suite's) seconds of JAX tracing, lowering and XLA compiling."""
    return m["trace_s"] + m["lower_s"] + m["backend_s"]


@table("bench_suite")
def bench_suite(results: Results) -> Table:
    """The test suite's time by module: the tests' wall time and what of it JAX spent compiling."""
    m = results(BENCH_SUITE)
    mods, total = m["modules"], m["total"]
    rest = {k: sum(r[k] for r in mods[SUITE_ROWS:]) for k in total}

    def row(name: str, r: dict) -> list:
        c = _compiling(r)
        cells = [count(r["tests"]), q(r["wall_s"], "s", 0), q(c, "s", 0), q(100 * c / r["wall_s"], "%", 0)]
        small = f"{count(r['small_programs'])} of {count(r['programs'])}: {q(r['small_backend_s'], 's', 0)}"
        return [name, *cells, q(r["backend_s"], "s", 0), small]

    rows = [row(f"`{r['module'].removeprefix('tests/')}`", r) for r in mods[:SUITE_ROWS]]
    rows += [row(f"the other {len(mods) - SUITE_ROWS} modules", rest), row("all", total)]
    header = ["module", "tests", "wall time", "compiling", "share", "of it, XLA's backend", "small programs"]
    note = (
        f"`pytest -q -n 2` on 2 cores: the suite took {q(m['suite_wall_s'], 's', 0)}; a test's wall time is "
        "pytest's (setup, call, teardown), in the worker that ran it; compiling is JAX's own events "
        "(tracing, lowering to MLIR, XLA's backend), not counting the `jaxafm` processes some tests start; "
        "small programs: those XLA compiled in under 0.3 s (one eager array operation, or a few), of all "
        "it compiled, and their XLA time."
    )
    return Table(header, rows, [BENCH_SUITE], note)


@table("bench_suite_trial")
def bench_suite_trial(results: Results) -> Table:
    """What the corrective-push test's program compiles: the whole, and with one part taken out."""
    rows = []
    for r in results(BENCH_SUITE_TRIAL)["rows"]:
        diff = r.get("largest_difference")
        rows.append(
            [
                r["program"] + ("" if diff is None else f" (results within {diff:.0e} nm)"),
                q(r["lower_s"], "s", 1),
                q(r["compile_s"], "s", 1),
                q(1e3 * r["run_s"], "ms", 0),
                count(r["while_loops"]),
            ]
        )
    header = ["program", "lowering", "XLA compiling", "a run", "loops in the compiled program"]
    note = "XLA on one thread, as in a test worker; four particles vmapped; a run: the median of three."
    return Table(header, rows, [BENCH_SUITE_TRIAL], note)


@table("bench_suite_flags")
def bench_suite_flags(results: Results) -> Table:
    """The corrective-push test's program compiled under each of XLA's CPU flags tried, beside none."""
    m = results(BENCH_SUITE_FLAGS)
    rows = []
    for r in m["rows"]:
        if "same" not in r:
            same = "the reference"
        elif r["same"]:
            same = "bit for bit the same"
        else:
            same = f"within {r['largest_difference']:.0e}"
        rows.append(
            [
                f"`{r['flags']}`" if r["flags"] else "none",
                q(r["lower_s"], "s", 1),
                f"{q(r['compile_s'], 's', 1)} ({span(r['compile_runs'], 's')})",
                q(1e3 * r["run_s"], "ms", 0),
                same,
            ]
        )
    header = ["XLA flag", "lowering", "XLA compiling (its range)", "a run", "results"]
    note = (
        f"Each compile a fresh process, XLA on one thread as in a test worker; {m['rounds']} rounds, each "
        "compiling without flags and with each flag in an order drawn anew; the medians over the rounds; "
        "four particles vmapped; a run: the median of three."
    )
    return Table(header, rows, [BENCH_SUITE_FLAGS], note)


@table("bench_blas_threads")
def bench_blas_threads(results: Results) -> Table:
    """Two loops written with two libraries' BLAS and with one: their wall times side by side."""
    m = results(BENCH_BLAS)
    rows = []
    for loop in m["loops"]:
        (mixed, a), (one, b) = loop["variants"].items()
        rows.append(
            [
                f"{loop['loop']} ({loop['problem']})",
                f"{mixed}: {q(1e3 * a['median_s'], 'ms', 0)} ({q(1e3 * a['max_s'], 'ms', 0)} worst)",
                f"{one}: {q(1e3 * b['median_s'], 'ms', 0)} ({q(1e3 * b['max_s'], 'ms', 0)} worst)",
                q(a["median_s"] / b["median_s"], "×", 1),
            ]
        )
    header = ["loop", "two libraries", "one library", "ratio of the medians"]
    note = (
        f"{m['repeats']} calls of each variant in a row, after a second without work; the same "
        "matrices and the same results in both (to round-off)."
    )
    return Table(header, rows, [BENCH_BLAS], note)


BAND_METHODS = (("ar1", "AR(1), the default"), ("blocks", "blocks"), ("iid", "i.i.d., the naive band"))


@table("uncertainty_real")
def uncertainty_real(results: Results) -> Table:
    m = results(UNCERTAINTY)["real"]
    rows = []
    for key, v in m.items():
        records, kind = key.split("/")
        fitted, _, scored = records.partition("->")
        rows.append(
            [UNCERTAINTY_MODELS[kind], UNCERTAINTY_RECORDS[fitted], UNCERTAINTY_RECORDS[scored or fitted]]
            + [q(v["iid_residual_sd_nm"], "nm", 0) if not scored else "–", q(v["rms_error_nm"], "nm", 0)]
            + [f"{q(v['fit_s'], 's')} + {q(v['posterior_s'], 's')}" if "fit_s" in v else "–"]
            + [
                f"{q(v[f'{meth}_coverage_90_pct'], '%')} / {q(v[f'{meth}_coverage_50_pct'], '%')} "
                f"(×{q(v[f'{meth}_width_90_over_rms'], '', 2)})"
                for meth, _ in BAND_METHODS
            ]
        )
    header = ["model", "fitted on", "scored on", "training rms", "held-out rms", "fit + posterior"]
    header += [name for _, name in BAND_METHODS]
    note = (
        "Each band cell: the held-out samples inside the 90 % / 50 % band, and (×) the 90 % band's mean "
        "width over the held-out rms error (a calibrated Gaussian band: 90 % / 50 %, ×3.3)."
    )
    return Table(header, rows, [UNCERTAINTY], note)


@table("posterior_check")
def posterior_check(results: Results) -> Table:
    rows = []
    for case, c in results(POSTERIOR_CHECK).items():
        for which, name in (
            ("mode", "Laplace at the AR(1) posterior's mode"),
            ("saved", "the saved fit and its AR(1) covariance"),
        ):
            v = c[which]
            rows.append(
                [case, name, count(c["parameters"]), count(c["samples"])]
                + [q(v["max_mean_gap_over_nuts_sd"], "sd", 2), q(100 * v["max_sd_error"], "%")]
            )
    header = ["record", "Gaussian", "parameters", "NUTS draws", "largest mean gap", "largest sd error"]
    return Table(
        header, rows, [POSTERIOR_CHECK], "Gaps and errors relative to the NUTS sd of each parameter."
    )


@table("uncertainty_generator")
def uncertainty_generator(results: Results) -> Table:
    m = results(UNCERTAINTY)["generator_summary"]
    rows = []
    for kind in ("pi", "gpi_creep"):
        for meth, name in BAND_METHODS:
            v = m[f"generator/{kind}/{meth}"]
            rows.append(
                [UNCERTAINTY_MODELS[kind], name, count(v["records"])]
                + [q(v[k], "%") for k in ("median_coverage_90_pct", "median_coverage_50_pct")]
                + [q(v["share_90_within_85_95_pct"], "%"), q(v["median_width_90_over_rms"], "×", 2)]
            )
    header = ["model", "noise model", "records", "median 90 % coverage", "median 50 % coverage"]
    header += ["records with 85–95 %", "median width / rms"]
    return Table(header, rows, [UNCERTAINTY])


PLAY_SCAN = (
    ("2 CPU cores", Run("bench_play_scan/cpu.json", "python experiments/bench_play_scan.py")),
    (
        "one H200",
        Run("bench_play_scan/gpu_nvidia_h200.json", "python experiments/bench_play_scan.py (on an H200)"),
    ),
)


def _scan_rows(
    results: Results, runs: Sequence[tuple], lead: Callable, tail: Callable = lambda r: []
) -> list:
    """A time-parallel benchmark's rows (``bench_play_scan``, ``bench_lag_scan``, ``bench_mode_scan``): per device and
    row, the ``lead`` cells, then samples/s sequential / associative with their ratio, forward
    and loss + gradient, both compile times, and the ``tail`` cells."""
    rows = []
    for device, run in runs:
        for r in results(run)["rows"]:
            cells = [device] + lead(r)
            for part in ("", "grad_"):
                seq, par = (r[f"{m}_{part}samples_per_s"] for m in ("sequential", "associative"))
                cells.append(f"{seq:.2e} / {par:.2e} ({q(par / seq, '×', 2)})")
            cells.append(" / ".join(q(r[f"{m}_compile_s"], "s", 2) for m in ("sequential", "associative")))
            rows.append(cells + tail(r))
    return rows


def _largest_difference(r: dict) -> list:
    """The larger relative difference of a time-parallel benchmark's row, values or gradients."""
    return [f"{max(r['max_relative_difference'], r['max_relative_gradient_difference']):.0e}"]


@table("play_scan")
def play_scan(results: Results) -> Table:
    rows = _scan_rows(results, PLAY_SCAN, lambda r: [count(r["T"])])
    header = ["device", "samples", "plays: samples/s, sequential / associative", "loss + gradient"]
    header += ["compile, sequential / associative"]
    return Table(header, rows, [run for _, run in PLAY_SCAN], "50 plays; the same numbers on both paths.")


LAG_SCAN = (
    ("2 CPU cores", Run("bench_lag_scan/cpu.json", "python experiments/bench_lag_scan.py")),
    (
        "one H200",
        Run("bench_lag_scan/gpu_nvidia_h200.json", "python experiments/bench_lag_scan.py (on an H200)"),
    ),
)


@table("lag_scan")
def lag_scan(results: Results) -> Table:
    rows = _scan_rows(results, LAG_SCAN, lambda r: [count(r["lags"]), count(r["T"])], _largest_difference)
    header = ["device", "lags", "samples", "lags: samples/s, sequential / associative", "loss + gradient"]
    header += ["compile, sequential / associative", "largest relative difference"]
    return Table(header, rows, [run for _, run in LAG_SCAN])


MODE_SCAN = Run("bench_mode_scan/cpu.json", "python experiments/bench_mode_scan.py")


@table("mode_scan")
def mode_scan(results: Results) -> Table:
    rows = _scan_rows(results, (("2 CPU cores", MODE_SCAN),), lambda r: [count(r["T"])], _largest_difference)
    header = ["device", "samples", "mode: samples/s, sequential / associative", "loss + gradient"]
    header += ["compile, sequential / associative", "largest relative difference"]
    return Table(header, rows, [MODE_SCAN])


@table("piezo_fit")
def piezo_fit(results: Results) -> Table:
    m = results(PIEZO_FIT)
    rows = grid(m, PIEZO_MODELS, FIT_COLS)
    for row, (_, prefix) in zip(rows, PIEZO_MODELS):
        row.append(q(m[f"{prefix}_converged"]))
    header = ["model (solver)"] + [c.header for c in FIT_COLS] + ["converged"]
    return Table(header, rows, [PIEZO_FIT], "Errors in % of the output range.")


CROSS_COLS = (
    Col("offset", "offset_nm", "nm", 0),
    Col("raw rms", "raw_rms_error_pct", "%", 2),
    Col("rms", "all_rms_error_pct", "%", 2),
    Col("max", "all_max_error_pct", "%", 2),
)


@table("cross_record")
def cross_record(results: Results) -> Table:
    m = results(CROSS_RECORD)
    names = {
        "pi": "PI",
        "gpi": "generalised PI",
        "preisach": "Preisach, 30 levels",
        "gpi_creep": "generalised PI + creep",
    }
    rows = []
    for fitted, scored in (("sine", "ramped"), ("ramped", "ramped"), ("ramped", "sine"), ("sine", "sine")):
        for model, name in names.items():
            prefix = f"{model}_on_{fitted}_scored_on_{scored}_"
            row = grid(m, [(name, prefix)], CROSS_COLS)[0]
            minor = [m.get(prefix + k) for k in ("minor_rms_error_pct", "minor_max_error_pct")]
            rows.append(row[:1] + [fitted, scored] + row[1:] + [q(v, "%", 2) for v in minor])
    header = ["model", "fitted on", "scored on"] + [c.header for c in CROSS_COLS] + ["minor rms", "minor max"]
    return Table(header, rows, [CROSS_RECORD], "Errors in % of the scored record's output range.")


@table("predict_compensate")
def predict_compensate(results: Results) -> Table:
    p, c, fit = results(PREDICT), results(COMPENSATE), results(PIEZO_FIT)
    rows = [
        (
            "`jaxafm predict`: the generalised PI on the held-out part, rms / max",
            f"{q(p['rms_error_pct'], '%', 3)} / {q(p['max_error_pct'], '%', 3)}",
        ),
        (
            "the fit table's held-out rms / max for the same model",
            f"{q(fit['gpi_heldout_rms_error_pct'], '%', 3)} / {q(fit['gpi_heldout_max_error_pct'], '%', 3)}",
        ),
        (
            "`jaxafm predict`: the model's 90 % band, mean width / held-out samples inside it",
            f"{q(p['band_width_nm'], 'nm')} / {q(p['coverage_pct'], '%')}",
        ),
        (
            "`jaxafm compensate`: the drive through the generalised PI, rms / max",
            " / ".join(q(c[f"tracking_{k}_error_nm"], "nm", 2, tiny=True) for k in ("rms", "max")),
        ),
        (
            "`jaxafm compensate`: the actuator itself expected within (90 %, the model's band)",
            f"± {q(c['expected_error_90_nm'], 'nm')}",
        ),
        (
            "the same drive through the Preisach model, rms / max",
            f"{q(c['check_model_preisach_tracking_rms_error_pct'], '%', 2)} / "
            f"{q(c['check_model_preisach_tracking_max_error_pct'], '%', 2)}",
        ),
        (
            "the same drive through the generalised PI + creep model, rms / max",
            f"{q(c['check_model_gpi_creep_tracking_rms_error_pct'], '%', 2)} / "
            f"{q(c['check_model_gpi_creep_tracking_max_error_pct'], '%', 2)}",
        ),
    ]
    return Table(["", "value"], facts(rows), [PREDICT, PIEZO_FIT, COMPENSATE])


@table("real_grating")
def real_grating(results: Results) -> Table:
    m = results(REAL_GRATING)
    rows = [
        ("edges fitted (rows)", f"{count(m['edges'])} ({count(m['rows_used'])})"),
        ("pitch", f"{q(m['pitch_nm'], 'nm')} ± {q(m['pitch_se_nm'], 'nm')}"),
        ("x calibration against a 3 µm nominal pitch", q(m["x_calibration_error_pct"], "%", 2)),
        (
            "fast-axis nonlinearity, peak to peak",
            f"{q(m['nonlinearity_ptp_nm'], 'nm')} "
            f"({q(m['nonlinearity_ptp_pct_of_width'], '%', 2)} of the width)",
        ),
        (
            "skew",
            f"{q(m['skew_nm_per_nm'], '', 4)} ± {q(m['skew_se_nm_per_nm'], '', 5)} "
            f"({q(m['skew_angle_deg'], '°', 2)} if a rotation)",
        ),
        ("bow", f"{q(m['bow_nm'], 'nm')} ± {q(m['bow_se_nm'], 'nm')}"),
        ("x-scale drift over the frame", q(m["x_scale_drift_pct"], "%", 2)),
        ("edge residual, rms", q(m["residual_rms_nm"], "nm")),
        (
            "local pitch spread, raw → corrected",
            f"{q(m['raw_pitch_std_nm'], 'nm')} ({q(m['raw_pitch_std_pct'], '%', 2)}) → "
            f"{q(m['corrected_pitch_std_nm'], 'nm')} ({q(m['corrected_pitch_std_pct'], '%', 2)})",
        ),
        (
            "local pitch peak to peak, raw → corrected",
            f"{q(m['raw_pitch_ptp_nm'], 'nm', 0)} → {q(m['corrected_pitch_ptp_nm'], 'nm', 0)}",
        ),
        ("pitch over the model variants, range", q(m["pitch_range_over_models_nm"], "nm", 2)),
    ]
    return Table(["", "value"], facts(rows), [REAL_GRATING])


@table("real_lattice")
def real_lattice(results: Results) -> Table:
    rows = [
        [
            frame.replace("_", " ").replace(" trace", ", trace").replace(" retrace", ", retrace"),
            q(r["turn_deg"], "°", 2),
            f"{q(r['nominal_heldout_gap_nm'], '', 0)} → {q(r['verdict_heldout_gap_nm'], '', 0)} nm",
            q(r["verdict_shrink_pct"], "%"),
            q(r["skew_beyond_turn"], "", 4),
            q(r["shape_slope"], "", 3),
            r["verdict"],
        ]
        for frame, r in results(REAL_LATTICE).items()
    ]
    header = [
        "frame",
        "turn (rows' tilt)",
        "held-out gap, nominal → verdict",
        "shrink",
        "skew beyond the turn",
    ]
    return Table(header + ["chord-midpoint slope", "verdict"], rows, [REAL_LATTICE])


# --- the model and the instrument (docs/model.md, docs/instrument.md) -------------------------


def _timed(r: dict) -> str:
    return f"{q(1e3 * r['median_s'], 'ms', 0)} ({q(r['compile_s'], 's', 2)})"


def _kinds(m: dict) -> list:
    """The bench's variants of one model: (label, kind, old baseline, fair baseline)."""
    if not m["model"].startswith("Preisach"):
        return [(m["model"], "hard", "loop", "play_loop")]
    return [
        (f"{m['model']}, relay grid", "hard", "relay_grid", "play_loop"),
        (f"{m['model']}, smooth", "smooth", None, "play_loop_smooth"),
    ]


@table("bench_hysteresis")
def bench_hysteresis(results: Results) -> Table:
    rows = []
    for m in results(BENCH_HYSTERESIS)["models"]:
        for label, kind, old, fair in _kinds(m):
            rows.append(
                [
                    label,
                    _timed(m[f"fwd_{kind}"]),
                    q(m["numpy"][old]["median_s"], "s", 2) if old else "–",
                    q(m[f"speedup_{kind}_vs_{old}"], "×") if old else "–",
                    q(1e3 * m["numpy"][fair]["median_s"], "ms", 0),
                    q(m[f"speedup_{kind}_vs_{fair}"], "×"),
                ]
            )
    header = ["model", "JAX forward (compile)", "naive baseline", "vs naive", "fair baseline", "vs fair"]
    return Table(header, rows, [BENCH_HYSTERESIS])


@table("bench_hysteresis_grad")
def bench_hysteresis_grad(results: Results) -> Table:
    rows = []
    for m in results(BENCH_HYSTERESIS)["models"]:
        for label, kind, _, _ in _kinds(m):
            rows.append(
                [
                    label,
                    f"{q(m[f'grad_over_fwd_{kind}'], '', 2)} ({q(m[f'grad_{kind}']['compile_s'], 's', 2)})",
                    f"{q(m[f'grad_all_over_fwd_{kind}'], '', 2)} ({q(m[f'grad_all_{kind}']['compile_s'], 's', 2)})",
                ]
            )
    header = ["model", "value+grad / forward, fitted arrays (compile)", "every array (compile)"]
    return Table(header, rows, [BENCH_HYSTERESIS])


def _run(m: dict, name: str) -> dict:
    """The run ``name`` of ``bench_preisach_fit``."""
    return next(r for r in m["runs"] if r["run"] == name)


def _exact_fit(m: dict) -> dict:
    return _run(m, "jaxafm.nnls")


def _peak_mb(r: dict) -> float:
    """A run's peak resident memory over its fits (MiB)."""
    return max(c["peak_mb"] for c in r["calls"])


def _gb(mib: float) -> float:
    """``mib`` MiB in GB (10^9 bytes), the unit of the fit's memory goal."""
    return mib * 2**20 / 1e9


@table("bench_preisach_fit")
def bench_preisach_fit(results: Results) -> Table:
    m = results(BENCH_PREISACH_FIT)
    rows = []
    for r in m["runs"]:
        last = r["calls"][-1]
        rows.append(
            [
                f"`{r['run']}`" if "." in r["run"] and " " not in r["run"] else r["run"],
                q(r["calls"][0]["seconds"], "s", 2),
                q(r["compiled_s"], "s", 2),
                f"{q(r['peak_before_mb'] / 1024, 'GiB', 2)} → {q(_peak_mb(r) / 1024, 'GiB', 2)}",
                q(r["train_rms_nm"], "nm", 3),
                q(r["heldout_rms_nm"], "nm", 3),
                last["message"].split(": ", 1)[-1],
            ]
        )
    header = [
        "fit",
        "first call",
        "compiled",
        "peak memory: before → after the fits",
        "training rms",
        "held-out rms",
        "how it ended",
    ]
    exact = _exact_fit(m)
    note = (
        f"{m['levels']} levels ({count(m['relays'])} relays), {count(m['samples'])} training samples; "
        f"the exact fit's parts: normal equations {q(exact['parts']['normal_equations_s'], 's', 2)}, "
        f"solve {q(exact['parts']['solve_s'], 's', 2)}; after it, its posterior as `jaxafm fit` makes it "
        f"{q(exact['posterior']['seconds'], 's', 2)}, the peak then "
        f"{q(exact['posterior']['peak_mb'] / 1024, 'GiB', 2)}."
    )
    return Table(header, rows, [BENCH_PREISACH_FIT], note)


@table("bench_preisach_ridge")
def bench_preisach_ridge(results: Results) -> Table:
    p = _exact_fit(results(BENCH_PREISACH_FIT))["parts"]
    rows = [
        [
            q(float(ridge), "", 0, tiny=True),
            r["how"],
            count(r["steps"]),
            q(r["seconds"], "s", 2),
            q(r["train_rms_nm"], "nm", 6),
        ]
        for ridge, r in p["ridges"].items()
    ]
    rows.append(
        ["scipy's `nnls` (Lawson–Hanson) at 1e-6", "–", "–", q(p["scipy_nnls_same_gram_s"], "s", 2), "–"]
    )
    header = ["ridge", "how it ended", "pivoting steps", "solve", "training rms"]
    note = (
        f"The same normal equations; the Gram matrix's rank {count(p['gram_rank'])} of {count(p['weights'])}."
    )
    return Table(header, rows, [BENCH_PREISACH_FIT], note)


@table("bench_scan")
def bench_scan(results: Results) -> Table:
    m = results(BENCH_SCAN)
    n = m["scan"]["samples_per_image"]
    vec = m["numpy_vectorised"]
    rows = [
        [
            "JAX forward (jitted)",
            q(m["jax_forward"]["median_s"], "s", 2),
            q(1e6 * m["jax_forward"]["median_s"] / n, "µs", 2),
            q(m["jax_forward"]["compile_s"], "s"),
        ],
        [
            f"JAX forward + gradient ({m['grad']['parameters']} parameters)",
            q(m["jax_forward_grad"]["median_s"], "s", 2),
            q(1e6 * m["jax_forward_grad"]["median_s"] / n, "µs", 2),
            q(m["jax_forward_grad"]["compile_s"], "s"),
        ],
        [
            "NumPy loop over samples",
            q(m["numpy"]["image_s"], "s"),
            q(1e6 * m["numpy"]["image_s"] / n, "µs", 0),
            "–",
        ],
        [
            "NumPy, only the sequential stages looped",
            q(vec["median_s"], "s", 2),
            q(1e6 * vec["median_s"] / n, "µs", 2),
            "–",
        ],
    ]
    return Table(["", "per image", "per sample", "compile"], rows, [BENCH_SCAN])


@table("bench_scan_ratios")
def bench_scan_ratios(results: Results) -> Table:
    m = results(BENCH_SCAN)
    loops = m["numpy_vectorised"]["sequential_loops_s"]
    agree = max(m["max_abs_diff_jax_vs_numpy_nm"].values())
    rows = [
        ("samples per image", count(m["scan"]["samples_per_image"])),
        ("JAX forward against the NumPy loop", q(m["numpy_over_jax_forward"], "×", 0)),
        ("JAX forward against the vectorised NumPy scan", q(m["numpy_vectorised_over_jax_forward"], "×")),
        ("gradient / forward", q(m["grad_over_forward"], "×")),
        (
            "the vectorised scan's loops: plays, lags and wander",
            ", ".join(q(v, "s", 2) for v in loops.values()),
        ),
        ("JAX and NumPy agree on every pixel to", q(agree, "nm", tiny=True)),
        ("peak memory", q(m["peak_rss_gib"], "GiB")),
    ]
    return Table(["", "value"], facts(rows), [BENCH_SCAN])


@table("bench_render")
def bench_render(results: Results) -> Table:
    m = results(BENCH_RENDER)
    rows = [
        [name.replace("\n", " "), q(r["median_s"], "s", 2), q(r["compile_s"], "s", 2)]
        for name, r in m["runs"].items()
    ]
    agree = q(m["max_difference_nm"], "nm", tiny=True)
    note = f"{m['particles']} spheres on a {m['pixels']}² survey; the images agree to {agree}."
    return Table(["the tip image of", "median", "compile"], rows, [BENCH_RENDER], note)


@table("simulated_grating_scan")
def simulated_grating_scan(results: Results) -> Table:
    m = results(GRATING_SCAN)
    rows = [
        (
            "true tip position against the wanted one: rms, max",
            f"{q(m['position_error_rms_nm'], 'nm', 0)}, {q(m['position_error_max_nm'], 'nm', 0)}",
        ),
        (
            "x error range, y error range",
            f"{span(m['x_error_range_nm'], 'nm', 0)}, {span(m['y_error_range_nm'], 'nm', 0)}",
        ),
        ("trace against retrace positions, rms", q(m["trace_retrace_offset_rms_nm"], "nm", 0)),
        ("trace image against retrace image, rms", q(m["trace_minus_retrace_rms_nm"], "nm", 0)),
        ("instrument time of the frame", q(m["frame_time_s"], "s", 0)),
    ]
    return Table(["", "value"], facts(rows), [GRATING_SCAN])


# --- pages -----------------------------------------------------------------------------------


def pages(root: Path) -> list[str]:
    """The pages that may hold tables, from the repository root."""
    found = {p.relative_to(root).as_posix() for pattern in PAGES for p in root.glob(pattern)}
    return sorted(found)


def make(name: str, results: Results) -> Table:
    """The table ``name``, or an error naming it and the key its results lack."""
    try:
        return TABLES[name](results)
    except (KeyError, IndexError, TypeError) as e:
        raise SystemExit(f"table {name!r}: its results have no {e}") from e


def blocks(text: str, page: str) -> list[tuple[str, int, int, str]]:
    """``(table, start, end, indent)`` for each marked block of ``text``: its body is
    ``text[start:end]``, and ``indent`` the spaces before its marker (a table inside a list item)."""
    found = []
    for m in BEGIN.finditer(text):
        end = text.find(END, m.end())
        if end < 0:
            raise SystemExit(f"{page}: <!-- results:{m.group(1)} --> has no {END}")
        if m.group(1) not in TABLES:
            raise SystemExit(
                f"{page}: <!-- results:{m.group(1)} --> names no table; tables: {', '.join(TABLES)}"
            )
        indent = text[text.rfind("\n", 0, m.start()) + 1 : m.start()]
        found.append((m.group(1), m.end(), end, indent if not indent.strip() else ""))
    return found


def written(text: str, page: str, results: Results) -> str:
    """``text`` with every marked block holding the table it names."""
    out, at = [], 0
    for name, start, end, indent in blocks(text, page):
        lines = [indent + line if line else "" for line in render(make(name, results), page)]
        out += [text[at:start], "\n" + "\n".join(lines) + "\n" + indent]
        at = end
    return "".join(out + [text[at:]])


def _cells(line: str) -> list[str]:
    """The cells of a Markdown table row."""
    return [c.strip() for c in line.strip().strip("|").split("|")]


def first_difference(name: str, page: str, old: str, new: str) -> str:
    """Where a stale table's text first differs from what the results give: the row and the
    column of a table cell, else the line."""
    old_lines, new_lines = (t.strip("\n").split("\n") for t in (old, new))
    header = _cells(new_lines[0])
    for i in range(max(len(old_lines), len(new_lines))):
        a = old_lines[i].strip() if i < len(old_lines) else ""
        b = new_lines[i].strip() if i < len(new_lines) else ""
        if a == b:
            continue
        if a.startswith("|") and b.startswith("|"):
            ca, cb = _cells(a), _cells(b)
            for j in range(max(len(ca), len(cb))):
                x, y = (ca[j] if j < len(ca) else ""), (cb[j] if j < len(cb) else "")
                if x != y:
                    col = header[j] if j < len(header) else f"column {j + 1}"
                    return (
                        f"{page}: table {name!r}, row {cb[0]!r}, column {col!r}: "
                        f"the page has {x!r}, the results give {y!r}"
                    )
        return f"{page}: table {name!r}, line {i + 1}: the page has {a!r}, the results give {b!r}"
    return f"{page}: table {name!r} differs in its blank lines or indentation"


def narration(text: str, page: str) -> list[str]:
    """Each line of ``text`` (outside code blocks and code spans) that narrates when something
    was measured."""
    found, fenced = [], False
    for i, line in enumerate(text.split("\n"), 1):
        fenced ^= line.lstrip().startswith("```")
        m = None if fenced else NARRATION.search(re.sub(r"`[^`]*`", "", line))
        if m:
            found.append(
                f"{page}:{i}: {m.group(0)!r} narrates history (the git log keeps it): {line.strip()}"
            )
    return found


def check(root: Path) -> list[str]:
    """Every problem with the pages under ``root``: stale tables, tables on no page, narration."""
    results, problems, shown = Results(root), [], set()
    for page in pages(root):
        text = (root / page).read_text()
        new = written(text, page, results)
        for (name, start, end, _), (_, nstart, nend, _) in zip(blocks(text, page), blocks(new, page)):
            shown.add(name)
            if text[start:end] != new[nstart:nend]:
                problems.append(first_difference(name, page, text[start:end], new[nstart:nend]))
        problems += narration(text, page)
    problems += [
        f"table {name!r} is on no page: mark it or remove it" for name in TABLES if name not in shown
    ]
    return problems


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Write the tables (or ``--check`` them); return the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 naming what is stale")
    ap.add_argument("--root", type=Path, default=ROOT, help="the repository (default: this one)")
    args = ap.parse_args(argv)
    root = args.root.resolve()
    if args.check:
        problems = check(root)
        for p in problems:
            print(p, file=sys.stderr)
        if problems:
            print(
                f"{len(problems)} problem(s); `python docs/results.py` rewrites the tables", file=sys.stderr
            )
        return 1 if problems else 0
    results = Results(root)
    for page in pages(root):
        text = (root / page).read_text()
        new = written(text, page, results)
        if new != text:
            (root / page).write_text(new)
            print(f"wrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
