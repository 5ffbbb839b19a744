"""Terms for Lagrangian mechanics on the state `y = (q, p)`.

A variational solver needs two maps of the problem: the momentum `ϑ(t, q, v) = ∂L/∂v` and the
force `f(t, q, v) = ∂L/∂q`. `LagrangianTerm` derives both from a Lagrangian with `jax.grad`;
`IODETerm` takes them directly, which covers degenerate (first-order) Lagrangians whose Legendre
map cannot be inverted. Both are also ordinary diffrax terms: their `vf` is Hamilton's equations
`(q̇, ṗ) = (v(t, q, p), f(t, q, v))`, so `diffrax.Tsit5()` and friends integrate the same term
for comparison (an `IODETerm` only when it is given a velocity map).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, ArrayLike, PyTree

from ._linalg import elimination_solve, regular_inverse, solve
from ._validation import check_state, check_times

__all__ = ["AbstractMechanicalTerm", "LagrangianTerm", "IODETerm", "unwrap_term"]


class AbstractMechanicalTerm(diffrax.AbstractTerm):
    """A mechanical system in `(q, p)` form described by its momentum and force maps.

    Subclasses provide `momentum_and_force(t, q, v, args) -> (ϑ, f)` and, for use with
    standard diffrax solvers, `velocity(t, q, p, args)` (the inverse Legendre map).
    """

    def momentum_and_force(self, t, q, v, args) -> tuple[Array, Array]:
        raise NotImplementedError

    def momentum(self, t, q, v, args) -> Array:
        """`ϑ(t, q, v) = ∂L/∂v`."""
        return self.momentum_and_force(t, q, v, args)[0]

    def force(self, t, q, v, args) -> Array:
        """`f(t, q, v) = ∂L/∂q`."""
        return self.momentum_and_force(t, q, v, args)[1]

    def velocity(self, t, q, p, args) -> Array:
        """The inverse Legendre map `v(t, q, p)`: the velocity at which `∂L/∂v = p`."""
        raise NotImplementedError

    def energy(self, t, q, p, args) -> Array:
        raise NotImplementedError

    @property
    def has_constraints(self) -> bool:
        """Whether the system has holonomic constraints `g(t, q) = 0` (see `LagrangianTerm`)."""
        return False

    def constraint_values(self, t, q, args) -> Array:
        """`g(t, q)`, the holonomic constraints' values (zero on the constraint)."""
        raise NotImplementedError

    def constraint_jacobian(self, t, q, args) -> Array:
        """`G = ∂g/∂q`, of shape `(M, D)`."""
        return jax.jacfwd(self.constraint_values, argnums=1)(t, q, args)

    def constraint_rate(self, t, q, args) -> Array:
        """`∂g/∂t` (zero for constraints that do not depend on time)."""
        t = jnp.asarray(t, jnp.result_type(q))
        return jax.jacfwd(self.constraint_values, argnums=0)(t, q, args)

    def check_state(self, y: Any) -> tuple[Array, Array]:
        """Return `(q, p)` if `y` is a state this term can integrate, else raise `ValueError`.

        The state is `y = (q, p)`: a tuple of two 1-D real floating arrays of one shape and
        dtype. Only static properties are checked, so it is free under `jit`.
        """
        return check_state(y)

    def state_from_velocity(
        self, t0: ArrayLike, q0: ArrayLike, v0: ArrayLike, args: PyTree = None
    ) -> tuple[Array, Array]:
        """The initial state `(q0, p0)` for positions `q0` and velocities `v0` at time `t0`.

        The state of every solver here is `(q, p)` with the canonical momentum
        `p = ∂L/∂v(t0, q0, v0)`, which differs from the velocity as soon as the kinetic
        energy has a mass matrix or the Lagrangian has terms linear in `v` (a magnetic field).
        This evaluates that momentum, so a problem stated with velocities starts correctly.
        `q0` and `v0` must be 1-D real floating arrays of one shape and dtype.
        """
        check_times(t0=t0)
        q0, v0 = check_state((q0, v0), what="(q0, v0)")
        p0 = jnp.asarray(self.momentum(t0, q0, v0, args))
        return q0, p0.astype(q0.dtype)

    # -- diffrax.AbstractTerm interface: Hamilton's equations ---------------------------------
    def vf(self, t, y, args):
        # diffrax evaluates `vf` on `y0` before any solver sees it: refuse a malformed state
        # here, with the message that names the expected form, not a JAX error further in.
        q, p = self.check_state(y)
        v, f = self.hamilton_vf(t, (q, p), args)
        if self.has_constraints:
            # diffrax evaluates `vf` for its shapes with every solver, so the refusal is at
            # run time (a traced "always true"), where only an explicit solver gets.
            always = jnp.isnan(jnp.sum(p)) | True
            v = eqx.error_if(
                v,
                always,
                "this term has holonomic constraints, which explicit diffrax solvers (Tsit5, "
                "Dopri8, ...) cannot honour: they would drift off g(t, q) = 0. Integrate it "
                "with a variational solver (diffrax_vi.CGVI), or write the system in "
                "coordinates that satisfy the constraints.",
            )
        return v, f

    def hamilton_vf(self, t, y, args):
        """Hamilton's equations `(q̇, ṗ)` of the system without its holonomic constraints."""
        q, p = y
        v = self.velocity(t, q, p, args)
        return v.astype(q.dtype), self.force(t, q, v, args).astype(p.dtype)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return jtu.tree_map(lambda x: (control * x).astype(x.dtype), vf)

    def to_ode(self) -> diffrax.ODETerm:
        """The same Hamiltonian vector field as a plain `diffrax.ODETerm`."""
        return diffrax.ODETerm(self.vf)

    def separable_terms(
        self, y0: tuple[ArrayLike, ArrayLike] | None = None, args: PyTree = None, *, t0=0.0
    ) -> tuple[diffrax.ODETerm, diffrax.ODETerm]:
        """The pair of terms `(dq/dt, dp/dt)` of a separable system, for
        `diffrax.SemiImplicitEuler` (or any solver that takes a pair of terms).

        Only valid when the Lagrangian separates as `L = T(t, v) − V(t, q)` (e.g.
        `T = ½ vᵀMv` with a constant mass matrix `M`), i.e. when the Hamiltonian is
        `K(t, p) + V(t, q)`. Then the velocity does not depend on `q` and the force does not
        depend on `v`, and the pair is

        - `diffrax.ODETerm(lambda t, p, args: velocity(t, 0, p, args))`, the inverse Legendre
          map evaluated at `q = 0` (`M⁻¹p` for a quadratic `T`),
        - `diffrax.ODETerm(lambda t, q, args: force(t, q, 0, args))`, the force `∂L/∂q = −∇V`
          evaluated at `v = 0`.

        For a non-separable system these are silently wrong, so pass a sample state to check:

        **Arguments:**

        - `y0`: optional sample state `(q, p)` (typically the initial condition). When given
          (and concrete, not traced), the mixed derivatives `∂ϑ/∂q = ∂²L/∂v∂q` and
          `∂f/∂v = ∂²L/∂q∂v` are evaluated at `q0` and a generic velocity, and a `ValueError`
          is raised unless both vanish (up to rounding). This is a check at one point, not a
          proof of separability.
        - `args`: the `args` the system will be integrated with (used by the check only).
        - `t0`: the time of the check.

        **Returns:**

        A tuple `(velocity_term, force_term)` of `diffrax.ODETerm`s, for
        `diffeqsolve((velocity_term, force_term), diffrax.SemiImplicitEuler(), ..., y0=(q0, p0))`.
        """
        if y0 is not None:
            _check_separable(self, y0, args, t0)
        return diffrax.ODETerm(_SeparableVelocity(self)), diffrax.ODETerm(_SeparableForce(self))


