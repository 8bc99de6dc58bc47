"""The ``jaxafm`` command line: one sub-command per job of the command table
(:data:`jaxafm.jobs.JOBS`), which it validates the config for, checks the output folder for, and
runs."""

from __future__ import annotations

import errno
import os
import socket
import sys
from pathlib import Path
from typing import Optional

import typer

from ..jobs import JOBS, run_folder, shared_run_folder

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="jaxafm: differentiable AFM scanner models and positioning in JAX.",
)


def _fail(message: str, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=code)


#: Errors that describe bad input (their message is the whole story); any other exception is a
#: bug in jaxafm and is reported as one.
USER_ERRORS = (ValueError, OSError, RuntimeError)


def _launch(config: Path, out: Optional[Path], flags: dict, command: str, cluster=None, **options) -> None:
    """Validate ``config`` against ``command``'s schema, check the output folder, then run the
    command's job (with ``options``; :data:`~jaxafm.jobs.JOBS`); the folder is prepared only once
    the job has checked its inputs. Errors become messages (``--debug``: with the traceback);
    Ctrl-C says what was saved and how to go on. The job's module (and with it JAX) is imported
    only here, so ``--help`` and a config error stay quick. With ``cluster`` (:func:`_cluster`),
    this process first joins the others (:func:`_connect`), and only process 0 touches the folder."""
    from ..config import load_config
    from .cache import enable_compilation_cache

    enable_compilation_cache()
    job = JOBS[command]
    folder = None
    try:
        cfg = load_config(config, job.schema)
        path = out or Path(cfg.output)
        if cluster is not None:
            _connect(**cluster)
        with (run_folder if cluster is None else shared_run_folder)(
            path, command, config, cfg, flags["overwrite"], flags.get("resume", False), typer.echo
        ) as folder:
            if folder.resuming:
                options["resume"] = True
            job.run(cfg, config, folder.output, log=typer.echo, **options)
    except KeyboardInterrupt:
        _interrupted(folder)
    except Exception as e:
        if flags["debug"]:
            raise
        if isinstance(e, USER_ERRORS):
            _fail(str(e))
        _fail(
            f"internal error ({type(e).__name__}: {e}); this is a bug in jaxafm: please report it with "
            "the output of the same command with --debug",
            code=3,
        )
    if folder.writes:
        typer.echo(f"wrote the results into {path}")


def _interrupted(folder) -> None:
    """What an interrupted run saved, and the command that goes on from it."""
    if folder is None or not folder.prepared:
        _fail("interrupted before any result was written; the output folder is as it was", code=130)
    files = folder.saved
    verb = "resumes it" if JOBS[folder.command].resumable else "replaces them"
    _fail(
        f"interrupted: {len(files)} file(s) saved in {folder.path}, marked unfinished in its "
        f"jaxafm-run.json; `{folder.again()}` {verb}",
        code=130,
    )


CONFIG = typer.Argument(..., help="YAML config (see configs/)")
OUT = typer.Option(None, help="output folder (default: the config's 'output')")
OVERWRITE = typer.Option(
    False, help="replace an earlier run's results in the output folder (only the files it wrote)"
)
DEBUG = typer.Option(False, help="show the traceback of an error")


@app.command()
def fit(config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG):
    """Fit hysteresis models to an actuator record; write models, metrics.json and fit.png."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "fit")


@app.command()
def calibrate(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """Step A: identify the scanner from a grating image pair, invert it and compensate; write
    fitted scanners, metrics.json and compensation.png."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "calibrate")


@app.command()
def run(config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG):
    """The paper's whole strategy on the simulated AFM: step A, landmarks (B), local scans (C) and the
    push, with an ablation table; write metrics.json, trials.npz, the fitted scanner and figures."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "run")


@app.command()
def diagnose(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """Sim-to-real gap: where the nominal model misses and which candidate effect closes the gap on
    held-out data; write diagnosis.json, metrics.json, residuals.png and report.md."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "diagnose")


