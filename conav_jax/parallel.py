"""Data parallelism: a 1-D device mesh whose one axis, "batch", splits the batch of episodes or
samples; parameters and optimiser state are replicated on every device.

`make_mesh(N)` -> `shard_batch` / `replicate` (device_put) on the host side, `constrain_batch`
inside jit (`jax.lax.with_sharding_constraint`); jit partitions the vmapped computation from
them. Work whose lanes are independent (env steps) can run per device instead, through
`per_device`: one single-device program per device, none partitioned. XLA cannot partition a
Pallas call: inside a partitioned program a kernel runs per device through `lanes_on_devices`.
Several hosts join through `maybe_initialize_distributed()` before the first jax call;
`jax.devices()` then lists every host's devices and a mesh spans them all. No other imports
from this repository: envs, train and eval use it.
"""

from __future__ import annotations

import contextlib
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
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
    """`fn` run on each device of `mesh` over its share of the lanes, as one single-device
    program per device: a host-level function (call it outside jit) whose positional arguments
    marked True in `in_batched` are split along their leading axis into `mesh.size` equal parts,
    part i placed on device i, the others copied to every device. The devices' programs are
    dispatched together and run concurrently; outputs marked True in `out_batched` (a prefix of
    the output tree) come back as arrays split over the mesh (the devices' parts, not copied),
    the others as device 0's (they must not depend on the device's lanes). `fn` jitted alone
    without a mesh.

    Lanes that never talk to each other need no partitioner: a Pallas call runs as on one GPU,
    and XLA's GPU compiler, which crashes compiling MJX's step inside a partitioned program
    (`jax.shard_map` or `jax.pmap`), compiles a single-device one."""
    jitted = jax.jit(fn)
    if mesh is None:
        return jitted
    devices = list(mesh.devices.flat)
    if any(d.process_index != jax.process_index() for d in devices):
        raise ValueError("per_device runs on this process's own devices; give it a mesh of those alone")
    n = len(devices)
    sharding = batch_sharding(mesh)

    def part(x, i):
        """Device i's part of a batched leaf: its shard where `x` is already split this way."""
        if isinstance(x, jax.Array) and x.sharding == sharding:
            return next(s.data for s in x.addressable_shards if s.device == devices[i])
        size = np.shape(x)[0]
        check_divisible(size, mesh)
        k = size // n
        return jax.device_put(x[i * k:(i + 1) * k], devices[i])

    def call(*args):
        if len(args) != len(in_batched):
            raise ValueError(f"per_device: {len(args)} arguments, but in_batched has {len(in_batched)} entries")
        shares = [
            [jax.tree.map(lambda x: part(x, i), a) if b else jax.device_put(a, devices[i])
             for a, b in zip(args, in_batched)]
            for i in range(n)
        ]
        # Threads: the first call compiles each device's program, and the compiles overlap.
        with ThreadPoolExecutor(n) as pool:
            outs = list(pool.map(lambda share: jitted(*share), shares))

        def join(batched, *subtrees):
            if not batched:
                return subtrees[0]
            return jax.tree.map(lambda *xs: jax.make_array_from_single_device_arrays(
                (n * xs[0].shape[0], *xs[0].shape[1:]), sharding, list(xs)), *subtrees)

        return jax.tree.map(join, out_batched, *outs)

    return call


def traced_under(mesh: Mesh | None):
    """A context to trace a program whose lanes are split over `mesh` in: Pallas kernels inside
    it then run per device (`lanes_on_devices`). Nothing without a mesh of several devices."""
    if mesh is None or mesh.size == 1:
        return contextlib.nullcontext()
    return jax.sharding.use_abstract_mesh(mesh.abstract_mesh)


def mesh_batch_devices() -> int:
    """The device count of the "batch" axis of the mesh the current trace runs under
    (`traced_under`); 1 without one."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or BATCH_AXIS not in mesh.axis_names:
        return 1
    return int(dict(zip(mesh.axis_names, mesh.axis_sizes))[BATCH_AXIS])


def lanes_on_devices(fn):
    """`fn` of one lane (positional array arguments) whose batched form, under `jax.vmap` inside
    a program partitioned over a mesh with several devices on the "batch" axis
    (`mesh_batch_devices`), runs each device's lanes on that device (`jax.shard_map`) and is a
    plain `jax.vmap` otherwise. For a Pallas kernel in such a program: XLA cannot partition a
    Pallas call, and a call per device needs no partitioning."""

    @jax.custom_batching.custom_vmap
    def one(*args):
        return fn(*args)

    @one.def_vmap
    def batched(axis_size, in_batched, *args):
        args = [jax.tree.map(lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))), a, bs)
                for a, bs in zip(args, in_batched)]
        run = jax.vmap(fn)
        devices = mesh_batch_devices()
        if devices > 1 and axis_size % devices == 0:
            run = jax.shard_map(run, mesh=jax.sharding.get_abstract_mesh(), in_specs=PartitionSpec(BATCH_AXIS),
                                out_specs=PartitionSpec(BATCH_AXIS), check_vma=False)
        out = run(*args)
        return out, jax.tree.map(lambda _: True, out)

    return one


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
