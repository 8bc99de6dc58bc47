"""Several processes: a small study run as two ``jaxafm study`` processes joined through
``jax.distributed`` (CPU collectives over TCP, the coordinator on localhost) gives the results of
one process; the options that join them fail, naming the option, where they cannot."""

import json
import os
import socket
import subprocess

import numpy as np
import pytest
from test_study import cli, results, write
from typer.testing import CliRunner

from jaxafm.cli import app
from jaxafm.jobs import read_manifest
from jaxafm.jobs.study import WALL_TIMES


def _gloo() -> bool:
    """Whether this jaxlib has the TCP collectives that processes on CPU need."""
    try:
        from jax._src.lib import _jax
    except ImportError:
        return False
    return hasattr(_jax, "make_gloo_tcp_collectives")


def free_port() -> int:
    """A TCP port nobody listens on now (the coordinator's)."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def finish(proc: subprocess.Popen, timeout: float = 300) -> str:
    """``proc``'s output once it has ended (killed after ``timeout`` s: a process left waiting
    for the others ends the test rather than hangs it)."""
    try:
        return proc.communicate(timeout=timeout)[0]
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()[0] + f"\n[killed after {timeout} s]"


def start(path, out, processes: int = 1) -> list:
    """``jaxafm study`` started in ``processes`` processes of one device each, joined on localhost
    (one process: with two host devices, as many as the pair has)."""
    if processes == 1:
        return [cli(path, "--out", out, devices=2)]
    join = ("--coordinator", f"localhost:{free_port()}", "--processes", processes, "--process-id")
    return [cli(path, "--out", out, *join, i) for i in range(processes)]


def ended(procs: list) -> list:
    """The outputs of ``procs`` once all have ended, each with exit status 0."""
    logs = [finish(p) for p in procs]
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]
    return logs


def chunks(out) -> dict:
    """Every chunk file's columns, by file name."""
    return {f.name: dict(np.load(f)) for f in sorted((out / "chunks").iterdir())}


def metrics(out) -> str:
    """``metrics.json`` but the wall times, as text (NaN equals NaN)."""
    doc = json.loads((out / "metrics.json").read_text())
    return json.dumps({k: v for k, v in doc.items() if k not in WALL_TIMES})


def assert_identical(got: dict, want: dict, where: str) -> None:
    """The same columns, equal to the last bit."""
    assert set(got) == set(want), where
    for k, v in want.items():
        np.testing.assert_array_equal(got[k], v, err_msg=f"{where} {k}")


GLOO = pytest.mark.skipif(not _gloo(), reason="this jaxlib has no CPU collectives (gloo) for jax.distributed")


@GLOO
def test_two_processes_give_the_results_of_one(tmp_path):
    """Three trials on one scanner in chunks of 2 (the second padded to 2), run by one process
    with two host devices and by two processes of one device each: the trial columns, each chunk
    file and the metrics are identical to the last bit (each device runs the same program on the
    same trials, one a device; a process gathers the others' trials as they are). Only process 0
    logs and writes; the run manifest lists the files."""
    path = write(tmp_path, trials=3, trials_per_scanner=3, chunk=2)
    one, two = tmp_path / "one", tmp_path / "two"
    # the one process, then the pair: not all three at once, which put three processes' XLA
    # compiles (nearly all of each run) on two cores beside the test session's own
    ended(start(path, one))
    logs = ended(start(path, two, processes=2))
    assert "3 trials on 1 scanner(s), 2 device(s) in 2 processes, chunks of 2" in logs[0]
    assert "wrote the results" in logs[0] and "process 1 of 2: joining" in logs[1]
    assert "wrote the results" not in logs[1] and "A+B" not in logs[1]  # no log, no table
    want = results(one)
    assert np.isfinite(want["AB_error_nm"]).all()
    assert_identical(results(two), want, "trials.npz")
    theirs, ours = chunks(two), chunks(one)
    assert list(ours) == ["trials_00000000_00000002.npz", "trials_00000002_00000003.npz"] == list(theirs)
    for name, columns in ours.items():
        assert_identical(theirs[name], columns, name)
    assert metrics(two) == metrics(one)
    manifest = read_manifest(two)
    assert manifest["status"] == "complete" and "metrics.json" in manifest["files"]
    assert not list(two.rglob(".jaxafm-*"))  # no half-written file of another process


@pytest.mark.parametrize(
    "options, message",
    [
        (["--processes", "2"], "--processes needs --coordinator"),
        (["--process-id", "1"], "--process-id needs --coordinator"),
        (["--coordinator", "localhost"], "--coordinator 'localhost': expected HOST:PORT"),
        (["--coordinator", "localhost:70000", "--processes", "2", "--process-id", "0"], "1 to 65535"),
        (["--coordinator", "localhost:1234", "--processes", "2"], "needs --process-id I"),
        (["--coordinator", "localhost:1234", "--process-id", "0"], "needs --processes N"),
        (
            ["--coordinator", "localhost:1234", "--processes", "0", "--process-id", "0"],
            "--processes 0: must be 1 or more",
        ),
        (
            ["--coordinator", "localhost:1234", "--processes", "2", "--process-id", "2"],
            "--process-id 2: must be 0 to 1",
        ),
        (
            ["--coordinator", "auto", "--processes", "2", "--process-id", "-1"],
            "--process-id -1: must be 0 to 1",
        ),
        (
            ["--coordinator", "no-such-host.invalid:1234", "--processes", "2", "--process-id", "1"],
            "--coordinator no-such-host.invalid:1234: unknown host",
        ),
    ],
)
def test_bad_process_options_fail_naming_the_option(tmp_path, options, message):
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["study", str(write(tmp_path)), "--out", str(out), *options])
    assert res.exit_code == 2 and message in res.output and not out.exists(), res.output


@GLOO
def test_coordinator_port_in_use_fails_naming_it(tmp_path):
    """Process 0 cannot listen on a port another program holds: the error names the option and
    the port (in a process of its own: a failed ``jax.distributed.initialize`` is not undone)."""
    with socket.socket(socket.AF_INET6 if socket.has_ipv6 else socket.AF_INET) as held:
        held.bind(("", 0))
        held.listen()
        port = held.getsockname()[1]
        join = ("--coordinator", f"localhost:{port}", "--processes", 2, "--process-id", 0)
        proc = cli(write(tmp_path), "--out", tmp_path / "out", *join)
        log = finish(proc, 120)
    assert proc.returncode == 2, log[-3000:]
    assert f"--coordinator localhost:{port}: process 0 cannot listen on port {port}" in log
    assert not (tmp_path / "out").exists()


def test_coordinator_auto_outside_a_cluster_fails_naming_it(tmp_path, monkeypatch):
    """``--coordinator auto`` where no cluster environment says where the coordinator is (in a
    process of its own: ``jax.distributed.initialize`` comes before any JAX computation)."""
    for name in os.environ:
        if name.startswith(("SLURM_", "OMPI_", "PMI_", "KUBERNETES_", "JAX_COORDINATOR")):
            monkeypatch.delenv(name)
    proc = cli(write(tmp_path), "--out", tmp_path / "out", "--coordinator", "auto")
    log = finish(proc, 120)
    assert proc.returncode == 2, log[-3000:]
    assert "--coordinator auto: no cluster environment gives the coordinator" in log
    assert "--coordinator HOST:PORT --processes N --process-id I" in log and not (tmp_path / "out").exists()
