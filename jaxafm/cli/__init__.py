"""The ``jaxafm`` command line: one sub-command per pipeline stage."""

from .commands import RUN_OUTPUTS, app, main, prepare_output

__all__ = ["RUN_OUTPUTS", "app", "main", "prepare_output"]
