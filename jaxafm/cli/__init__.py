"""The ``jaxafm`` command line: one sub-command per pipeline stage (``commands``) and the
output folders they write into, with their run manifests (``output``). Imports no JAX until a
command runs its job."""

from .commands import app, main
from .output import RunFolder, read_manifest, run_folder

__all__ = ["RunFolder", "app", "main", "read_manifest", "run_folder"]
