"""The ``jaxafm`` command line: one sub-command per pipeline stage (``commands``) and the
output folders they write into (``output``). Imports no JAX until a command runs its job."""

from .commands import app, main
from .output import RUN_OUTPUTS, prepare_output

__all__ = ["RUN_OUTPUTS", "app", "main", "prepare_output"]
