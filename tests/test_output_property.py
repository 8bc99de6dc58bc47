"""A user's files in an output folder survive any sequence of runs (the ownership rule of
``jaxafm.jobs.folder``): random interleavings, from a seeded generator, of

- runs of three cheap commands (``fit`` on a tiny simulated record, ``predict``, ``compensate``)
  into one folder, each with or without ``--overwrite``, one after another;
- runs stopped at a random point: Ctrl-C (``KeyboardInterrupt`` in this process) or a kill
  (``SIGKILL`` of a ``jaxafm`` process);
- the user's files, written before a run, while it runs (from another thread, at a random point
  of the run) and after it: new files, some at the paths of the commands' outputs, and edits of
  files a run wrote (which makes them the user's).

After every run every file of the user's holds the bytes the user last wrote. The points are the
runs' own steps (each file hashed, each manifest record of the running run), counted by wrapping
:func:`jaxafm.jobs.folder.file_hash` and :meth:`jaxafm.jobs.folder.RunFolder.record`, so that each
iteration does the same thing at every run of the test; the user's thread writes while the run
waits for it.
"""

import hashlib
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from jaxafm.cli import app
from jaxafm.jobs import folder as folder_module
from jaxafm.jobs import read_manifest

SEED = 41
ITERATIONS = 8  # folders, each taking RUNS runs
RUNS = 5
KILLS = 3  # runs stopped by SIGKILL in a process of their own, over the whole test (the costly kind)

FIT = {
    "simulate": {"duration_s": 1.0, "sample_rate_hz": 100.0, "modulation_period_s": 0.5, "noise_nm": 1.0},
    "models": [{"name": "pi", "kind": "pi", "operators": 4, "max_steps": 10}],
}

#: where the user puts files: paths no command writes, and the paths of each command's outputs
OWN = ["notes.txt", "sub/notes.md", "my_analysis/metrics.json", ".jaxafm-notmine.fit.png", "run.log"]
OUTPUTS_OF = {
    "fit": ["metrics.json", "fit.png", "model_pi.json"],
    "predict": ["metrics.json", "prediction.csv", "predict.png"],
    "compensate": ["metrics.json", "drive.csv", "tracking.csv", "compensate.png"],
}
OUTPUTS = sorted(set().union(*OUTPUTS_OF.values()))

#: what a process killed at the ``kill_at``-th step of its run runs (the steps as in the module docstring)
KILLED = """
import os, signal, sys
from jaxafm.cli import main
from jaxafm.jobs import folder
steps, kill_at = [0], int(sys.argv.pop(1))
def counted(real):
    def step(*args, **kwargs):
        steps[0] += 1
        if steps[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(*args, **kwargs)
    return step
folder.file_hash = counted(folder.file_hash)
folder.RunFolder.record = counted(folder.RunFolder.record)
main()
"""


@pytest.fixture(scope="module")
def configs(tmp_path_factory) -> dict:
    """The three commands' configs: a fit, and a predict and a compensate of the model it wrote
    (a record and a trajectory inside the model's fitted ranges)."""
    tmp = tmp_path_factory.mktemp("configs")
    (tmp / "fit.yaml").write_text(yaml.safe_dump(FIT))
    made = CliRunner().invoke(app, ["fit", str(tmp / "fit.yaml"), "--out", str(tmp / "model")])
    assert made.exit_code == 0, made.output
    t = np.arange(100) / 100.0
    u = 4.0 * np.sin(2 * np.pi * t)
    lines = ["t_s,u_v,d_nm"] + [f"{a},{b},{400.0 * b}" for a, b in zip(t, u)]
    (tmp / "record.csv").write_text("\n".join(lines) + "\n")
    record = {
        "path": "record.csv",
        "input_columns": ["u_v"],
        "output_columns": ["d_nm"],
        "time_column": "t_s",
    }
    (tmp / "predict.yaml").write_text(
        yaml.safe_dump(
            {"model": "model/model_pi.json", "data": record | {"output_unit": "nm", "delimiter": ","}}
        )
    )
    triangle = {"amplitudes_nm": [100.0], "period_s": 0.5, "sample_rate_hz": 50.0}
    (tmp / "compensate.yaml").write_text(
        yaml.safe_dump({"model": "model/model_pi.json", "trajectory": {"triangle": triangle}, "cycle_s": 0.2})
    )
    return {name: tmp / f"{name}.yaml" for name in ("fit", "predict", "compensate")}


