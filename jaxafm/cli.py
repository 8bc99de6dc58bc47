"""The ``jaxafm`` command line: one sub-command per pipeline stage."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="jaxafm: differentiable AFM scanner models and positioning in JAX.")


FIT_OUTPUTS = ("metrics.json", "fit.png", "model_*.json")  # what `jaxafm fit` writes
CALIBRATE_OUTPUTS = ("metrics.json", "compensation.png", "model_*.json")  # what `jaxafm calibrate` writes
RUN_OUTPUTS = ("metrics.json", "trials.npz", "landmarks.png", "local_scan.png", "push.png", "errors.png",
               "model_scanner.json")  # what `jaxafm run` writes


def prepare_output(out: Path, overwrite: bool, outputs: tuple) -> None:
    """Create ``out``; an existing, non-empty one only with ``overwrite``, which removes
    just the files this command writes and leaves everything else where it is."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"output {out} exists and is not a folder: choose another with --out")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise ValueError(f"output folder {out} exists and is not empty: choose another with --out, "
                             "or pass --overwrite to replace the results in it")
        for pattern in outputs:
            for f in out.glob(pattern):
                f.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _fail(e: Exception) -> None:
    typer.echo(f"error: {e}", err=True)
    raise typer.Exit(code=2)


@app.command()
def fit(
    config: Path = typer.Argument(..., help="YAML config (see configs/)"),
    out: Optional[Path] = typer.Option(None, help="output folder (default: the config's 'output')"),
    overwrite: bool = typer.Option(False, help="replace the output folder's contents"),
):
    """Fit hysteresis models to an actuator record; write models, metrics.json and fit.png."""
    from . import actuator_fit
    from .config import load_config

    try:
        cfg = load_config(config)
        folder = out or Path(cfg.output)
        actuator_fit.run(cfg, config, folder, prepare=lambda: prepare_output(folder, overwrite, FIT_OUTPUTS),
                         log=typer.echo)
    except (ValueError, OSError) as e:
        _fail(e)
    typer.echo(f"wrote {', '.join(FIT_OUTPUTS)} into {folder}")


@app.command()
def calibrate(
    config: Path = typer.Argument(..., help="YAML config (see configs/step_a_*.yaml)"),
    out: Optional[Path] = typer.Option(None, help="output folder (default: the config's 'output')"),
    overwrite: bool = typer.Option(False, help="replace the output folder's contents"),
):
    """Step A: identify the scanner from a grating image pair, invert it and compensate; write
    fitted scanners, metrics.json and compensation.png."""
    from . import step_a
    from .config import CalibrateConfig, load_config

    try:
        cfg = load_config(config, CalibrateConfig)
        folder = out or Path(cfg.output)
        step_a.run(cfg, config, folder, prepare=lambda: prepare_output(folder, overwrite, CALIBRATE_OUTPUTS),
                   log=typer.echo)
    except (ValueError, OSError, RuntimeError) as e:
        _fail(e)
    typer.echo(f"wrote the results into {folder}")


@app.command()
def run(
    config: Path = typer.Argument(..., help="YAML config (see configs/paper.yaml)"),
    out: Optional[Path] = typer.Option(None, help="output folder (default: the config's 'output')"),
    overwrite: bool = typer.Option(False, help="replace the output folder's contents"),
):
    """The paper's whole strategy on the simulated AFM: step A, landmarks (B), local scans (C) and the
    push, with an ablation table; write metrics.json, the fitted scanner and figures."""
    from . import strategy
    from .config import RunConfig, load_config

    try:
        cfg = load_config(config, RunConfig)
        folder = out or Path(cfg.output)
        strategy.run(cfg, config, folder, prepare=lambda: prepare_output(folder, overwrite, RUN_OUTPUTS),
                     log=typer.echo)
    except (ValueError, OSError, RuntimeError) as e:
        _fail(e)
    typer.echo(f"wrote the results into {folder}")


@app.command()
def effects():
    """List the effect names used in configs and diagnosis."""
    from .effects import EFFECTS

    typer.echo("\n".join(EFFECTS))


def main() -> None:  # pragma: no cover
    app(prog_name="jaxafm", args=sys.argv[1:])
