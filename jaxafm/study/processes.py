"""A study's trials over every JAX device of every process (``jax.distributed``): trials split
over a one-axis mesh (``trials``), what every trial shares copied to each device, and the
collectives that keep several processes in step (each computes its scanners' step A and surveys
itself; :func:`check_same` checks that they agree, and :func:`from_process_0` gives every process
process 0's view of the output folder)."""

from __future__ import annotations

import hashlib

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec


def shard(arrays: dict, mesh: Mesh, size: int) -> dict:
    """``arrays`` (leading axis: trials) padded to ``size`` trials, a multiple of the device count
    (repeating the last trial), and split over the mesh's devices."""
    sharding = NamedSharding(mesh, PartitionSpec("trials"))

    def put(a):
        a = np.concatenate([a, np.repeat(a[-1:], size - len(a), 0)])
        return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])

    return {k: put(v) for k, v in arrays.items()}


def replicate(tree, mesh: Mesh):
    """Every array of ``tree`` copied to each of the mesh's devices. With several processes, each
    puts its own copy once one collective has checked that all hold the same (:func:`check_same`;
    ``jax.device_put`` would check each array on its own, a collective and a compilation each)."""
    arrays, rest = eqx.partition(tree, eqx.is_array)
    sharding = NamedSharding(mesh, PartitionSpec())
    if jax.process_count() == 1:
        return eqx.combine(jax.device_put(arrays, sharding), rest)
    host = jax.tree_util.tree_map(np.asarray, arrays)
    check_same(
        host,
        "computed another survey or step A model than process 0: each process computes them itself, "
        "so all must run the same JAX on the same kind of CPU",
    )
    put = lambda a: jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])
    return eqx.combine(jax.tree_util.tree_map(put, host), rest)


def check_same(tree, differs: str) -> None:
    """Check that every process holds the same NumPy arrays ``tree``: one gather of a SHA-256
    digest of them.

    Raises:
        RuntimeError: on every process, where one holds other values than process 0: naming
            them, then ``differs``.
    """
    from jax.experimental import multihost_utils

    digest = hashlib.sha256()
    for a in jax.tree_util.tree_leaves(tree):
        digest.update(f"{a.shape}{a.dtype}".encode() + np.ascontiguousarray(a).tobytes())
    every = multihost_utils.process_allgather(np.frombuffer(digest.digest(), np.uint32))
    other = [p for p in range(len(every)) if not np.array_equal(every[p], every[0])]
    if other:
        raise RuntimeError(f"process(es) {', '.join(map(str, other))} {differs}")


def gather(tree, n: int):
    """The first ``n`` trials of ``tree`` (arrays split over the mesh) as NumPy arrays, on every
    process (gathered from all of them: a collective)."""
    if jax.process_count() > 1:  # pragma: no cover - several processes
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree_util.tree_map(lambda a: np.array(a)[:n], tree)


def from_process_0(value) -> np.ndarray:
    """``value`` (a NumPy scalar or array of the same shape on every process) as process 0 has it,
    on every process: a collective with several processes, ``np.asarray(value)`` with one."""
    if jax.process_count() == 1:
        return np.asarray(value)
    from jax.experimental import multihost_utils

    return multihost_utils.broadcast_one_to_all(np.asarray(value))
