"""Nothing a user saved is lost: the run manifest, --overwrite that removes only what jaxafm wrote,
unfinished runs that are replaced or resumed without a flag hunt, Ctrl-C that says how to go on,
and errors without tracebacks (``--debug`` shows them)."""

import hashlib
import json
import os
import signal
import subprocess
import sys
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
    assert all(JOBS["fit"].planned(cfg, f) for f in out.written), JOBS["fit"].planned_outputs(cfg)


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
    assert list(m["files"]) == ["model_pi.json"]
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
    """A manifest left 'running' by a process that is gone: the files it records (with the hash
    of their bytes) and its unfinished temporary files are removed by the next run; the user's
    notes, the user's file the manifest does not record and the one it records with other bytes
    are kept. One whose process still runs (this one) refuses a second writer."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "model_half.json").write_text("{}")  # written by the killed run
    (out / ".jaxafm-0123456789abcdef.fit.png").write_text("half a figure")  # its temporary file
    (out / "model_edited.json").write_text("{}")  # written by it, then edited by the user
    kept = mine(out, {"notes.txt": "keep me", "model_edited.json": "{ edited }", "model_mine.json": "{}"})
    manifest = {
        "format": "jaxafm-run",
        "version": 2,
        "command": "fit",
        "status": "running",
        "host": os.uname().nodename,
        "pid": 2**22 + 12345,  # above the default pid_max: no such process
        "started_ns": 0,
        "token": "0123456789abcdef",
        "foreign": ["notes.txt"],
        "files": {f: [hashlib.sha256(b"{}").hexdigest()] for f in ("model_half.json", "model_edited.json")},
        "dirs": [],
    }
    (out / MANIFEST).write_text(json.dumps(manifest))
    result = fit(config(tmp_path))
    assert result.exit_code == 0, result.output
    assert unchanged(out, kept) and f"keeping {out / 'model_edited.json'}" in result.output
    assert not (out / "model_half.json").exists() and not (out / ".jaxafm-0123456789abcdef.fit.png").exists()
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


def test_an_unwritable_folder_is_refused_before_work(tmp_path):
    if writes_into_read_only_folders(tmp_path):
        pytest.skip("this process writes into read-only folders (root)")
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


# ---------------------------------------------------------------- a user's files, whatever runs

# two chunks of one scanner: the tests below stop or watch a study at its second chunk, and none
# needs a second scanner's step A and survey
STUDY = """
trials: 4
trials_per_scanner: 4
chunk: 2
stages: [open_loop]
scanner: {creep: {gamma: {uniform: [0.005, 0.02]}}}
particle_radius_nm: {uniform: [10.0, 20.0]}
calibration:
  simulate: {pixels: 32, size_nm: 8000.0, line_rate_hz: 10.0, seed: 0}
  grating: {pitch_nm: 1000.0}
  model: {name: pi, kind: pi, operators: 4, effects: []}
  solver: {max_steps: 1, blur_px: [1.0]}
workspace: {size_nm: 2000.0, centre_nm: [0.0, 0.0], pixels: 32, line_rate_hz: 10.0}
landmarks: {n: 2, start_px: 8, step_px: 16, depth_nm: 50.0, interpolation: [polynomial], m: 2, degree: 1}
local_scan: {points: 16, line_time_s: 0.5, margin_nm: 40.0, max_lines: 3}
seed: 0
output: runs/a
"""

CALIBRATE = """
simulate: {pixels: 32, size_nm: 4000.0, line_rate_hz: 10.0, seed: 0}
grating: {pitch_nm: 1000.0}
models: [{name: gpi, kind: pi, operators: 4, effects: []}]
solver: {max_steps: 1, blur_px: [1.0]}
compensate: null
"""


def command(name: str, cfg: Path, out: Path, *flags: str):
    return runner.invoke(app, [name, str(cfg), "--out", str(out), *flags])


def mine(folder: Path, files: dict) -> dict:
    """Write the user's ``files`` (relative path -> text) into ``folder``; returns their hashes."""
    for name, text in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
    return {k: v for k, v in snapshot(folder).items() if k in files}


def unchanged(folder: Path, before: dict) -> bool:
    now = snapshot(folder)
    return all(now.get(k) == v for k, v in before.items())


def chunk_hook(monkeypatch, on_call):
    """Wrap the study's ``run_chunk``: ``on_call(n)`` runs before its ``n``-th call (1, 2, ...)."""
    from jaxafm.jobs import study as study_job

    real, calls = study_job.run_chunk, []

    def hooked(*args, **kwargs):
        calls.append(1)
        on_call(len(calls))
        return real(*args, **kwargs)

    monkeypatch.setattr(study_job, "run_chunk", hooked)


