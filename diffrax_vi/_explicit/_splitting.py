"""One step of a kick-drift splitting `K(b_m) D(a_m) … K(b_1) D(a_1) K(b_0)`.

A drift `D(a)` moves `q ← q + a h M⁻¹ (p − a₀)` and the time `t ← t + a h`; a kick `K(b)` moves
`p ← p + b h F(t, q, v)`, with `F = ∂L/∂q + F_ext` the total force. Every method of the package
is such a sequence (`Splitting`): a symmetric composition of Störmer-Verlet merges the half
kicks of neighbouring sub-steps, a Runge-Kutta-Nyström splitting lists its own coefficients.

The positions and momenta are accumulated as increments from the step's start, so that the
step's total change can be added to the state by compensated summation. The force at the
step's end is returned for the next step's first kick (first same as last).

A non-conservative force that reads the velocity makes a kick implicit in `p`. Each kick of a
symmetric composition is then the explicit half of its sub-step followed by the implicit half
of the previous one (explicit Euler and its adjoint, implicit Euler, at the same position):
the base step stays symmetric, so its compositions keep their order.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._linalg import elimination_solve
from .._precision import as_dtype, eps

__all__ = ["Splitting", "composition_splitting", "kick_drift_splitting", "KickModel",
           "run_splitting", "UNROLL_LIMIT"]

# Splittings with more drifts than this run their stages in a `lax.scan` (one traced stage)
# rather than unrolled: compile time stays bounded for Suzuki's 125-stage eighth order.
UNROLL_LIMIT = 40


class Splitting(NamedTuple):
    """The coefficients of a kick-drift splitting, fractions of the step `h` (NumPy float64).

    - `drifts` (`m`): `a_1 … a_m`, summing to one;
    - `implicit` (`m + 1`): the part of each kick taken implicitly (implicit Euler in `p`)
      where the force reads the velocity; `explicit` (`m + 1`): the part taken explicitly.
      Where the force does not read the velocity each kick is one explicit kick of weight
      `implicit + explicit`.
    """

    drifts: np.ndarray
    implicit: np.ndarray
    explicit: np.ndarray

    @property
    def kicks(self) -> np.ndarray:
        return self.implicit + self.explicit

    @property
    def times(self) -> np.ndarray:
        """The fraction of the step reached after each drift (the last is one)."""
        return np.cumsum(self.drifts)


def composition_splitting(gammas) -> Splitting:
    """The splitting of the composition `Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}` of Störmer-Verlet
    (kick-drift-kick): kick `j` is the last half kick of sub-step `j` (implicit part) and the
    first half kick of sub-step `j + 1` (explicit part)."""
    g = np.asarray(gammas, np.float64)
    zero = np.zeros(1)
    return Splitting(drifts=g, implicit=np.concatenate([zero, g / 2]),
                     explicit=np.concatenate([g / 2, zero]))


def kick_drift_splitting(kicks, drifts) -> Splitting:
    """A splitting with explicit kicks `b_0 … b_m` and drifts `a_1 … a_m` (an RKN splitting)."""
    b = np.asarray(kicks, np.float64)
    return Splitting(drifts=np.asarray(drifts, np.float64), implicit=np.zeros_like(b),
                     explicit=b)


class KickModel(NamedTuple):
    """The two maps of a separable system at one step.

    - `velocity(p)`: `v = M⁻¹ (p − a₀)`;
    - `force(t, q, p)`: the total force `∂L/∂q + F_ext` at the velocity of `p`;
    - `reads_velocity`: whether `force` depends on `p` (then kicks are implicit);
    - `kick_iterations`: Newton iterations of an implicit kick.
    """

    velocity: Callable[[Array], Array]
    force: Callable[[Array, Array, Array], Array]
    reads_velocity: bool
    kick_iterations: int


def implicit_kick(model: KickModel, t, q, p, guess_force, c) -> tuple[Array, Array, Array]:
    """`(p', F(t, q, p'), ok)` with `p' = p + c F(t, q, p')` (`c` a multiple of `h`), by
    Newton's method from the explicit kick. `ok`: the last correction is at round-off."""

    def residual(x):
        return x - p - c * model.force(t, q, x)

    def newton(x, _):
        r, jac = residual(x), jax.jacfwd(residual)(x)
        dx = elimination_solve(jac, r)
        return x - dx, dx

    x0 = p + c * guess_force
    x, dx = jax.lax.scan(newton, x0, None, length=model.kick_iterations)
    scale = jnp.max(jnp.abs(x)) + jnp.max(jnp.abs(x - p))
    ok = jnp.max(jnp.abs(dx[-1])) <= 64 * eps(p.dtype) * (1 + scale)
    return x, model.force(t, q, x), ok


