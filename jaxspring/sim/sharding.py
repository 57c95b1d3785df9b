"""Batches across devices: a 1-D mesh over `jax.devices()` with the batch axis sharded.

Batched rollouts are `jax.vmap` over a leading batch axis; placing that axis on a
mesh lets `jax.jit` split the batch across devices (GSPMD), with no change to the
simulation code, and the results are the same numbers as on one device.

Example:
    >>> ks = js.sim.shard_batch(jnp.linspace(500.0, 1500.0, 64))
    >>> run = jax.jit(jax.vmap(lambda k: js.rollout(model, params.replace(ks=k), state, 1000, 100).x))
    >>> x = run(ks)        # (64, 11, N, 3), computed on all devices

Several hosts: start every process with `jax.distributed.initialize(...)`; then
`jax.devices()` lists the devices of all hosts and the same mesh spans them (each
process feeds its own slice of the batch, see JAX's multi-process documentation).
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "batch"


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named "batch" over `devices` (default: every device JAX sees)."""
    devices = list(devices) if devices is not None else jax.devices()
    return Mesh(np.asarray(devices), (AXIS,))


def shard_batch(tree, mesh: Mesh | None = None):
    """Place every array of `tree` with its leading (batch) axis split over the mesh.

    Arrays whose leading axis does not divide evenly by the device count, and
    scalars, are replicated instead.
    """
    mesh = mesh or batch_mesh()
    count = mesh.devices.size

    def place(leaf):
        leaf = jax.numpy.asarray(leaf)
        if leaf.ndim >= 1 and leaf.shape[0] % count == 0:
            spec = PartitionSpec(AXIS, *([None] * (leaf.ndim - 1)))
        else:
            spec = PartitionSpec()
        return jax.device_put(leaf, NamedSharding(mesh, spec))

    return jax.tree_util.tree_map(place, tree)
