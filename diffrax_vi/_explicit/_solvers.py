"""The explicit solvers: Störmer-Verlet, its symmetric compositions, Blanes-Moan's RKN
splittings. One base class does the diffrax side (state, error estimate, dense output,
failures); each method only names its splitting."""

from __future__ import annotations

from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from .._precision import as_dtype, compensated_add
from .._results import STEP_FAILURES
from .._terms import LagrangianTerm, unwrap_term
from ._coefficients import composition_gammas, composition_schemes, rkn_coefficients
from ._splitting import (
    KickModel,
    Splitting,
    composition_splitting,
    kick_drift_splitting,
    run_splitting,
)
from ._structure import force_reads_velocity, kinetics

__all__ = ["AbstractSplittingSolver", "StormerVerlet", "Composition", "BlanesMoan",
           "SplittingState"]


class SplittingState(eqx.Module):
    """What an explicit solver carries from step to step.

    - `force`: the total force at the state (the last kick's, reused by the next step's first
      kick where no jump intervened);
    - `compensation`: the roundings `(e_q, e_p)` of the compensated sums of the state.
    """

    force: Array
    compensation: tuple[Array, Array]


class AbstractSplittingSolver(diffrax.AbstractAdaptiveSolver):
    """The diffrax side of the explicit solvers on a `LagrangianTerm`.

    A step runs the method's kick-drift splitting (`_splitting`) from the state `(q, p)`. The
    error estimate is step doubling: the step is also taken as two half steps, and
    `(y_h − y_{h/2,h/2}) 2^p / (2^p − 1)` estimates the local error of `y_h`, the state
    returned (so a step is the same step with any controller). Under constant steps nothing
    reads the estimate and XLA removes it from the program.

    Adaptive steps make any of these methods non-symplectic: the step size is a function of
    the state, so the map from one step to the next is no longer a symplectic map and the
    bounded energy error of long runs is lost. Use constant steps for long integrations.
    """

    compensated: eqx.AbstractVar[bool]
    kick_iterations: eqx.AbstractVar[int]
    constraint_iterations: eqx.AbstractVar[int]

    term_structure: ClassVar = LagrangianTerm
    interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation

    # Per method -------------------------------------------------------------------------
    def _splitting(self) -> Splitting:
        raise NotImplementedError

    def _constrained_gammas(self) -> tuple[float, ...]:
        """The fractions of the RATTLE sub-steps for a constrained term."""
        raise NotImplementedError

    def _check_force(self, reads_velocity: bool) -> None:
        """Refuse a force the method cannot take (`BlanesMoan`: one reading the velocity)."""

    def order(self, terms) -> int:
        raise NotImplementedError

    def error_order(self, terms) -> int:
        return self.order(terms) + 1

    @property
    def _name(self) -> str:
        return type(self).__name__

    # diffrax ----------------------------------------------------------------------------
    def _model(self, term, t, q: Array, args):
        """The kinetics of `term` (refusing a non-separable one by this solver's name) and
        the kick model."""
        if not isinstance(term, LagrangianTerm):
            raise TypeError(f"{self._name} needs a diffrax_vi.LagrangianTerm, got "
                            f"{type(term).__name__}")
        if q.ndim != 1:
            raise ValueError(f"{self._name} needs coordinates q of shape (D,), got {q.shape}")
        kin = kinetics(self._name, term, t, q, args)
        reads = force_reads_velocity(term, t, q, args)
        self._check_force(reads)

        def force(t, q, p):
            v = kin.velocity(p)
            zero = jnp.zeros_like(q)
            f = jax.grad(term.__call__, argnums=1)(t, q, zero, args)
            if term.nonconservative_force is not None:
                f = f + term.external_force(t, q, v, args)
            return f.astype(q.dtype)

        return kin, KickModel(kin.velocity, force, reads, self.kick_iterations)

    def init(self, terms, t0, t1, y0, args) -> SplittingState:
        term, direction = unwrap_term(terms)
        q0, p0 = term.check_state(y0)
        t = jnp.asarray(direction * t0, q0.dtype)
        _, model = self._model(term, t, q0, args)
        force = jnp.zeros_like(p0) if term.has_constraints else model.force(t, q0, p0)
        return SplittingState(force, (jnp.zeros_like(q0), jnp.zeros_like(p0)))

    def _check_direction(self, terms, t0, t1):
        """Inside `diffeqsolve` steps always go forward in the normalised time. A bare term
        (stepping by hand) with `t1 < t0` is a step of the wrong sign: refused."""
        if not isinstance(terms, LagrangianTerm):
            return t1
        message = (
            f"{self._name}: a step must go forward from t0 to t1 (t1 >= t0); it was given a "
            "step of negative length. To integrate backwards in time, call "
            "diffrax.diffeqsolve with t1 < t0 and a negative dt0 (diffrax then steps forward "
            "in reversed time)."
        )
        try:
            negative = bool(t1 < t0)
        except jax.errors.ConcretizationTypeError:
            return eqx.error_if(t1, t1 < t0, message)
        if negative:
            raise ValueError(message)
        return t1

    def step(self, terms, t0, t1, y0, args, solver_state: SplittingState, made_jump):
        t1 = self._check_direction(terms, t0, t1)
        term, direction = unwrap_term(terms)
        q0, p0 = term.check_state(y0)
        dtype = q0.dtype
        t_real = direction * t0
        h_real = direction * (t1 - t0)
        t = jnp.asarray(t_real, dtype)
        kin, model = self._model(term, t, q0, args)
        if term.has_constraints:
            return self._constrained_step(term, kin, t_real, h_real, q0, p0, args, solver_state)
        if made_jump is False:
            g0 = solver_state.force
        else:
            g0 = jax.lax.cond(made_jump, lambda: model.force(t, q0, p0),
                              lambda: solver_state.force)
        splitting = self._splitting()
        dq, dp, g1, ok = run_splitting(splitting, model, t_real, h_real, q0, p0, g0)
        # Step doubling: two half steps from the same start.
        half = 0.5 * h_real
        dq_a, dp_a, g_a, ok_a = run_splitting(splitting, model, t_real, half, q0, p0, g0)
        dq_b, dp_b, _, ok_b = run_splitting(splitting, model, t_real + half, half, q0 + dq_a,
                                            p0 + dp_a, g_a)
        doubled = (dq_a + dq_b, dp_a + dp_b)
        (q1, p1), compensation = self._add(q0, p0, dq, dp, solver_state.compensation)
        h = jnp.asarray(h_real, dtype)
        k0 = (h * kin.velocity(p0), h * g0)
        k1 = (h * kin.velocity(p1), h * g1)
        return self._finish(y0, (q1, p1), (dq, dp), doubled, ok, ok_a & ok_b, k0, k1,
                            SplittingState(g1, compensation),
                            STEP_FAILURES["vi_step_max_iterations"])

    def _add(self, q0, p0, dq, dp, compensation):
        """`((q1, p1), compensation)`: the state plus the step's increments, compensated
        where `self.compensated`."""
        if not self.compensated:
            return (q0 + dq, p0 + dp), compensation
        (q1, eq), (p1, ep) = (compensated_add(x, d, e)
                              for x, d, e in zip((q0, p0), (dq, dp), compensation, strict=True))
        return (q1, p1), (eq, ep)

    def _finish(self, y0, y1, single, doubled, ok, ok_doubled, k0, k1, state, failure):
        """The step's 5-tuple: the error estimate from the doubled step, the failure where a
        solve inside the step failed or the end state is not finite."""
        q1, p1 = y1
        dtype = q1.dtype
        p = self.error_order(None) - 1
        factor = as_dtype(2.0**p / (2.0**p - 1.0), dtype)
        finite = jnp.all(jnp.isfinite(q1)) & jnp.all(jnp.isfinite(p1))
        good = ok & ok_doubled & finite
        y_error = tuple(jnp.where(good, factor * (a - b), jnp.inf).astype(dtype)
                        for a, b in zip(single, doubled, strict=True))
        result = diffrax.RESULTS.where(ok, diffrax.RESULTS.successful, failure)
        result = diffrax.RESULTS.where(finite | ~ok, result, STEP_FAILURES["vi_step_nonfinite"])
        y1 = tuple(jnp.where(ok, a, jnp.nan).astype(dtype) for a in y1)
        dense_info = dict(y0=tuple(y0), y1=y1, k0=k0, k1=k1)
        return y1, y_error, dense_info, state, result

    def _constrained_step(self, term, kin, t_real, h_real, q0, p0, args, state):
        """A composition of RATTLE steps (`diffrax_vi._explicit._rattle`) for a term with
        holonomic constraints."""
        gammas = self._constrained_gammas()
        try:
            from ._rattle import rattle_step
        except ImportError as error:
            raise ValueError(f"{self._name} cannot yet take a term with holonomic "
                             "constraints (RATTLE is not available); integrate it with "
                             "diffrax_vi.CGVI") from error
        dtype = q0.dtype
        minv = kin.minv

        def run(t_start, h, q, p):
            ok, tau = jnp.asarray(True), 0.0
            for gamma in gammas:
                t_stage = jnp.asarray(t_start + tau * h, dtype)
                step = as_dtype(gamma, dtype) * jnp.asarray(h, dtype)
                q, p, ok_stage = rattle_step(term, t_stage, step, q, p, args, minv,
                                             self.constraint_iterations, offset=kin.offset)
                ok, tau = ok & ok_stage, tau + gamma
            return q, p, ok

        q1s, p1s, ok = run(t_real, h_real, q0, p0)
        half = 0.5 * h_real
        qa, pa, ok_a = run(t_real, half, q0, p0)
        qb, pb, ok_b = run(t_real + half, half, qa, pa)
        single, doubled = (q1s - q0, p1s - p0), (qb - q0, pb - p0)
        (q1, p1), compensation = self._add(q0, p0, *single, state.compensation)
        h = jnp.asarray(h_real, dtype)
        dp = p1 - p0
        k0, k1 = (h * kin.velocity(p0), dp), (h * kin.velocity(p1), dp)
        return self._finish((q0, p0), (q1, p1), single, doubled, ok, ok_a & ok_b, k0, k1,
                            SplittingState(state.force, compensation),
                            STEP_FAILURES["vi_constraint_unmet"])

    def func(self, terms, t0, y0, args) -> PyTree:
        return terms.vf(t0, y0, args)


