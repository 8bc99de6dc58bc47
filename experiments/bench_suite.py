"""Where the test suite's time goes: compiling or running, module by module, and what one of its
largest programs, a positioning trial, is made of.

    python experiments/bench_suite.py            # the README's test command, profiled (about 14 min)
    python experiments/bench_suite.py --trial    # the trial program's compile alone (about 1 min)
    python experiments/bench_suite.py --flags    # the same program under XLA's CPU flags (about 14 min)

The suite runs as the README runs it (``pytest -q -n 2``) with this file as a pytest plugin: in
each worker, JAX's own compile events (``jax.monitoring``: tracing to a jaxpr, lowering to MLIR,
XLA's backend compile, reads from the persistent compilation cache) are summed per test beside
the test's duration as pytest reports it (setup, call and teardown). What a test's subprocesses
(the ``jaxafm`` processes some tests start) compile is not counted, only their wall time inside
the test. ``--trial`` compiles the program of ``tests/test_positioning.py``'s corrective-push test
(four particles, vmapped: reached with an approach, found by a local scan, pushed and checked)
with XLA on one thread, as a test worker runs it, and again with one part taken out at a time,
to say what its compile is made of, and once at XLA's backend optimisation level 0. ``--flags``
compiles it in a fresh process for each of :data:`FLAGS` (XLA reads its flags once, when it
starts) and for none of them, each three times in an order drawn anew each round, and compares
each one's results with those without flags.

Writes ``experiments/results/bench_suite/suite.json``, ``trial.json`` and ``flags.json`` (the
tables ``bench_suite``, ``bench_suite_trial`` and ``bench_suite_flags`` of docs/development.md).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "bench_suite"
#: where each worker writes its part (set by main for the pytest run; the plugin is off without it)
PARTS = "JAXAFM_BENCH_SUITE_PARTS"
#: JAX's compile events, by the names this file gives them
EVENTS = {
    "trace_s": "/jax/core/compile/jaxpr_trace_duration",
    "lower_s": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "backend_s": "/jax/core/compile/backend_compile_duration",
    "cache_read_s": "/jax/compilation_cache/cache_retrieval_time_sec",
}
#: what the plugin counts of XLA's compiles: programs, the small ones, their compile time (s)
PROGRAMS = ("programs", "small_programs", "small_backend_s")
#: a program XLA compiles in less is "small": one eager array operation, or a few (s)
SMALL_PROGRAM_S = 0.3
#: XLA on one thread, as tests/conftest.py runs it in each pytest-xdist worker
ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
#: XLA's CPU flags that might shorten a compile (each a switch this jaxlib's XLA reads)
FLAGS = (
    "--xla_cpu_disable_loop_unrolling=true",
    "--xla_cpu_disable_slp_vectorizer=true",
    "--xla_cpu_optimize_for_size=true",
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_cpu_disable_new_fusion_emitters=true",
    "--xla_cpu_disable_tiled_emitter=true",
    "--xla_cpu_use_xnnpack=false",
    "--xla_cpu_copy_insertion_use_region_analysis=false",
    "--xla_cpu_parallel_codegen_split_count=1",
)

# ---------------------------------------------------------------------------------------------
# The plugin (loaded in every pytest process by ``-p bench_suite``)

_now: list = [None]  # the test running now (its node id)
OUTSIDE = "<outside any test>"  # what compiles between tests (collection, the workers' start)
_tests: dict = defaultdict(lambda: defaultdict(float))


def pytest_configure(config):
    if os.environ.get(PARTS):
        import jax.monitoring

        by_event = {v: k for k, v in EVENTS.items()}

        def listen(event, duration, **_):
            if event in by_event:
                test = _tests[_now[0] or OUTSIDE]
                test[by_event[event]] += duration
                if by_event[event] == "backend_s":  # one event a compiled program
                    test["programs"] += 1
                    if duration < SMALL_PROGRAM_S:
                        test["small_programs"] += 1
                        test["small_backend_s"] += duration

        jax.monitoring.register_event_duration_secs_listener(listen)


def pytest_runtest_logstart(nodeid, location):
    _now[0] = nodeid


def pytest_runtest_logreport(report):
    if os.environ.get(PARTS):
        _tests[report.nodeid]["wall_s"] += report.duration


def pytest_runtest_logfinish(nodeid, location):
    _now[0] = None


def pytest_sessionfinish(session):
    folder = os.environ.get(PARTS)
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if folder and worker:  # the workers hold the tests; the controlling process none
        (Path(folder) / f"{worker}.json").write_text(json.dumps(_tests))


# ---------------------------------------------------------------------------------------------
# The suite


def profile_suite(parts: Path) -> dict:
    """Run the README's test command with this plugin; :func:`summarise` its parts, then remove them."""
    parts.mkdir(parents=True, exist_ok=True)
    for old in parts.glob("gw*.json"):
        old.unlink()
    env = os.environ | {PARTS: str(parts), "PYTHONPATH": str(ROOT / "experiments")}
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "bench_suite"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    print(run.stdout[-400:])
    if run.returncode != 0:
        raise SystemExit(f"the suite failed (exit {run.returncode}); nothing written")
    doc = summarise(parts, run.stdout.strip().splitlines()[-1])
    for f in parts.glob("gw*.json"):
        f.unlink()
    parts.rmdir()
    return doc