def _check_scalar(value, what: str, dtype) -> Array:
    if jnp.shape(value) != ():
        raise ValueError(f"{what} must return a scalar; it returned shape {jnp.shape(value)}")
    if jnp.result_type(value) != jnp.dtype(dtype):
        raise ValueError(
            f"{what} returned dtype {jnp.result_type(value)} for {jnp.dtype(dtype)} input; "
            "keep the Lagrangian in the working precision (no float64 constants)"
        )
    return value


def _check_constraint(value, q) -> Array:
    shape, dtype = jnp.shape(value), jnp.result_type(value)
    if len(shape) != 1 or not 1 <= shape[0] < jnp.shape(q)[0]:
        raise ValueError(
            "the constraint must return a 1-D array of M values, 1 <= M < D, for coordinates "
            f"of shape {jnp.shape(q)} (D = {jnp.shape(q)[0]}); it returned shape {shape}"
        )
    if dtype != jnp.result_type(q):
        raise ValueError(
            f"the constraint returned dtype {dtype} for {jnp.result_type(q)} coordinates; keep "
            "it in the working precision (no float64 constants, no integer arrays)"
        )
    return value


def _check_force(value, q) -> Array:
    shape, dtype = jnp.shape(value), jnp.result_type(value)
    if shape != jnp.shape(q):
        raise ValueError(
            f"the force must return an array of the coordinates' shape {jnp.shape(q)}; it "
            f"returned shape {shape}"
        )
    if dtype != jnp.result_type(q):
        raise ValueError(
            f"the force returned dtype {dtype} for {jnp.result_type(q)} coordinates; keep it "
            "in the working precision (no float64 constants, no integer arrays)"
        )
    return value


