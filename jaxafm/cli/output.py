"""Output folders: what each command writes, and how a folder is made ready for it."""

from __future__ import annotations

from pathlib import Path

FIT_OUTPUTS = ("metrics.json", "fit.png", "model_*.json")  # what `jaxafm fit` writes
CALIBRATE_OUTPUTS = ("metrics.json", "compensation.png", "model_*.json")  # what `jaxafm calibrate` writes
RUN_OUTPUTS = (
    "metrics.json",
    "trials.npz",
    "landmarks.png",
    "local_scan.png",
    "push.png",
    "errors.png",
    "model_scanner.json",
)  # what `jaxafm run` writes
STUDY_OUTPUTS = (
    "metrics.json",
    "trials.npz",
    "trials.csv",
    "errors.png",
    "study.yaml",
    "scanners.json",
    "chunks/trials_*.npz",
    "scanners/model_*.json",
)  # what `jaxafm study` writes
DIAGNOSE_OUTPUTS = (
    "metrics.json",
    "diagnosis.json",
    "residuals.png",
    "report.md",
)  # what `jaxafm diagnose` writes


def prepare_output(out: Path, overwrite: bool, outputs: tuple) -> None:
    """Create the output folder ``out``; an existing, non-empty one only with ``overwrite``,
    which removes just the files this command writes and leaves everything else where it is.

    Arguments:
        out: the output folder.
        overwrite: whether results already in ``out`` may be replaced.
        outputs: glob patterns (relative to ``out``) of the files the command writes.

    Raises:
        ValueError: ``out`` is a file, or a non-empty folder without ``overwrite``.
    """
    if out.exists() and not out.is_dir():
        raise ValueError(f"output {out} exists and is not a folder: choose another with --out")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise ValueError(
                f"output folder {out} exists and is not empty: choose another with --out, "
                "or pass --overwrite to replace the results in it"
            )
        for pattern in outputs:
            for f in out.glob(pattern):
                f.unlink()
    out.mkdir(parents=True, exist_ok=True)
