"""Output folders that lose nothing: the run manifest that records what a run wrote, and the
folder as a job writes into it (:class:`Output`, through which every file of a job goes, and
whose :meth:`~Output.write_metrics` writes every job's ``metrics.json``). What each command
writes is the command table's (:data:`~jaxafm.jobs.JOBS`).

**Who owns a file.** A run owns exactly the files it wrote: each one is recorded in the run's
manifest, ``jaxafm-run.json``, by its path relative to the output folder and the sha256 of its
bytes, before it is put in place under its name (:meth:`Output.write`), so that a run killed at
any point has already recorded everything it wrote. Anything else in the folder is the user's,
and is never removed or replaced, with or without ``--overwrite``, whatever command runs next,
after a crash, a Ctrl-C or a finished run. A file a run wrote whose bytes have changed since
(the user edited or replaced it) is the user's too; the next run keeps it and says so. Besides
its files, a run removes only its own unfinished temporary files, whose names carry the run's
random token (``.jaxafm-TOKEN.NAME``, the token in its manifest), and the folders it created
once they are empty.

Every run writes its manifest into the output folder before its first result: the command, the
config (as validated), the jaxafm version, its token, the files that were in the folder before
and are not jaxafm's (``foreign``), the files it wrote (``files``: path -> the sha256 of the
bytes it put there; a file written again keeps the hash of its earlier bytes too, so that a kill
between the two steps of a rewrite loses nothing), the folders it created, and its status,
``running`` until it ends ``complete``, ``failed`` or ``interrupted``. From it:

- ``--overwrite`` removes only the files an earlier run owns (recorded, bytes unchanged);
- a file that is not the run's own and has the name of one of the command's outputs stops the
  run before any work, with or without ``--overwrite``; one that appears while the run goes on
  is never replaced (the run stops there);
- an incomplete folder is replaced by the next run of any command without a flag, except a
  study with the same config (``output`` aside), which resumes; a study with another config
  needs ``--overwrite``;
- a run killed outright (its manifest says ``running``, its process is gone) counts as
  incomplete: its files are those its manifest records;
- a run in several JAX processes (``jax.distributed``; :func:`shared_run_folder`): process 0 alone
  checks, prepares and records the folder and writes the results; the others never write into it.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import shlex
import socket
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Optional

from .table import JOBS

MANIFEST = "jaxafm-run.json"
FORMAT, VERSION = "jaxafm-run", 2

METRICS = "metrics.json"
#: the commands whose unfinished run goes on where it stopped (any other's is replaced)
RESUMABLE = tuple(name for name, job in JOBS.items() if job.resumable)
#: config keys that say where the results go, not what they are: a change in them alone does
#: not stop a resume
PLACE_KEYS = ("output",)


def file_hash(path: Path) -> str:
    """The sha256 of the file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def temporary(token: str, name: str) -> str:
    """The name of the temporary file a run with ``token`` writes ``name`` into first. It ends as
    ``name`` does, so that a writer that picks the format by the suffix (a figure, ``np.savez``)
    writes the same file."""
    return f".jaxafm-{token}.{name}"


