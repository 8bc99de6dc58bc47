"""The ``jaxafm`` command line: one sub-command per pipeline stage."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .output import (
    CALIBRATE_OUTPUTS,
    DIAGNOSE_OUTPUTS,
    FIT_OUTPUTS,
    RUN_OUTPUTS,
    STUDY_OUTPUTS,
    prepare_output,
)

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="jaxafm: differentiable AFM scanner models and positioning in JAX.",
)


def _fail(e: Exception) -> None:
    typer.echo(f"error: {e}", err=True)
    raise typer.Exit(code=2)


def _launch(
    config: Path, out: Optional[Path], overwrite: bool, schema: str, job: str, outputs: tuple, **options
) -> None:
    """Validate ``config`` against ``jaxafm.config.<schema>``, then ``jaxafm.<job>.run`` it (with
    ``options``) into the output folder, prepared only once the inputs have been checked; errors
    become messages. The job's module (and with it JAX) is imported only here, so ``--help`` and
    a config error stay quick."""
    import importlib

    from .. import config as configs

    try:
        cfg = configs.load_config(config, getattr(configs, schema))
        folder = out or Path(cfg.output)
        importlib.import_module(f"jaxafm.{job}").run(
            cfg,
            config,
            folder,
            prepare=lambda: prepare_output(folder, overwrite, outputs),
            log=typer.echo,
            **options,
        )
    except (ValueError, OSError, RuntimeError) as e:
        _fail(e)
    typer.echo(f"wrote the results into {folder}")


CONFIG = typer.Argument(..., help="YAML config (see configs/)")
OUT = typer.Option(None, help="output folder (default: the config's 'output')")
OVERWRITE = typer.Option(False, help="replace the output folder's contents")


@app.command()
def fit(config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE):
    """Fit hysteresis models to an actuator record; write models, metrics.json and fit.png."""
    _launch(config, out, overwrite, "ActuatorFitConfig", "identify.actuator_fit", FIT_OUTPUTS)


@app.command()
def calibrate(config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE):
    """Step A: identify the scanner from a grating image pair, invert it and compensate; write
    fitted scanners, metrics.json and compensation.png."""
    _launch(config, out, overwrite, "CalibrateConfig", "identify.step_a", CALIBRATE_OUTPUTS)


@app.command()
def run(config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE):
    """The paper's whole strategy on the simulated AFM: step A, landmarks (B), local scans (C) and the
    push, with an ablation table; write metrics.json, trials.npz, the fitted scanner and figures."""
    _launch(config, out, overwrite, "RunConfig", "position.strategy", RUN_OUTPUTS)


@app.command()
def diagnose(config: Path = CONFIG, out: Optional[Path] = OUT, overwrite: bool = OVERWRITE):
    """Sim-to-real gap: where the nominal model misses and which candidate effect closes the gap on
    held-out data; write diagnosis.json, metrics.json, residuals.png and report.md."""
    _launch(config, out, overwrite, "DiagnoseConfig", "diagnose.run", DIAGNOSE_OUTPUTS)


@app.command()
def study(
    config: Path = CONFIG,
    out: Optional[Path] = OUT,
    overwrite: bool = OVERWRITE,
    resume: bool = typer.Option(False, help="go on with an interrupted study in the output folder"),
):
    """A Monte-Carlo positioning study: trials over drawn scanners, particles and targets, in
    vmapped batches over every JAX device; writes per-chunk results, trials.csv/npz, metrics.json
    and errors.png. Interrupted, it resumes with --resume."""
    if resume and overwrite:
        _fail(
            ValueError(
                "--resume goes on with the results in the output folder; --overwrite would delete them: "
                "pass one of them"
            )
        )
    _launch(config, out, overwrite, "StudyConfig", "study.monte_carlo", STUDY_OUTPUTS, resume=resume)


@app.command()
def effects():
    """List the effect names used in configs and diagnosis."""
    from ..config.names import EFFECTS

    typer.echo("\n".join(EFFECTS))


def main() -> None:  # pragma: no cover
    app(prog_name="jaxafm", args=sys.argv[1:])