class User:
    """The user's files in ``folder``: what they last wrote to each (relative path -> bytes)."""

    def __init__(self, folder: Path, rng: np.random.Generator):
        self.folder, self.rng, self.files = folder, rng, {}

    def write(self, rel: str, exclusive: bool = False) -> None:
        """Write random bytes to ``rel`` (``exclusive``: only where no file lies yet)."""
        path = self.folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        data = self.rng.bytes(int(self.rng.integers(1, 64)))
        try:
            with open(path, "xb" if exclusive else "wb") as f:
                f.write(data)
        except FileExistsError:
            return
        self.files[rel] = data

    def some(self) -> None:
        """A new file (one in ten at an output's path), or (one in ten) an edit of a file a run wrote."""
        written = sorted(set(jaxafm_files(self.folder)) - set(self.files))
        if written and self.rng.random() < 0.1:
            self.write(written[int(self.rng.integers(len(written)))])
        else:
            pool = OUTPUTS if self.rng.random() < 0.1 else OWN
            self.write(pool[int(self.rng.integers(len(pool)))])

    def tidy(self) -> None:
        """Move away (delete) the user's files at the outputs' paths, which stop runs."""
        for rel in [f for f in self.files if f in OUTPUTS]:
            (self.folder / rel).unlink()
            del self.files[rel]

    def during(self, command: str) -> None:
        """A new file (one in two at the path of one of ``command``'s outputs), written from another
        thread while the run waits."""
        pool = OUTPUTS_OF[command] if self.rng.random() < 0.5 else OWN
        rel = pool[int(self.rng.integers(len(pool)))]
        thread = threading.Thread(target=self.write, args=(rel, True))
        thread.start()
        thread.join()

    def check(self, what: str) -> None:
        for rel, data in self.files.items():
            path = self.folder / rel
            assert path.is_file(), f"the user's {rel} is gone after {what}"
            assert path.read_bytes() == data, f"the user's {rel} was changed by {what}"


def jaxafm_files(folder: Path) -> list:
    """The files the folder's manifest records, with the bytes it recorded."""
    manifest = read_manifest(folder) if folder.is_dir() else None
    files = (manifest or {}).get("files", {})
    return [
        rel
        for rel, hashes in files.items()
        if (folder / rel).is_file() and hashlib.sha256((folder / rel).read_bytes()).hexdigest() in hashes
    ]


def in_process(cfg: Path, out: Path, flags: list, stop_at: int, user: User, user_at: int, monkeypatch):
    """The command in this process; at step ``user_at`` the user writes a file from another
    thread, at step ``stop_at`` a Ctrl-C (0: none)."""
    steps = [0]

    def counted(real):
        def step(*args, **kwargs):
            if real is folder_module.RunFolder.record and (args[1:] or kwargs):
                return real(*args, **kwargs)  # the run's end: its process would be gone after a Ctrl-C there
            steps[0] += 1
            if steps[0] == user_at:
                user.during(cfg.stem)
            if steps[0] == stop_at:
                raise KeyboardInterrupt
            return real(*args, **kwargs)

        return step

    with monkeypatch.context() as m:
        m.setattr(folder_module, "file_hash", counted(folder_module.file_hash))
        m.setattr(folder_module.RunFolder, "record", counted(folder_module.RunFolder.record))
        result = CliRunner().invoke(app, [cfg.stem, str(cfg), "--out", str(out), *flags])
    assert result.exit_code in (0, 2, 130), result.output  # 3: a bug; 1: an exception escaped
    assert "Traceback" not in result.output, result.output


def killed(cfg: Path, out: Path, flags: list, kill_at: int):
    """The command in a process of its own, killed (SIGKILL) at step ``kill_at``."""
    done = subprocess.run(
        [sys.executable, "-c", KILLED, str(kill_at), cfg.stem, str(cfg), "--out", str(out), *flags],
        capture_output=True,
        text=True,
    )
    assert done.returncode in (0, 2, -signal.SIGKILL), done.stdout[-2000:] + done.stderr[-2000:]


def test_a_users_files_survive_any_interleaving_of_runs(configs, tmp_path, monkeypatch):
    rng = np.random.default_rng(SEED)
    kills = sorted(rng.choice(ITERATIONS * RUNS, KILLS, replace=False))
    for i in range(ITERATIONS):
        out = tmp_path / f"out{i}"
        user = User(out, rng)
        for r in range(RUNS):
            command = ("fit", "predict", "compensate")[int(rng.integers(3))]
            flags = ["--overwrite"] if rng.random() < 0.75 else []
            if rng.random() < 0.5:
                user.some()
            stop = int(rng.integers(1, 12)) if rng.random() < 0.5 else 0
            what = f"iteration {i}, run {r}: {command} {' '.join(flags)}"
            if i * RUNS + r in kills:
                killed(configs[command], out, flags, int(rng.integers(1, 12)))
                what += " killed"
            else:
                in_process(configs[command], out, flags, stop, user, int(rng.integers(1, 12)), monkeypatch)
                what += f" stopped at step {stop}" if stop else ""
            user.check(what)
            if rng.random() < 0.5:
                user.some()
            if rng.random() < 0.5:
                user.tidy()
        assert user.files, "no file of the user's in this folder: the test checks nothing"
        assert os.listdir(out)
