"""Devices, meshes and batch sharding: how a stage spreads independent work over devices and hosts.

Every parallel stage has one batch axis whose entries are independent or averaged: the ordered pairs
of cross-timestep initialisation, the views of a refinement or training step, the views an evaluation
renders. ``device_mesh`` lays the chosen devices out as a one-axis ``jax.sharding.Mesh`` named
``"batch"``. ``shard_batch`` places an array (or pytree) with its leading axis split over that axis
and ``replicate`` places it whole on every device; inside ``jit``, ``map_batch`` runs a function over
the items of a batch, each device over its share (``jax.shard_map``), and a sum of its results over
the batch becomes an all-reduce (XLA's partitioner). ``padded`` rounds a batch up to a multiple of
the device count (the padding rows are copies of row 0 whose results the caller drops).

Several processes (hosts, or processes on one machine) form one mesh after
``initialize_from_environment`` has called ``jax.distributed.initialize``; every process runs the
same program on the same inputs, builds its arrays with ``jax.make_array_from_callback`` (each
supplies the slices its devices hold) and reads results back with ``to_host`` (an all-gather).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cfgs_jax.errors import InputError

AXIS = "batch"

ENVIRONMENT = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")


def initialize_from_environment() -> bool:
    """``jax.distributed.initialize`` from ``JAX_COORDINATOR_ADDRESS`` (host:port of process 0),
    ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` when all three are set (CPU collectives: gloo);
    True when it did. Call once, before any JAX computation."""
    values = [os.environ.get(k) for k in ENVIRONMENT]
    if not any(values):
        return False
    if not all(values):
        missing = [k for k, v in zip(ENVIRONMENT, values) if not v]
        raise InputError(
            f"a multi-process run needs all of {', '.join(ENVIRONMENT)}; {', '.join(missing)} unset",
            field="environment",
            fix="set the three variables in every process (see the README, 'Several devices and hosts')",
        )
    try:
        count, index = int(values[1]), int(values[2])
    except ValueError as exc:
        raise InputError(f"JAX_NUM_PROCESSES / JAX_PROCESS_ID must be integers: {exc}", field="environment") from exc
    if not 0 <= index < count:
        raise InputError(f"JAX_PROCESS_ID {index} not in [0, {count})", field="environment")
    if jax.distributed.is_initialized():
        return True
    jax.distributed.initialize(values[0], count, index)
    return True


def select_devices(devices: int | str | Sequence[jax.Device] | None = "all") -> list[jax.Device]:
    """The devices a stage runs on: ``"all"`` / None (every device of every process), a count N (the
    first N of ``jax.devices()``; in several processes N must take devices of each) or a list."""
    available = jax.devices()
    if devices is None or devices == "all":
        return list(available)
    if isinstance(devices, str):
        try:
            devices = int(devices)
        except ValueError:
            raise InputError(f"expected a count or 'all', got {devices!r}", field="--devices") from None
    if isinstance(devices, (int, np.integer)):
        if not 1 <= devices <= len(available):
            raise InputError(
                f"{devices} devices asked for, {len(available)} available ({available[0].platform})",
                field="--devices",
                fix=f"pass a count from 1 to {len(available)}, or 'all'",
            )
        chosen = list(available[: int(devices)])
        if jax.process_count() > 1 and len({d.process_index for d in chosen}) < jax.process_count():
            raise InputError(
                f"{devices} devices leave some processes without one",
                field="--devices",
                fix="use 'all' in a multi-process run",
            )
        return chosen
    return list(devices)


def device_mesh(devices: int | str | Sequence[jax.Device] | Mesh | None = "all") -> Mesh:
    """A one-axis mesh (axis ``"batch"``) over ``select_devices(devices)``; a Mesh is returned as is."""
    if isinstance(devices, Mesh):
        return devices
    return Mesh(np.asarray(select_devices(devices)), (AXIS,))


def mesh_size(mesh: Mesh | None) -> int:
    """How many devices the mesh spans (1 without one)."""
    return 1 if mesh is None else int(mesh.devices.size)


def is_parallel(mesh: Mesh | None) -> bool:
    """Whether a stage should shard its batch (a mesh of more than one device)."""
    return mesh_size(mesh) > 1


def padded(n: int, mesh: Mesh | None) -> int:
    """``n`` rounded up to a multiple of the mesh's device count."""
    k = mesh_size(mesh)
    return -(-int(n) // k) * k


def pad_rows(x, count: int):
    """``x`` ([n, ...]) followed by copies of its row 0 up to ``count`` rows (numpy)."""
    x = np.asarray(x)
    extra = count - x.shape[0]
    return x if extra <= 0 else np.concatenate([x, np.repeat(x[:1], extra, axis=0)])


def _place(tree, sharding_of):
    def one(x):
        if isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return jax.random.wrap_key_data(one(jax.random.key_data(x)), impl=jax.random.key_impl(x))
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding_of(x), lambda index: x[index])

    return jax.tree_util.tree_map(one, tree)


def on_device(tree):
    """Every leaf of ``tree`` as a JAX array (host data copied to the default device once, so a loop
    does not send it again each step); JAX arrays as they are."""
    return jax.tree_util.tree_map(lambda x: x if isinstance(x, jax.Array) else jnp.asarray(x), tree)


def stack(items):
    """The pytrees ``items`` (e.g. cameras) stacked along a new leading axis, as numpy arrays."""
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *items)


def shard_batch(tree, mesh: Mesh | None):
    """Every array of ``tree`` (host data, the same in every process) with its leading axis split over
    the mesh; the axis length must be a multiple of the device count (``padded``). Without a mesh of
    several devices, on the default device (``on_device``)."""
    if not is_parallel(mesh):
        return on_device(tree)
    k = mesh_size(mesh)
    for x in jax.tree_util.tree_leaves(tree):
        if np.shape(x)[0] % k:
            raise ValueError(f"batch of {np.shape(x)[0]} does not split over {k} devices (pad it first)")
    return _place(tree, lambda x: NamedSharding(mesh, PartitionSpec(AXIS)))


def replicate(tree, mesh: Mesh | None):
    """Every array of ``tree`` whole on every device of the mesh; without a mesh of several devices,
    on the default device (``on_device``)."""
    if not is_parallel(mesh):
        return on_device(tree)
    return _place(tree, lambda x: NamedSharding(mesh, PartitionSpec()))


def to_host(tree):
    """Every array of ``tree`` as a numpy array of its full (global) value: an all-gather across
    processes when it is split over several."""

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable and not x.is_fully_replicated:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree_util.tree_map(one, tree)


def map_batch(fn, batched, shared, mesh: Mesh | None = None):
    """``fn(item, shared)`` for every item along the leading axis of the pytree ``batched``, stacked:
    one item after another (``jax.lax.map``, each item compiled as an unbatched call — ``jax.vmap`` of
    the splatting kernel runs 2–3× slower than its items one by one on a CPU), and with a mesh of
    several devices each device over its share (``jax.shard_map``; ``shared`` replicated). Call inside
    ``jit``; the batch length must be a multiple of the device count."""

    def local(items, common):
        return jax.lax.map(lambda item: fn(item, common), items)

    if not is_parallel(mesh):
        return local(batched, shared)
    spec = PartitionSpec(AXIS)
    return jax.shard_map(local, mesh=mesh, in_specs=(spec, PartitionSpec()), out_specs=spec, check_vma=False)(
        batched, shared
    )


def is_primary() -> bool:
    """True in process 0 (the one that reports), and in a single-process run."""
    return jax.process_index() == 0