def summarise(parts: Path, summary: str) -> dict:
    """Per module and in all: the tests, their wall time and the compile events (s), from the
    workers' parts; the suite's wall time from pytest's ``summary`` line (``... in 694.03s``)."""
    tests = {}
    for f in sorted(parts.glob("gw*.json")):
        tests |= json.loads(f.read_text())
    keys = ["wall_s", *EVENTS, *PROGRAMS]
    modules = defaultdict(lambda: dict.fromkeys(["tests", *keys], 0.0))
    for nodeid, t in tests.items():
        m = modules[nodeid.split("::")[0]]
        m["tests"] += "::" in nodeid
        for k, v in t.items():
            m[k] += v
    outside = modules.pop(OUTSIDE, dict.fromkeys(keys, 0.0))
    total = {k: sum(m[k] for m in modules.values()) for k in ["tests", *keys]}
    rows = sorted(({"module": name} | m for name, m in modules.items()), key=lambda r: -r["wall_s"])
    wall = float(re.search(r" in ([\d.]+)s", summary).group(1))
    doc = {"suite_wall_s": wall, "workers": 2, "summary": summary, "total": total, "modules": rows}
    return doc | {"outside_tests": {k: outside[k] for k in (*EVENTS, *PROGRAMS)}}


# ---------------------------------------------------------------------------------------------
# The trial program


def _trial_program() -> tuple:
    """The corrective-push test's program (``tests/test_positioning.py``: four particles, vmapped)
    and its arguments: the jitted function, the instrument, step A's model and a function of
    ``(instrument, model)`` giving the arguments."""
    import benchutil  # noqa: F401  (puts tests/ on sys.path)
    import jax
    import jax.numpy as jnp
    import test_positioning as tp

    from jaxafm.instrument.afm import default_afm, run_cycle
    from jaxafm.instrument.samples import Plane
    from jaxafm.position.online import NO_PUSH_FIELD
    from jaxafm.position.positioning import Positioner

    afm = default_afm(drift_nm_per_min=(0.0, 0.0))  # the test's instrument and step A model
    model = default_afm(loop_width=0.145).scanner.without("drift", "noise")
    state = run_cycle(afm, Plane(), afm.initial_state((0.0, 0.0), 0.0, tp.CYCLE), tp.CYCLE, jax.random.key(0))
    centres = jnp.array([[300.0, -200.0], [-250.0, 400.0], [200.0, 100.0], [-300.0, -300.0]])
    directions = jnp.array([[0.6, 0.8], [-1.0, 0.0], [0.0, -1.0], [0.8, 0.6]])

    def arguments(instrument, twin_model) -> tuple:
        pos = Positioner(instrument, twin_model)
        stand = pos.start(state, None if twin_model is None else tp.twin_after_cycle(afm, twin_model))
        return (pos, stand, centres, directions, 5.0, 600.0, 500.0, jax.random.key(1), NO_PUSH_FIELD)

    return tp._scan_push_and_check, afm, model, arguments


def compile_trial(jitted, args) -> dict:
    """``jitted`` lowered and compiled for ``args``: lowering and compile time (s), a run's time
    (s, the median of three), the optimised program's size (kilo-characters of its text), its while
    loops and its outputs flattened (``outputs``)."""
    import jax
    import numpy as np

    jax.clear_caches()
    t0 = time.perf_counter()
    lowered = jitted.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    runs = []
    for _ in range(3):
        t3 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t3)
    text = compiled.compiled.as_text()
    row = {"lower_s": t1 - t0, "compile_s": t2 - t1, "run_s": sorted(runs)[1]}
    row |= {"hlo_kchars": len(text) / 1e3, "while_loops": text.count(" while(")}
    return row | {
        "outputs": np.concatenate([np.ravel(np.asarray(x, float)) for x in jax.tree_util.tree_leaves(out)])
    }


def trial_under(flags: str) -> None:
    """Print the trial program's :func:`compile_trial` row as JSON, XLA on one thread with ``flags``
    (run in a process of its own, before JAX starts)."""
    os.environ["XLA_FLAGS"] = " ".join([ONE_THREAD, flags]).strip()
    jitted, afm, model, arguments = _trial_program()
    row = compile_trial(jitted, arguments(afm, model))
    print(json.dumps(row | {"outputs": row["outputs"].tolist()}))