class StormerVerlet(AbstractSplittingSolver):
    """Störmer-Verlet (velocity Verlet, leapfrog) in kick-drift-kick form, for a separable
    `LagrangianTerm` `L = ½ vᵀ M v − U(t, q)` with a constant kinetic matrix `M`.

    Explicit, symplectic, symmetric, second order, one force evaluation per step (the last
    kick's force is the next step's first). A non-conservative force enters the kicks; where
    it reads the velocity the second half kick is implicit in `p` (a few Newton iterations on
    `D` unknowns), which keeps the step symmetric and second order. A term with holonomic
    constraints is stepped by RATTLE. The error estimate (step doubling) lets
    `diffrax.PIDController` choose steps, at the price of symplecticity (see
    `AbstractSplittingSolver`).

    **Arguments:**

    - `compensated`: add each step's increments to the state by compensated summation
      (rounding errors of long runs then grow like a random walk of the increments' roundings
      rather than of the state's). Default `True`.
    - `kick_iterations`: Newton iterations of an implicit kick (only for a force that reads
      the velocity). Default 4.
    - `constraint_iterations`: Newton iterations of RATTLE's position-level solve (only for a
      constrained term). Default 20.
    """

    compensated: bool = eqx.field(static=True, default=True)
    kick_iterations: int = eqx.field(static=True, default=4)
    constraint_iterations: int = eqx.field(static=True, default=20)

    def order(self, terms) -> int:
        return 2

    def _splitting(self) -> Splitting:
        return composition_splitting((1.0,))

    def _constrained_gammas(self) -> tuple[float, ...]:
        return (1.0,)

    def __check_init__(self):
        _check_options(self)


