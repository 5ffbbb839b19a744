"""RATTLE: the symmetric second-order step of a separable Lagrangian on holonomic constraints.

For `L = ½ vᵀMv − U(t, q)` with a constant kinetic matrix `M`, and constraints
`g(t, q) = 0` (`M_c` of them, `G = ∂g/∂q`), one step of length `h` from a state on both the
constraint and its hidden (velocity-level) constraint `G v + ∂g/∂t = 0` is

    p_½ = p + (h/2) f(t, q, v) − G(t, q)ᵀ ν,              q₁ = q + h M⁻¹ p_½,
    p₁  = p_½ + (h/2) f(t + h, q₁, v₁) − G(t + h, q₁)ᵀ μ,

with `f = ∂L/∂q + F` the term's whole force (`F` a non-conservative force), `v = M⁻¹ p`,
`v₁ = M⁻¹ p₁`, and the impulses `ν`, `μ` (the multipliers times `h/2`) fixed by

    g(t + h, q₁) = 0,        G(t + h, q₁) v₁ + ∂g/∂t(t + h, q₁) = 0.

`ν` is found by Newton's iteration on its `M_c` unknowns alone (its matrix is
`h G(q₁) M⁻¹ G(q)ᵀ`), to round-off; `μ` then solves one linear system with the matrix
`G(q₁) M⁻¹ G(q₁)ᵀ`. Where the force reads the velocity (damping), the second kick is
implicit in `p₁`: `p₁` is the fixed point of the kick followed by that projection, found by
iterating it (one force evaluation and one small solve an update; it contracts at the rate
`(h/2) |∂F/∂v M⁻¹|`).

Reading the force at the start's velocity in the first kick and at the end's in the second
makes the step symmetric: the step of `−h` from `(q₁, p₁)` swaps the two kicks and returns
to `(q, p)` (with `ν` and `μ` swapped), so it is time-reversible and of order two, and
compositions of it reach orders four and more. Without a velocity-dependent force it is the
classical RATTLE (Andersen 1983; Leimkuhler and Skeel 1994): the Lobatto IIIA–IIIB pair of
`diffrax_vi._step.holonomic` at `s = 1`, symplectic on the constraint's cotangent bundle, with no
Jacobian of the force and no factorisation larger than `M_c × M_c`.

The derivatives of a step are those of its root (`jax.lax.custom_root`: the implicit function
theorem on the equations above), not those of the iteration that found it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._linalg import solve
from .._precision import lapack_dtype
from ._structure import force_reads_velocity

__all__ = ["rattle_step"]

# The iteration stops once its update is this many ulps of the state's size.
_STOP = 8.0


def _small_solve(matrix: Array, rhs: Array) -> Array:
    """`matrix⁻¹ rhs` (`rhs` a vector or a matrix) by Gauss–Jordan elimination without
    pivoting, unrolled (the size is known when traced), in the dtype of `rhs` (float32 below
    32 bits).

    The step's systems are small (`M_c × M_c`) and their pivots stay away from zero:
    `h G(q₁) M⁻¹ G(q)ᵀ` and `G M⁻¹ Gᵀ` are (near) definite for independent constraints. At
    these sizes a few fused rank-one updates are several times faster than a LAPACK call on
    a CPU. A zero pivot (dependent constraints) gives non-finite values, which the step
    reports as not ok.
    """
    dtype = rhs.dtype
    work = lapack_dtype(dtype)
    n = matrix.shape[0]
    columns = rhs.reshape(n, -1).astype(work)
    a = jnp.concatenate([matrix.astype(work), columns], axis=1)
    others = 1 - jnp.eye(n, dtype=work)
    for k in range(n):
        row = a[k] / a[k, k]
        a = a.at[k].set(row) - jnp.outer(others[k] * a[:, k], row)
    return a[:, n:].reshape(rhs.shape).astype(dtype)


def _iterate(update_of: Callable, start: Array, size_of: Callable, max_iterations,
             noise: float, contraction: bool = False) -> tuple[Array, Array]:
    """`x ← x − update_of(x)` from `start` until an update is at round-off:
    `(x, converged)`.

    An update counts as round-off when its size (`size_of(update)`, relative to the state)
    is a few ulps, or when it stopped halving below `noise` (relative): there a converging
    iteration would have shrunk it, so what is left is rounding. With `contraction` (a
    linearly converging iteration) the state also counts as converged once the error left
    after an update, `size ρ / (1 − ρ)` for the rate `ρ = size / previous` of the last two,
    is a few ulps: this saves the updates that would only confirm it. A non-finite update
    stops the iteration, unconverged; so does the cap `max_iterations`.
    """
    dtype = start.dtype
    eps = float(jnp.finfo(dtype).eps)
    tiny, floor = jnp.asarray(_STOP * eps, dtype), jnp.asarray(noise, dtype)

    def cond(carry):
        _, k, _, _, stopped = carry
        return ~stopped & (k < max_iterations)

    def body(carry):
        x, k, previous, _, _ = carry
        update = update_of(x)
        x = x - update
        size = size_of(update)
        finite = jnp.isfinite(size)
        converged = (size <= tiny) | ((size >= previous / 2) & (size <= floor))
        if contraction:
            left = size * size / (previous - size)  # size ρ / (1 − ρ), ρ = size / previous
            converged = converged | (jnp.isfinite(previous) & (size < previous / 2)
                                     & (left <= tiny))
        converged = converged & finite
        return x, k + 1, size, converged, converged | ~finite

    no = jnp.array(False)
    carry = (start, jnp.array(0, jnp.int32), jnp.asarray(jnp.inf, dtype), no, no)
    x, _, _, converged, _ = jax.lax.while_loop(cond, body, carry)
    return x, converged


def _newton(residual: Callable, start: Array, size_of: Callable, max_iterations
            ) -> tuple[Array, Array]:
    """Newton's iteration on `residual` (`_iterate`). Below `sqrt(eps)` an update that does
    not halve is rounding: Newton's would at least square it."""

    def update_of(x):
        matrix, value = jax.jacfwd(lambda y: (residual(y),) * 2, has_aux=True)(x)
        return _small_solve(matrix, value)

    noise = float(jnp.finfo(start.dtype).eps) ** 0.5
    return _iterate(update_of, start, size_of, max_iterations, noise)


