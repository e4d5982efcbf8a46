"""Data parallelism over every visible device with ``jax.sharding``: parameters replicated, the
batch split along its first axis. On one device every function here is the identity (no
copies, no new compiled shapes), so callers use them unconditionally.

    mesh = data_mesh()                      # all of jax.devices(), one axis "data"
    params = replicate(params, mesh)
    batch = shard_batch(batch, mesh)        # leading axis divisible by the device count
    state, metrics = train_step(state, batch, key)   # jit partitions it (SPMD)

The random draws inside a jitted step do not depend on the sharding (JAX's partitionable
threefry), so N devices give the numbers one device gives, up to the order of float sums.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["data_mesh", "padded_size", "replicate", "shard_batch"]

AXIS = "data"


def data_mesh(devices=None) -> Mesh:
    """A one-axis mesh ("data") over ``devices`` (default: every device JAX sees)."""
    devices = list(jax.devices() if devices is None else devices)
    return Mesh(np.array(devices), (AXIS,))


def padded_size(n: int, mesh: Mesh) -> int:
    """The smallest multiple of the mesh's device count that holds ``n`` rows."""
    d = mesh.size
    return -(-n // d) * d


def replicate(tree, mesh: Mesh):
    """Every leaf on every device of ``mesh`` (one device: ``tree`` as it is)."""
    if mesh.size == 1:
        return tree
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def shard_batch(tree, mesh: Mesh):
    """Every leaf split along its first axis over the devices of ``mesh`` (one device: ``tree``
    as it is). Raises ValueError when a leading axis does not divide evenly."""
    if mesh.size == 1:
        return tree
    for leaf in jax.tree.leaves(tree):
        if np.ndim(leaf) == 0 or np.shape(leaf)[0] % mesh.size:
            raise ValueError(
                f"a batch of {np.shape(leaf)[:1] or 'a scalar'} cannot be split over "
                f"{mesh.size} devices: use a batch size that is a multiple of {mesh.size}"
            )
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec(AXIS)))
