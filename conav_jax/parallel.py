"""Data parallelism: a 1-D device mesh whose one axis, "batch", splits the batch of episodes or
samples; parameters and optimiser state are replicated on every device.

`make_mesh(N)` -> `shard_batch` / `replicate` (device_put) on the host side, `constrain_batch`
inside jit (`jax.lax.with_sharding_constraint`); jit partitions the vmapped computation from
them. Work whose lanes are independent (env steps, rollouts) runs per device instead, through
`per_device` (`jax.shard_map`): XLA cannot partition a Pallas call, and nothing needs to. Several hosts join through `maybe_initialize_distributed()` before the first jax call;
`jax.devices()` then lists every host's devices and a mesh spans them all. No other imports
from this repository: envs, train and eval use it.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXIS = "batch"
PyTree = Any


def make_mesh(num_devices: int | None = None) -> Mesh:
    """A 1-D mesh over the first `num_devices` of `jax.devices()` (None: all visible ones,
    every host's after `maybe_initialize_distributed`), axis name "batch". ValueError if
    `num_devices < 1`, more than are visible, or, with several processes, not all of them
    (each process must hold a part of the mesh)."""
    devices = jax.devices()
    n = len(devices) if num_devices is None else int(num_devices)
    if n < 1:
        raise ValueError(f"need at least 1 device, got {num_devices}")
    if n > len(devices):
        raise ValueError(
            f"asked for {n} devices but only {len(devices)} {devices[0].platform} device(s) are visible "
            "(on CPU, set XLA_FLAGS=--xla_force_host_platform_device_count=N before jax starts)"
        )
    if jax.process_count() > 1 and n != len(devices):
        raise ValueError(
            f"with {jax.process_count()} processes the mesh must span all {len(devices)} devices, got {n}"
        )
    return Mesh(np.asarray(devices[:n]), (BATCH_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split over the mesh's devices, the rest of each array whole."""
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    """A full copy on every device of the mesh."""
    return NamedSharding(mesh, PartitionSpec())


def check_divisible(size: int, mesh: Mesh, what: str = "batch") -> None:
    """ValueError unless `size` splits evenly over the mesh's devices."""
    if size % mesh.size:
        raise ValueError(f"{what} size {size} is not divisible by the device count {mesh.size}")


def shard_batch(tree: PyTree, mesh: Mesh) -> PyTree:
    """`tree` on the mesh, every array's leading axis split over the devices (each host passes
    the same, whole arrays). ValueError if a leading size is not divisible by the device count."""
    for x in jax.tree.leaves(tree):
        if np.ndim(x) == 0:
            raise ValueError("shard_batch needs arrays with a leading batch axis, got a scalar")
        check_divisible(np.shape(x)[0], mesh)
    return jax.device_put(tree, batch_sharding(mesh))


def replicate(tree: PyTree, mesh: Mesh) -> PyTree:
    """`tree` copied to every device of the mesh (parameters, optimiser state, keys)."""
    return jax.device_put(tree, replicated(mesh))


def constrain_batch(tree: PyTree, mesh: Mesh | None) -> PyTree:
    """Inside jit: `tree`'s leading axis (the batch) split over the mesh's devices, so what
    follows runs data-parallel; `tree` unchanged without a mesh."""
    return tree if mesh is None else jax.lax.with_sharding_constraint(tree, batch_sharding(mesh))


def per_device(fn, mesh: Mesh | None, in_batched: tuple, out_batched: Any = True):
    """`fn` run once on each device of `mesh` over its share of the lanes (`jax.shard_map`):
    each positional argument whose `in_batched` entry is True has its leading axis split over
    the devices, the others are replicated; likewise the outputs by `out_batched` (a prefix of
    the output tree). Outputs marked False must be the same on every device (e.g. reduced with
    `jax.lax.psum(x, BATCH_AXIS)` inside `fn`). The body sees one device's lanes, so a Pallas
    kernel inside it runs as on one GPU. `fn` itself without a mesh."""
    if mesh is None:
        return fn

    def spec(batched):
        return jax.tree.map(lambda b: PartitionSpec(BATCH_AXIS) if b else PartitionSpec(), batched)

    # The lanes never talk to each other, so the replication checks (which a Pallas call and
    # lax.cond over per-lane data do not satisfy) have nothing to find.
    return jax.shard_map(fn, mesh=mesh, in_specs=spec(tuple(in_batched)), out_specs=spec(out_batched),
                         check_vma=False)


def round_up(size: int, mesh: Mesh | None) -> int:
    """The smallest multiple of the mesh's device count >= `size` (`size` without a mesh):
    a batch padded to it splits evenly."""
    n = 1 if mesh is None else mesh.size
    return -(-size // n) * n


def to_host(tree: PyTree) -> PyTree:
    """Numpy copies of `tree`'s arrays; arrays spread over several hosts are gathered whole on
    every process first."""

    def get(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            from jax.experimental import multihost_utils

            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree.map(get, tree)


def maybe_initialize_distributed() -> bool:
    """Join a multi-host run (`jax.distributed.initialize()`) when the environment describes
    one, before any other jax call; True if it did. Nothing happens for a single process.

    Multi-host is recognised from either
    - `JAX_COORDINATOR_ADDRESS` (host:port of process 0, read by jax itself) together with
      `JAX_NUM_PROCESSES` > 1 and `JAX_PROCESS_ID` (ours, passed on to jax), or with a cluster
      jax detects on its own (SLURM, Open MPI, Kubernetes, Cloud TPU) supplying them; or
    - a SLURM step of several tasks (`SLURM_STEP_NUM_TASKS` > 1, as `srun -n N` sets) or an
      Open MPI launch of several ranks (`OMPI_COMM_WORLD_SIZE` > 1), whose variables jax reads.
    ValueError if `JAX_NUM_PROCESSES` / `JAX_PROCESS_ID` are not integers."""
    if jax.distributed.is_initialized():
        return False
    env = os.environ

    def as_int(name: str) -> int | None:
        if env.get(name) in (None, ""):
            return None
        try:
            return int(env[name])
        except ValueError:
            raise ValueError(f"{name} must be an integer, got {env[name]!r}") from None

    if env.get("JAX_COORDINATOR_ADDRESS"):
        num, pid = as_int("JAX_NUM_PROCESSES"), as_int("JAX_PROCESS_ID")
        if num == 1:
            return False
        jax.distributed.initialize(num_processes=num, process_id=pid)
        return True
    if (as_int("SLURM_STEP_NUM_TASKS") or 1) > 1 or (as_int("OMPI_COMM_WORLD_SIZE") or 1) > 1:
        jax.distributed.initialize()
        return True
    return False
