"""The command table: per ``jaxafm`` command, its config schema, its job's ``run``, the files it
writes and whether an unfinished run resumes. The command line (``jaxafm.cli``) and the output
folders (:mod:`jaxafm.jobs.folder`) read it. Importing it imports no JAX: a job's module, and JAX
with it, is imported when the job runs."""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from fnmatch import fnmatchcase
from typing import Optional

from .. import config


@dataclasses.dataclass(frozen=True)
class Job:
    """One command's job.

    Attributes:
        name: the ``jaxafm`` sub-command, and the module of :mod:`jaxafm.jobs` that holds its ``run``.
        outputs: every file it may write, as paths relative to its output folder; a ``*`` stands
            for any characters within one name (``chunks/trials_*_*.npz``), never for a folder.
        per_model: the files it writes per configured model (its config's ``models``), with
            ``{name}`` for the model's name.
        resumable: whether an unfinished run goes on where it stopped (else the next run
            replaces it).
    """

    name: str
    outputs: tuple
    per_model: tuple = ()
    resumable: bool = False

    @property
    def schema(self) -> type:
        """Its config schema (:data:`jaxafm.config.SCHEMAS`)."""
        return config.SCHEMAS[self.name]

    @property
    def run(self) -> Callable:
        """The job: ``run(cfg, config_path, out, log=print, **options) -> metrics``, with ``cfg`` a
        validated :attr:`schema`, ``config_path`` the YAML file (data paths are relative to it),
        ``out`` an :class:`~jaxafm.jobs.folder.Output`. Imports the job's module (and JAX)."""
        return importlib.import_module(f"{__package__}.{self.name}").run

    def planned_outputs(self, cfg) -> tuple:
        """Every file (a path relative to the output folder, ``*`` within a name) the job may
        write with the config ``cfg``."""
        models = tuple(p.format(name=m.name) for m in getattr(cfg, "models", ()) for p in self.per_model)
        return self.outputs + models

    def planned(self, cfg, path: str) -> Optional[str]:
        """The planned output (:meth:`planned_outputs`) that ``path`` (relative to the output
        folder, ``/`` between names) is, or None: compared name by name, so that
        ``my_analysis/metrics.json`` is not ``metrics.json``."""
        parts = path.split("/")
        for pattern in self.planned_outputs(cfg):
            names = pattern.split("/")
            if len(names) == len(parts) and all(fnmatchcase(p, n) for p, n in zip(parts, names)):
                return pattern
        return None


#: command -> its :class:`Job`
JOBS = {
    job.name: job
    for job in (
        Job("fit", ("metrics.json", "fit.png"), per_model=("model_{name}.json",)),
        Job(
            "calibrate",
            ("metrics.json", "compensation.png"),
            per_model=("model_{name}.json", "validation_{name}.png"),
        ),
        Job(
            "run",
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
            (
                "metrics.json",
                "trials.npz",
                "trials.csv",
                "errors.png",
                "push_odds.png",
                "learning.png",
                "position_coverage.png",
                "scanners.json",
                "chunks/trials_*_*.npz",
                "scanners/model_*.json",
            ),
            resumable=True,
        ),
        Job(
            "diagnose",
            ("metrics.json", "diagnosis.json", "residuals.png", "report.md"),
        ),
        Job(
            "predict",
            (
                "metrics.json",
                "prediction.csv",
                "predict.png",
                "predict_x.png",
                "predict_y.png",
                "predict_band.png",
            ),
        ),
        Job(
            "compensate",
            (
                "metrics.json",
                "drive.csv",
                "tracking.csv",
                "compensate.png",
                "compensate_x.png",
                "compensate_y.png",
            ),
        ),
    )
}