class Output:
    """The output folder as a job writes into it: :meth:`prepare` readies it once the job has
    checked its inputs, :meth:`write` writes each file (recorded in the run's manifest with its
    hash before it is put in place), and :meth:`write_metrics` writes ``metrics.json``, every
    job's machine-readable results. A file that is not this run's is never replaced.

    Arguments:
        path: the folder.
        folder: the :class:`RunFolder` that records the run in its manifest (it makes its own
            Output, :attr:`RunFolder.output`); ``None``: nothing is recorded on disk (a job run
            from Python into a folder of the caller's).
    """

    def __init__(self, path, folder=None):
        self.path = Path(path)
        self._folder = folder
        self.token = folder.token if folder is not None else secrets.token_hex(8)
        #: whether this process writes (not a process other than 0 of a run in several)
        self.writes = folder is None or folder.writes
        #: every file the run owns, relative path -> [sha256 of the bytes it wrote there]; while
        #: a file of the run's is being replaced, the hashes of its old and its new bytes
        self.files: dict = {}
        #: the folders (relative) the run created
        self.dirs: list = []
        #: the files this job wrote, in order
        self.written: list = []

    def prepare(self) -> None:
        """Ready the folder: called once, after the job's inputs are checked, before its first file."""
        if self._folder is None:
            self.path.mkdir(parents=True, exist_ok=True)
        else:
            self._folder.prepare()

    def write(self, name: str, writer: Callable[[Path], object]) -> Path:
        """Write the file ``name`` (relative to the folder, ``/`` between names): ``writer(path)``
        writes it to a temporary path beside it; then its hash is recorded and it is put in place
        (whole or not at all). Returns its path.

        Raises:
            ValueError: a file that is not this run's lies where it belongs (the user's: kept).
        """
        rel, dest = self._destination(name)
        if not self.writes:
            return dest
        tmp = dest.with_name(temporary(self.token, dest.name))
        try:
            writer(tmp)
            self._place(rel, tmp, dest)
        finally:
            tmp.unlink(missing_ok=True)
        return dest

    def write_metrics(self, metrics: dict) -> dict:
        """Write ``metrics`` (flat keys, units in the names) as ``metrics.json``; returns them."""
        self.write(METRICS, lambda p: p.write_text(json.dumps(metrics, indent=1)))
        return metrics

    def _destination(self, name: str) -> tuple:
        """``name`` as a path relative to the folder, checked, and its path; its folders made."""
        rel = PurePosixPath(name)
        if rel.is_absolute() or ".." in rel.parts or not rel.parts:
            raise ValueError(f"{name!r}: an output is a path inside the output folder")
        dest = self.path.joinpath(*rel.parts)
        if self.writes:
            self._make_folders(rel.parent)
        return rel.as_posix(), dest

    def _make_folders(self, rel: PurePosixPath) -> None:
        """Create the folder ``rel`` and those above it in the output folder, recording those created."""
        for part in reversed([rel, *rel.parents][:-1]):  # outermost first; "." (the folder) left out
            folder = self.path / part
            try:
                folder.mkdir()
            except FileExistsError:
                if not folder.is_dir():  # a file of the user's: kept, and the run stops
                    raise ValueError(
                        f"{folder} is a file of yours where the run writes a folder of results: move it, "
                        "or choose another --out"
                    ) from None
            else:
                self.dirs.append(part.as_posix())

    def _place(self, rel: str, tmp: Path, dest: Path) -> None:
        """Record ``tmp``'s hash as ``rel``'s and put it in place: a new file by a hard link, which
        fails if a file of that name appeared meanwhile; a file this run wrote by a rename over it."""
        digest = file_hash(tmp)
        earlier = self.files.get(rel, [])
        if os.path.lexists(dest):
            if not earlier or file_hash(dest) not in earlier:
                raise ValueError(self._not_ours(dest))
            self._record(rel, [earlier[-1], digest])
            os.replace(tmp, dest)
        else:
            self._record(rel, [digest])
            try:
                os.link(tmp, dest)
            except FileExistsError:
                self._record(rel, earlier)
                raise ValueError(self._not_ours(dest)) from None
            except OSError:  # a filesystem without hard links
                if os.path.lexists(dest):
                    self._record(rel, earlier)
                    raise ValueError(self._not_ours(dest)) from None
                os.replace(tmp, dest)
        self.files[rel] = [digest]
        if rel not in self.written:
            self.written.append(rel)

    def _record(self, rel: str, hashes: list) -> None:
        """``rel``'s hashes, recorded in the manifest (an empty list: not the run's)."""
        if hashes:
            self.files[rel] = hashes
        else:
            self.files.pop(rel, None)
        if self._folder is not None:
            self._folder.record()

    def _not_ours(self, dest: Path) -> str:
        return (
            f"{dest} is not a file this run wrote (it appeared while the run went on, or it changed "
            "since the run wrote it): jaxafm never replaces a file of yours; it is kept as it is. Move "
            "it, or choose another --out"
        )


def _files(folder: Path) -> list:
    """Every file under ``folder`` but its manifest, relative, ``/`` between names."""
    names = (p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() or p.is_symlink())
    return sorted(n for n in names if n not in (MANIFEST, _MANIFEST_TMP))


_MANIFEST_TMP = f".{MANIFEST}.tmp"


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


