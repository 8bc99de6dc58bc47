"""The command table: per ``jaxafm`` command, its config schema, its job's ``run``, the files it
writes and whether an unfinished run resumes. The command line (``jaxafm.cli``) and the output
folders (:mod:`jaxafm.jobs.folder`) read it. Importing it imports no JAX: a job's module, and JAX
with it, is imported when the job runs."""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable

from .. import config


@dataclasses.dataclass(frozen=True)
class Job:
    """One command's job.

    Attributes:
        name: the ``jaxafm`` sub-command, and the module of :mod:`jaxafm.jobs` that holds its ``run``.
        schema: its config schema (:mod:`jaxafm.config`).
        outputs: the files it writes, glob patterns relative to its output folder.
        writes_models: whether it also writes ``model_<name>.json`` per configured model
            (its config's ``models``).
        resumable: whether an unfinished run goes on where it stopped (else the next run
            replaces it).
    """

    name: str
    schema: type
    outputs: tuple
    writes_models: bool = False
    resumable: bool = False

    @property
    def run(self) -> Callable:
        """The job: ``run(cfg, config_path, out, log=print, **options) -> metrics``, with ``cfg`` a
        validated :attr:`schema`, ``config_path`` the YAML file (data paths are relative to it),
        ``out`` an :class:`~jaxafm.jobs.folder.Output`. Imports the job's module (and JAX)."""
        return importlib.import_module(f"{__package__}.{self.name}").run

    def planned_outputs(self, cfg) -> tuple:
        """The files (glob patterns) the job writes with the config ``cfg``."""
        models = tuple(f"model_{m.name}.json" for m in cfg.models) if self.writes_models else ()
        return self.outputs + models


#: command -> its :class:`Job`
JOBS = {
    job.name: job
    for job in (
        Job("fit", config.ActuatorFitConfig, ("metrics.json", "fit.png"), writes_models=True),
        Job("calibrate", config.CalibrateConfig, ("metrics.json", "compensation.png"), writes_models=True),
        Job(
            "run",
            config.RunConfig,
            (
                "metrics.json",
                "trials.npz",
                "landmarks.png",
                "local_scan.png",
                "push.png",
                "errors.png",
                "model_scanner.json",
            ),
        ),
        Job(
            "study",
            config.StudyConfig,
            (
                "metrics.json",
                "trials.npz",
                "trials.csv",
                "errors.png",
                "scanners.json",
                "chunks/*",
                "scanners/*",
            ),
            resumable=True,
        ),
        Job(
            "diagnose",
            config.DiagnoseConfig,
            ("metrics.json", "diagnosis.json", "residuals.png", "report.md"),
        ),
        Job("predict", config.PredictConfig, ("metrics.json", "prediction.csv", "predict*.png")),
        Job(
            "compensate",
            config.CompensateConfig,
            ("metrics.json", "drive.csv", "tracking.csv", "compensate*.png"),
        ),
    )
}