def profile_flags(rounds: int) -> list:
    """:func:`trial_under` with none of :data:`FLAGS` and with each, ``rounds`` times, each round in
    its own order (so that what drifts on the machine, or comes first, meets every one alike), each
    compile in a fresh process: a row
    for each, its flags, the medians of its lowering, compile and run times, its compile times
    (``compile_runs``, s) and, for the flags, whether the results are those without flags (bit for
    bit) and their largest difference."""
    import numpy as np

    def run(flags: str) -> dict:
        out = subprocess.run(
            [sys.executable, __file__, f"--under={flags}"], capture_output=True, text=True, check=True
        )
        row = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{flags or 'none'}: compile {row['compile_s']:.1f} s, a run {1e3 * row['run_s']:.0f} ms")
        return row

    every = ("", *FLAGS)
    runs = {flags: [] for flags in every}
    for k in range(rounds):
        for flags in random.Random(k).sample(every, len(every)):  # a new order each round
            runs[flags].append(run(flags))
    want = np.array(runs[""][0]["outputs"])
    rows = []
    for flags, done in runs.items():
        row = {"flags": flags, "compile_runs": [r["compile_s"] for r in done]}
        row |= {k: float(np.median([r[k] for r in done])) for k in ("lower_s", "compile_s", "run_s")}
        if flags:
            got = [np.array(r["outputs"]) for r in done]
            row["same"] = all(np.array_equal(g, want, equal_nan=True) for g in got)
            row["largest_difference"] = max(float(np.nanmax(np.abs(g - want))) for g in got)
        rows.append(row)
    return rows


def profile_trial() -> list:
    """The corrective-push test's program compiled as the test compiles it, and with one part
    taken out at a time, and compiled at XLA's backend optimisation level 0: lowering and compile
    time (s), a run's time (s, the median of three), the optimised program's size (its text,
    kilo-characters) and its while loops; for level 0, its largest difference from the default's
    results."""
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), ONE_THREAD]).strip()
    jitted, afm, model, arguments = _trial_program()
    import equinox as eqx
    import numpy as np

    import jaxafm.identify.inverse as inverse

    blocked_only = inverse._or_per_sample

    def without_fallback(axis, v, t, state, t0, u0, lo, hi, blocked):
        u, _, after = blocked
        return u, (u < lo) | (u > hi), after

    def compile_once(label: str, instrument, twin_model, program=jitted) -> dict:
        row = {"program": label} | compile_trial(program, arguments(instrument, twin_model))
        print(
            f"{label}: lowering {row['lower_s']:.1f} s, compile {row['compile_s']:.1f} s, a run {row['run_s']:.3f} s"
        )
        return row

    quiet = eqx.tree_at(lambda a: a.scanner, afm, afm.scanner.without("drift", "noise"))
    at_o0 = eqx.filter_jit(jitted.__wrapped__, compiler_options={"xla_backend_optimization_level": 0})
    rows = [
        compile_once("as the test compiles it", afm, model),
        compile_once("the same at XLA's backend optimisation level 0", afm, model, at_o0),
        compile_once("the nominal calibration in place of step A's inverse", afm, None),
        compile_once("the instrument without drift and position noise", quiet, model),
    ]
    inverse._or_per_sample = without_fallback
    try:
        rows.append(compile_once("the inverse without its sample-by-sample fallback", afm, model))
    finally:
        inverse._or_per_sample = blocked_only
    same = rows[1].pop("outputs") - rows[0]["outputs"]
    rows[1]["largest_difference"] = float(np.nanmax(np.abs(same)))
    for r in rows:
        r.pop("outputs", None)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trial", action="store_true", help="the trial program's compile alone")
    ap.add_argument("--flags", action="store_true", help="the trial program under each of XLA's FLAGS")
    ap.add_argument("--rounds", type=int, default=3, help="--flags: compiles of each, in turn (default 3)")
    ap.add_argument("--under", help=argparse.SUPPRESS)  # one of --flags' processes
    args = ap.parse_args()
    if args.under is not None:
        return trial_under(args.under)
    OUT.mkdir(parents=True, exist_ok=True)
    if args.flags:
        (OUT / "flags.json").write_text(
            json.dumps(
                {"xla_flags": ONE_THREAD, "rounds": args.rounds, "rows": profile_flags(args.rounds)}, indent=1
            )
        )
        return
    if args.trial:
        (OUT / "trial.json").write_text(
            json.dumps({"xla_flags": ONE_THREAD, "rows": profile_trial()}, indent=1)
        )
        return
    doc = profile_suite(OUT / "parts")
    (OUT / "suite.json").write_text(json.dumps(doc, indent=1))
    t = doc["total"]
    compile_s = t["trace_s"] + t["lower_s"] + t["backend_s"]
    print(
        f"suite {doc['suite_wall_s']:.0f} s; tests {t['wall_s']:.0f} s in both workers, {compile_s:.0f} s compiling"
    )


if __name__ == "__main__":
    main()