class EarlierRun:
    """What an earlier run (its manifest ``doc``, or None) owns in ``folder``: the files whose
    bytes are those it recorded (``owned``: relative path -> sha256), its unfinished
    ``temporaries``, and ``changed``: the files it recorded that hold other bytes now (or that a
    manifest of format version 1, which records no hashes, lists), which are the user's."""

    def __init__(self, folder: Path, doc: Optional[dict]):
        self.doc = doc or {}
        self.owned, self.changed, self.temporaries = {}, [], []
        recorded = self.doc.get("files", {})
        if isinstance(recorded, list):  # format version 1: no hashes, nothing can be told apart
            recorded = {f: [] for f in recorded}
        for rel, hashes in recorded.items():
            path = folder / rel
            if not path.is_file():
                continue
            digest = file_hash(path)
            if digest in hashes:
                self.owned[rel] = digest
            else:
                self.changed.append(rel)
        token = self.doc.get("token")
        if token and folder.is_dir():
            mark = f".jaxafm-{token}."
            self.temporaries = [f for f in _files(folder) if PurePosixPath(f).name.startswith(mark)]

    @property
    def what(self) -> str:
        return f"`jaxafm {self.doc.get('command')}` started {self.doc.get('started', '?')}"


class RunFolder:
    """An output folder checked for a run of ``command`` before any work starts. The job writes
    into it through :attr:`output`.

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
        self.job, self.validated = JOBS[command], config
        self.config = config.model_dump(mode="json")
        self.token = secrets.token_hex(8)
        self.before = EarlierRun(self.path, read_manifest(self.path) if self.path.is_dir() else None)
        self.mode = self._mode(overwrite, resume)
        self.prepared, self.saved = False, []
        present = _files(self.path) if self.path.is_dir() else []
        ours = set(self.before.owned) | set(self.before.temporaries)
        self.foreign = [f for f in present if f not in ours]
        for f in self.before.changed:
            log(
                f"keeping {self.path / f}: {self.before.what} wrote it, but its bytes have changed since "
                "(or its manifest records no hash): it is yours now"
            )
        self._check_writable()
        self._check_collisions()
        self.output = Output(self.path, self)

    @property
    def resuming(self) -> bool:
        """Whether the run goes on from the results in the folder."""
        return self.mode == "resume"

    def _mode(self, overwrite: bool, resume: bool) -> str:
        """``new``, ``replace`` (an earlier run's files go), ``resume`` or ``beside`` (foreign files stay)."""
        p, before = self.path, self.before.doc
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
        if not before:
            if resume:
                raise ValueError(f"--resume: {p} holds no jaxafm run ({MANIFEST} is missing)")
            if not overwrite:
                raise ValueError(
                    f"output folder {p} is not empty and holds no jaxafm run: choose another with --out, or "
                    "pass --overwrite to write beside its files (none of them is removed or changed)"
                )
            return "beside"
        what, status = self.before.what, before.get("status")
        if (
            status == "running"
            and before.get("host") == socket.gethostname()
            and _alive(before.get("pid", -1))
        ):
            raise ValueError(f"output folder {p} is in use: {what} (pid {before['pid']}) is writing into it")
        same = before.get("command") == self.command
        changed = self._changed() if same else ["(another command)"]
        if overwrite and not resume:
            return "replace"
        if status == "complete":
            if resume and same and not changed:
                return "resume"
            raise ValueError(
                f"output folder {p} holds the results of {what}: pass --overwrite to replace them (only "
                f"the {len(self.before.owned)} files that run wrote are removed), or choose another --out"
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

    def _changed(self) -> list:
        """The config keys that differ from the earlier run's, but those that only place the results."""
        earlier = {k: v for k, v in (self.before.doc.get("config") or {}).items() if k not in PLACE_KEYS}
        now = {k: v for k, v in self.config.items() if k not in PLACE_KEYS}
        return _changed_keys(earlier, now)

    def _check_writable(self) -> None:
        """The folder and every folder inside it that the run writes into take files (or can be
        made where they are missing)."""
        folders = {PurePosixPath(p).parent for p in self.job.planned_outputs(self.validated)}
        for rel in sorted(folders, key=lambda f: len(f.parts)):
            folder = self.path.joinpath(*rel.parts)
            if os.path.lexists(folder) and not folder.is_dir():
                raise ValueError(
                    f"{folder} is a file of yours where `jaxafm {self.command}` writes a folder of results: "
                    "move it, or choose another --out"
                )
            while not folder.exists():
                folder = folder.parent
            if not os.access(folder, os.W_OK | os.X_OK):
                raise ValueError(
                    f"cannot write into {folder}: permission denied; make it writable or choose another --out"
                )

    def _check_collisions(self) -> None:
        """No file of the user's has the name of one of the command's outputs."""
        for f in self.foreign:
            pattern = self.job.planned(self.validated, f)
            if pattern is None:
                continue
            why = (
                f"{self.before.what} wrote it, but its bytes have changed since: it is yours now"
                if f in self.before.changed
                else "no run manifest records it: it is yours"
            )
            writes = "that very file" if pattern == f else f"files named {pattern}"
            raise ValueError(
                f"{self.path / f}: {why}, and `jaxafm {self.command}` writes {writes}; jaxafm never "
                "replaces a file of yours: move it, or choose another --out"
            )

    def prepare(self) -> None:
        """Make the folder ready once the job's inputs are checked: remove the replaced run's
        files (only those) or take over the resumed run's, remove its unfinished temporary
        files, and record this run as ``running``. Once: a second call does nothing."""
        if self.prepared:
            return
        for f in self.before.temporaries:
            (self.path / f).unlink(missing_ok=True)
        if self.mode == "replace":
            for f in self.before.owned:
                (self.path / f).unlink(missing_ok=True)
            for d in sorted(self.before.doc.get("dirs", []), key=lambda d: -len(PurePosixPath(d).parts)):
                folder = self.path / d
                if folder.is_dir() and not any(folder.iterdir()):
                    folder.rmdir()
        elif self.mode == "resume":
            self.output.files = {f: [h] for f, h in self.before.owned.items()}
            self.output.dirs = list(self.before.doc.get("dirs", []))
        self.path.mkdir(parents=True, exist_ok=True)
        self.started_ns = time.time_ns()
        self.prepared = True
        self.record()

    def record(self, status: str = "running", error: str = "") -> None:
        """Write the manifest: this run as ``status``, with the files it owns (whole or not at all).

        Raises:
            RuntimeError: the folder is not prepared (a job wrote before :meth:`prepare`).
        """
        from .._version import __version__

        if not self.prepared:
            raise RuntimeError(f"a file was written into {self.path} before the run prepared it")
        doc = {
            "format": FORMAT,
            "version": VERSION,
            "command": self.command,
            "status": status,
            "config_file": str(self.config_file.resolve()),
            "config": self.config,
            "jaxafm_version": __version__,
            "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.started_ns / 1e9)),
            "started_ns": self.started_ns,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "token": self.token,
            "foreign": self.foreign,
            "files": self.output.files,
            "dirs": self.output.dirs,
        } | ({"error": error} if error else {})
        tmp = self.path / _MANIFEST_TMP
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(self.path / MANIFEST)

    def end(self, status: str, error: str = "") -> list:
        """Record the run as ``complete``, ``failed`` or ``interrupted``; returns the files it owns
        (with those of the run it resumed)."""
        if self.prepared:  # else the job stopped before prepare(), and the folder is as it was
            self.saved = sorted(self.output.files)
            self.record(status, error)
        return self.saved

    def again(self) -> str:
        """The command that resumes (a study) or replaces (any other) this run's results."""
        return shlex.join(["jaxafm", self.command, str(self.config_file), "--out", str(self.path)])


class Follower:
    """The output folder as a process other than process 0 of a run in several JAX processes
    sees it: it neither checks, prepares nor records it (process 0 does), and writes nothing."""

    writes, prepared, resuming, saved = False, False, False, []
    token = "follower"

    def __init__(self, path, command, config_file):
        self.path, self.command, self.config_file = Path(path), command, Path(config_file)
        self.output = Output(self.path, self)

    def prepare(self) -> None:
        """Nothing: process 0 prepares the folder."""

    def record(self) -> None:
        """Nothing: process 0 records the run."""

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
