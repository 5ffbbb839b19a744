"""The constrained step solved by a split iteration, for a Lagrangian whose kinetic matrix is
constant.

For `L = ½ vᵀMv − U(t, q)` (plus any non-conservative force `F(t, q, v)`) the constrained
step's balance equations (`diffrax_vi._step.holonomic`) at the points `j = 1..s` read

    (1/h) Σ_k A_jk M X_k + h b_j f_j − G_jᵀ μ_j + δ_j1 p_n = 0,    g(Q_{k+1}) = 0,

with `X_k = Q_{k+1} − q_n` the curve's increments, `A = (DᵀBD)[:s, 1:]` a constant matrix of the
Lobatto rule, `f_j` the forces (`−∇U + F`) and `G_j = ∂g/∂q` at the points. The node values
are a fixed linear map of the forces and impulses, so the split iteration treats the two
apart, as SHAKE and RATTLE do:

- the forces are those of the last curve (Picard's iteration, as the unconstrained engine
  `_step.jacobian_free` updates its node values; a force that reads the velocity, such as a
  joint damping, enters the same way, evaluated on the last curve),
- the impulses are Newton's: the constraints' derivatives in the impulses through the node
  values, the matrix `S = h [A⁻¹_kj G_{k+1} M⁻¹ G_jᵀ]` of the small blocks `G M⁻¹ Gᵀ`, formed
  and inverted once per step at its start (a chord in the impulses).

One update is `z ← z − P⁻¹ R(z)`, with `R` the step's own residual (so that the fixed point is
its root as rounded in this step) and `P` its Jacobian without the derivatives of the forces
and of the reactions `Gᵀμ` in the node values; it contracts at the rate of order `(hω)²` of the
engine. No Jacobian of the residual is formed. A step on which it does not contract is handed
to the general solve (`holonomic._newton`) from the same start, which costs nothing unless
some member of a batch needs it.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._kinetic_structure import kinetic_structure
from .._linalg import constant_product, unpivoted_inverse, well_conditioned
from .._precision import lapack_dtype
from .._root_finder.jacobian_free import MAX_GROWTH, MAX_UPDATES, NOISE, PREDICT_MARGIN
from .lobatto import lobatto_arrays, lobatto_rule

__all__ = ["ConstantKinetic", "constant_kinetic", "split_solve"]

# The stopping rules share the unconstrained iteration's constants: a predicted remaining
# change below 1/PREDICT_MARGIN of a rounding unit, changes that stop shrinking within NOISE
# rounding units, MAX_GROWTH growing updates above that, at most MAX_UPDATES updates.


class ConstantKinetic(NamedTuple):
    """Products with a constant kinetic matrix `M` and its inverse (on the last axis), and the
    momentum's offset `∂L/∂v` at `v = 0`, for the velocity `v = M⁻¹ (p − offset)`."""

    times_minv: object
    minv: Array
    offset: object

    def velocity(self, t, q, p, args):
        return self.times_minv(p - self.offset(t, q, args))


def constant_kinetic(term, t, q0, args) -> ConstantKinetic | None:
    """The `ConstantKinetic` of `term` where its kinetic matrix `∂²L/∂v²` is constant (read off
    its program when the step is traced, as the engine decides it) and well conditioned; else
    `None` (the general solve)."""
    structure = kinetic_structure(term, t, q0, args)
    if structure is None or not structure.mass_constant:
        return None
    dim = q0.shape[0]
    dtype = q0.dtype

    def offset(t, q, args):
        return jax.grad(term.__call__, argnums=2)(t, q, jnp.zeros_like(q), args)

    if structure.mass is not None:
        if not well_conditioned(structure.mass):
            return None
        if np.array_equal(structure.mass, np.eye(dim)):
            return ConstantKinetic(lambda x: x, jnp.eye(dim, dtype=dtype), offset)
        minv = jnp.asarray(np.linalg.inv(structure.mass), dtype)
    else:  # constant, but set by the term's parameters or `args`: formed once per step
        mass = jax.hessian(term.__call__, argnums=2)(t, q0, jnp.zeros_like(q0), args)
        minv = unpivoted_inverse(mass).astype(dtype)
    # M is symmetric (a Hessian): rows times M⁻¹ on the last axis
    return ConstantKinetic(lambda x: x @ minv, minv, offset)


