"""What an explicit splitting needs to know about a term, decided when the step is traced.

A kick-drift splitting is explicit when the Hamiltonian separates as `T(p) + U(t, q)`: the
drift `q̇ = ∂T/∂p` then moves only `q` and the kick `ṗ = −∂U/∂q` only `p`. For a Lagrangian this
is `L = ½ vᵀ M v + aᵀ v − U(t, q)` with a constant kinetic matrix `M` and a constant offset `a`
(so `p = M v + a`, `v = M⁻¹ (p − a)`), and a force `∂L/∂q` that does not read the velocity.
The program of the Lagrangian decides it (`_kinetic_structure.kinetic_structure`), not a
sample of its values. A non-conservative force may read the velocity: the kicks then solve for it.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._kinetic_structure import kinetic_structure
from .._precision import as_dtype, lapack_dtype

__all__ = ["Kinetics", "kinetics", "force_reads_velocity"]


class Kinetics(NamedTuple):
    """The kinetic part of a separable Lagrangian at one step.

    - `minv`: `M⁻¹` in the working dtype, or `None` for the identity (no product at all);
    - `offset`: the constant momentum offset `a = ∂L/∂v (v = 0)`.
    """

    minv: Array | None
    offset: Array

    def velocity(self, p: Array) -> Array:
        """`v = M⁻¹ (p − a)`."""
        w = p - self.offset
        # Elementwise, not a dot: a library call in the step would keep XLA's CPU backend from
        # compiling the whole solve loop as one (see `diffrax_vi._linalg.elimination_solve`).
        return w if self.minv is None else jnp.sum(self.minv * w[None, :], axis=1)


def _refuse(solver: str, why: str) -> ValueError:
    return ValueError(
        f"{solver} needs a separable Lagrangian L = ½ vᵀMv − U(t, q) (a constant kinetic "
        f"matrix M, no coupling of q and v): {why}. Integrate it with a variational solver "
        "such as diffrax_vi.CGVI, which takes any regular Lagrangian."
    )


def kinetics(solver: str, term, t, q: Array, args) -> Kinetics:
    """The `Kinetics` of `term` at `(t, q)`, or a `ValueError` naming `solver` where the
    Lagrangian is not separable (the structure is read when the step is traced)."""
    structure = kinetic_structure(term, t, q, args)
    if structure is None:
        raise _refuse(solver, "its program cannot be read apart to check this")
    if not structure.mass_constant:
        raise _refuse(solver, "its kinetic matrix ∂²L/∂v² depends on the state or the time")
    if structure.offset_moves:
        raise _refuse(solver, "its momentum offset ∂L/∂v at v = 0 depends on q or t (a "
                      "magnetic or gyroscopic term)")
    if structure.force_reads_velocity:
        raise _refuse(solver, "its force ∂L/∂q depends on the velocity")
    dtype = q.dtype
    zero = jnp.zeros_like(q)
    offset = jax.grad(term.__call__, argnums=2)(t, q, zero, args).astype(dtype)
    if structure.mass is not None:
        mass = np.asarray(structure.mass, np.float64)
        if mass.shape != (q.size, q.size):
            raise _refuse(solver, f"its coordinates are not a vector (shape {q.shape})")
        if not np.all(np.isfinite(mass)) or np.linalg.cond(mass) > 1 / np.finfo(dtype).eps:
            raise _refuse(solver, "its kinetic matrix is singular (a degenerate Lagrangian)")
        if np.array_equal(mass, np.eye(q.size)):
            return Kinetics(None, offset)
        return Kinetics(as_dtype(np.linalg.inv(mass), dtype), offset)
    # Constant in the state, but read from `args` or the term's parameters: inverted per step.
    mass = jax.hessian(term.__call__, argnums=2)(t, q, zero, args)
    wide = lapack_dtype(dtype)
    minv = jnp.linalg.inv(mass.astype(wide)).astype(dtype)
    return Kinetics(minv, offset)


def force_reads_velocity(term, t, q: Array, args) -> bool:
    """Whether the term's non-conservative force reads the velocity, from its program
    (dead-code elimination: a dependence that cancels numerically still counts)."""
    if getattr(term, "nonconservative_force", None) is None:
        return False
    from jax._src.interpreters import partial_eval as pe

    dynamic, static = eqx.partition(args, eqx.is_array)

    def force(t, q, v, dynamic):
        return term.external_force(t, q, v, eqx.combine(dynamic, static))

    closed = jax.make_jaxpr(force)(jnp.asarray(t), q, jnp.zeros_like(q), dynamic)
    _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    return bool(used[2])
