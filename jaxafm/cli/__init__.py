"""The ``jaxafm`` command line (``commands``): one sub-command per job of :mod:`jaxafm.jobs`, a
thin layer that validates, checks the output folder and runs; ``cache``: JAX's persistent
compilation cache. Imports no JAX until a command runs its job."""

from .commands import app, main

__all__ = ["app", "main"]
