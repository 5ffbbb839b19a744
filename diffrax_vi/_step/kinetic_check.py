"""A start the variational step cannot solve: coordinates the equations of motion do not see.

A variational step determines the motion of every coordinate from the momentum `ϑ = ∂L/∂v`
and the force `f = ∂L/∂q` along a trial curve. Where the kinetic matrix `M = ∂ϑ/∂v` is
singular, the coordinates of its null space have no inertia; a first-order Lagrangian (linear
in the velocities, `M = 0`) still fixes their motion through how `ϑ` and `f` depend on them,
and so does a purely algebraic dependence. But a direction `k` of the null space that none of
`∂ϑ/∂q`, `∂f/∂v` and `∂f/∂q` sees either is free: any motion along it satisfies the step's
equations, the step's Jacobian is singular, and the root finder ends in NaN. Such a start is
refused by name here, before the first step (diffrax's explicit solvers, which need the
inverse Legendre map, name it too).

The check costs nothing where the kinetic matrix is known when the solve is traced and is
regular (most mechanical systems), nor where it varies with the state and is regular at a
random state (a double pendulum's): such a matrix is singular at most at special states.
Where it is singular, the constant parts of the linearisation are read then too: if they
settle the question, a blind direction is a `ValueError` naming it; otherwise the rest is
evaluated at the start, `(t0, q0)` and the velocity `M⁺ (p0 − ϑ(t0, q0, 0))`, and a blind
direction is a run-time error with the same diagnosis. Only a `LagrangianTerm` is checked:
not an `IODETerm` (whose maps its author states, degenerate ones on purpose), not a kinetic
matrix whose program reads the velocity (evaluated at a guessed velocity it could make a
false alarm), not a term with holonomic constraints (whose multipliers may fix such
directions).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._precision import lapack_dtype

__all__ = [
    "DEGENERATE_START_MESSAGE", "blind_directions", "kinetic_matrix_regular",
    "refuse_degenerate_start",
]

SINGULAR_AT_START = "degenerate Lagrangian: the kinetic matrix ∂²L/∂v² is singular at the start"
DEGENERATE_START_MESSAGE = (
    f"{SINGULAR_AT_START}, and along "
    "its null space the equations of motion do not see the coordinates at all (neither the "
    "momentum ∂L/∂v nor the force ∂L/∂q depends on their position or velocity there), so no "
    "step can determine their motion. Remove those coordinates from q, or give them a term "
    "of their own (a kinetic energy, a potential, or a first-order coupling)."
)

# The blocks of the linearisation, in the order of `_blocks`' outputs.
NAMES = ("∂ϑ/∂v", "∂ϑ/∂q", "∂f/∂v", "∂f/∂q")


def _tolerance(dtype, size: int) -> float:
    """A singular value below this, relative to its block's norm, is a null direction."""
    return 10.0 * max(size, 1) * float(jnp.finfo(dtype).eps)


def blind_directions(blocks, basis: np.ndarray, tol: float) -> np.ndarray:
    """An orthonormal basis (columns) of the directions in the span of `basis`'s columns that
    every matrix of `blocks` maps to zero, each block relative to its own norm (NumPy)."""
    rows = []
    for block in blocks:
        block = np.asarray(block, np.float64)
        norm = np.linalg.norm(block)
        if norm > 0:
            rows.append(block @ basis / norm)
    if not rows or basis.shape[1] == 0:
        return basis
    _, s, vt = np.linalg.svd(np.concatenate(rows), full_matrices=True)
    s = np.concatenate([s, np.zeros(vt.shape[0] - s.shape[0])])
    return basis @ vt[s <= tol].T


def _blocks(term, static):
    """`(t, q, v, dynamic) ↦ (∂ϑ/∂v, ∂ϑ/∂q, ∂f/∂v, ∂f/∂q)`, the term's arrays and `args` as
    `dynamic`. Each block is its own derivative, so that what each one reads can be told
    apart (one Jacobian of both arguments would read everything for every block)."""

    def blocks(t, q, v, dynamic, which=(0, 1, 2, 3)):
        term_, args_ = eqx.combine(dynamic, static)
        momentum = lambda q_, v_: term_.momentum(t, q_, v_, args_)
        force = lambda q_, v_: term_.force(t, q_, v_, args_)
        maps = ((momentum, 1), (momentum, 0), (force, 1), (force, 0))
        return tuple(jax.jacfwd(maps[i][0], argnums=maps[i][1])(q, v) for i in which)

    return blocks


