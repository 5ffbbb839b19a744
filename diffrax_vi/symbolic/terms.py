"""Lagrangian terms written as sympy expressions.

`sympy_lagrangian_term` takes a Lagrangian
`L(t, q, v; params)` as a sympy expression, differentiates it with sympy and compiles `L`, the
momentum and force `(∂L/∂v, ∂L/∂q)`, the Hessian `∂²L/∂v²` of the Legendre inverse and the
energy `v·∂L/∂v − L` to JAX with `diffrax_vi.symbolic.compile_exprs`. The resulting
`SympyLagrangianTerm` is a `LagrangianTerm`: the variational solvers and diffrax's own solvers
integrate it unchanged. This module imports sympy; `import diffrax_vi` does not.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import sympy
from jaxtyping import Array, PyTree

from .._codegen import compile_exprs
from .._linalg import solve
from .._terms import LagrangianTerm
from .._validation import check_state

__all__ = ["SympyLagrangianTerm", "sympy_lagrangian_term"]

# Stands in for the time of a time-independent Lagrangian; a Dummy never clashes with a user
# symbol, and being one fixed object it keeps the compiled functions cached.
_NO_TIME = sympy.Dummy("t")


class _Kernels(NamedTuple):
    """Compiled functions of `(t, q_1..q_D, v_1..v_D, params...)`."""

    lagrangian: Callable[..., tuple[Array, ...]]  # (L,)
    momentum_force: Callable[..., tuple[Array, ...]]  # (∂L/∂v_i..., ∂L/∂q_i...)
    legendre: Callable[..., tuple[Array, ...]]  # (∂L/∂v_i..., ∂²L/∂v_i∂v_j row-major...)
    energy: Callable[..., tuple[Array, ...]]  # (v·∂L/∂v − L,)


class _SympyLagrangian(eqx.Module):
    """The compiled Lagrangian `L(t, q, v, args)` and the kernels of its derivatives."""

    kernels: _Kernels = eqx.field(static=True)
    dim: int = eqx.field(static=True)
    param_names: tuple[str, ...] = eqx.field(static=True)

    def parameter_values(self, args: PyTree, dtype) -> tuple[Array, ...]:
        names = self.param_names
        if not names:
            return ()
        if isinstance(args, Mapping):
            missing = [n for n in names if n not in args]
            if missing:
                raise ValueError(
                    f"the Lagrangian's parameter(s) {', '.join(map(repr, missing))} are missing "
                    f"from args; it needs {names} (args={{name: value}} or a tuple in that order)"
                )
            values = [args[n] for n in names]
        elif isinstance(args, tuple | list):
            if len(args) != len(names):
                raise ValueError(
                    f"the Lagrangian has {len(names)} parameter(s) {names}, but args is a "
                    f"sequence of length {len(args)}"
                )
            values = list(args)
        else:
            raise TypeError(
                f"the Lagrangian has parameters {names}: pass their values as args, either a "
                f"dict keyed by name or a tuple in that order; got args of type "
                f"{type(args).__name__}"
            )
        out = []
        for name, value in zip(names, values, strict=True):
            value = jnp.asarray(value)
            if value.shape != ():
                raise ValueError(
                    f"the parameter {name!r} must be a scalar, got shape {value.shape} (use "
                    "jax.vmap for a batch of parameter values)"
                )
            out.append(value.astype(dtype))
        return tuple(out)

    def inputs(self, t, q, v, args) -> tuple[Array, ...]:
        """The compiled kernels' inputs `(t, q_1..q_D, v_1..v_D, params...)`, all in the
        working dtype of `q` and `v`."""
        q, v = jnp.asarray(q), jnp.asarray(v)
        for name, x in (("q", q), ("v", v)):
            if x.shape != (self.dim,):
                raise ValueError(
                    f"the Lagrangian has {self.dim} coordinate(s): {name} must have shape "
                    f"({self.dim},), got {x.shape}"
                )
        dtype = jnp.result_type(q, v)
        if not jnp.issubdtype(dtype, jnp.inexact):
            dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
        params = self.parameter_values(args, dtype)
        return (jnp.asarray(t, dtype), *q.astype(dtype), *v.astype(dtype), *params)

    def __call__(self, t, q, v, args) -> Array:
        return self.kernels.lagrangian(*self.inputs(t, q, v, args))[0]


class SympyLagrangianTerm(LagrangianTerm):
    """A `LagrangianTerm` whose Lagrangian and derivatives are compiled sympy expressions.

    Build it with `sympy_lagrangian_term`. It has the methods
    of every `LagrangianTerm` (`momentum_and_force`, `velocity`, `energy`, `vf`, ...), computed
    from the closed forms instead of `jax.grad`:

    - `momentum_and_force`: the compiled `(∂L/∂v, ∂L/∂q)`;
    - `velocity`: Newton's method on `∂L/∂v(t, q, v) = p` from `v = 0` with the compiled
      Hessian `∂²L/∂v²` (one step, exact, when `L` is quadratic in `v`), or the closed form
      given as `velocity=`;
    - `energy`: the compiled `v·∂L/∂v − L` at that velocity.

    The parameters of `L` come through diffrax's `args`: a dict keyed by parameter name (extra
    keys are ignored) or a tuple in the order of `params`; each value is a scalar, cast to the
    working dtype. Every input is cast to the dtype of `q` and `v`, so a float32 state keeps
    the whole computation in float32.

    The symbolic description is kept in static fields (`expression`, `coordinates`,
    `velocities`, `time`, `parameters`); the compiled functions are cached per expression, so
    two terms built from the same Lagrangian compare equal and share jit caches.
    """

    expression: Any = eqx.field(static=True, default=None)
    coordinates: tuple = eqx.field(static=True, default=())
    velocities: tuple = eqx.field(static=True, default=())
    time: Any = eqx.field(static=True, default=None)
    parameters: tuple = eqx.field(static=True, default=())
    degenerate: bool = eqx.field(static=True, default=False)

    def __init__(
        self,
        lagrangian: _SympyLagrangian,
        velocity: Callable | None,
        legendre_iterations: int | None,
        *,
        expression,
        coordinates,
        velocities,
        time,
        parameters,
        degenerate: bool,
    ):
        self.lagrangian = lagrangian
        self.velocity_map = velocity
        self.legendre_iterations = legendre_iterations
        self.expression = expression
        self.coordinates = coordinates
        self.velocities = velocities
        self.time = time
        self.parameters = parameters
        self.degenerate = degenerate

    @property
    def dim(self) -> int:
        """The number of coordinates `D`."""
        return self.lagrangian.dim

    def check_state(self, y: Any) -> tuple[Array, Array]:
        """The checks of every term, and that `q` has one entry per coordinate symbol."""
        q, p = check_state(y)
        if q.shape[0] != self.dim:
            raise ValueError(
                f"this Lagrangian has {self.dim} coordinates {list(map(str, self.coordinates))}, "
                f"so y0 = (q, p) needs arrays of shape ({self.dim},); got {q.shape[0]} entries"
            )
        return q, p

    def _inputs(self, t, q, v, args):
        return self.lagrangian.inputs(t, q, v, args)

    def momentum_and_force(self, t, q, v, args):
        out = self.lagrangian.kernels.momentum_force(*self._inputs(t, q, v, args))
        d = self.dim
        return jnp.stack(out[:d]), jnp.stack(out[d:])

    def velocity(self, t, q, p, args):
        """Inverse Legendre map `p ↦ v`: the closed form if given, else Newton from `v = 0`."""
        if self.velocity_map is not None:
            return self.velocity_map(t, q, p, args)
        if self.degenerate:
            raise ValueError(
                "the Lagrangian is degenerate (∂²L/∂v² = 0: it is at most linear in the "
                "velocities), so p = ∂L/∂v cannot be solved for v; pass velocity=v(t, q, p, "
                "args) to sympy_lagrangian_term for a standard solver, or integrate with NetworkVI"
            )
        n = self.legendre_iterations
        if n is None:
            raise ValueError(
                "the Lagrangian is not quadratic in the velocities, so one Newton step does not "
                "invert p = ∂L/∂v; pass legendre_iterations=n (Newton steps from v = 0) or a "
                "closed-form velocity=v(t, q, p, args) to sympy_lagrangian_term"
            )
        q, p = jnp.asarray(q), jnp.asarray(p)
        dtype = jnp.result_type(q, p)
        if not jnp.issubdtype(dtype, jnp.inexact):
            dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
        p = p.astype(dtype)
        d = self.dim

        def newton(_, v):
            out = self.lagrangian.kernels.legendre(*self._inputs(t, q, v, args))
            momentum = jnp.stack(out[:d])
            mass = jnp.stack(out[d:]).reshape(d, d)
            return v - solve(mass, momentum - p)

        v0 = jnp.zeros(q.shape, dtype)
        if n == 1:
            return newton(0, v0)
        return jax.lax.fori_loop(0, n, newton, v0)

    def energy(self, t, q, p, args):
        """`H(t, q, p) = v·∂L/∂v − L` at the velocity `v(t, q, p)` of the Legendre inverse."""
        v = self.velocity(t, q, p, args)
        return self.lagrangian.kernels.energy(*self._inputs(t, q, v, args))[0]

    def separable_terms(self, y0=None, args=None, *, t0=0.0):
        """As `AbstractMechanicalTerm.separable_terms`, with separability checked exactly:
        raises `ValueError` unless every `∂²L/∂q_i∂v_j` vanishes identically (sympy)."""
        coupled = _couplings(self.expression, self.coordinates, self.velocities)
        if coupled:
            shown = "; ".join(f"∂²L/∂{q}∂{v} = {d}" for q, v, d in coupled[:3])
            raise ValueError(
                "the Lagrangian is not separable (L = T(t, v) − V(t, q)), so it cannot be split "
                f"into the pair of terms of SemiImplicitEuler: {shown}. Integrate the term "
                "itself with a standard solver (Tsit5) or a variational one (NetworkVI)."
            )
        return super().separable_terms(y0, args, t0=t0)


def _couplings(expr, qs, vs) -> list[tuple[Any, Any, Any]]:
    out = []
    for q in qs:
        dq = sympy.diff(expr, q)
        for v in vs:
            d = sympy.diff(dq, v)
            if d != 0 and sympy.simplify(d) != 0:
                out.append((q, v, d))
    return out


def _names(items, role: str) -> list:
    if isinstance(items, str):
        return [n for n in re.split(r"[\s,]+", items) if n]
    if isinstance(items, sympy.Basic) and not isinstance(items, sympy.MatrixBase):
        return [items]
    try:
        return list(items)
    except TypeError:
        raise TypeError(
            f"{role} must be a sympy Symbol, a name, or a sequence of them; got {items!r}"
        ) from None


def _resolve(item, free: set, role: str) -> sympy.Symbol:
    """A symbol given as a `sympy.Symbol`, or by name (matched against `L`'s free symbols)."""
    if isinstance(item, sympy.Symbol):
        return item
    if isinstance(item, str):
        matches = [s for s in free if s.name == item]
        if len(matches) > 1:
            raise ValueError(
                f"the name {item!r} in {role} is ambiguous: the Lagrangian has several symbols "
                f"of that name (with different assumptions); pass the sympy Symbol itself"
            )
        return matches[0] if matches else sympy.Symbol(item)
    raise TypeError(f"{role} must hold sympy Symbols or names, got {item!r}")


@functools.lru_cache(maxsize=128)
def _build(expr, qs, vs, t, ps, cse) -> tuple[_Kernels, bool, bool]:
    symbols = (t, *qs, *vs, *ps)
    d_v = [sympy.diff(expr, v) for v in vs]
    d_q = [sympy.diff(expr, q) for q in qs]
    hessian = [sympy.diff(dv, v) for dv in d_v for v in vs]
    quadratic = not any(h.has(*vs) for h in hessian)
    degenerate = all(h == 0 for h in hessian)
    energy = sympy.Add(*(v * dv for v, dv in zip(vs, d_v, strict=True))) - expr
    kernels = _Kernels(
        lagrangian=compile_exprs([expr], symbols, cse=cse),
        momentum_force=compile_exprs([*d_v, *d_q], symbols, cse=cse),
        legendre=compile_exprs([*d_v, *hessian], symbols, cse=cse),
        energy=compile_exprs([energy], symbols, cse=cse),
    )
    return kernels, quadratic, degenerate


def _declared_symbols(expr, q_symbols, v_symbols, t, params):
    """The coordinates, velocities, parameters and time symbol of `expr`, each declared once
    and covering every free symbol of `expr`."""
    free = expr.free_symbols
    qs = tuple(_resolve(s, free, "q_symbols") for s in _names(q_symbols, "q_symbols"))
    vs = tuple(_resolve(s, free, "v_symbols") for s in _names(v_symbols, "v_symbols"))
    ps = tuple(_resolve(s, free, "params") for s in _names(params, "params"))
    ts = None if t is None else _resolve(t, free, "t")
    if len(qs) != len(vs):
        raise ValueError(
            f"q_symbols and v_symbols must have the same length; got {len(qs)} coordinates "
            f"{qs} and {len(vs)} velocities {vs}"
        )
    if not qs:
        raise ValueError("the Lagrangian needs at least one coordinate")

    roles: dict[sympy.Symbol, str] = {}
    declared = [(s, "a coordinate") for s in qs] + [(s, "a velocity") for s in vs]
    declared += [(s, "a parameter") for s in ps]
    if ts is not None:
        declared.append((ts, "the time"))
    for symbol, role in declared:
        if symbol in roles:
            raise ValueError(
                f"the symbol {symbol} is declared twice (as {roles[symbol]} and as {role})"
            )
        roles[symbol] = role
    names = [p.name for p in ps]
    for name in names:
        if names.count(name) > 1:
            raise ValueError(f"two parameters are named {name!r}; args is keyed by name")

    unknown = sorted(free - set(roles), key=str)
    if unknown:
        listed = ", ".join(str(s) for s in unknown)
        raise ValueError(
            f"the Lagrangian contains the symbol(s) {listed}, which are neither coordinates "
            f"{qs}, velocities {vs}, the time ({ts}) nor parameters {ps}; declare "
            "parameters with params=... and pass their values through args"
        )
    return qs, vs, ps, ts


def sympy_lagrangian_term(
    lagrangian: Any,
    q_symbols: Any,
    v_symbols: Any,
    t: Any = None,
    params: Any = (),
    *,
    velocity: Callable | None = None,
    legendre_iterations: int | None = None,
    cse: bool = True,
) -> SympyLagrangianTerm:
    """A `LagrangianTerm` from a sympy expression of the Lagrangian.

    **Arguments:**

    - `lagrangian`: the scalar sympy expression `L` (anything `sympy.sympify` accepts), using
      the functions `compile_exprs` supports.
    - `q_symbols`, `v_symbols`: the coordinates `q_1..q_D` and velocities `v_1..v_D`, as
      sympy Symbols or names (a name is matched against the free symbols of `L`; a string
      may list several, separated by spaces or commas). The state `q`, `v` of the term are
      arrays of shape `(D,)` in this order.
    - `t`: the time symbol of a time-dependent `L` (a Symbol or a name), or `None`.
    - `params`: the symbols (or names) of the parameters of `L`. Their values are passed at
      call time through diffrax's `args`: either a dict keyed by parameter *name* (other keys
      are ignored, so `args` may carry more) or a tuple/list in the order of `params`. Each
      value is a scalar (`jax.vmap` over `args` for a batch), cast to the working dtype.
    - `velocity`: optional closed-form inverse Legendre map `v(t, q, p, args)`.
    - `legendre_iterations`: Newton steps of the numerical Legendre inverse. Default: one
      step when `L` is quadratic in `v` (where it is exact); otherwise it must be given (or
      `velocity`) before `velocity`, `energy` or `vf` can be used. `momentum_and_force`,
      which is all the variational solvers need, works regardless.
    - `cse`: share common subexpressions in the compiled code.

    **Returns:**

    A `SympyLagrangianTerm`.

    **Raises:**

    `ValueError` if `L` has a free symbol that is neither a coordinate, a velocity, the time
    nor a parameter (the symbol is named), if `q_symbols` and `v_symbols` differ in length or
    are empty, or if a symbol is declared twice; `TypeError` for a non-scalar `L`.
    """
    if isinstance(lagrangian, sympy.MatrixBase | list | tuple):
        raise TypeError("the Lagrangian must be a scalar sympy expression, not a matrix/list")
    expr = sympy.sympify(lagrangian)
    if not isinstance(expr, sympy.Expr):
        raise TypeError(f"the Lagrangian must be a scalar sympy expression, got {expr!r}")

    qs, vs, ps, ts = _declared_symbols(expr, q_symbols, v_symbols, t, params)
    names = [p.name for p in ps]
    if velocity is not None and not callable(velocity):
        raise TypeError(f"velocity must be callable or None, got {type(velocity).__name__}")
    if legendre_iterations is not None and (
        not isinstance(legendre_iterations, int) or legendre_iterations < 1
    ):
        raise ValueError(
            f"legendre_iterations must be a positive int or None, got {legendre_iterations!r}"
        )

    kernels, quadratic, degenerate = _build(
        expr, qs, vs, _NO_TIME if ts is None else ts, ps, bool(cse)
    )
    if legendre_iterations is None and quadratic:
        legendre_iterations = 1
    return SympyLagrangianTerm(
        _SympyLagrangian(kernels, len(qs), tuple(names)),
        velocity,
        legendre_iterations,
        expression=expr,
        coordinates=qs,
        velocities=vs,
        time=ts,
        parameters=ps,
        degenerate=degenerate,
    )
