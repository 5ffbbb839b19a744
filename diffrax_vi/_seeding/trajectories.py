"""Initial trajectories: a cheap estimate of the step's motion that the network is fitted to.

Each strategy returns "labels" — positions at the uniform grid `τ_i = i/N`, `i = 0..N` — and
an estimate of the end momentum `p_{n+1}`. All of them start at the step's own time `t_n` (the
reference starts its sub-integration at `t = 0`, which is wrong for time-dependent
Lagrangians).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._linalg import solve
from .._terms import AbstractMechanicalTerm

__all__ = [
    "AbstractInitialTrajectory",
    "HermiteExtrapolation",
    "StepHistory",
    "IntegratorExtrapolation",
    "NoExtrapolation",
    "PreviousStep",
    "implicit_midpoint",
    "labels_curve",
]


class StepHistory(eqx.Module):
    """The previous step, as the solver carries it: its start time `t`, length `h`, and
    position, velocity, momentum and force at its start (`q0, v0, p0, f0`) and velocity and
    force at its end (`v1, f1`; its end position and momentum are the current state).
    Velocities are those of the converged curve. `valid` is false before the first step and
    after a jump."""

    valid: Array
    t: Array
    h: Array
    q0: Array
    v0: Array
    p0: Array
    f0: Array
    v1: Array
    f1: Array

    @classmethod
    def empty(cls, q: Array, t: Array) -> StepHistory:
        z = jnp.zeros_like(q)
        return cls(jnp.array(False), t, jnp.ones_like(t), z, z, z, z, z, z)


class AbstractInitialTrajectory(eqx.Module):
    """A way to estimate the motion over one step, sampled on `N + 1` uniform points.

    Subclasses have an attribute `substeps` (`N`, even).
    """

    def __check_init__(self):
        n = self.substeps
        if not isinstance(n, int) or isinstance(n, bool) or n < 2 or n % 2:
            raise ValueError(
                f"substeps must be an even integer >= 2 (the seed fit uses Simpson weights on "
                f"the sub-step grid); got {n!r}"
            )

    def with_substeps(self, substeps: int) -> AbstractInitialTrajectory:
        """This estimate on `substeps` sub-steps (the reference's `extrapolation_substep`);
        an estimate that continues another replaces the other's."""
        return dataclasses.replace(self, substeps=substeps)

    def labels(
        self,
        term: AbstractMechanicalTerm,
        t,
        h,
        q0: Array,
        p0: Array,
        args,
        history: StepHistory | None = None,
    ) -> tuple[Array, Array]:
        """Positions `(N + 1, D)` on `τ_i = i/N` and an estimate of `p_{n+1}`."""
        raise NotImplementedError


def implicit_midpoint(
    term: AbstractMechanicalTerm, t, h, q0: Array, p0: Array, args, substeps: int, iterations: int
) -> tuple[Array, Array]:
    """The variational midpoint rule over `[t, t + h]` in `substeps` equal sub-steps.

    Per sub-step of length `δ` it solves `ϑ(t̃, Q, V) − p_k − (δ/2) f(t̃, Q, V) = 0` for the
    midpoint velocity `V` (with `Q = q_k + (δ/2) V`, `t̃ = s_k + δ/2`) by a fixed number of
    Newton iterations, then `q_{k+1} = q_k + δV`, `p_{k+1} = p_k + δ f`. Only `ϑ` and `f` are
    used, so degenerate systems work too. Returns all positions `(substeps + 1, D)` and the
    final momentum.
    """
    dtype = q0.dtype
    delta = (jnp.asarray(h, dtype) / substeps).astype(dtype)
    half = (delta / 2).astype(dtype)

    def substep(carry, k):
        q, p, v = carry
        tm = t + (k * delta + half).astype(dtype)

        def equation(vel):
            pm, fm = term.momentum_and_force(tm, q + half * vel, vel, args)
            return pm - p - half * fm

        def newton(_, vel):
            r, jac = equation(vel), jax.jacfwd(equation)(vel)
            return vel - solve(jac, r)

        v = jax.lax.fori_loop(0, iterations, newton, v)
        _, fm = term.momentum_and_force(tm, q + half * v, v, args)
        q1 = q + delta * v
        p1 = p + delta * fm
        return (q1, p1, v), q1

    steps = jnp.arange(substeps, dtype=dtype)
    (_, p_end, _), qs = jax.lax.scan(substep, (q0, p0, jnp.zeros_like(q0)), steps)
    return jnp.concatenate([q0[None], qs], axis=0), p_end


def labels_curve(labels: Array):
    """`τ ↦` the labels' piecewise-linear curve (`labels`: `(N + 1, D)` on the uniform grid
    `τ_i = i/N`), with the values and slopes of `jnp.interp` on that grid, bit for bit.

    The interval comes from the grid's own arithmetic (`⌊τN⌋`, moved by one where rounding
    put it off), not from a binary search: a step's compiled program then holds a few
    gathers where `jnp.interp` compiles a search loop per coordinate and per use."""
    m = labels.shape[0]
    if m < 2:
        raise ValueError(f"labels_curve needs at least two labels, got {m}")
    grid = jnp.arange(m, dtype=labels.dtype) / (m - 1)

    def curve(tau: Array) -> Array:
        tau = jnp.asarray(tau, labels.dtype)
        guess = jnp.clip(jnp.floor(tau * (m - 1)).astype(jnp.int32), 0, m - 1)
        above = jnp.minimum(guess + 1, m - 1)
        # the number of grid points at or before τ (`searchsorted(grid, τ, side="right")`)
        count = guess + (grid[guess] <= tau) + ((guess + 1 < m) & (grid[above] <= tau))
        i = jnp.clip(count, 1, m - 1)
        start, end = labels[i - 1], labels[i]
        value = start + ((tau - grid[i - 1]) / (grid[i] - grid[i - 1])) * (end - start)
        value = jnp.where(tau < grid[0], labels[0], value)
        return jnp.where(tau > grid[-1], labels[-1], value)

    return curve


class IntegratorExtrapolation(AbstractInitialTrajectory):
    """Integrate the step with the variational midpoint rule on `substeps` sub-steps.

    The reference's default. The positions of the sub-steps are the labels; the final
    momentum seeds `p_{n+1}`.

    **Arguments:**

    - `substeps`: number of sub-steps `N` (even; the seed fit uses Simpson weights). Default 10.
    - `newton_iterations`: fixed Newton iterations per sub-step for the midpoint velocity.
    """

    substeps: int = eqx.field(static=True, default=10)
    newton_iterations: int = eqx.field(static=True, default=4)

    def labels(self, term, t, h, q0, p0, args, history=None):
        del history
        return implicit_midpoint(term, t, h, q0, p0, args, self.substeps, self.newton_iterations)


class NoExtrapolation(AbstractInitialTrajectory):
    """A motionless trajectory: every label is `q_n` and `p_{n+1}` is seeded with `p_n`.

    **Arguments:**

    - `substeps`: size of the (constant) label grid, even. Default 10.
    """

    substeps: int = eqx.field(static=True, default=10)

    def labels(self, term, t, h, q0, p0, args, history=None):
        del term, t, h, args, history
        return jnp.broadcast_to(q0, (self.substeps + 1,) + q0.shape), p0


class PreviousStep(AbstractInitialTrajectory):
    """Warm start: continue the previous step's converged network past its end.

    After each step the solver keeps the converged parameters; the next step starts from
    them advanced by one step (`σ(wτ + b) ↦ σ(w(1 + ρτ) + b)`, i.e. `b ← b + w`, `w ← ρw`, with
    `ρ` the ratio of step sizes) and `p_{n+1}` seeded by the momentum of the continued curve at
    its end — no trajectory and no fit. A cheap acceptance test guards it: if the residual of
    the variational equations at the warm start exceeds `tolerance·scale` (`scale = 1 +
    max(|q_n|, |p_n|)`), the step is seeded by `first` instead, as are the first step and a
    step after `made_jump`. If the solve from an accepted warm start fails, it restarts once
    from `first`'s seed (with `LevenbergMarquardt` or `RegularisedNewton`).

    **Arguments:**

    - `first`: the strategy for the first step and the fallback. Default
      `IntegratorExtrapolation()`.
    - `tolerance`: acceptance bound on `max|F|` of the warm start, relative to `scale`;
      `None` means `sqrt(eps)` of the working dtype.
    """

    first: AbstractInitialTrajectory = IntegratorExtrapolation()
    tolerance: float | None = eqx.field(static=True, default=None)

    @property
    def substeps(self) -> int:
        return self.first.substeps

    def __check_init__(self):
        if isinstance(self.first, PreviousStep):
            raise ValueError("PreviousStep(first=...) needs a strategy that works without history")

    def with_substeps(self, substeps: int) -> AbstractInitialTrajectory:
        return dataclasses.replace(self, first=self.first.with_substeps(substeps))

    def accept_tolerance(self, dtype) -> float:
        if self.tolerance is not None:
            return self.tolerance
        return float(jnp.finfo(dtype).eps) ** 0.5

    def labels(self, term, t, h, q0, p0, args, history=None):
        return self.first.labels(term, t, h, q0, p0, args, history)


def hermite_cubic(y0: Array, dy0: Array, y1: Array, dy1: Array, h_prev, s: Array) -> Array:
    """The cubic through `(0, y0)` and `(1, y1)` with slopes `h_prev·dy0`, `h_prev·dy1` (time
    derivatives rescaled to the normalised time `σ`), evaluated at `σ = s` (shape `(M,)`);
    returns `(M, D)`."""
    a1 = h_prev * dy0
    a2 = 3 * (y1 - y0) - h_prev * (2 * dy0 + dy1)
    a3 = 2 * (y0 - y1) + h_prev * (dy0 + dy1)
    s = s[:, None]
    return y0 + s * (a1 + s * (a2 + s * a3))


class HermiteExtrapolation(AbstractInitialTrajectory):
    """Extrapolate the previous step: cubic Hermite interpolation in time.

    Positions come from the cubic through `(t_{n−1}, q_{n−1}, q̇_{n−1})` and
    `(t_n, q_n, q̇_n)` (velocities of the previous step's converged curve at its two ends),
    evaluated at `t_n + τ_i h`; the end momentum likewise from `(p, ṗ = f)` at the same two
    times, evaluated at `t_n + h`. No sub-integration, so it is the cheapest trajectory;
    it is accurate when the step size is small against the time scale of the motion. The first
    step (and the step after a jump) has no history and uses `first`.

    **Arguments:**

    - `substeps`: size `N` of the label grid (even). Default 10.
    - `first`: the strategy without history, on the same label grid (`substeps`; another
      grid is refused). Default `IntegratorExtrapolation(substeps)`.
    """

    substeps: int = eqx.field(static=True, default=10)
    first: AbstractInitialTrajectory | None = None

    def __check_init__(self):
        super().__check_init__()
        if isinstance(self.first, HermiteExtrapolation | PreviousStep):
            raise ValueError("HermiteExtrapolation(first=...) needs a strategy without history")
        if self.first is not None and self.first.substeps != self.substeps:
            raise ValueError(
                f"HermiteExtrapolation(substeps={self.substeps}) needs a first strategy on the "
                f"same label grid; got {self.first!r} with substeps={self.first.substeps}"
            )

    def with_substeps(self, substeps: int) -> AbstractInitialTrajectory:
        first = None if self.first is None else self.first.with_substeps(substeps)
        return dataclasses.replace(self, substeps=substeps, first=first)

    def _first(self) -> AbstractInitialTrajectory:
        return self.first if self.first is not None else IntegratorExtrapolation(self.substeps)

    def labels(self, term, t, h, q0, p0, args, history=None):
        first = self._first()
        if history is None:
            return first.labels(term, t, h, q0, p0, args)
        dtype = q0.dtype
        ratio = (h / history.h).astype(dtype)
        grid = jnp.arange(self.substeps + 1, dtype=dtype) / self.substeps

        def extrapolate():
            v1, f1 = history.v1, history.f1
            qs = hermite_cubic(history.q0, history.v0, q0, v1, history.h, 1 + ratio * grid)
            s_end = jnp.reshape(1 + ratio, (1,))
            p_end = hermite_cubic(history.p0, history.f0, p0, f1, history.h, s_end)[0]
            # Label 0 is q_n itself (the cubic reproduces it up to rounding).
            qs = qs.at[0].set(q0)
            return qs.astype(dtype), p_end.astype(p0.dtype)

        def fallback():  # on the same label grid: `__check_init__` sees to it
            return first.labels(term, t, h, q0, p0, args)

        return jax.lax.cond(history.valid, extrapolate, fallback)
