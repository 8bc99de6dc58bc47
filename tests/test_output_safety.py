"""Nothing a user saved is lost: the run manifest, --overwrite that removes only what jaxafm wrote,
unfinished runs that are replaced or resumed without a flag hunt, Ctrl-C that says how to go on,
and errors without tracebacks (``--debug`` shows them)."""

import hashlib
import json
import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from jaxafm.cli import app
from jaxafm.jobs import JOBS, MANIFEST, Output, read_manifest
from jaxafm.jobs import fit as fit_job

runner = CliRunner()

FIT = """
simulate: {duration_s: 2, sample_rate_hz: 100, modulation_period_s: 1}
models:
  - {name: pi, kind: pi, operators: 4, max_steps: 50}
output: out
"""


def config(tmp_path: Path, text: str = FIT) -> Path:
    path = tmp_path / "fit.yaml"
    path.write_text(text)
    return path


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` -> the hash of its bytes."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in folder.rglob("*")
        if p.is_file()
    }


def fit(cfg: Path, *flags: str):
    return runner.invoke(app, ["fit", str(cfg), "--out", str(cfg.parent / "out"), *flags])


def test_a_run_records_its_files_and_config(tmp_path):
    result = fit(config(tmp_path))
    assert result.exit_code == 0, result.output
    m = read_manifest(tmp_path / "out")
    assert m["status"] == "complete" and m["command"] == "fit"
    assert set(m["files"]) == {"metrics.json", "fit.png", "model_pi.json"}
    assert m["config"]["models"][0]["operators"] == 4 and m["foreign"] == []


def test_a_job_writes_the_files_its_command_plans(tmp_path):
    """The files a job writes, as its :class:`~jaxafm.jobs.Output` records them, are every file
    in its folder and each is one the command table plans for its command and config."""
    from jaxafm.config import ActuatorFitConfig, load_config

    path = config(tmp_path, FIT.replace("models:", "models:\n  - {name: line, kind: linear, max_steps: 5}"))
    cfg = load_config(path, ActuatorFitConfig)
    out = Output(tmp_path / "direct")
    JOBS["fit"].run(cfg, path, out, log=lambda line: None)
    on_disk = sorted(p.relative_to(out.path).as_posix() for p in out.path.rglob("*") if p.is_file())
    assert sorted(out.written) == on_disk == ["fit.png", "metrics.json", "model_line.json", "model_pi.json"]
    planned = JOBS["fit"].planned_outputs(cfg)
    assert all(any(Path(f).match(pattern) for pattern in planned) for f in out.written), planned


def test_every_command_is_a_job_of_the_table():
    """The command line's commands are the command table's, and ``effects``."""
    commands = {c.name or c.callback.__name__ for c in app.registered_commands}
    assert commands == set(JOBS) | {"effects"}


def test_overwrite_removes_only_what_jaxafm_wrote(tmp_path):
    """A user's own model_mine.json and notes beside a finished fit survive --overwrite; the
    fit's own files are replaced (and a model the new config no longer writes is removed)."""
    cfg = config(tmp_path, FIT.replace("name: pi", "name: old"))
    assert fit(cfg).exit_code == 0
    out = tmp_path / "out"
    (out / "model_mine.json").write_text('{"mine": true}')
    (out / "sub").mkdir()
    (out / "sub" / "notes.txt").write_text("keep me")
    mine = {k: v for k, v in snapshot(out).items() if k in ("model_mine.json", "sub/notes.txt")}
    again = fit(config(tmp_path), "--overwrite")
    assert again.exit_code == 0, again.output
    assert {k: v for k, v in snapshot(out).items() if k in mine} == mine
    assert not (out / "model_old.json").exists() and (out / "model_pi.json").is_file()
    assert set(read_manifest(out)["foreign"]) == {"model_mine.json", "sub/notes.txt"}


def test_finished_results_need_overwrite(tmp_path):
    cfg = config(tmp_path)
    assert fit(cfg).exit_code == 0
    before = snapshot(tmp_path)
    again = fit(cfg)
    assert again.exit_code == 2 and "--overwrite" in again.output and "jaxafm fit" in again.output
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("flags", [(), ("--overwrite",)])
def test_a_users_file_with_an_outputs_name_is_never_replaced(tmp_path, flags):
    """A folder jaxafm did not write: without --overwrite nothing is written into it; with it,
    a file named like one of the outputs (here metrics.json) stops the run before any work."""
    cfg = config(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("my own metrics")
    before = snapshot(tmp_path)
    result = fit(cfg, *flags)
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert ("metrics.json" in result.output) if flags else ("--overwrite" in result.output)
    assert snapshot(tmp_path) == before


def test_overwrite_writes_beside_a_users_files(tmp_path):
    cfg = config(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    result = fit(cfg, "--overwrite")
    assert result.exit_code == 0, result.output
    assert (out / "notes.txt").read_text() == "keep me" and (out / "model_pi.json").is_file()
    assert read_manifest(out)["foreign"] == ["notes.txt"]


def test_a_failed_run_is_marked_and_the_next_one_replaces_it(tmp_path, monkeypatch):
    """A fit that fails after writing its first model leaves a folder marked 'failed' (the model
    listed as the failed run's file); the same command, without a flag, replaces it."""
    calls = []
    real = fit_job.fit_operator

    def fail_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("the solver broke down")
        return real(*args, **kwargs)

    monkeypatch.setattr(fit_job, "fit_operator", fail_second)
    two = FIT.replace("output: out", "  - {name: pi2, kind: pi, operators: 5, max_steps: 50}")
    cfg = config(tmp_path, two)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    result = fit(cfg, "--overwrite")
    assert result.exit_code == 2 and "the solver broke down" in result.output
    m = read_manifest(out)
    assert m["status"] == "failed" and "the solver broke down" in m["error"]
    assert m["files"] == ["model_pi.json"]
    monkeypatch.setattr(fit_job, "fit_operator", real)
    again = fit(cfg)
    assert again.exit_code == 0, again.output
    assert "replacing the unfinished results (failed)" in again.output
    assert read_manifest(out)["status"] == "complete" and (out / "notes.txt").read_text() == "keep me"


def test_ctrl_c_says_what_was_saved_and_how_to_go_on(tmp_path, monkeypatch):
    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_job, "fit_operator", interrupt)
    cfg = config(tmp_path)
    result = fit(cfg)
    out = tmp_path / "out"
    assert result.exit_code == 130
    assert "interrupted" in result.output and f"jaxafm fit {cfg} --out {out}" in result.output
    assert read_manifest(out)["status"] == "interrupted"


def test_a_run_killed_outright_is_replaced_and_a_live_one_refused(tmp_path):
    """A manifest left 'running' by a process that is gone: its files (not foreign, written
    after it started) are removed by the next run, the foreign ones kept. One whose process
    still runs (this one) refuses a second writer."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    (out / "model_half.json").write_text("{")  # written by the killed run
    manifest = {
        "format": "jaxafm-run",
        "command": "fit",
        "status": "running",
        "host": os.uname().nodename,
        "pid": 2**22 + 12345,  # above the default pid_max: no such process
        "started_ns": 0,
        "foreign": ["notes.txt"],
        "files": [],
    }
    (out / MANIFEST).write_text(json.dumps(manifest))
    result = fit(config(tmp_path))
    assert result.exit_code == 0, result.output
    assert not (out / "model_half.json").exists() and (out / "notes.txt").read_text() == "keep me"
    (out / MANIFEST).write_text(json.dumps(manifest | {"pid": os.getpid()}))
    busy = fit(config(tmp_path))
    assert busy.exit_code == 2 and "in use" in busy.output


def test_output_that_is_a_file_or_a_broken_manifest(tmp_path):
    cfg = config(tmp_path)
    (tmp_path / "out").write_text("a file")
    result = fit(cfg)
    assert result.exit_code == 2 and "not a folder" in result.output
    (tmp_path / "out").unlink()
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / MANIFEST).write_text("{ not json")
    result = fit(cfg, "--overwrite")
    assert result.exit_code == 2 and MANIFEST in result.output and "Traceback" not in result.output


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_an_unwritable_folder_is_refused_before_work(tmp_path):
    cfg = config(tmp_path)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        result = runner.invoke(app, ["fit", str(cfg), "--out", str(locked / "out")])
    finally:
        locked.chmod(0o700)
    assert result.exit_code == 2 and "permission denied" in result.output


def test_a_bug_is_reported_as_one_and_debug_shows_the_traceback(tmp_path, monkeypatch):
    def bug(*args, **kwargs):
        raise IndexError("index 3 is out of bounds")

    monkeypatch.setattr(fit_job, "fit_operator", bug)
    cfg = config(tmp_path)
    result = fit(cfg)
    assert result.exit_code == 3 and "bug in jaxafm" in result.output and "--debug" in result.output
    assert "Traceback" not in result.output
    debug = fit(cfg, "--debug")
    assert isinstance(debug.exception, IndexError)


def test_resume_only_where_there_is_a_study(tmp_path):
    result = fit(config(tmp_path), "--resume")
    assert result.exit_code == 2  # fit has no --resume option: typer's usage error
    study = tmp_path / "study.yaml"
    study.write_text("trials: 4\nchunk: 4\ntrials_per_scanner: 4\n")
    out = tmp_path / "empty"
    result = runner.invoke(app, ["study", str(study), "--out", str(out), "--resume"])
    assert result.exit_code == 2 and "holds no run to resume" in result.output
    assert not out.exists()


def test_a_run_refused_by_its_data_leaves_the_earlier_results_as_they_were(tmp_path):
    """--overwrite on a finished fit, with a config whose record cannot be read: the error comes
    before the folder is prepared, so the earlier results and their manifest stay as they were."""
    cfg = config(tmp_path)
    assert fit(cfg).exit_code == 0
    before = snapshot(tmp_path / "out")
    cfg.write_text("data: {path: missing.csv}\nmodels: [{name: pi, kind: pi}]\n")
    result = fit(cfg, "--overwrite")
    assert result.exit_code == 2 and "missing.csv" in result.output
    assert snapshot(tmp_path / "out") == before