def _reads(fn, inputs) -> list[tuple[bool, bool, bool]]:
    """For each output of `fn(t, q, v, dynamic)`: whether it reads `q`, whether it reads `v`,
    and whether it reads any input (dead-code elimination of its program: structural, a
    dependence that cancels still counts)."""
    from jax._src.interpreters import partial_eval as pe

    closed = jax.make_jaxpr(fn)(*inputs)
    n_out = len(closed.jaxpr.outvars)
    found = []
    for i in range(n_out):
        _, used = pe.dce_jaxpr(closed.jaxpr, [j == i for j in range(n_out)])
        found.append((bool(used[1]), bool(used[2]), any(used)))
    return found


def _known_mass(ctx):
    """The kinetic matrix as a NumPy array where it is constant and known when traced."""
    from .._kinetic_structure import kinetic_structure

    try:
        structure = kinetic_structure(ctx.term, ctx.t, ctx.q0, ctx.args)
    except Exception:  # no fast answer: the full analysis below decides
        return None
    return None if structure is None else structure.mass


def _generically_regular(blocks, ctx, dynamic, static, tol: float) -> bool:
    """Whether a kinetic matrix that varies with the state is regular at a random state (its
    rank where it is not at a special state: the double pendulum's is regular everywhere).
    Evaluated now, with the term's own parameters where they are known (else `False`)."""
    from .._kinetic_structure import evaluated_now

    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(dynamic)):
        return False
    dtype = ctx.q0.dtype
    rng = np.random.default_rng(0)
    size = ctx.q0.shape[0]
    inputs = (np.asarray(0.375, dtype), rng.normal(size=size).astype(dtype),
              rng.normal(size=size).astype(dtype),
              jax.tree_util.tree_map(np.asarray, dynamic))
    try:
        mass = np.asarray(evaluated_now(_mass_block(blocks), static, inputs), np.float64)
    except Exception:  # a program that cannot run on such a state: checked as before
        return False
    if not np.all(np.isfinite(mass)):
        return False
    return blind_directions([mass], np.eye(size), tol).shape[1] == 0


def kinetic_matrix_regular(ctx) -> bool:
    """Whether the term's kinetic matrix is known, when the step is traced, to be regular at
    a random state: constant and regular, or varying and regular there. Such a matrix
    vanishes nowhere but at special states, so its end states need no first-order
    correction. `False` where this cannot be told now (a constrained term, an `IODETerm`,
    parameters that are traced)."""
    from .._terms import LagrangianTerm

    if not isinstance(ctx.term, LagrangianTerm) or ctx.term.has_constraints:
        return False
    if jnp.ndim(ctx.q0) != 1:
        return False
    size = ctx.q0.shape[0]
    tol = _tolerance(ctx.q0.dtype, size)
    mass = _known_mass(ctx)
    if mass is not None:
        return blind_directions([mass], np.eye(size), tol).shape[1] == 0
    dynamic, static = eqx.partition((ctx.term, ctx.args), eqx.is_array)
    return _generically_regular(_blocks(ctx.term, static), ctx, dynamic, static, tol)


def _mass_block(blocks):
    def mass(t, q, v, dynamic):
        return blocks(t, q, v, dynamic, which=(0,))[0]

    return mass


def _name(direction: np.ndarray) -> str:
    """`q[i]` for an axis, else the combination of coordinates (to three digits)."""
    direction = direction / direction[np.argmax(np.abs(direction))]
    parts = [(i, c) for i, c in enumerate(direction) if abs(c) > 1e-3]
    if len(parts) == 1:
        return f"q[{parts[0][0]}]"
    return "(" + " + ".join(f"{c:.3g}·q[{i}]" for i, c in parts) + ")"


def _refuse_now(directions: np.ndarray) -> None:
    names = ", ".join(_name(directions[:, j]) for j in range(directions.shape[1]))
    raise ValueError(
        f"{SINGULAR_AT_START}, in the direction(s) {names} of "
        "the coordinates, which the equations of motion do not see at all: neither the "
        "momentum ∂L/∂v nor the force ∂L/∂q depends on the position or the velocity along "
        "them, so no step can determine their motion there (the step's Jacobian is singular "
        "and its solve would end in NaN). Remove those coordinates from q, or give them a "
        "term of their own (a kinetic energy, a potential, or a first-order coupling)."
    )


def _start_velocity(ctx, mass: Array) -> Array:
    """`M⁺ (p0 − ϑ(t0, q0, 0))`, the pseudo-inverse by SVD in the working precision."""
    zero = jnp.zeros_like(ctx.q0)
    rhs = ctx.p0 - ctx.term.momentum(ctx.t, ctx.q0, zero, ctx.args)
    work = lapack_dtype(ctx.q0.dtype)
    u, s, vt = jnp.linalg.svd(mass.astype(work))
    cut = jnp.max(s) * _tolerance(work, ctx.q0.shape[0])
    inverse = jnp.where(s > cut, 1 / jnp.where(s > cut, s, 1), 0)
    return (vt.T @ (inverse * (u.T @ rhs.astype(work)))).astype(ctx.q0.dtype)


