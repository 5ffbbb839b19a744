"""The `Problem` record shared by the reference problems, and helpers to build them.

A problem bundles a mechanical term (`LagrangianTerm` or `IODETerm`), an initial state
`y0 = (q0, p0)` in a chosen floating dtype, a default time span and step, an energy function for
drift measurements and a float64 reference solution (closed form where one exists, otherwise a
stored extended-precision solution or a tight scipy DOP853 integration of Hamilton's equations).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._terms import AbstractMechanicalTerm

__all__ = ["Problem", "ReferenceFlow", "ClosedFormFlow", "DOP853Flow"]


# Tolerances of every numerical reference solution (see the reference notes, §1).
REFERENCE_RTOL = 1e-13
REFERENCE_ATOL = 1e-15


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A test problem for the mechanical solvers.

    The reference flow is handed the time elapsed since `t0`. For an autonomous problem that is
    all it depends on; a problem whose Lagrangian depends on `t` explicitly (e.g.
    `modulated_oscillator`) builds its flow for its own `t0`, so shifting the start changes
    the reference (its stored data then no longer applies and scipy takes over).

    **Fields:**

    - `name`: a short identifier, e.g. `"harmonic_oscillator"`.
    - `term`: the `LagrangianTerm` or `IODETerm` to integrate; pass it to `diffrax.diffeqsolve`.
    - `y0`: the initial state `(q0, p0)`, two arrays of shape `(D,)` in the problem's dtype.
    - `t0`, `t1`: the default time span (python floats).
    - `dt`: the default step size (python float).
    - `args`: the `args` to hand to `diffeqsolve` and to the term's maps. The physical
      parameters are baked into the term as python floats (so they adopt the dtype of the state),
      hence this is `None` for the built-in problems.
    - `params`: the physical parameters, a mapping from name to python float, for reports.
    - `hamiltonian`: optional `H(t, q, p, args)`; `energy` uses it, else the term's own energy.
    - `reference_flow`: the exact (or DOP853) flow of the nominal float64 problem: a callable
      taking elapsed times `ts - t0` (float64 array of shape `(N,)`) and returning `(q, p)`, two
      float64 numpy arrays of shape `(N, D)` (a time-dependent problem's flow knows its `t0`).
      Use `reference` rather than calling it directly.
    - `reference_method`: `"closed form"` or `"DOP853"`, how the reference is obtained (or
      `"stored"` for a tabulated high-accuracy solution, see `problems.stored`).
    - `invariants`: optional conserved quantities, a mapping from name to `I(t, q, p, args)`
      (same signature as `hamiltonian`; the value may be a scalar or an array, e.g. an
      angular-momentum vector). Empty for problems that only conserve their energy. Adiabatic
      invariants (only approximately conserved) are listed too where a problem says so in its
      docstring, e.g. the oscillatory energy of `fermi_pasta_ulam`.
    """

    name: str
    term: AbstractMechanicalTerm
    y0: tuple[Array, Array]
    t0: float
    t1: float
    dt: float
    args: Any = None
    params: Mapping[str, float] = dataclasses.field(default_factory=dict)
    hamiltonian: Callable | None = None
    reference_flow: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    reference_method: str = "closed form"
    invariants: Mapping[str, Callable] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if not (isinstance(self.y0, tuple) and len(self.y0) == 2):
            raise ValueError("y0 must be a pair (q0, p0)")
        q0, p0 = self.y0
        if jnp.shape(q0) != jnp.shape(p0) or jnp.ndim(q0) != 1:
            raise ValueError(
                f"q0 and p0 must be 1-D arrays of equal shape; got {jnp.shape(q0)} and "
                f"{jnp.shape(p0)}"
            )
        _check_span(self.t0, self.t1, self.dt)

    # -- conveniences --------------------------------------------------------------------------
    @property
    def dtype(self) -> np.dtype:
        """The floating dtype of the initial state."""
        return jnp.result_type(self.y0[0])

    @property
    def dim(self) -> int:
        """The number of degrees of freedom `D` (components of `q`)."""
        return int(jnp.shape(self.y0[0])[0])

    @property
    def n_steps(self) -> int:
        """The number of steps of size `dt` in `[t0, t1]`; an error if `dt` does not divide it."""
        ratio = (self.t1 - self.t0) / self.dt
        n = round(ratio)
        if n < 1 or abs(ratio - n) > 1e-9 * max(1.0, abs(ratio)):
            raise ValueError(
                f"dt = {self.dt} does not divide the span ({self.t0}, {self.t1}) into whole steps"
            )
        return n

    @property
    def ts(self) -> np.ndarray:
        """The float64 step grid `t0, t0 + dt, ..., t1` (`n_steps + 1` points)."""
        n = self.n_steps
        grid = self.t0 + self.dt * np.arange(n + 1, dtype=np.float64)
        grid[-1] = self.t1
        return grid

    def with_span(
        self, t1: float | None = None, *, dt: float | None = None, n_steps: int | None = None
    ) -> Problem:
        """A copy with a new end time and/or step size (the start `t0` and `y0` are kept).

        **Arguments:**

        - `t1`: the new end time (default: unchanged, or `t0 + n_steps * dt` if `n_steps` is
          given).
        - `dt`: the new step size (default: unchanged).
        - `n_steps`: alternatively to `t1`, the number of steps of size `dt`; the span becomes
          `(t0, t0 + n_steps * dt)`, as in the reference benchmark's `(0, 10 dt)` horizons.
        """
        new_dt = self.dt if dt is None else float(dt)
        if n_steps is not None:
            if t1 is not None:
                raise ValueError("give either t1 or n_steps, not both")
            if not isinstance(n_steps, int) or n_steps < 1:
                raise ValueError(f"n_steps must be a positive int, got {n_steps!r}")
            new_t1 = self.t0 + n_steps * new_dt
        else:
            new_t1 = self.t1 if t1 is None else float(t1)
        return dataclasses.replace(self, t1=new_t1, dt=new_dt)

    # -- diagnostics ---------------------------------------------------------------------------
    def energy(self, t: ArrayLike, q: Array, p: Array) -> Array:
        """The energy `H(t, q, p)` of one state (`q`, `p` of shape `(D,)`).

        Traceable and vmappable; it keeps the dtype of `q` and `p`.
        """
        if self.hamiltonian is not None:
            return self.hamiltonian(t, q, p, self.args)
        return self.term.energy(t, q, p, self.args)

    def reference(self, ts: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The reference solution at times `ts`, as float64 numpy arrays of shape `(len(ts), D)`.

        It solves the nominal problem (parameters and initial data as float64 numbers), so a
        low-precision run differs from it at least by the rounding of its initial data. Numerical
        references are computed once per set of times and memoised.
        """
        if self.reference_flow is None:
            raise ValueError(f"the problem {self.name!r} has no reference solution")
        ts = np.atleast_1d(np.asarray(ts, dtype=np.float64))
        if ts.ndim != 1:
            raise ValueError(f"ts must be a scalar or a 1-D array; got shape {ts.shape}")
        q, p = self.reference_flow(ts - self.t0)
        return q.copy(), p.copy()

    def __repr__(self) -> str:
        return (
            f"Problem(name={self.name!r}, dim={self.dim}, dtype={self.dtype}, "
            f"span=({self.t0}, {self.t1}), dt={self.dt}, reference={self.reference_method!r})"
        )


def _check_span(t0: float, t1: float, dt: float) -> None:
    for name, x in (("t0", t0), ("t1", t1), ("dt", dt)):
        if not isinstance(x, int | float) or not math.isfinite(x):
            raise ValueError(f"{name} must be a finite python number, got {x!r}")
    if not t1 > t0:
        raise ValueError(f"the span must run forwards (t1 > t0); got ({t0}, {t1})")
    if dt <= 0:
        raise ValueError(f"dt must be positive, got {dt}")


# -- dtypes and initial data --------------------------------------------------------------------
def resolve_dtype(dtype: Any) -> np.dtype:
    """Validate a floating dtype (`None` means JAX's default float)."""
    if dtype is None:
        return jnp.dtype(jnp.result_type(float))
    dtype = jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"dtype must be a floating dtype, got {dtype}")
    if dtype == jnp.float64 and not jax.config.jax_enable_x64:
        raise ValueError(
            "dtype=float64 needs 64-bit JAX: call jax.config.update('jax_enable_x64', True) "
            "before building the problem"
        )
    return dtype


def as_vector(x: ArrayLike | Sequence[float], size: int | None, what: str) -> np.ndarray:
    """`x` as a float64 numpy vector (a scalar becomes a 1-vector), checking its length."""
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    if x.ndim != 1 or (size is not None and x.shape[0] != size):
        expected = "a vector" if size is None else f"{size} component(s)"
        raise ValueError(f"{what} must have {expected}; got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} must be finite; got {x}")
    return x


def make_state(q0: np.ndarray, p0: np.ndarray, dtype: np.dtype) -> tuple[Array, Array]:
    """The initial state `(q0, p0)` as JAX arrays of `dtype`."""
    return jnp.asarray(q0, dtype=dtype), jnp.asarray(p0, dtype=dtype)


# -- reference solutions ------------------------------------------------------------------------
ReferenceFlow = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class ClosedFormFlow:
    """A reference flow from a closed-form solution `solution(tau) -> (q, p)` (vectorised)."""

    def __init__(self, solution: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]):
        self.solution = solution

    def __call__(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q, p = self.solution(np.asarray(tau, dtype=np.float64))
        return np.asarray(q, dtype=np.float64), np.asarray(p, dtype=np.float64)


class DOP853Flow:
    """A reference flow by scipy's DOP853 (`rtol = 1e-13`, `atol = 1e-15`).

    **Arguments:**

    - `rhs`: `rhs(y) -> dy/dt` on the flat float64 state `y = concat(q, p)` (autonomous).
      A time-dependent system is made autonomous by appending the absolute time as a last
      component: `y = concat(q, p, [t])`, `dt/dt = 1` (odd length; the flow returns `q`, `p`).
    - `y0`: the flat float64 initial state (with the start time last in the augmented form).
    - `cache_size`: how many distinct time grids to memoise.

    Times before and after the start are integrated backwards and forwards from `y0`.
    """

    def __init__(self, rhs: Callable[[np.ndarray], np.ndarray], y0: np.ndarray, *, cache_size=32):
        self.rhs = rhs
        self.y0 = np.array(y0, dtype=np.float64)
        self.dim = self.y0.shape[0] // 2
        self.cache_size = cache_size
        self._cache: collections.OrderedDict[bytes, np.ndarray] = collections.OrderedDict()

    def __call__(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tau = np.asarray(tau, dtype=np.float64)
        key = tau.tobytes()
        ys = self._cache.get(key)
        if ys is None:
            ys = self._solve(tau)
            self._cache[key] = ys
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        return ys[:, : self.dim].copy(), ys[:, self.dim : 2 * self.dim].copy()

    def _solve(self, tau: np.ndarray) -> np.ndarray:
        try:
            from scipy.integrate import solve_ivp
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise ImportError(
                "this problem's reference solution is computed with scipy's DOP853; install "
                "scipy (e.g. `pip install diffrax_vi[test]`)"
            ) from e

        if not np.all(np.isfinite(tau)):
            raise ValueError("reference times must be finite")
        out = np.empty((tau.shape[0], self.y0.shape[0]), dtype=np.float64)
        out[tau == 0] = self.y0
        fun = lambda _, y: self.rhs(y)
        for sign in (1.0, -1.0):
            mask = sign * tau > 0
            if not np.any(mask):
                continue
            targets = np.unique(tau[mask])  # sorted ascending
            if sign < 0:
                targets = targets[::-1]
            sol = solve_ivp(
                fun,
                (0.0, targets[-1]),
                self.y0,
                method="DOP853",
                t_eval=targets,
                rtol=REFERENCE_RTOL,
                atol=REFERENCE_ATOL,
            )
            if not sol.success:
                raise RuntimeError(f"the DOP853 reference failed: {sol.message}")
            values = sol.y.T
            index = np.searchsorted(targets[::-1] if sign < 0 else targets, tau[mask])
            if sign < 0:
                index = targets.shape[0] - 1 - index
            out[mask] = values[index]
        return out
