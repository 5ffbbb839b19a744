"""The energy check of a step: a converged step whose energy jumped is a wrong root.

A root finder that converged has found *a* root of the step's equations, not necessarily the
one that continues the motion: at steps near the motion's time scale the equations have other
roots, and a solve seeded far from the right one may end on one of them. Nothing in the
solve's residual tells them apart. The motion's physics does: where the Lagrangian does not
depend on time and no non-conservative force acts, the energy `H(q, p) = p·v − L(q, v)` is
conserved, and a variational step changes it only by its own error, a small fraction of the
energy that moves between the kinetic and the potential parts. A wrong root changes it by
many times that.

The check compares `|H(q₁, p₁) − H(q₀, p₀)|` with the energy's scale at the start of the step,
`|p₀·v₀| + |L(q₀, v₀)|` (twice the kinetic energy plus the size of the Lagrangian: both parts of
the energy, where `|H₀|` alone may be zero), and fails the step
(`RESULTS.vi_step_energy_jump`) where the ratio exceeds `JUMP_TOLERANCE`. Its cost is two
energy evaluations a step (each an evaluation of `L` and its velocity gradient; the kinetic
matrix is formed only where it is not known when the step is traced).

Whether the check applies is decided when the step is traced, from the program of the term
(dead-code elimination, as `_kinetic_structure.kinetic_structure`): a `LagrangianTerm` whose
Lagrangian and holonomic constraints do not read the time, without a non-conservative force
(whose work would have to be accounted for). Elsewhere the step is not checked. A start whose
energy cannot be evaluated (a singular kinetic matrix) passes.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._kinetic_structure import kinetic_structure, used_inputs
from .._linalg import regular_inverse
from .._results import JUMP_TOLERANCE
from .._terms import LagrangianTerm

__all__ = ["JUMP_TOLERANCE", "applies", "energy_and_scale", "relative_jump"]



def applies(term, t, q: Array, args) -> bool:
    """Whether the energy of `term` is conserved, read from its program when the step is
    traced: a `LagrangianTerm` without a non-conservative force whose Lagrangian (and
    constraint, if any) does not read the time."""
    if not isinstance(term, LagrangianTerm) or term.nonconservative_force is not None:
        return False
    dynamic, static = eqx.partition((term, args), eqx.is_array)
    t = jnp.asarray(t)

    def lagrangian(t, q, dynamic):
        term_, args_ = eqx.combine(dynamic, static)
        return term_(t, q, jnp.zeros_like(q), args_) + term_(t, q, jnp.ones_like(q), args_)

    def constraint(t, q, dynamic):
        term_, args_ = eqx.combine(dynamic, static)
        return term_.constraint_values(t, q, args_)

    structure = kinetic_structure(term, t, q, args)
    if (structure is not None and structure.mass is not None
            and regular_inverse(structure.mass, q.dtype) is None):
        return False  # a degenerate Lagrangian: no velocity map, no energy of (q, p)
    try:
        if used_inputs(lagrangian, t, q, dynamic)[0]:
            return False
        if term.has_constraints and used_inputs(constraint, t, q, dynamic)[0]:
            return False
    except Exception:  # a program that cannot be traced apart: no check, never a false alarm
        return False
    return True


def energy_and_scale(term: LagrangianTerm, t, q: Array, p: Array, args) -> tuple[Array, Array]:
    """`(H, S)`: the energy `p·v − L(q, v)` of `(q, p)` and its scale `|p·v| + |L(q, v)|`."""
    structure = kinetic_structure(term, t, q, args)
    mass = None if structure is None or not structure.mass_constant else structure.mass
    v = term.legendre_inverse(t, q, p, args, mass=mass, in_step=True)
    pv = jnp.sum(p * v)
    lagrangian = term(t, q, v, args)
    return pv - lagrangian, jnp.abs(pv) + jnp.abs(lagrangian)


def relative_jump(term: LagrangianTerm, t, q0, p0, q1, p1, args) -> Array:
    """`|H(q₁, p₁) − H(q₀, p₀)| / S(q₀, p₀)` of one step (0 where the start's energy is not
    finite: a singular kinetic matrix, which the check cannot judge)."""
    # Both ends in one batched evaluation: the same kernels as one (their count, not their
    # size, is what a small step pays for on the CPU).
    energies, scales = jax.vmap(lambda q, p: energy_and_scale(term, t, q, p, args))(
        jnp.stack([q0, q1]), jnp.stack([p0, p1]))
    e0, e1, scale = energies[0], energies[1], scales[0]
    jump = jnp.abs(e1 - e0) / scale
    # A non-finite end energy with a finite start is a jump (inf); a non-finite start, none.
    judged = jnp.isfinite(e0) & jnp.isfinite(scale) & (scale > 0)
    inf, zero = jnp.full_like(jump, jnp.inf), jnp.zeros_like(jump)
    return jnp.where(judged, jnp.where(jnp.isnan(jump), inf, jump), zero).astype(q0.dtype)
