"""Ensembles: one compiled solve mapped over many initial conditions or parameters, on one
device (`jax.vmap`) or split across several (`jax.sharding`, `jax.shard_map`)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PyTree

__all__ = ["ensemble", "ensemble_mesh"]

_AXIS = "ensemble"


def ensemble_mesh(devices: Sequence[jax.Device] | None = None, axis_name: str = _AXIS) -> Mesh:
    """A one-dimensional device mesh for `ensemble(..., mesh=...)`.

    **Arguments:**

    - `devices`: the devices to split the ensemble over. Default `jax.devices()`: every device
      of every process (after `jax.distributed.initialize()`, that spans all hosts).
    - `axis_name`: the name of the mesh axis.
    """
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("ensemble_mesh needs at least one device")
    return Mesh(np.asarray(devices, dtype=object), (axis_name,))


def _batch_size(args: tuple, in_axes: tuple) -> int:
    sizes = set()
    for i, (arg, axis) in enumerate(zip(args, in_axes, strict=True)):
        if axis is None:
            continue
        leaves = jax.tree_util.tree_leaves(arg)
        if not leaves:
            raise ValueError(f"argument {i} is mapped (in_axes[{i}] = 0) but has no arrays")
        for leaf in leaves:
            shape = np.shape(leaf)
            if len(shape) == 0:
                raise ValueError(
                    f"argument {i} is mapped over its leading axis but holds a scalar; give "
                    f"it in_axes[{i}] = None to share it across the ensemble"
                )
            sizes.add(shape[0])
    if not sizes:
        raise ValueError("ensemble needs at least one mapped argument (an in_axes entry of 0)")
    if len(sizes) > 1:
        raise ValueError(f"mapped arguments disagree on the ensemble size: {sorted(sizes)}")
    (size,) = sizes
    if size < 1:
        raise ValueError("the ensemble is empty (leading axis of length 0)")
    return size


def _normalise_axes(in_axes, nargs: int) -> tuple:
    if isinstance(in_axes, int | None):
        in_axes = (in_axes,) * nargs
    in_axes = tuple(in_axes)
    if len(in_axes) != nargs:
        raise ValueError(f"in_axes has {len(in_axes)} entries for {nargs} arguments")
    for axis in in_axes:
        if axis not in (0, None):
            raise ValueError(f"in_axes entries must be 0 (mapped) or None (shared), got {axis!r}")
    return in_axes


@functools.lru_cache(maxsize=32)
def _compiled(fn: Callable, in_axes: tuple, mesh: Mesh | None, axis_name: str) -> Callable:
    """The jitted batched function; cached so that repeated calls do not retrace."""
    batched = jax.vmap(fn, in_axes=in_axes)
    if mesh is None:
        return jax.jit(batched)
    specs = tuple(PartitionSpec(axis_name) if a == 0 else PartitionSpec() for a in in_axes)
    # Each device runs the vmapped solve on its own slice; members never communicate.
    sharded = jax.shard_map(
        batched, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(axis_name), check_vma=False
    )
    return jax.jit(sharded)


def ensemble(
    fn: Callable[..., PyTree],
    *args: PyTree,
    in_axes: int | None | Sequence[int | None] = 0,
    mesh: Mesh | None = None,
) -> PyTree:
    """Run `fn` on every member of an ensemble in one compiled program.

    `fn` is the solve of one member, e.g. `lambda y0, k: diffrax.diffeqsolve(term, solver, ...,
    y0, args=k)`. Every argument with `in_axes` entry `0` is a pytree whose arrays carry the
    ensemble along their leading axis (the same length `B` for all); entries `None` are shared
    by all members. The result is `fn`'s output with a leading axis of length `B`.

    Without `mesh` this is `jax.jit(jax.vmap(fn))` on the default device: all members advance
    together, and every loop of the step (seed fit, Newton iterations, line search) runs as
    long as its slowest member. (On a 2-core CPU a batch of 1024 oscillator solves measured
    about 10x *slower* than a Python loop of single solves, `benchmarks/speed.py`: check the
    throughput on your hardware before relying on batching.) With a `mesh` (see
    `ensemble_mesh`) the ensemble is split along the mesh's single axis with `jax.shard_map`:
    each device solves its slice with `vmap`, with no communication between devices. Members
    are independent, so the numbers are those of the unsharded run (up to rounding in the last
    bit). If `B` is not a multiple of the number of devices, the ensemble is padded with copies
    of its last member, which are dropped from the result.

    Several hosts: call `jax.distributed.initialize()` on every process first, build the mesh
    from `jax.devices()` (all devices of all processes) and call `ensemble` with the same
    global inputs on every process. The result is then a global `jax.Array`; each process
    reads the members on its own devices from `result.addressable_shards` (or all of them with
    `jax.experimental.multihost_utils.process_allgather`).

    The compiled program is cached per `(fn, in_axes, mesh)`: pass the same function object
    to reuse it (a new `lambda` on every call compiles again).

    **Arguments:**

    - `fn`: the solve of one member; a function of `len(args)` pytrees.
    - `args`: the arguments, batched along their leading axis where `in_axes` is `0`.
    - `in_axes`: `0` (default: every argument is batched), `None`, or one entry per argument.
    - `mesh`: a one-axis `jax.sharding.Mesh` to split the ensemble over; default: no sharding.

    **Returns:**

    `fn`'s output for every member, stacked along a new leading axis.
    """
    if not callable(fn):
        raise TypeError(f"ensemble needs a callable fn, got {type(fn).__name__}")
    in_axes = _normalise_axes(in_axes, len(args))
    size = _batch_size(args, in_axes)
    if mesh is None:
        return _compiled(fn, in_axes, None, _AXIS)(*args)
    if not isinstance(mesh, Mesh) or len(mesh.axis_names) != 1:
        raise ValueError(
            f"mesh must be a one-axis jax.sharding.Mesh (see ensemble_mesh), got {mesh!r}"
        )
    (axis_name,) = mesh.axis_names
    ndev = mesh.devices.size
    padded = -(-size // ndev) * ndev

    def pad(x):
        x = jnp.asarray(x)
        if padded == size:
            return x
        extra = jnp.broadcast_to(x[-1:], (padded - size,) + x.shape[1:])
        return jnp.concatenate([x, extra], axis=0)

    placed = []
    for arg, axis in zip(args, in_axes, strict=True):
        if axis is None:
            sharding = NamedSharding(mesh, PartitionSpec())
            placed.append(jax.tree_util.tree_map(lambda x: jax.device_put(x, sharding), arg))
        else:
            sharding = NamedSharding(mesh, PartitionSpec(axis_name))
            placed.append(jax.tree_util.tree_map(lambda x: jax.device_put(pad(x), sharding), arg))
    out = _compiled(fn, in_axes, mesh, axis_name)(*placed)
    if padded == size:
        return out
    return jax.tree_util.tree_map(lambda x: x[:size], out)
