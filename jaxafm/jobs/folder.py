"""Output folders that lose nothing: the run manifest that records what a run wrote, and the
folder as a job writes into it (:class:`Output`, whose :meth:`~Output.write_metrics` writes every
job's ``metrics.json``). What each command writes is the command table's (:data:`~jaxafm.jobs.JOBS`).

Every run writes ``jaxafm-run.json`` into its output folder before its first result: the command,
the config (as validated), the jaxafm version, the files that were in the folder before
(``foreign``: never removed or replaced) and its status, ``running`` until it ends
``complete``, ``failed`` or ``interrupted`` with the list of files it wrote. From it:

- ``--overwrite`` removes only the files an earlier run recorded as its own;
- a run never replaces a file it did not write: a foreign file with an output's name is an error;
- an incomplete folder is replaced by the next run of any command without a flag, except a
  study with the same config, which resumes; a study with another config needs ``--overwrite``;
- a run killed outright (its manifest says ``running``, its process is gone) counts as
  incomplete; its files are those not foreign and written after it started;
- a run in several JAX processes (``jax.distributed``; :func:`shared_run_folder`): process 0 alone
  checks, prepares and records the folder and writes the results; the others never write into it.
"""

from __future__ import annotations

import json
import os
import shlex
import socket
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

from .table import JOBS

MANIFEST = "jaxafm-run.json"
FORMAT = "jaxafm-run"

METRICS = "metrics.json"
#: the commands whose unfinished run goes on where it stopped (any other's is replaced)
RESUMABLE = tuple(name for name, job in JOBS.items() if job.resumable)


class Output:
    """The output folder as a job writes into it: :meth:`prepare` readies it once the job has
    checked its inputs, :meth:`file` names each file the job writes (and records it in
    :attr:`written`), and :meth:`write_metrics` writes ``metrics.json``, every job's
    machine-readable results.

    Arguments:
        path: the folder.
        prepare: readies the folder (a :class:`RunFolder`'s ``prepare``, which records the run
            in its manifest); ``None``: create the folder.
    """

    def __init__(self, path, prepare: Optional[Callable[[], None]] = None):
        self.path = Path(path)
        self._prepare = prepare
        #: the files the job wrote (or is writing), relative to :attr:`path`, in order
        self.written: list = []

    def prepare(self) -> None:
        """Ready the folder: called once, after the job's inputs are checked, before its first file."""
        if self._prepare is None:
            self.path.mkdir(parents=True, exist_ok=True)
        else:
            self._prepare()

    def file(self, name: str) -> Path:
        """The path of the file ``name`` (relative to the folder) that the job writes."""
        if name not in self.written:
            self.written.append(name)
        return self.path / name

    def write_metrics(self, metrics: dict) -> dict:
        """Write ``metrics`` (flat keys, units in the names) as ``metrics.json``, whole or not at
        all (a temporary file renamed onto it); returns them."""
        path = self.file(METRICS)
        tmp = path.with_name(f".tmp{os.getpid()}.{path.name}")
        tmp.write_text(json.dumps(metrics, indent=1))
        os.replace(tmp, path)
        return metrics


def _files(folder: Path) -> dict:
    """Every file under ``folder`` but the manifest: relative path -> modification time (ns)."""
    return {
        p.relative_to(folder).as_posix(): p.stat().st_mtime_ns
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != MANIFEST
    }


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _changed_keys(before, now, prefix: str = "") -> list:
    """The dotted keys whose values differ between two config dumps."""
    if isinstance(before, dict) and isinstance(now, dict):
        return [
            k
            for key in sorted(set(before) | set(now), key=str)
            for k in _changed_keys(before.get(key), now.get(key), f"{prefix}{key}.")
        ]
    return [] if before == now else [prefix.rstrip(".")]


def read_manifest(folder: Path) -> Optional[dict]:
    """The run manifest in ``folder``, or None where there is none.

    Raises:
        ValueError: the file exists but is no jaxafm run manifest.
    """
    path = Path(folder) / MANIFEST
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(
            f"{path} is not a jaxafm run manifest ({e}): move it out of the output folder"
        ) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"{path} is not a jaxafm run manifest: move it out of the output folder")
    return doc