def _constant_values(blocks, inputs, which: list[int]) -> dict[int, np.ndarray]:
    """The blocks of index `which`, which read no input: their values, computed when traced."""
    if not which:
        return {}
    with jax.ensure_compile_time_eval():
        zeros = jax.tree_util.tree_map(lambda a: np.zeros(a.shape, a.dtype), inputs)
        values = jax.jit(lambda *a: blocks(*a, which=tuple(which)))(*zeros)
    return {i: np.asarray(value, np.float64) for i, value in zip(which, values, strict=True)}


def _blind_at_start(ctx, blocks, dynamic, known: dict, runtime: list[int],
                    candidates: np.ndarray, tol: float) -> Array:
    """Whether, at the start, the blocks of index `runtime` also map some direction in the
    span of `candidates` to zero (each block relative to its norm)."""
    t = jnp.asarray(ctx.t)
    # The kinetic matrix reads no velocity (else nothing is checked): one evaluation serves.
    mass = known.get(0)
    if mass is None:
        mass = blocks(t, ctx.q0, jnp.zeros_like(ctx.q0), dynamic, which=(0,))[0]
    mass = jax.lax.stop_gradient(jnp.asarray(mass, ctx.q0.dtype))
    v0 = _start_velocity(ctx, mass)
    later = tuple(i for i in runtime if i != 0)
    values = dict(zip(later, jax.lax.stop_gradient(blocks(t, ctx.q0, v0, dynamic, which=later)),
                      strict=True))
    values[0] = mass
    work = lapack_dtype(ctx.q0.dtype)
    basis = jnp.asarray(candidates, work)
    rows = []
    for i in runtime:
        block = values[i].astype(work)
        norm = jnp.linalg.norm(block)
        rows.append(block @ basis / jnp.where(norm > 0, norm, 1))
    smallest = jnp.linalg.svd(jnp.concatenate(rows), compute_uv=False)[-1]
    finite = jnp.all(jnp.isfinite(ctx.q0)) & jnp.all(jnp.isfinite(ctx.p0))
    return finite & (smallest <= tol)


def refuse_degenerate_start(ctx):
    """`ctx`, after refusing a start whose singular kinetic matrix leaves coordinates that the
    equations of motion do not see (see the module's docstring).

    Where the answer is known when the solve is traced, a blind direction raises a
    `ValueError` naming it then. Where it needs the start's values, the returned context's
    time `t` carries a run-time error (equinox's `error_if`, with `DEGENERATE_START_MESSAGE`):
    the solver must use that context, and keep its `t` in the state every step reads, for the
    check to stay in the program. Where nothing needs checking, `ctx` itself.

    **Arguments:**

    - `ctx`: the first step's `StepContext` (term, `t0`, `q0`, `p0`, `args`).
    """
    from .._terms import LagrangianTerm

    t = ctx.t
    # An `IODETerm` states its momentum and force maps itself, degenerate ones on purpose.
    if not isinstance(ctx.term, LagrangianTerm) or ctx.term.has_constraints:
        return ctx
    if jnp.ndim(ctx.q0) != 1:
        return ctx
    size = ctx.q0.shape[0]
    tol = _tolerance(ctx.q0.dtype, size)
    mass = _known_mass(ctx)
    if mass is not None and blind_directions([mass], np.eye(size), tol).shape[1] == 0:
        return ctx  # a regular kinetic matrix, known now: nothing to check
    dynamic, static = eqx.partition((ctx.term, ctx.args), eqx.is_array)
    blocks = _blocks(ctx.term, static)
    if mass is None and _generically_regular(blocks, ctx, dynamic, static, tol):
        return ctx  # singular at most at special states: not checked when the solve runs
    inputs = (jnp.asarray(t), ctx.q0, jnp.zeros_like(ctx.q0), dynamic)
    try:
        reads = _reads(blocks, inputs)
    except Exception:  # a term that cannot be traced apart: not checked, never wrong
        return ctx
    if reads[0][1]:  # a kinetic matrix whose program reads the velocity: not checked
        return ctx
    constant = [i for i, r in enumerate(reads) if not r[2]]
    known = _constant_values(blocks, inputs, constant)
    candidates = blind_directions(list(known.values()), np.eye(size), tol)
    if candidates.shape[1] == 0:
        return ctx
    runtime = [i for i in range(len(NAMES)) if i not in known]
    if not runtime:
        _refuse_now(candidates)
    blind = _blind_at_start(ctx, blocks, dynamic, known, runtime, candidates, tol)
    return eqx.tree_at(lambda c: c.t, ctx, eqx.error_if(t, blind, DEGENERATE_START_MESSAGE))