class LagrangianTerm(AbstractMechanicalTerm):
    """A mechanical system given by its Lagrangian `L(t, q, v, args) -> scalar`.

    The momentum `∂L/∂v`, the force `∂L/∂q` and the energy `H(t, q, p) = p·v − L` come from
    `jax.grad`. For standard (non-variational) diffrax solvers the velocity `v(t, q, p)` is
    obtained by inverting `p = ∂L/∂v` with `legendre_iterations` Newton steps started at
    `v = 0`: one step is exact when `L` is quadratic in `v` (every mechanical Lagrangian
    `½ vᵀM(q)v − V(q)`, also with magnetic terms linear in `v`); a general `L` needs more, or a
    closed-form `velocity`.

    **Arguments:**

    - `lagrangian`: `L(t, q, v, args)`, with `q`, `v` arrays of shape `(D,)`. It may be an
      `equinox.Module` (e.g. a neural Lagrangian), whose array leaves are differentiable.
    - `velocity`: optional closed-form inverse Legendre map `v(t, q, p, args)`.
    - `legendre_iterations`: Newton steps of the numerical inverse (default 1).
    - `force`: optional non-conservative generalised force `F(t, q, v, args) -> (D,)`
      (friction, damping, a drive, a control torque). It enters the discrete action's
      variation as virtual work (the Lagrange–d'Alembert principle): every solver sees the
      force `∂L/∂q + F`, the variational steps through the same quadrature as the action,
      the explicit ones in Hamilton's equations `ṗ = ∂L/∂q + F`. `None` (default): a
      conservative system.
    - `constraint`: optional holonomic constraints `g(t, q, args) -> (M,)`, `1 <= M < D`,
      held at zero: the system moves on `g = 0` (a pendulum in Cartesian coordinates, a
      chain of rigid links). `CGVI` steps it with one multiplier per constraint and node
      (`diffrax_vi._step.holonomic`), keeping `g = 0` and its hidden velocity-level constraint
      `G(q) v + ∂g/∂t = 0` at every step's end; the start must satisfy both. Explicit
      solvers cannot honour constraints and stop with an error at run time. `None`
      (default): free coordinates.
    """

    lagrangian: Callable
    velocity_map: Callable | None = None
    legendre_iterations: int = eqx.field(static=True, default=1)
    nonconservative_force: Callable | None = None
    holonomic_constraint: Callable | None = None

    def __init__(
        self,
        lagrangian: Callable,
        velocity: Callable | None = None,
        *,
        legendre_iterations: int = 1,
        force: Callable | None = None,
        constraint: Callable | None = None,
    ):
        if not callable(lagrangian):
            raise TypeError(f"lagrangian must be callable, got {type(lagrangian).__name__}")
        if velocity is not None and not callable(velocity):
            raise TypeError(f"velocity must be callable or None, got {type(velocity).__name__}")
        if force is not None and not callable(force):
            raise TypeError(f"force must be callable or None, got {type(force).__name__}")
        if constraint is not None and not callable(constraint):
            raise TypeError(
                f"constraint must be callable or None, got {type(constraint).__name__}"
            )
        if not isinstance(legendre_iterations, int) or legendre_iterations < 1:
            raise ValueError(
                f"legendre_iterations must be a positive int, got {legendre_iterations!r}"
            )
        self.lagrangian = lagrangian
        self.velocity_map = velocity
        self.legendre_iterations = legendre_iterations
        self.nonconservative_force = force
        self.holonomic_constraint = constraint

    def __call__(self, t, q, v, args) -> Array:
        """Evaluate `L(t, q, v, args)`, checking that it is a scalar of `q`'s dtype."""
        return _check_scalar(self.lagrangian(t, q, v, args), "the Lagrangian", jnp.result_type(q))

    def momentum_and_force(self, t, q, v, args):
        f, p = jax.grad(self.__call__, argnums=(1, 2))(t, q, v, args)
        if self.nonconservative_force is not None:
            f = f + self.external_force(t, q, v, args)
        return p, f

    def external_force(self, t, q, v, args) -> Array:
        """The non-conservative force `F(t, q, v, args)` (zero without one), checked to be an
        array of `q`'s shape and dtype."""
        if self.nonconservative_force is None:
            return jnp.zeros_like(q)
        return _check_force(self.nonconservative_force(t, q, v, args), q)

    @property
    def has_constraints(self) -> bool:
        return self.holonomic_constraint is not None

    def constraint_values(self, t, q, args) -> Array:
        """`g(t, q, args)`, checked to be a 1-D array of `M < D` values in `q`'s dtype."""
        if self.holonomic_constraint is None:
            raise ValueError("this LagrangianTerm was built without a constraint=g(t, q, args)")
        return _check_constraint(self.holonomic_constraint(t, q, args), q)

    def velocity(self, t, q, p, args):
        """Inverse Legendre map `p ↦ v`: closed form if given, else Newton from `v = 0`."""
        if self.velocity_map is not None:
            return self.velocity_map(t, q, p, args)
        v = self.legendre_inverse(t, q, p, args)
        # A degenerate Lagrangian (∂²L/∂v² singular) has no velocity map: refuse it loudly
        # rather than hand NaN velocities to an explicit solver.
        finite_input = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(p))
        return eqx.error_if(
            v,
            finite_input & ~jnp.all(jnp.isfinite(v)),
            "LagrangianTerm: the Legendre map v -> dL/dv cannot be inverted here (dL^2/dv^2 is "
            "singular: a degenerate Lagrangian). Explicit diffrax solvers need the velocity; "
            "integrate degenerate systems with NetworkVI (e.g. as an IODETerm).",
        )

    def legendre_inverse(self, t, q, p, args, *, mass=None, in_step: bool = False) -> Array:
        """The velocity at which `∂L/∂v = p`, unchecked (NaN where the kinetic matrix is
        singular): the closed form if given; where the caller knows the kinetic matrix to be
        the constant `mass` (NumPy) and it is regular, one Newton update from rest (the
        momentum is affine in `v`: exact); else `legendre_iterations` Newton updates from
        `v = 0`. `in_step` writes the updates out, solved by elimination, for use inside a
        step (a loop or a library call there costs more than the arithmetic)."""
        if self.velocity_map is not None:
            return self.velocity_map(t, q, p, args).astype(q.dtype)

        def momentum(v):
            return jax.grad(self.__call__, argnums=2)(t, q, v, args)

        minv = None if mass is None else regular_inverse(mass, q.dtype)
        if minv is not None:
            w = p - momentum(jnp.zeros_like(q))
            return w if minv is True else jnp.sum(jnp.asarray(minv, q.dtype) * w, axis=1)

        def newton(_, v):
            kinetic = jax.jacfwd(momentum)(v)
            return v - (elimination_solve if in_step else solve)(kinetic, momentum(v) - p)

        v = jnp.zeros_like(q)
        if not in_step:
            return jax.lax.fori_loop(0, self.legendre_iterations, newton, v)
        for i in range(self.legendre_iterations):
            v = newton(i, v)
        return v

    def energy(self, t, q, p, args):
        """`H(t, q, p) = p·v − L(t, q, v)` with `v` from the inverse Legendre map."""
        v = self.velocity(t, q, p, args)
        return jnp.sum(p * v) - self(t, q, v, args)


