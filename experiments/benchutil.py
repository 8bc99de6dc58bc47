"""What the benchmarks share: timing a jitted function and the machine they ran on.

Importing it also puts ``tests/`` on the path: the NumPy reference implementations the
benchmarks time (``tests/reference.py``) are test code, not part of the installed package.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def time_jax(fn, *args, repeats: int):
    """Compile time, then median/min of ``repeats`` warmed-up calls; returns (stats, output)."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    out = jax.block_until_ready(compiled(*args))  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return {
        "compile_s": compile_s,
        "median_s": statistics.median(times),
        "min_s": min(times),
        "max_s": max(times),
        "repeats": repeats,
    }, out


def machine_info():
    import jaxlib

    return {
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "equinox": eqx.__version__,
        "numpy": np.__version__,
        "python": sys.version.split()[0],
        "devices": str(jax.devices()),
        "device_kind": jax.devices()[0].device_kind,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor(),
        "x64": bool(jax.config.jax_enable_x64),
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
        "loadavg_at_start": os.getloadavg(),
    }


def device_label(machine: dict) -> str:
    """The machine a result was measured on, for a figure's labels ("2-core CPU", "GPU: ...")."""
    if "Cuda" in machine["devices"]:
        return "GPU: " + machine.get("device_kind", "CUDA")
    return f"{machine['cpu_count']}-core CPU"