@app.command()
def predict(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """Apply a saved model (model_*.json) to a record's input; write the prediction
    (prediction.csv), its errors where the record has measured output (metrics.json) and predict.png."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "predict")


@app.command()
def compensate(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """The drive that makes a saved model (one axis or a scanner) follow a wanted trajectory (CSV,
    triangle or raster), after the initialisation cycle; write drive.csv, tracking.csv, metrics.json
    and compensate.png."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "compensate")


@app.command()
def study(
    config: Path = CONFIG,
    out: Optional[Path] = OUT,
    overwrite: bool = OVERWRITE,
    resume: bool = typer.Option(
        False, help="go on with an unfinished study in the output folder (done without it too)"
    ),
    coordinator: Optional[str] = typer.Option(
        None,
        help="run as one of several processes (jax.distributed): HOST:PORT of process 0, which "
        "listens there (the same on every process); 'auto': taken from the cluster (SLURM, Open MPI)",
    ),
    processes: Optional[int] = typer.Option(
        None, help="with --coordinator HOST:PORT: how many processes take part"
    ),
    process_id: Optional[int] = typer.Option(
        None, help="with --coordinator HOST:PORT: this process's number, 0 to --processes - 1"
    ),
    debug: bool = DEBUG,
):
    """A Monte-Carlo positioning study: trials over drawn scanners, particles and targets, in
    vmapped batches over every JAX device (of every process, with --coordinator); writes
    per-chunk results, trials.csv/npz, metrics.json and errors.png. An unfinished study with the
    same config resumes where it stopped."""
    if resume and overwrite:
        _fail(
            "--resume goes on with the results in the output folder; --overwrite would delete them: "
            "pass one of them"
        )
    try:
        cluster = _cluster(coordinator, processes, process_id)
    except ValueError as e:
        _fail(str(e))
    _launch(
        config,
        out,
        dict(overwrite=overwrite, resume=resume, debug=debug),
        "study",
        cluster=cluster,
    )


def _cluster(coordinator: Optional[str], processes: Optional[int], process_id: Optional[int]):
    """The arguments of :func:`_connect` from ``--coordinator``, ``--processes`` and
    ``--process-id`` (None: one process on its own), checked.

    Raises:
        ValueError: naming the option, its value and what is allowed.
    """
    if coordinator is None:
        if processes is not None or process_id is not None:
            given = "--processes" if processes is not None else "--process-id"
            raise ValueError(
                f"{given} needs --coordinator: HOST:PORT of process 0, or auto on a cluster (SLURM, Open MPI)"
            )
        return None
    if processes is not None and processes < 1:
        raise ValueError(f"--processes {processes}: must be 1 or more")
    if coordinator == "auto":
        if process_id is not None and processes is not None and not 0 <= process_id < processes:
            raise ValueError(
                f"--process-id {process_id}: must be 0 to {processes - 1} (--processes {processes})"
            )
        return dict(address=None, processes=processes, process_id=process_id)
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(
            f"--coordinator {coordinator!r}: expected HOST:PORT, process 0's host and a free port on it "
            "(1 to 65535; e.g. localhost:12345 or node01:12345), or auto"
        )
    if processes is None or process_id is None:
        missing = "--processes N" if processes is None else "--process-id I"
        raise ValueError(
            f"--coordinator {coordinator}: needs {missing} too (or --coordinator auto on a cluster)"
        )
    if not 0 <= process_id < processes:
        raise ValueError(f"--process-id {process_id}: must be 0 to {processes - 1} (--processes {processes})")
    return dict(address=coordinator, processes=processes, process_id=process_id)


#: how long a process waits for all the others to join (s), and at the end for them to finish
#: their last step (a process that failed alone makes the rest stop after it)
CONNECT_TIMEOUT_S, SHUTDOWN_TIMEOUT_S = 300, 60


def _connect(address: Optional[str], processes: Optional[int], process_id: Optional[int]) -> None:
    """Join the study's processes: ``jax.distributed.initialize`` (before any JAX computation),
    with CPU collectives over TCP (gloo, JAX's default; set if switched off). ``address`` None:
    JAX takes the coordinator, process count and id from the cluster's environment.

    Raises:
        ValueError: the coordinator's host is unknown, or no cluster environment was found.
        RuntimeError: process 0 cannot listen on the coordinator's port.
    """
    import jax

    if jax.config.jax_cpu_collectives_implementation is None:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    if address is not None:
        host, port = address.rpartition(":")[::2]
        try:
            socket.getaddrinfo(host.strip("[]"), int(port))
        except OSError as e:
            raise ValueError(f"--coordinator {address}: unknown host {host!r} ({e})") from None
        if process_id == 0 and not _can_listen(int(port)):
            raise RuntimeError(f"--coordinator {address}: process 0 cannot listen on port {port}: {_IN_USE}")
        typer.echo(
            f"process {process_id} of {processes}: joining the others through {address} (waits up to "
            f"{CONNECT_TIMEOUT_S} s for all {processes})"
        )
    try:
        jax.distributed.initialize(
            address,
            processes,
            process_id,
            initialization_timeout=CONNECT_TIMEOUT_S,
            shutdown_timeout_seconds=SHUTDOWN_TIMEOUT_S,
        )
    except ValueError as e:
        if address is None:
            raise ValueError(
                f"--coordinator auto: no cluster environment gives the coordinator ({e}); pass "
                "--coordinator HOST:PORT --processes N --process-id I"
            ) from None
        raise
    except RuntimeError as e:
        if "RPC server" not in str(e):
            raise
        raise RuntimeError(
            f"--coordinator {address}: process 0 cannot listen on port {address.rpartition(':')[2]} ({e}): {_IN_USE}"
        ) from None


_IN_USE = "is it in use? choose another"


def _can_listen(port: int) -> bool:
    """Whether this process could listen on ``port`` where JAX's coordinator does (every address,
    unless ``JAX_COORDINATOR_BIND_ADDRESS`` says otherwise: then it is not checked here). A
    failed start of the coordinator is not undone cleanly, so a port in use is caught first."""
    if os.environ.get("JAX_COORDINATOR_BIND_ADDRESS"):
        return True
    try:
        with socket.socket(socket.AF_INET6 if socket.has_ipv6 else socket.AF_INET) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("", port))
    except OSError as e:
        return e.errno != errno.EADDRINUSE  # anything else: JAX says what
    return True


@app.command()
def effects():
    """List the effect names used in configs and diagnosis."""
    from ..config.names import EFFECTS

    typer.echo("\n".join(EFFECTS))


def main() -> None:  # pragma: no cover
    app(prog_name="jaxafm", args=sys.argv[1:])