class RunFolder:
    """An output folder checked for a run of ``command`` before any work starts.

    Arguments:
        path: the output folder.
        command: the ``jaxafm`` sub-command.
        config_file: the YAML file the run was started with.
        config: the validated config (a pydantic model).
        overwrite: whether an earlier run's results may be replaced.
        resume: whether an interrupted study is to be continued (also done without it).
        log: where progress messages go.

    Raises:
        ValueError: the folder cannot take the run; the message says why and what to do.
    """

    #: whether this process writes the run's results (:class:`Follower`: it does not)
    writes = True

    def __init__(self, path, command, config_file, config, overwrite=False, resume=False, log=print):
        self.path, self.command, self.log = Path(path), command, log
        self.config_file = Path(config_file)
        self.config = config.model_dump(mode="json")
        self.outputs = JOBS[command].planned_outputs(config)
        self.before = read_manifest(self.path) if self.path.is_dir() else None
        self.mode = self._mode(overwrite, resume)
        self.prepared = False
        present = _files(self.path) if self.path.is_dir() else {}
        self.owned = self._owned(present)
        self.foreign = sorted(set(present) - set(self.owned))
        self._check_writable()
        self._check_collisions()

    @property
    def resuming(self) -> bool:
        """Whether the run goes on from the results in the folder."""
        return self.mode == "resume"

    def _mode(self, overwrite: bool, resume: bool) -> str:
        """``new``, ``replace`` (an earlier run's files go), ``resume`` or ``beside`` (foreign files stay)."""
        p, before = self.path, self.before
        if p.exists() and not p.is_dir():
            raise ValueError(f"output {p} exists and is not a folder: choose another with --out")
        if resume and self.command not in RESUMABLE:
            raise ValueError(
                f"--resume: only {', '.join(RESUMABLE)} resumes; `jaxafm {self.command}` runs anew"
            )
        if not p.is_dir() or not any(p.iterdir()):
            if resume:
                raise ValueError(f"--resume: {p} holds no run to resume; start it without --resume")
            return "new"
        if before is None:
            if resume:
                raise ValueError(f"--resume: {p} holds no jaxafm run ({MANIFEST} is missing)")
            if not overwrite:
                raise ValueError(
                    f"output folder {p} is not empty and holds no jaxafm run: choose another with --out, or "
                    "pass --overwrite to write beside its files (none of them is removed or changed)"
                )
            return "beside"
        what = f"`jaxafm {before.get('command')}` started {before.get('started', '?')}"
        status = before.get("status")
        if (
            status == "running"
            and before.get("host") == socket.gethostname()
            and _alive(before.get("pid", -1))
        ):
            raise ValueError(f"output folder {p} is in use: {what} (pid {before['pid']}) is writing into it")
        same = before.get("command") == self.command
        changed = _changed_keys(before.get("config"), self.config) if same else ["(another command)"]
        if overwrite and not resume:
            return "replace"
        if status == "complete":
            if resume and same and not changed:
                return "resume"
            raise ValueError(
                f"output folder {p} holds the results of {what}: pass --overwrite to replace them (only "
                f"the {len(before.get('files', []))} files that run wrote are removed), or choose another --out"
            )
        if self.command in RESUMABLE and same:
            if changed:
                raise ValueError(
                    f"output folder {p} holds an unfinished {what} of another config (keys: "
                    f"{', '.join(changed)}): restore them to resume it, pass --overwrite to discard "
                    "its results, or choose another --out"
                )
            self.log(f"resuming the unfinished {what} in {p}")
            return "resume"
        if resume:
            raise ValueError(f"--resume: {p} holds an unfinished {what}, not this command's run")
        self.log(f"replacing the unfinished results ({status}) of {what} in {p}")
        return "replace"

    def _owned(self, present: dict) -> list:
        """The files in the folder that an earlier run wrote (its manifest says so)."""
        if self.before is None:
            return []
        if self.before.get("status") != "running":
            return [f for f in self.before.get("files", []) if f in present]
        foreign = set(self.before.get("foreign", []))
        start = self.before.get("started_ns", 0)
        return [f for f, t in present.items() if f not in foreign and t >= start]  # killed outright

    def _check_writable(self) -> None:
        folder = self.path
        while not folder.exists():
            folder = folder.parent
        if not os.access(folder, os.W_OK | os.X_OK):
            raise ValueError(f"cannot write into {folder}: permission denied; choose another --out")

    def _check_collisions(self) -> None:
        for f in self.foreign:
            if any(Path(f).match(pattern) for pattern in self.outputs):
                raise ValueError(
                    f"{self.path / f} was not written by jaxafm (no run manifest lists it), and "
                    f"`jaxafm {self.command}` writes a file of that name: move it, or choose another --out"
                )

    def prepare(self) -> None:
        """Make the folder ready once the job's inputs are checked: remove the replaced run's
        files (only those), and record this run as ``running``."""
        if self.mode == "replace":
            for f in self.owned:
                (self.path / f).unlink(missing_ok=True)
            for d in sorted({(self.path / f).parent for f in self.owned}, key=lambda d: -len(d.parts)):
                if d != self.path and d.is_dir() and not any(d.iterdir()):
                    d.rmdir()
            self.owned = []
        self.path.mkdir(parents=True, exist_ok=True)
        self.started_ns = time.time_ns()
        self._write("running")
        self.prepared = True

    def end(self, status: str, error: str = "") -> list:
        """Record the run as ``complete``, ``failed`` or ``interrupted`` with the files it wrote
        (and those of the run it resumed); returns them."""
        self.saved = []
        if self.prepared:  # else the job stopped before prepare(), and the folder is as it was
            self.saved = sorted(set(_files(self.path)) - set(self.foreign))
            self._write(status, self.saved, error)
        return self.saved

    def _write(self, status: str, files=(), error: str = "") -> None:
        from .._version import __version__

        doc = {
            "format": FORMAT,
            "version": 1,
            "command": self.command,
            "status": status,
            "config_file": str(self.config_file.resolve()),
            "config": self.config,
            "jaxafm_version": __version__,
            "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.started_ns / 1e9)),
            "started_ns": self.started_ns,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "foreign": self.foreign,
            "files": list(files),
        } | ({"error": error} if error else {})
        tmp = self.path / f".{MANIFEST}.tmp"
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(self.path / MANIFEST)

    def again(self) -> str:
        """The command that resumes (a study) or replaces (any other) this run's results."""
        return shlex.join(["jaxafm", self.command, str(self.config_file), "--out", str(self.path)])