def _check_options(solver) -> None:
    name = type(solver).__name__
    for field in ("kick_iterations", "constraint_iterations"):
        value = getattr(solver, field)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name}: {field} must be a positive int, got {value!r}")
    if not isinstance(solver.compensated, bool):
        raise ValueError(f"{name}: compensated must be True or False, got "
                         f"{solver.compensated!r}")


class Composition(AbstractSplittingSolver):
    """A symmetric composition of Störmer-Verlet of order 4, 6 or 8, for a separable
    `LagrangianTerm` `L = ½ vᵀ M v − U(t, q)` with a constant kinetic matrix `M`.

    The step is `Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}` with Störmer-Verlet `Φ`; the half kicks of
    neighbouring sub-steps merge, so a step costs `s` force evaluations. Being a composition of
    a symmetric step with symmetric fractions, it is explicit, symplectic and time-reversible.
    Its order holds for any force that enters the kicks, velocity-dependent non-conservative
    forces included (the base step stays symmetric, see `StormerVerlet`), and for a term with
    holonomic constraints, whose sub-steps are RATTLE steps.

    Schemes (`diffrax_vi._explicit._coefficients.composition_gammas`):

    - `"triple_jump"`: the recursive triple jump of Creutz and Gocksch, Suzuki and Yoshida
      (1989-1990), `3^{p/2−1}` sub-steps, some of them negative and long;
    - `"suzuki"`: Suzuki's recursive five-fold fractal (1990), `5^{p/2−1}` sub-steps with
      smaller error constants (orders 4 and 6);
    - `"yoshida"`: Yoshida's seven-stage solution A of "Construction of higher order
      symplectic integrators" (1990), order 6;
    - `"kahan_li"`: Kahan and Li's optimised nine-stage (order 6) and seventeen-stage (order 8)
      sets (1997).

    **Arguments:**

    - `order`: 4, 6 or 8.
    - `scheme`: the name of the set of fractions; default `"suzuki"` at order 4,
      `"kahan_li"` at orders 6 and 8.
    - `compensated`, `kick_iterations`, `constraint_iterations`: as for `StormerVerlet`.
    """

    composition_order: int = eqx.field(static=True)
    scheme: str = eqx.field(static=True)
    compensated: bool = eqx.field(static=True)
    kick_iterations: int = eqx.field(static=True)
    constraint_iterations: int = eqx.field(static=True)

    def __init__(self, order: int = 4, scheme: str | None = None, *, compensated: bool = True,
                 kick_iterations: int = 4, constraint_iterations: int = 20):
        if isinstance(order, bool) or order not in (4, 6, 8):
            raise ValueError(f"Composition: order must be 4, 6 or 8, got {order!r} (order 2 is "
                             "StormerVerlet())")
        if scheme is None:
            scheme = "suzuki" if order == 4 else "kahan_li"
        if scheme not in composition_schemes(order):
            raise ValueError(f"Composition: no scheme {scheme!r} of order {order}; the schemes "
                             f"of order {order} are {list(composition_schemes(order))}")
        self.composition_order = order
        self.scheme = scheme
        self.compensated = compensated
        self.kick_iterations = kick_iterations
        self.constraint_iterations = constraint_iterations
        _check_options(self)

    def order(self, terms) -> int:
        return self.composition_order

    @property
    def gammas(self) -> tuple[float, ...]:
        """The fractions `γ_i` of the sub-steps."""
        return composition_gammas(self.composition_order, self.scheme)

    def _splitting(self) -> Splitting:
        return composition_splitting(self.gammas)

    def _constrained_gammas(self) -> tuple[float, ...]:
        return self.gammas


