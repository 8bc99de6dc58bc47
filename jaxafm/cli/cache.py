"""JAX's persistent compilation cache for the command line: a second run of a command with the
same shapes loads its compiled functions from disk instead of compiling them again (step A's
solver is most of a run's compile time).

The folder is ``$JAXAFM_CACHE_DIR`` if set, else ``~/.cache/jaxafm/xla``; ``JAXAFM_CACHE_DIR=off``
switches the cache off. A cache that JAX was already given (``JAX_COMPILATION_CACHE_DIR``) is
left as it is. Only compilations that took at least a second are kept.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

#: the environment variable naming the cache folder (``off``: no cache)
CACHE_VARIABLE = "JAXAFM_CACHE_DIR"


def cache_dir() -> Optional[Path]:
    """The persistent compilation cache's folder, or ``None`` when switched off."""
    value = os.environ.get(CACHE_VARIABLE, "").strip()
    if value.lower() == "off":
        return None
    return Path(value).expanduser() if value else Path.home() / ".cache" / "jaxafm" / "xla"


def enable_compilation_cache() -> Optional[Path]:
    """Point JAX's persistent compilation cache at :func:`cache_dir` (before the first
    compilation); returns the folder, or ``None`` when switched off or not writable."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return Path(jax.config.jax_compilation_cache_dir)
    folder = cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return folder
