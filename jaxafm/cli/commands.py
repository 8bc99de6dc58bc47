"""The ``jaxafm`` command line: one sub-command per pipeline stage."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .output import run_folder

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


def _launch(config: Path, out: Optional[Path], flags: dict, command: str, job: str, **options) -> None:
    """Validate ``config`` against ``command``'s schema, check the output folder, then
    ``jaxafm.<job>.run`` it (with ``options``); the folder is prepared only once the job has
    checked its inputs. Errors become messages (``--debug``: with the traceback); Ctrl-C says
    what was saved and how to go on. The job's module (and with it JAX) is imported only
    here, so ``--help`` and a config error stay quick."""
    import importlib

    from .. import config as configs

    schema = {
        "fit": configs.ActuatorFitConfig,
        "calibrate": configs.CalibrateConfig,
        "run": configs.RunConfig,
        "study": configs.StudyConfig,
        "diagnose": configs.DiagnoseConfig,
        "predict": configs.PredictConfig,
        "compensate": configs.CompensateConfig,
    }[command]
    folder = None
    try:
        cfg = configs.load_config(config, schema)
        path = out or Path(cfg.output)
        with run_folder(
            path, command, config, cfg, flags["overwrite"], flags.get("resume", False), typer.echo
        ) as folder:
            if folder.resuming:
                options["resume"] = True
            importlib.import_module(f"jaxafm.{job}").run(
                cfg, config, path, prepare=folder.prepare, log=typer.echo, **options
            )
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
    typer.echo(f"wrote the results into {path}")


def _interrupted(folder) -> None:
    """What an interrupted run saved, and the command that goes on from it."""
    if folder is None or not folder.prepared:
        _fail("interrupted before any result was written; the output folder is as it was", code=130)
    files = folder.saved
    verb = "resumes it" if folder.command == "study" else "replaces them"
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
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "fit", "identify.actuator_fit")


@app.command()
def calibrate(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """Step A: identify the scanner from a grating image pair, invert it and compensate; write
    fitted scanners, metrics.json and compensation.png."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "calibrate", "identify.step_a")


@app.command()
def run(config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG):
    """The paper's whole strategy on the simulated AFM: step A, landmarks (B), local scans (C) and the
    push, with an ablation table; write metrics.json, trials.npz, the fitted scanner and figures."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "run", "position.strategy")


@app.command()
def diagnose(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """Sim-to-real gap: where the nominal model misses and which candidate effect closes the gap on
    held-out data; write diagnosis.json, metrics.json, residuals.png and report.md."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "diagnose", "diagnose.run")


@app.command()
def predict(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """Apply a saved model (model_*.json) to a record's input; write the prediction
    (prediction.csv), its errors where the record has measured output (metrics.json) and predict.png."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "predict", "identify.predict")


@app.command()
def compensate(
    config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE, debug: bool = DEBUG
):
    """The drive that makes a saved model (one axis or a scanner) follow a wanted trajectory (CSV,
    triangle or raster), after the initialisation cycle; write drive.csv, tracking.csv, metrics.json
    and compensate.png."""
    _launch(config, out, dict(overwrite=overwrite, debug=debug), "compensate", "identify.compensate")


@app.command()
def study(
    config: Path = CONFIG,
    out: Optional[Path] = OUT,
    overwrite: bool = OVERWRITE,
    resume: bool = typer.Option(
        False, help="go on with an unfinished study in the output folder (done without it too)"
    ),
    debug: bool = DEBUG,
):
    """A Monte-Carlo positioning study: trials over drawn scanners, particles and targets, in
    vmapped batches over every JAX device; writes per-chunk results, trials.csv/npz, metrics.json
    and errors.png. An unfinished study with the same config resumes where it stopped."""
    if resume and overwrite:
        _fail(
            "--resume goes on with the results in the output folder; --overwrite would delete them: "
            "pass one of them"
        )
    _launch(config, out, dict(overwrite=overwrite, resume=resume, debug=debug), "study", "study.monte_carlo")


@app.command()
def effects():
    """List the effect names used in configs and diagnosis."""
    from ..config.names import EFFECTS

    typer.echo("\n".join(EFFECTS))


def main() -> None:  # pragma: no cover
    app(prog_name="jaxafm", args=sys.argv[1:])