def test_calibrate_never_replaces_a_users_validation_figure(tmp_path):
    """Item 1 of issue 41: ``validation_<name>.png`` is one of calibrate's planned outputs, so a
    user's file of that name stops it before any work, with --overwrite too."""
    cfg = config(tmp_path, CALIBRATE)
    out = tmp_path / "o"
    out.mkdir()
    before = mine(out, {"validation_gpi.png": "my own figure", "notes.txt": "keep me"})
    result = command("calibrate", cfg, out, "--overwrite")
    assert unchanged(out, before)
    assert result.exit_code == 2 and "validation_gpi.png" in result.output, result.output


@pytest.mark.parametrize("figure", ["errors.png", "push_odds.png", "learning.png", "position_coverage.png"])
def test_study_never_replaces_a_users_figure(tmp_path, figure):
    """Every figure a study may draw (``jaxafm.jobs.study.summarise``: the push's odds, the
    learning curve and the positions' coverage with ``learning`` and a push) is one of its
    planned outputs: a user's file of that name stops it before any work, with --overwrite too,
    instead of at the end of a long study."""
    cfg = config(tmp_path, STUDY)
    out = tmp_path / "o"
    out.mkdir()
    before = mine(out, {figure: "my own figure"})
    result = command("study", cfg, out, "--overwrite")
    assert unchanged(out, before)
    assert result.exit_code == 2 and figure in result.output and "trials" not in result.output, result.output


@pytest.mark.parametrize("interrupt", [True, False], ids=["ctrl-c", "finished"])
def test_a_file_saved_during_a_study_stays_the_users(tmp_path, monkeypatch, interrupt):
    """Items 2 and 3 of issue 41: the user saves notes.txt into the folder while a study runs;
    the study (interrupted by Ctrl-C at its second chunk, or finished) records only the files it
    wrote, and ``--overwrite`` then removes those alone."""
    cfg = config(tmp_path, STUDY)
    out = tmp_path / "o"

    def user_then_ctrl_c(n):
        if n == 1:
            (out / "notes.txt").write_text("written while the study ran")
        if n == 2 and interrupt:
            raise KeyboardInterrupt

    chunk_hook(monkeypatch, user_then_ctrl_c)
    first = command("study", cfg, out)
    assert first.exit_code == (130 if interrupt else 0), first.output
    before = {k: v for k, v in snapshot(out).items() if k == "notes.txt"}
    files = set(read_manifest(out)["files"])
    assert "notes.txt" not in files and "chunks/trials_00000000_00000002.npz" in files
    if interrupt:
        assert f"interrupted: {len(files)} file(s) saved" in first.output
    monkeypatch.undo()
    again = command("study", cfg, out, "--overwrite")
    assert again.exit_code == 0, again.output
    assert unchanged(out, before)


KILL_AT_SECOND_CHUNK = """
import os, signal, sys
from jaxafm.cli import main
from jaxafm.jobs import study
real, calls = study.run_chunk, []
def killed(*args, **kwargs):
    calls.append(1)
    if len(calls) == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    return real(*args, **kwargs)
study.run_chunk = killed
main()
"""