def _stage(model, t_at, q0, p0, h, has_implicit=None):
    """The body of one stage: kick (implicit part, explicit part), then drift, then the force
    at the new position. `has_implicit`: whether the kick has an implicit part, where known
    when traced (`None`: decided at run time)."""

    def body(carry, coefficients):
        dq, dp, g, ok = carry
        c_impl, c_expl, a, tau_prev, tau = coefficients
        if model.reads_velocity and has_implicit is False:
            dp = dp + (c_expl * h) * g
        elif model.reads_velocity:
            p_new, g_new, ok_kick = implicit_kick(model, t_at(tau_prev), q0 + dq, p0 + dp, g,
                                                  c_impl * h)
            # No implicit part (the first kick): keep the explicit force; the solve is a no-op.
            has_impl = c_impl != 0
            dp = jnp.where(has_impl, p_new - p0, dp)
            g = jnp.where(has_impl, g_new, g)
            ok = ok & (ok_kick | ~has_impl)
            dp = dp + (c_expl * h) * g
        else:
            dp = dp + ((c_impl + c_expl) * h) * g
        dq = dq + (a * h) * model.velocity(p0 + dp)
        g = model.force(t_at(tau), q0 + dq, p0 + dp)
        return (dq, dp, g, ok), None

    return body


def run_splitting(
    splitting: Splitting, model: KickModel, t0, t_dtype_h, q0: Array, p0: Array, g0: Array
) -> tuple[Array, Array, Array, Array]:
    """`(dq, dp, g1, ok)`: the increments of one step of `splitting` from `(t0, q0, p0)` with
    the force `g0` there, the force at the end, and whether every implicit kick converged.

    `t_dtype_h` is the step in the time's dtype (stage times are `t0 + τ h` rounded once to the
    working dtype); the kicks and drifts use `h` in the working dtype."""
    dtype = q0.dtype
    h = jnp.asarray(t_dtype_h, dtype)

    def t_at(tau):
        return jnp.asarray(t0 + tau * t_dtype_h, dtype)

    m = len(splitting.drifts)
    taus = splitting.times
    tau_prev = np.concatenate([[0.0], taus[:-1]])
    table = np.stack([splitting.implicit[:m], splitting.explicit[:m], splitting.drifts,
                      tau_prev, taus], axis=1)
    carry = (jnp.zeros_like(q0), jnp.zeros_like(p0), g0, jnp.asarray(True))
    if m <= UNROLL_LIMIT:
        for row in table:
            # Coefficients as constants of the working dtype (times stay float64 until cast).
            coefficients = tuple(as_dtype(x, dtype) for x in row[:3]) + (row[3], row[4])
            body = _stage(model, t_at, q0, p0, h, has_implicit=bool(row[0] != 0))
            carry, _ = body(carry, coefficients)
    else:
        body = _stage(model, t_at, q0, p0, h)
        columns = tuple(as_dtype(table[:, i], dtype) for i in range(3))
        times = tuple(jnp.asarray(table[:, i], jnp.result_type(t0, float)) for i in (3, 4))
        carry, _ = jax.lax.scan(body, carry, columns + times)
    dq, dp, g, ok = carry
    c_last = as_dtype(splitting.implicit[m], dtype)
    if model.reads_velocity:
        p_new, g, ok_kick = implicit_kick(model, t_at(1.0), q0 + dq, p0 + dp, g, c_last * h)
        dp, ok = p_new - p0, ok & ok_kick
    else:
        dp = dp + (as_dtype(splitting.kicks[m], dtype) * h) * g
    return dq, dp, g, ok
