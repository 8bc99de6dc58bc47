"""The test session's compilation cache.

JAX compiles again whatever it runs op by op that holds a loop (a ``lax.scan``: every
eager call of a scanner, a move, a press), and the tests of one session compile many
programs more than once (the same scan in several tests, the same study in this process
and in the ``jaxafm study`` processes test_study starts). A persistent compilation cache
in a folder of this session's own turns each repeat into a read: the same executable,
so nothing a test computes or checks changes. The folder starts empty (no result of an
earlier run is reused) and is removed when the session ends. The pytest process makes it
before pytest-xdist starts its workers, which find it through ``JAXAFM_TEST_XLA_CACHE`` and
share it: a program one worker compiled, the other reads.

After each test module the in-memory executables are dropped (``jax.clear_caches``); the next
module reads what it shares from the folder. Kept for the whole session, they crashed it twice in
XLA's compiler (a segmentation fault in test_step_a_sets, at 95 % of the suite; the file passes
alone). Each executable holds memory maps, and a process may have 65,530: one module's tests
reached 5,348 maps before the drop and the process was back at 1,428 after it (measured), so the
session no longer grows towards that limit.

Under pytest-xdist each worker runs XLA (and OpenBLAS) on one thread: with two workers on two
cores, each one's programs spreading over both cores made them contend (the suite 7 min 43 s and
7 min 56 s with the threads left to XLA, 7 min 24 s with one each, in one session; the same
tests and results).

The longest modules are collected first (:data:`LONGEST_FIRST`), and ``--no-loadscope-reorder``
(``pyproject.toml``) keeps that order: ``--dist loadfile`` hands whole modules to the two workers
in it, each worker the next module when its last is nearly done, so the long ones start early and
the short ones fill in at the end, instead of one worker finishing a long module alone. Without
that option pytest-xdist orders the modules by their number of tests, which puts modules of a few
long tests (test_step_a_wide_loop, test_diagnose_independent) last.
"""

import os
import shutil
import tempfile

if "PYTEST_XDIST_WORKER" in os.environ:  # -n 2 on 2 cores: one core to each worker (set before JAX starts)
    os.environ["XLA_FLAGS"] = " ".join(
        [os.environ.get("XLA_FLAGS", ""), "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"]
    ).strip()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax
import pytest

_OWNER = "JAXAFM_TEST_XLA_CACHE" not in os.environ  # the pytest process that made the folder
_BEFORE = {
    k: os.environ.get(k) for k in ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")
}
_CACHE = os.environ.get("JAXAFM_TEST_XLA_CACHE") or tempfile.mkdtemp(prefix="jaxafm-tests-xla-")
_SETTINGS = {
    "JAXAFM_TEST_XLA_CACHE": _CACHE,  # xdist's workers, started after this, find and share it
    "JAX_COMPILATION_CACHE_DIR": _CACHE,
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
}

jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
os.environ.update(_SETTINGS)  # the processes the tests start share it


#: modules by their measured time in one suite (s, ``--durations=0``, 2 workers), longest first
LONGEST_FIRST = (
    "test_study.py",  # 141
    "test_positioning.py",  # 139
    "test_diagnose_independent.py",  # 113
    "test_step_a_sets.py",  # 101
    "test_step_a.py",  # 98
    "test_step_a_wide_loop.py",  # 82
    "test_diagnose_record.py",  # 71
    "test_diagnose.py",  # 56
    "test_distributed.py",  # 55
    "test_time_parallel.py",  # 53
    "test_diagnose_scans.py",  # 51
    "test_fit.py",  # 39
    "test_step_a_independent.py",  # 38
    "test_wander.py",  # 38
)


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest as collected


@pytest.fixture(autouse=True, scope="module")
def _drop_executables():
    yield
    jax.clear_caches()


def pytest_unconfigure(config):
    if not _OWNER:  # a worker: the process that made the folder removes it
        return
    os.environ.pop("JAXAFM_TEST_XLA_CACHE", None)
    for k, v in _BEFORE.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    shutil.rmtree(_CACHE, ignore_errors=True)