def _tangent_solve(linear: Callable, rhs: Array) -> Array:
    # The linearised equations at the root, formed densely (only where a derivative is taken).
    return solve(jax.jacfwd(linear)(jnp.zeros_like(rhs)), rhs)


def _root(residual: Callable, start: Array, find: Callable) -> tuple[Array, Array]:
    """The root of `residual` found by `find(residual, start) -> (x, converged)`,
    differentiated by the implicit function theorem (the iteration itself is not)."""

    def solve_root(f, guess):
        x, converged = find(f, guess)
        # as a float: custom_root gives its auxiliary output a tangent of its own dtype
        return x, converged.astype(guess.dtype)

    x, converged = jax.lax.custom_root(residual, start, solve_root, _tangent_solve,
                                       has_aux=True)
    return x, jax.lax.stop_gradient(converged) > 0


def _reads_velocity(term, t, q, args) -> bool:
    """Whether the force of `term` may read the velocity: a `LagrangianTerm`'s external
    force, read from its program (`∂L/∂q` does not: the caller has checked it); any other
    term's force may."""
    if not hasattr(term, "nonconservative_force"):
        return True
    return force_reads_velocity(term, t, q, args)


# A fixed-point update within this many ulps that stopped halving is rounding noise.
_NOISE = 64.0


def _second_kick(term, t1, h, q1, p_half, args, velocity, linear, max_iterations,
                 reads_velocity: bool) -> tuple[Array, Array]:
    """`(p₁, settled)`: the second half kick at `q₁` and the impulse `μ` that puts `p₁` on
    the hidden constraint, `μ = (G M⁻¹ Gᵀ)⁻¹ (G M⁻¹ p̂ + ∂g/∂t)` for the kicked momentum
    `p̂`: one linear solve where the force does not read the velocity.

    Where it does, `p₁` is the fixed point of that map with the force read at `M⁻¹ p₁`: it
    contracts at the rate `(h/2) |∂F/∂v M⁻¹|`, small wherever the step resolves the
    force's time scale (as an explicit method needs to be accurate), and each update costs
    one evaluation of the force, no Jacobian. An iteration that does not contract is not
    settled."""
    g1 = term.constraint_jacobian(t1, q1, args)
    rate = term.constraint_rate(t1, q1, args)
    half = h / 2
    schur = g1 @ linear(g1.T)  # G M⁻¹ Gᵀ
    if reads_velocity:  # formed once for all the updates
        inverse = _small_solve(schur, jnp.eye(schur.shape[0], dtype=schur.dtype))
        schur_solve = lambda r: inverse @ r  # noqa: E731
    else:
        schur_solve = lambda r: _small_solve(schur, r)  # noqa: E731

    def project(p1_guess):
        kicked = p_half + half * term.force(t1, q1, velocity(p1_guess), args)
        mu = schur_solve(g1 @ velocity(kicked) + rate)
        return kicked - g1.T @ mu, mu

    if not reads_velocity:
        return project(p_half)[0], jnp.array(True)
    d = q1.shape[0]

    def balance(x):
        p1, mu = x[:d], x[d:]
        v1 = velocity(p1)
        kick = p1 - p_half - half * term.force(t1, q1, v1, args) + g1.T @ mu
        return jnp.concatenate([kick, g1 @ v1 + rate])

    frozen = jax.lax.stop_gradient(p_half)
    scale = 1 + jnp.max(jnp.abs(frozen))
    eps = float(jnp.finfo(q1.dtype).eps)

    def find(_, guess):
        def update_of(x):
            return x - jnp.concatenate(project(x[:d]))

        return _iterate(update_of, guess, lambda u: jnp.max(jnp.abs(u[:d])) / scale,
                        max_iterations, _NOISE * eps, contraction=True)

    start = jnp.concatenate([p_half, jnp.zeros_like(rate)])
    x, settled = _root(balance, start, find)
    return x[:d], settled