class IODETerm(AbstractMechanicalTerm):
    """A mechanical system given directly by its momentum and force maps.

    This is the form of the reference's implicit ODEs (IODEs), and it is needed for degenerate
    Lagrangians (linear in the velocities, e.g. the reference's pendulum), for which
    `∂²L/∂v²` is singular and `v(q, p)` does not exist: only the variational solvers, which
    evaluate `ϑ` and `f` along a trial trajectory, can integrate those. A standard diffrax
    solver can use this term only if a `velocity` map `v(t, q, p, args)` is supplied.

    **Arguments:**

    - `momentum`: `ϑ(t, q, v, args) -> (D,)`, the momentum `∂L/∂v`.
    - `force`: `f(t, q, v, args) -> (D,)`, the force `∂L/∂q`.
    - `velocity`: optional `v(t, q, p, args)` (the reference's `v̄`), for standard solvers.
    - `hamiltonian`: optional `H(t, q, p, args)`, returned by `energy`.
    """

    momentum_map: Callable
    force_map: Callable
    velocity_map: Callable | None = None
    hamiltonian: Callable | None = None

    def __init__(
        self,
        momentum: Callable,
        force: Callable,
        velocity: Callable | None = None,
        hamiltonian: Callable | None = None,
    ):
        for name, fn in (("momentum", momentum), ("force", force)):
            if not callable(fn):
                raise TypeError(f"{name} must be callable, got {type(fn).__name__}")
        for name, fn in (("velocity", velocity), ("hamiltonian", hamiltonian)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable or None, got {type(fn).__name__}")
        self.momentum_map = momentum
        self.force_map = force
        self.velocity_map = velocity
        self.hamiltonian = hamiltonian

    def momentum_and_force(self, t, q, v, args):
        p = jnp.asarray(self.momentum_map(t, q, v, args))
        f = jnp.asarray(self.force_map(t, q, v, args))
        for name, x in (("momentum", p), ("force", f)):
            if x.shape != q.shape:
                raise ValueError(f"the {name} map returned shape {x.shape}; expected {q.shape}")
            if x.dtype != q.dtype:
                raise ValueError(
                    f"the {name} map returned dtype {x.dtype} for {q.dtype} input; keep it in "
                    "the working precision"
                )
        return p, f

    def velocity(self, t, q, p, args):
        """The given velocity map `v(t, q, p, args)`; without one, an error at run time (a
        degenerate system has no velocity map: only `NetworkVI` can integrate it)."""
        if self.velocity_map is None:
            # diffeqsolve traces `vf` once for its shapes before any solver runs, so a missing
            # velocity map must not fail at trace time (NetworkVI never evaluates it). The
            # predicate is a traced "always true": a solver that really evaluates the vector
            # field (Tsit5, Dopri8, ...) stops with this error at run time; called eagerly on
            # concrete values, it raises at once.
            always = jnp.isnan(jnp.sum(p)) | True
            return eqx.error_if(
                jnp.full_like(p, jnp.nan),
                always,
                "this IODETerm has no velocity map v(t, q, p, args), so standard diffrax solvers "
                "(Tsit5, Dopri8, ...) cannot integrate it. Degenerate Lagrangians can only be "
                "integrated by the variational solvers (NetworkVI); pass velocity=... to "
                "IODETerm to use a standard solver.",
            )
        return self.velocity_map(t, q, p, args)

    def energy(self, t, q, p, args):
        """`H(t, q, p, args)` from the `hamiltonian` the term was built with."""
        if self.hamiltonian is None:
            raise ValueError("this IODETerm was built without a hamiltonian=H(t, q, p, args)")
        return self.hamiltonian(t, q, p, args)


class _SeparableVelocity(eqx.Module):
    """`(t, p, args) ↦ v(t, 0, p)`: the velocity of a separable system."""

    term: AbstractMechanicalTerm

    def __call__(self, t, p, args):
        p = jnp.asarray(p)
        return self.term.velocity(t, jnp.zeros_like(p), p, args).astype(p.dtype)


class _SeparableForce(eqx.Module):
    """`(t, q, args) ↦ f(t, q, 0)`: the force of a separable system."""

    term: AbstractMechanicalTerm

    def __call__(self, t, q, args):
        q = jnp.asarray(q)
        return self.term.force(t, q, jnp.zeros_like(q), args).astype(q.dtype)


def _check_separable(term: AbstractMechanicalTerm, y0, args, t0) -> None:
    q0, p0 = term.check_state(y0)

    def mixed(t, q, p, args):
        v = term.velocity(t, q, p, args)
        # A generic velocity: ∂²L/∂v∂q = M'(q)·v vanishes at v = 0 even for a q-dependent mass.
        v = v + (0.5 + jnp.arange(v.size, dtype=v.dtype).reshape(v.shape) / (v.size + 1))
        dp_dq = jax.jacfwd(lambda x: term.momentum(t, x, v, args))(q)
        df_dv = jax.jacfwd(lambda x: term.force(t, q, x, args))(v)
        dp_dv = jax.jacfwd(lambda x: term.momentum(t, q, x, args))(v)
        return jnp.max(jnp.abs(dp_dq)), jnp.max(jnp.abs(df_dv)), jnp.max(jnp.abs(dp_dv))

    try:
        values = [float(x) for x in mixed(t0, q0, p0, args)]
    except jax.errors.ConcretizationTypeError:
        return  # traced inputs: nothing to check at trace time
    dp_dq, df_dv, scale = values
    tol = 64 * float(jnp.finfo(jnp.result_type(q0)).eps) * max(1.0, scale)
    if not (dp_dq <= tol and df_dv <= tol):
        raise ValueError(
            "the system is not separable (L = T(v) − V(t, q)), so its velocity and force "
            "cannot be split into the pair of terms of SemiImplicitEuler: at the sample state "
            f"max|∂²L/∂v∂q| = {max(dp_dq, df_dv):.3g} (allowed {tol:.1g}). Integrate the "
            "term itself with a standard solver (Tsit5) or a variational one (NetworkVI)."
        )


def unwrap_term(terms: PyTree[Any]) -> tuple[AbstractMechanicalTerm, ArrayLike]:
    """Return `(term, direction)` from what diffrax hands a solver.

    `diffeqsolve` wraps the user's term as `WrapTerm(term, direction)` to normalise the
    direction of time; a solver that needs the term's own methods unwraps it here and works in
    real time `direction * t`. Manual stepping passes the bare term (direction 1).
    """
    direction = 1
    while not isinstance(terms, AbstractMechanicalTerm):
        inner = getattr(terms, "term", None)
        if inner is None or not hasattr(terms, "direction"):
            raise TypeError(
                "a variational solver needs a LagrangianTerm or IODETerm; got "
                f"{type(terms).__name__}"
            )
        direction = direction * terms.direction
        terms = inner
    return terms, direction