class BlanesMoan(AbstractSplittingSolver):
    """Blanes and Moan's symmetric Runge-Kutta-Nyström splittings of order 4 and 6 (2002),
    for a separable `LagrangianTerm` `L = ½ vᵀ M v − U(t, q)` with a constant kinetic matrix.

    A kick-drift sequence with its own coefficients (six drifts at order 4, eleven at order 6,
    as many force evaluations per step), optimised for `q̈ = g(t, q)`: such systems satisfy
    `[B, [B, [B, A]]] = 0` for the kick `B` and the drift `A`, which removes order conditions,
    and the error constants are far smaller than those of compositions of the same order.
    Explicit, symplectic, time-reversible. A non-conservative force that depends on the
    position and time only keeps the order (the system is still `q̈ = g(t, q)`); one that
    reads the velocity does not fit the method and is refused, as are holonomic constraints
    (use `Composition`, which takes both).

    **Arguments:**

    - `order`: 4 or 6.
    - `compensated`: as for `StormerVerlet`.
    """

    rkn_order: int = eqx.field(static=True)
    compensated: bool = eqx.field(static=True)
    kick_iterations: int = eqx.field(static=True)
    constraint_iterations: int = eqx.field(static=True)

    def __init__(self, order: int = 6, *, compensated: bool = True):
        if isinstance(order, bool) or order not in (4, 6):
            raise ValueError(f"BlanesMoan: order must be 4 or 6, got {order!r}")
        self.rkn_order = order
        self.compensated = compensated
        self.kick_iterations = 1
        self.constraint_iterations = 1
        _check_options(self)

    def order(self, terms) -> int:
        return self.rkn_order

    def _splitting(self) -> Splitting:
        return kick_drift_splitting(*rkn_coefficients(self.rkn_order))

    def _check_force(self, reads_velocity: bool) -> None:
        if reads_velocity:
            raise ValueError(
                "BlanesMoan: the term's non-conservative force reads the velocity, and an RKN "
                "splitting reaches its order only for forces of the position and time; use "
                f"diffrax_vi.Composition(order={self.rkn_order}), whose kicks take it"
            )

    def _constrained_gammas(self) -> tuple[float, ...]:
        raise ValueError(
            "BlanesMoan cannot take a term with holonomic constraints (an RKN splitting has no "
            f"RATTLE form); use diffrax_vi.Composition(order={self.rkn_order}) or "
            "StormerVerlet(), which step constrained terms by RATTLE"
        )