@functools.cache
def _lobatto_blocks(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """`(A, A⁻¹)` (float64, `s × s`): `A = (DᵀBD)[:s, 1:]`, the kinetic rows of the balance
    equations at the points `1..s` in the increments at the points `2..s+1`."""
    _, b, d = lobatto_rule(degree)
    a = (d.T @ np.diag(b) @ d)[:degree, 1:]
    return a, np.linalg.inv(a)


class _Carry(NamedTuple):
    increments: Array
    impulses: Array
    stats: Array  # change, rate, fastest, growth, updates, converged, done


_CHANGE, _RATE, _FAST, _GROWTH, _UPDATES, _CONVERGED, _DONE = range(7)


def split_solve(kinetic: ConstantKinetic, degree: int, t, h, q0, args, term, residual,
                start, scale):
    """The step's equations `residual(z) -> (balance, on)` solved by the split iteration from
    `start = (increments, impulses)`: `(z, iterations, converged, finite, last relative
    change)`, as `holonomic._newton` returns them."""
    dtype = q0.dtype
    eps = float(jnp.finfo(dtype).eps)
    tiny = float(jnp.finfo(dtype).tiny)
    work = lapack_dtype(dtype)
    a_np, ainv_np = _lobatto_blocks(degree)
    x0, mu0 = start
    jacobian = jax.vmap(term.constraint_jacobian, in_axes=(0, 0, None))
    tau, _, _ = lobatto_arrays(degree, dtype)
    values = jnp.concatenate([q0[None], q0 + x0])
    g = jacobian(t + tau * h, values, args)  # (s + 1, M, D) at the start's curve
    # S_(k,m),(j,n) = h A⁻¹_kj (G_{k+1} M⁻¹ G_jᵀ)_mn. With T = (A ⊗ I) S / h,
    # S⁻¹ = T⁻¹ (A ⊗ I) / h, and T is nearly block diagonal: T_ij = Σ_k A_ik A⁻¹_kj G_{k+1}
    # M⁻¹ G_jᵀ, where Σ_k A_ik A⁻¹_kj = δ_ij and the G_k differ by O(h) within the step.
    # The update takes its diagonal blocks G_{j+1} M⁻¹ G_jᵀ, one small M × M matrix per
    # point (tridiagonal for a chain), inverted once per step.
    diag = jnp.einsum("jmd,jnd->jmn", g[1:], kinetic.times_minv(g[:-1]))
    diag_inverse = jax.vmap(unpivoted_inverse)(diag.astype(work)).astype(dtype)

    def apply_s_inverse(rhs):
        w = constant_product(a_np, rhs) / h
        return jnp.sum(diag_inverse * w[:, None, :], axis=-1)

    g_on, g_reaction = g[1:], g[:-1]

    def correction(balance, on):
        y = h * constant_product(ainv_np, kinetic.times_minv(balance))  # (s, D)
        rhs = jnp.einsum("kmd,kd->km", g_on, y) - on
        d_mu = apply_s_inverse(rhs)
        reaction = jnp.einsum("jmd,jm->jd", g_reaction, d_mu)
        d_x = h * constant_product(ainv_np, kinetic.times_minv(reaction)) - y
        return d_x, d_mu

    def update(c: _Carry) -> _Carry:
        balance, on = residual((c.increments, c.impulses))
        d_x, d_mu = correction(balance, on)
        x, mu = c.increments + d_x, c.impulses + d_mu
        size_x = jnp.max(jnp.abs(d_x)) / (1 + jnp.max(jnp.abs(x)))
        size_mu = jnp.max(jnp.abs(d_mu)) / (scale + jnp.max(jnp.abs(mu)))
        change = jnp.maximum(size_x, size_mu)
        last = c.stats
        known = jnp.isfinite(last[_CHANGE]) & (last[_CHANGE] > 0)
        rate = change / jnp.where(known, last[_CHANGE], 1)
        worst = jnp.maximum(rate, last[_RATE])
        predicted = known & (worst < 1) & (change * worst <= (1 - worst) * eps / PREDICT_MARGIN)
        # the changes stopped shrinking: at round-off where they are within a few rounding
        # units, or where the updates contracted fast before (the worse of two consecutive
        # rates below 1/4, so that the error left is below the change that stalled): the
        # impulses' rounding is that of `S⁻¹` times the residual's, far above a unit of theirs
        fastest = jnp.minimum(last[_FAST], worst)
        stalled = change >= 0.5 * last[_CHANGE]
        # (the curve's own change at round-off: a slow mode would show there too)
        at_noise = stalled & ((change <= NOISE * eps)
                              | ((size_x <= NOISE * eps) & (last[_FAST] < 0.25)
                                 & (change <= eps ** 0.5)))
        finite = jnp.isfinite(change)
        converged = ((change <= tiny) | predicted | at_noise) & finite
        growing = (change > NOISE * eps) & (change >= last[_CHANGE])
        growth = jnp.where(growing, last[_GROWTH] + 1, 0)
        updates = last[_UPDATES] + 1
        done = converged | ~finite | (growth > MAX_GROWTH) | (updates >= MAX_UPDATES)
        stats = jnp.stack([change, jnp.where(known, rate, jnp.inf),
                           jnp.where(known, fastest, jnp.inf), growth, updates, converged,
                           done]).astype(dtype)
        return _Carry(x, mu, stats)

    stats = np.zeros(7)
    stats[[_CHANGE, _RATE, _FAST]] = np.inf
    end = jax.lax.while_loop(lambda c: c.stats[_DONE] == 0, update,
                             _Carry(x0, mu0, jnp.asarray(stats, dtype)))
    change = end.stats[_CHANGE]
    finite = jnp.isfinite(change)
    return ((end.increments, end.impulses), end.stats[_UPDATES].astype(jnp.int32),
            end.stats[_CONVERGED] != 0, finite, change)
