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

__all__ = ["ensemble", "ensemble_mesh", "ensemble_gather"]

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


def _resolve_batch_size(batch_size) -> int | None:
    if batch_size is None:
        return None
    if not isinstance(batch_size, int) or isinstance(batch_size, bool) or batch_size < 1:
        raise ValueError(
            f"batch_size must be None or a positive integer, got {batch_size!r}"
        )
    return batch_size


# XLA's CPU backend (recent jaxlib) hands small reductions to YNNPACK fusions, which on the
# tiny per-member arrays of a vmapped solve run several times slower than XLA's own loops;
# only its dot products keep that route.
_CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}


def _all_cpu(mesh: Mesh | None) -> bool:
    devices = jax.devices() if mesh is None else list(mesh.devices.flat)
    return all(d.platform == "cpu" for d in devices)


@functools.cache
def cpu_compiler_options() -> tuple[tuple[str, str], ...]:
    """The XLA options `ensemble` compiles with on CPUs (`_CPU_OPTIONS`) where this jaxlib
    knows them, else none; public so that a measurement can compile alongside it alike."""
    try:
        jax.jit(lambda x: x + 1, compiler_options=_CPU_OPTIONS).lower(1.0).compile()
    except Exception:  # an older or newer XLA without the option
        return ()
    return tuple(_CPU_OPTIONS.items())


def _chunked(fn: Callable, in_axes: tuple, batch_size: int | None) -> Callable:
    """`fn` over the leading axis of the mapped arguments: `vmap` over all members at once
    (`batch_size=None`), or `lax.map` over chunks of `batch_size` vmapped members."""
    if batch_size is None:
        return jax.vmap(fn, in_axes=in_axes)

    def mapped(*args):
        batched = tuple(a for a, axis in zip(args, in_axes, strict=True) if axis is not None)

        def member(xs):
            it = iter(xs)
            pairs = zip(args, in_axes, strict=True)
            return fn(*(a if axis is None else next(it) for a, axis in pairs))

        return jax.lax.map(member, batched, batch_size=None if batch_size == 1 else batch_size)

    return mapped


@functools.lru_cache(maxsize=32)
def _compiled(
    fn: Callable, in_axes: tuple, mesh: Mesh | None, axis_name: str, batch_size: int | None
) -> Callable:
    """The jitted batched function; cached so that repeated calls do not retrace."""
    batched = _chunked(fn, in_axes, batch_size)
    options = dict(cpu_compiler_options()) if _all_cpu(mesh) else {}
    if mesh is None:
        return jax.jit(batched, compiler_options=options)
    specs = tuple(PartitionSpec(axis_name) if a == 0 else PartitionSpec() for a in in_axes)
    # Each device runs the vmapped solve on its own slice; members never communicate.
    sharded = jax.shard_map(
        batched, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(axis_name), check_vma=False
    )
    return jax.jit(sharded, compiler_options=options)


def ensemble(
    fn: Callable[..., PyTree],
    *args: PyTree,
    in_axes: int | None | Sequence[int | None] = 0,
    mesh: Mesh | None = None,
    batch_size: int | None = None,
) -> PyTree:
    """Run `fn` on every member of an ensemble in one compiled program.

    `fn` is the solve of one member, e.g. `lambda y0, k: diffrax.diffeqsolve(term, solver, ...,
    y0, args=k)`. Every argument with `in_axes` entry `0` is a pytree whose arrays carry the
    ensemble along their leading axis (the same length `B` for all); entries `None` are shared
    by all members. The result is `fn`'s output with a leading axis of length `B`.

    **How members share the hardware** (`batch_size`). By default (`None`) the members are
    vectorised with `jax.vmap` and advance in lockstep: every loop of the solve runs as long
    as its slowest member. With an integer `batch_size = k` the ensemble runs as a compiled
    loop (`jax.lax.map`) over chunks of `k` vmapped members; `k = 1` solves one member after
    another inside one program, which suits solves whose members take very different
    numbers of iterations (the all-parameter network step on a CPU). The benchmarks page
    compares them.

    With a `mesh` (see `ensemble_mesh`) the ensemble is split along the mesh's single axis with
    `jax.shard_map`: each device solves its slice as above, with no communication between
    devices. Members are independent, so the numbers are those of the unsharded run (up to
    rounding in the last bit). If `B` is not a multiple of the number of devices, the ensemble
    is padded with copies of its last member, which are dropped from the result.

    Several processes (hosts, or one process per GPU): call `jax.distributed.initialize()` on
    every process first, build the mesh from `jax.devices()` (all devices of all processes)
    and call `ensemble` with the same global inputs on every process. The result is then a
    global `jax.Array`; each process reads the members on its own devices from
    `result.addressable_shards`, or all of them with `ensemble_gather`. The members are those
    of one process with as many devices.

    The compiled program is cached per `(fn, in_axes, mesh, batch_size)`: pass the same
    function object to reuse it (a new `lambda` on every call compiles again).

    **Arguments:**

    - `fn`: the solve of one member; a function of `len(args)` pytrees.
    - `args`: the arguments, batched along their leading axis where `in_axes` is `0`.
    - `in_axes`: `0` (default: every argument is batched), `None`, or one entry per argument.
    - `mesh`: a one-axis `jax.sharding.Mesh` to split the ensemble over; default: no sharding.
    - `batch_size`: `None` (default: vmap over all members of a device at once) or a positive
      integer (a compiled loop over chunks of that many vmapped members).

    **Returns:**

    `fn`'s output for every member, stacked along a new leading axis.
    """
    if not callable(fn):
        raise TypeError(f"ensemble needs a callable fn, got {type(fn).__name__}")
    in_axes = _normalise_axes(in_axes, len(args))
    size = _batch_size(args, in_axes)
    if mesh is None:
        chunk = _resolve_batch_size(batch_size)
        return _compiled(fn, in_axes, None, _AXIS, chunk)(*args)
    if not isinstance(mesh, Mesh) or len(mesh.axis_names) != 1:
        raise ValueError(
            f"mesh must be a one-axis jax.sharding.Mesh (see ensemble_mesh), got {mesh!r}"
        )
    (axis_name,) = mesh.axis_names
    chunk = _resolve_batch_size(batch_size)
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
    out = _compiled(fn, in_axes, mesh, axis_name, chunk)(*placed)
    if padded == size:
        return out
    return jax.tree_util.tree_map(lambda x: x[:size], out)


def ensemble_gather(result: PyTree) -> PyTree:
    """Every member of an ensemble's result as NumPy arrays, on every process.

    In one process this is `np.asarray` of each leaf. After `jax.distributed.initialize()` the
    result of a sharded `ensemble` spans the devices of all processes, and a process can read
    only its own shards; here the processes exchange them
    (`jax.experimental.multihost_utils.process_allgather`), so every process must call it.

    **Arguments:**

    - `result`: the output of `ensemble` (a pytree of arrays).
    """

    def gather(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            from jax.experimental import multihost_utils

            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree_util.tree_map(gather, result)