class Follower:
    """The output folder as a process other than process 0 of a run in several JAX processes
    sees it: it neither checks, prepares nor records it (process 0 does), and writes nothing."""

    writes, prepared, resuming, saved = False, False, False, []

    def __init__(self, path, command, config_file):
        self.path, self.command, self.config_file = Path(path), command, Path(config_file)

    def prepare(self) -> None:
        """Nothing: process 0 prepares the folder."""

    def end(self, status: str, error: str = "") -> list:
        """Nothing: process 0 records the run."""
        return []

    again = RunFolder.again


@contextmanager
def shared_run_folder(path, command, config_file, config, overwrite=False, resume=False, log=print):
    """:func:`run_folder` for a run in several JAX processes (``jax.distributed`` initialised):
    process 0 checks the folder as :class:`RunFolder` does and tells the others whether it may
    be used (a collective: every process enters this together); they get a :class:`Follower`.

    Raises:
        ValueError: the folder cannot take the run (process 0 says why; the others say so).
    """
    import jax
    import numpy as np
    from jax.experimental.multihost_utils import broadcast_one_to_all

    if jax.process_index() == 0:
        try:
            folder = RunFolder(path, command, config_file, config, overwrite, resume, log)
        except BaseException:
            broadcast_one_to_all(np.int32(0))  # the others stop too
            raise
        broadcast_one_to_all(np.int32(1))
    elif broadcast_one_to_all(np.int32(0)) == 1:
        folder = Follower(path, command, config_file)
    else:
        raise ValueError(f"process 0 cannot use the output folder {path}: its message says why")
    with _recorded(folder):
        yield folder


@contextmanager
def run_folder(path, command, config_file, config, overwrite=False, resume=False, log=print):
    """A :class:`RunFolder` for the ``with`` block's run: marked ``complete`` when the block
    ends, ``failed`` or ``interrupted`` (and the error re-raised) when it does not."""
    with _recorded(RunFolder(path, command, config_file, config, overwrite, resume, log)) as folder:
        yield folder


@contextmanager
def _recorded(folder):
    """``folder`` for the ``with`` block: ended ``complete``, ``failed`` or ``interrupted``."""
    try:
        yield folder
    except KeyboardInterrupt:
        folder.end("interrupted", "interrupted by the user")
        raise
    except BaseException as e:
        folder.end("failed", f"{type(e).__name__}: {e}")
        raise
    folder.end("complete")