def test_a_killed_study_leaves_the_users_file_to_the_next_command(tmp_path):
    """Item 4 of issue 41: a study killed outright (SIGKILL, at its second chunk), then the user
    writes crash_notes.txt, then another command without a flag (``fit``, the quickest to run)
    replaces the unfinished study: the study's own files go, the user's stays byte for byte."""
    cfg = config(tmp_path, STUDY)
    out = tmp_path / "o"
    killed = subprocess.run(
        [sys.executable, "-c", KILL_AT_SECOND_CHUNK, "study", str(cfg), "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert killed.returncode == -signal.SIGKILL, killed.stdout[-2000:] + killed.stderr[-2000:]
    assert read_manifest(out)["status"] == "running" and (out / "chunks").is_dir()
    before = mine(out, {"crash_notes.txt": "what I saw when it crashed"})
    other = command("fit", config(tmp_path), out)
    assert unchanged(out, before)
    assert other.exit_code == 0, other.output
    assert "replacing the unfinished results (running) of `jaxafm study`" in other.output
    assert not (out / "chunks").exists()


def test_overwrite_compares_paths_inside_the_folder(tmp_path):
    """Item 13 of issue 41: the user's my_analysis/metrics.json is not the fit's metrics.json:
    with --overwrite the fit writes beside it."""
    out = tmp_path / "out"
    out.mkdir()
    before = mine(out, {"my_analysis/metrics.json": '{"mine": 1}'})
    result = fit(config(tmp_path), "--overwrite")
    assert result.exit_code == 0, result.output
    assert unchanged(out, before) and (out / "metrics.json").is_file()


def writes_into_read_only_folders(tmp_path: Path) -> bool:
    """Whether this process writes into a folder without write permission (root, or a process
    with CAP_DAC_OVERRIDE, does)."""
    locked = tmp_path / "probe"
    locked.mkdir(mode=0o555)
    try:
        (locked / "probe").write_text("")
        return True
    except PermissionError:
        return False
    finally:
        locked.chmod(0o755)


def test_a_read_only_folder_the_study_writes_into_is_refused_before_work(tmp_path, monkeypatch):
    """Item 14 of issue 41: a read-only chunks/ is refused before any scanner is prepared,
    naming the folder."""
    from jaxafm.jobs import study as study_job

    if writes_into_read_only_folders(tmp_path):
        pytest.skip("this process writes into read-only folders (root)")
    prepared = []
    monkeypatch.setattr(study_job, "prepare_scanner", lambda *a, **k: prepared.append(1))
    cfg = config(tmp_path, STUDY)
    out = tmp_path / "o"
    (out / "chunks").mkdir(parents=True)
    (out / "chunks").chmod(0o555)
    try:
        result = command("study", cfg, out, "--overwrite")
    finally:
        (out / "chunks").chmod(0o755)
    assert result.exit_code == 2 and f"cannot write into {out / 'chunks'}" in result.output, result.output
    assert "permission denied" in result.output and not prepared


def test_a_users_file_in_a_folder_the_study_writes_into(tmp_path):
    """Item 15 of issue 41 (first part): chunks/readme.txt is no chunk file: the study writes its
    chunks beside it, and it stays byte for byte."""
    out = tmp_path / "o"
    out.mkdir()
    before = mine(out, {"chunks/readme.txt": "my notes on these chunks"})
    result = command("study", config(tmp_path, STUDY), out, "--overwrite")
    assert result.exit_code == 0, result.output
    assert unchanged(out, before) and (out / "chunks" / "trials_00000000_00000002.npz").is_file()


def test_a_changed_output_key_alone_does_not_block_a_resume(tmp_path, monkeypatch):
    """Item 15 of issue 41 (second part): where the results go is no part of what they are: a
    study interrupted with ``output: runs/a`` resumes under ``output: runs/b`` with the same --out."""

    def ctrl_c(n):
        if n == 2:
            raise KeyboardInterrupt

    chunk_hook(monkeypatch, ctrl_c)
    out = tmp_path / "o"
    assert command("study", config(tmp_path, STUDY), out).exit_code == 130
    monkeypatch.undo()
    moved = config(tmp_path, STUDY.replace("output: runs/a", "output: runs/b"))
    result = command("study", moved, out)
    assert result.exit_code == 0, result.output
    assert "resuming the unfinished `jaxafm study`" in result.output and "resuming: 2 done" in result.output


def test_predict_on_inputs_alone_writes_metrics(tmp_path):
    """Item 15 of issue 41 (third part): every command writes metrics.json, a prediction from a
    record without output columns too."""
    import numpy as np

    from jaxafm import PrandtlIshlinskii
    from jaxafm.model.io import describe, save_model

    u = 2.0 + 2.0 * np.sin(np.linspace(0, 4 * np.pi, 100))
    pi = PrandtlIshlinskii.uniform(4, 2.0, 100.0)
    save_model(pi, tmp_path / "model.json", describe(pi, u, 100.0 * u))
    t = np.arange(100) / 100.0
    (tmp_path / "inputs.csv").write_text("t_s,u_v\n" + "\n".join(f"{a},{b}" for a, b in zip(t, u)))
    cfg = config(
        tmp_path,
        "model: model.json\ndata: {path: inputs.csv, input_columns: [u_v], time_column: t_s, delimiter: ','}\n",
    )
    result = command("predict", cfg, tmp_path / "out")
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["samples"] == 100 and metrics["outside_fitted_range_pct"] == 0.0


def test_every_committed_run_can_be_made_again_over_its_own_folder():
    """Each committed run's files hold the bytes its manifest records (those the run wrote), so
    that its documented command with ``--overwrite`` replaces them rather than keeping them as a
    user's file and refusing the run. A figure redrawn from a run's results must be recorded in its
    manifest (its chunk files, left out of the repository, are not checked)."""
    root = Path(__file__).resolve().parents[1] / "experiments" / "results"
    manifests, changed = sorted(root.rglob(MANIFEST)), []
    for manifest in manifests:
        recorded = json.loads(manifest.read_text())["files"]
        assert isinstance(recorded, dict), f"{manifest}: no hashes recorded"
        for rel, hashes in recorded.items():
            path = manifest.parent / rel
            if path.is_file() and hashlib.sha256(path.read_bytes()).hexdigest() not in hashes:
                changed.append(str(path.relative_to(root)))
    assert len(manifests) >= 40  # the committed runs are where this looks
    assert not changed, f"files whose bytes their run's manifest does not record: {changed}"
