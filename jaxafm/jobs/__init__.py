"""The jobs: one per ``jaxafm`` command, on top of the library and under the command line.

A job (``fit``, ``calibrate``, ``run``, ``study``, ``diagnose``, ``predict``, ``compensate``:
one module each) takes its command's validated config, reads and checks everything the config
names before the output folder is touched, calls the library with typed arguments, and writes
each of its results through an :class:`Output` (:meth:`Output.write`, which records the file in
the run's manifest; ``metrics.json`` through :meth:`Output.write_metrics`): a run owns exactly
the files it wrote. The command table :data:`JOBS` gives each command's schema, job, files and
whether it resumes; :mod:`~jaxafm.jobs.folder` keeps output folders and their run manifests.
The library below never imports this package. Importing it imports no JAX: a job's module is
imported when it runs.
"""

from .folder import MANIFEST, Output, RunFolder, read_manifest, run_folder, shared_run_folder
from .table import JOBS, Job

__all__ = [
    "JOBS",
    "MANIFEST",
    "Job",
    "Output",
    "RunFolder",
    "read_manifest",
    "run_folder",
    "shared_run_folder",
]
