"""What a Lagrangian's derivatives depend on, read off its program when a step is traced.

The Jacobian-free iteration, the energy check, the degenerate-start check and the explicit
solvers each decide from it, at trace time, what a step needs: whether the kinetic matrix
`∂²L/∂v²` is constant (and its value, where nothing traced enters it), whether the momentum
has an offset that moves, whether the force reads the velocity. The answers come from
dead-code elimination of the term's program, so they are structural, never sampled.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._numpy_eval import Unsupported, evaluate_jaxpr

__all__ = ["KineticStructure", "evaluated_now", "kinetic_structure", "used_inputs"]


class KineticStructure(NamedTuple):
    """What a Lagrangian's derivatives depend on, read off its program (not sampled).

    - `mass_constant`: `∂²L/∂v²` depends on none of `t`, `q`, `v`;
    - `offset_moves`: `∂L/∂v` at `v = 0` depends on `t` or `q` (a magnetic term);
    - `force_reads_velocity`: `∂L/∂q` depends on `v`;
    - `mass`: `∂²L/∂v²` as a NumPy array where it depends on nothing traced at all (neither
      the state nor `args` nor the term's parameters), else `None`.
    """

    mass_constant: bool
    offset_moves: bool
    force_reads_velocity: bool
    mass: np.ndarray | None


def used_inputs(fn, *inputs) -> list[bool]:
    """Which leaves of `inputs` the outputs of `fn(*inputs)` depend on: dead-code elimination
    of its program, so the answer is structural (a dependence that cancels numerically still
    counts)."""
    from jax._src.interpreters import partial_eval as pe

    closed = jax.make_jaxpr(fn)(*inputs)
    _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    return list(used)


def kinetic_structure(term, t, q, args) -> KineticStructure | None:
    """The `KineticStructure` of the Lagrangian of `term` (a `LagrangianTerm`) at the shapes
    and dtypes of `t`, `q` and `args`; `None` where the term is no Lagrangian or its program
    cannot be read."""
    from ._terms import LagrangianTerm

    if not isinstance(term, LagrangianTerm):
        return None
    dynamic, static = eqx.partition((term, args), eqx.is_array)
    # The answer depends on the program and the shapes only (a known mass is one that reads
    # no input at all): kept per term settings and shapes, as a solve asks for it in `init`
    # and in every trace of its step.
    leaves, tree = jax.tree_util.tree_flatten((jnp.asarray(t), q, dynamic))
    try:
        key = (static, tree, tuple((np.shape(a), jnp.result_type(a)) for a in leaves))
        hash(key)
    except TypeError:  # unhashable settings: read afresh
        return _kinetic_structure(t, q, dynamic, static)
    if key not in _STRUCTURES:
        if len(_STRUCTURES) >= 64:
            _STRUCTURES.pop(next(iter(_STRUCTURES)))
        _STRUCTURES[key] = _kinetic_structure(t, q, dynamic, static)
    return _STRUCTURES[key]


_STRUCTURES: dict = {}


def _kinetic_structure(t, q, dynamic, static) -> KineticStructure | None:
    v = jnp.zeros_like(q)

    def lagrangian(t, q, v, dynamic):
        term_, args_ = eqx.combine(dynamic, static)
        return term_(t, q, v, args_)

    def mass(t, q, v, dynamic):
        return jax.hessian(lagrangian, argnums=2)(t, q, v, dynamic)

    def offset(t, q, v, dynamic):
        return jax.grad(lagrangian, argnums=2)(t, q, jnp.zeros_like(v), dynamic)

    def force(t, q, v, dynamic):
        return jax.grad(lagrangian, argnums=1)(t, q, v, dynamic)

    try:
        inputs = (jnp.asarray(t), q, v, dynamic)
        used_mass = used_inputs(mass, *inputs)
        used_offset = used_inputs(offset, *inputs)
        used_force = used_inputs(force, *inputs)
    except Exception:  # a program that cannot be traced apart: no fast path, never wrong
        return None
    mass_constant = not any(used_mass[:3])
    known = None
    if mass_constant and not any(used_mass):
        zeros = jax.tree_util.tree_map(
            lambda a: np.zeros(np.shape(a), a.dtype), (jnp.asarray(t), q, v, dynamic)
        )
        known = np.asarray(evaluated_now(mass, static, zeros), np.float64)
    return KineticStructure(
        mass_constant=mass_constant,
        offset_moves=bool(used_offset[0] or used_offset[1]),
        force_reads_velocity=bool(used_force[2]),
        mass=known,
    )


def evaluated_now(fn, static, inputs):
    """`fn(*inputs)` for NumPy `inputs`, computed now even while a solve is being traced: its
    jaxpr evaluated in NumPy where its primitives allow (`_numpy_eval`: no program compiled),
    else as one program compiled ahead of time (a compiled executable runs on its arguments;
    a call of `jax.jit` would be staged into the trace, and eager evaluation would compile
    every operation on its own). Either is kept per program (`fn`'s code), term settings
    `static` (where hashable) and input shapes."""
    shapes = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), inputs)
    leaves, tree = jax.tree_util.tree_flatten(shapes)
    try:
        key = (fn.__code__, static, tree, tuple(leaves))
        program = _PROGRAMS.get(key)
    except TypeError:  # a term with unhashable settings: read for this call
        key, program = None, None
    if program is None:
        program = _NowProgram(fn, shapes)
        if key is not None:
            if len(_PROGRAMS) >= 64:
                _PROGRAMS.pop(next(iter(_PROGRAMS)))
            _PROGRAMS[key] = program
    return program(inputs)


class _NowProgram:
    """`fn` at inputs of the given shapes: in NumPy, or compiled once NumPy cannot."""

    def __init__(self, fn, shapes):
        self.fn, self.shapes = fn, shapes
        self.jaxpr, out_shapes = jax.make_jaxpr(fn, return_shape=True)(*shapes)
        self.out_tree = jax.tree_util.tree_structure(out_shapes)
        self.compiled = None

    def __call__(self, inputs):
        if self.compiled is None:
            try:
                flat = evaluate_jaxpr(self.jaxpr, *jax.tree_util.tree_leaves(inputs))
                return jax.tree_util.tree_unflatten(self.out_tree, flat)
            except Unsupported:
                self.compiled = jax.jit(self.fn).lower(*self.shapes).compile()
        return self.compiled(*inputs)


_PROGRAMS: dict = {}