def rattle_step(term, t, h, q: Array, p: Array, args, minv: Array | None,
                max_iterations: int, *, offset: Array | None = None
                ) -> tuple[Array, Array, Array]:
    """One RATTLE step of `term` (a separable Lagrangian with holonomic constraints) from
    `(q, p)` at time `t` over `h`: `(q₁, p₁, ok)`.

    The step is the one of this module's docstring. It is symmetric (the step of `−h` from
    `(q₁, p₁)` returns to `(q, p)` to round-off) and of order two; compose it for higher
    orders. The whole step is `jit`-, `vmap`- and `grad`-compatible, and runs in the dtype of
    `q` (tolerances are multiples of that dtype's `eps`).

    **Arguments:**

    - `term`: an `AbstractMechanicalTerm` with constraints (`term.has_constraints`); its
      Lagrangian must be `½ vᵀMv (+ aᵀv) − U(t, q)` with a constant `M`: the step trusts the
      caller's `minv` and does not check this.
    - `t`, `h`: the step's start time and length (negative to step backwards).
    - `q`, `p`: the start state, on the constraint `g(t, q) = 0` and on its hidden constraint
      `G(t, q) v + ∂g/∂t = 0`.
    - `args`: the term's `args`.
    - `minv`: `M⁻¹` as a `(D, D)` array in `q`'s dtype, or `None` for the identity.
    - `max_iterations`: the cap on the updates of each iteration of the step (an
      `int`, or an integer array: it may be traced).
    - `offset`: the constant momentum offset `a = ∂L/∂v` at `v = 0` (`p = Mv + a`); `None`
      for zero.

    **Returns:** `q₁`, `p₁` and `ok`, a scalar boolean array: `True` where the start was on
    both constraint levels (within `sqrt(eps)` of the state's size, as
    `_step.holonomic` asks) and every iteration of the step converged to round-off, with a
    finite end state. `False` where the constraint could not be reached (a step too long for
    the constraint manifold, an iteration cap too small), or the start is off it.
    """
    dtype = q.dtype
    h = jnp.asarray(h, dtype)
    t1 = t + h
    eps = float(jnp.finfo(dtype).eps)
    a = jnp.zeros_like(p) if offset is None else offset

    def linear(x):
        return x if minv is None else minv @ x

    def velocity(x):
        return linear(x - a)

    v0 = velocity(p)
    g0 = term.constraint_jacobian(t, q, args)
    kicked = p + (h / 2) * term.force(t, q, v0, args)

    def on_constraint(nu):
        return term.constraint_values(t1, q + h * velocity(kicked - g0.T @ nu), args)

    frozen = jax.lax.stop_gradient((q, v0, g0, h))
    q_scale = 1 + jnp.max(jnp.abs(frozen[0]))

    def moved(nu_update):  # how far an update of ν moves q₁, relative to q
        return jnp.max(jnp.abs(frozen[3] * linear(frozen[2].T @ nu_update))) / q_scale

    nu, found = _root(on_constraint, jnp.zeros(g0.shape[0], dtype),
                      lambda f, guess: _newton(f, guess, moved, max_iterations))
    p_half = kicked - g0.T @ nu
    q1 = q + h * velocity(p_half)
    p1, settled = _second_kick(term, t1, h, q1, p_half, args, velocity, linear,
                               max_iterations, _reads_velocity(term, t, q, args))

    start = jax.lax.stop_gradient(jnp.stack([
        jnp.max(jnp.abs(term.constraint_values(t, q, args))),
        jnp.max(jnp.abs(g0 @ v0 + term.constraint_rate(t, q, args))),
    ]))
    tolerance = eps ** 0.5 * jnp.stack([q_scale, 1 + jnp.max(jnp.abs(frozen[1]))])
    finite = jnp.all(jnp.isfinite(q1)) & jnp.all(jnp.isfinite(p1))
    ok = found & settled & finite & jnp.all(start <= tolerance)
    return q1.astype(dtype), p1.astype(dtype), ok
