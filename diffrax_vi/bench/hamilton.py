"""Hamilton's equations of a problem, in sympy, from its JAX Hamiltonian.

The problem's Hamiltonian `H(t, q, p)` (the JAX function `Problem.energy`) is traced to a
jaxpr, the jaxpr is evaluated on sympy symbols (its constants as exact binary fractions), and
sympy differentiates: `q' = ∂H/∂p`, `p' = −∂H/∂q`. `check_equations` compares the result with
the term's own vector field at the initial state, so that a Hamiltonian written in other
coordinates than the term's `(q, p)` is refused. A JAX operation the translation does not
know raises `NotImplementedError` naming it. The heyoka peer (`diffrax_vi.bench.peers`) builds
its equations from these.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["check_equations", "hamilton_equations"]


def _sympy():
    import sympy

    return sympy


def _is_symbolic(x) -> bool:
    return isinstance(x, np.ndarray) and x.dtype == object


def _as_object(x) -> np.ndarray:
    """`x` (sympy expression, number or array) as an object array of sympy expressions."""
    if _is_symbolic(x):
        return x
    arr = np.asarray(x)
    out = np.empty(arr.shape, dtype=object)
    for index in np.ndindex(arr.shape):
        out[index] = _number(arr[index])
    return out


def _number(v):
    """A NumPy number as an exact sympy number (floats as their exact binary fractions)."""
    sp = _sympy()
    if isinstance(v, sp.Basic):
        return v
    if isinstance(v, bool | np.bool_):
        return sp.Integer(int(v))
    if isinstance(v, int | np.integer):
        return sp.Integer(int(v))
    v = float(v)
    if not math.isfinite(v):
        raise NotImplementedError(f"the Hamiltonian holds the non-finite constant {v}")
    return sp.Integer(int(v)) if v.is_integer() else sp.Rational(v)


def _wrap(value) -> np.ndarray:
    """A reduction's result (array or lone element) as an object array of sympy values."""
    if isinstance(value, np.ndarray | np.number):
        return _as_object(value)
    out = np.empty((), dtype=object)
    out[()] = value
    return out


def _elementwise(fn, *xs) -> np.ndarray:
    xs = np.broadcast_arrays(*(_as_object(x) for x in xs))
    out = np.empty(xs[0].shape, dtype=object)
    for index in np.ndindex(out.shape):
        out[index] = fn(*(x[index] for x in xs))
    return out


def _unary_table():
    sp = _sympy()
    half = sp.Rational(1, 2)
    table: dict[str, Callable] = {
        "neg": lambda x: -x,
        "sqrt": sp.sqrt,
        "rsqrt": lambda x: x**-half,
        "cbrt": lambda x: x ** sp.Rational(1, 3),
        "square": lambda x: x**2,
        "exp": sp.exp,
        "exp2": lambda x: 2**x,
        "log": sp.log,
        "log1p": lambda x: sp.log(1 + x),
        "expm1": lambda x: sp.exp(x) - 1,
        "logistic": lambda x: 1 / (1 + sp.exp(-x)),
        "erf": sp.erf,
        "erfc": sp.erfc,
    }
    for name in ("sin", "cos", "tan", "asin", "acos", "atan", "sinh", "cosh", "tanh",
                 "asinh", "acosh", "atanh"):
        table[name] = getattr(sp, name)
    return table


_BINARY: dict[str, Callable] = {
    "add": lambda a, b: a + b,
    "add_any": lambda a, b: a + b,
    "sub": lambda a, b: a - b,
    "mul": lambda a, b: a * b,
    "div": lambda a, b: a / b,
    "pow": lambda a, b: a**b,
    "atan2": lambda a, b: _sympy().atan2(a, b),
}

_IDENTITY = {"convert_element_type", "copy", "copy_p", "reduce_precision",
             "optimization_barrier"}

# Primitives that only move, copy or pick elements: applied to arrays of element indices.
# The value is which inputs carry data (the others, e.g. gather's indices, must be known).
_STRUCTURAL: dict[str, Callable[[int], Sequence[int]]] = {
    name: (lambda n: range(n))
    for name in ("broadcast_in_dim", "reshape", "squeeze", "expand_dims", "slice",
                 "concatenate", "transpose", "rev", "stack", "split", "pad")
}
_STRUCTURAL.update({
    "gather": lambda n: (0,),
    "dynamic_slice": lambda n: (0,),
    "dynamic_update_slice": lambda n: (0, 1),
    "select_n": lambda n: range(1, n),
})

# Calls of a nested jaxpr on the same inputs: evaluated inline.
_CALLS = {"pjit", "jit", "closed_call", "core_call", "remat", "checkpoint", "custom_jvp_call",
          "custom_vjp_call", "custom_vjp_call_jaxpr"}


def _structural(prim, inputs, params):
    data = set(_STRUCTURAL[prim.name](len(inputs)))
    pool: list = []
    args = []
    for i, x in enumerate(inputs):
        if i in data:
            obj = _as_object(x)
            args.append(np.arange(len(pool), len(pool) + obj.size,
                                  dtype=np.int64).reshape(obj.shape))
            pool.extend(obj.ravel().tolist())
        elif _is_symbolic(x):
            raise NotImplementedError(
                f"the Hamiltonian's `{prim.name}` takes a computed index or predicate; the "
                "heyoka translation needs it known when the Hamiltonian is traced")
        else:
            args.append(x)
    out = prim.bind(*(jnp.asarray(a) for a in args), **params)
    pool_array = np.empty(len(pool), dtype=object)
    pool_array[:] = pool

    def pick(idx):
        idx = np.asarray(idx)
        return pool_array[idx.ravel()].reshape(idx.shape)

    return [pick(o) for o in out] if prim.multiple_results else pick(out)


def _apply(prim, inputs, params):
    name = prim.name
    if name in _CALLS and any(_is_symbolic(x) for x in inputs):
        inner = next(params[k] for k in ("jaxpr", "call_jaxpr", "fun_jaxpr") if k in params)
        jaxpr, consts = (inner.jaxpr, inner.consts) if hasattr(inner, "consts") \
            else (inner, ())
        return _eval_jaxpr(jaxpr, consts, inputs)
    if not any(_is_symbolic(x) for x in inputs):  # known values: let JAX compute them
        out = prim.bind(*(jnp.asarray(x) for x in inputs), **params)
        return [np.asarray(o) for o in out] if prim.multiple_results else np.asarray(out)
    if name in _IDENTITY:
        return list(inputs) if prim.multiple_results else inputs[0]
    if name in _BINARY:
        return _elementwise(_BINARY[name], *inputs)
    if name == "integer_pow":
        return _elementwise(lambda x: x ** int(params["y"]), inputs[0])
    unary = _unary_table()
    if name in unary:
        return _elementwise(unary[name], inputs[0])
    if name in ("reduce_sum", "reduce_prod"):
        reduce = np.sum if name == "reduce_sum" else np.prod
        return _wrap(reduce(_as_object(inputs[0]), axis=tuple(params["axes"])))
    if name == "dot_general":
        (lc, rc), (lb, rb) = params["dimension_numbers"]
        if lb or rb:
            raise NotImplementedError("the heyoka translation has no batched dot_general")
        return _wrap(np.tensordot(_as_object(inputs[0]), _as_object(inputs[1]),
                                  axes=(tuple(lc), tuple(rc))))
    if name in _STRUCTURAL:
        return _structural(prim, inputs, params)
    raise NotImplementedError(
        f"the Hamiltonian uses the JAX operation `{name}`, which the heyoka translation does "
        "not know; give the equations by hand with HeyokaPeer(..., system=...)")


def _eval_jaxpr(jaxpr, consts, args) -> list:
    env: dict = {}

    def read(v):
        return np.asarray(v.val) if hasattr(v, "val") else env[v]

    for v, c in zip(jaxpr.constvars, consts, strict=True):
        env[v] = np.asarray(c)
    for v, a in zip(jaxpr.invars, args, strict=True):
        env[v] = a
    for eqn in jaxpr.eqns:
        out = _apply(eqn.primitive, [read(v) for v in eqn.invars], eqn.params)
        outs = out if eqn.primitive.multiple_results else [out]
        for v, o in zip(eqn.outvars, outs, strict=True):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _float64_state(problem) -> tuple[np.ndarray, np.ndarray]:
    return tuple(np.asarray(x, np.float64) for x in problem.y0)


def hamilton_equations(problem):
    """Hamilton's equations of `problem` in sympy: `(t, qs, ps, H, rhs)` with the symbols `t`,
    `q_i`, `p_i`, the Hamiltonian `H` and `rhs = [∂H/∂p_i ..., −∂H/∂q_i ...]`.

    `H` is `problem.energy(t, q, p)` traced by JAX in float64 (64-bit JAX must be on, so that
    the constants of the problem keep their float64 values) and evaluated on the symbols; its
    constants are exact binary fractions."""
    sp = _sympy()
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "the heyoka peer traces the Hamiltonian in float64: call "
            "jax.config.update('jax_enable_x64', True) first")
    d = problem.dim
    q0, p0 = _float64_state(problem)
    closed = jax.make_jaxpr(lambda t, q, p: problem.energy(t, q, p))(
        jnp.float64(problem.t0), jnp.asarray(q0), jnp.asarray(p0))
    t = sp.Symbol("t", real=True)
    qs = sp.symbols(f"q0:{d}", real=True)
    ps = sp.symbols(f"p0:{d}", real=True)
    args = [_wrap(t), _wrap(np.array(qs, dtype=object)), _wrap(np.array(ps, dtype=object))]
    (h,) = _eval_jaxpr(closed.jaxpr, closed.consts, args)
    if np.shape(h) != ():
        raise ValueError(f"{problem.name}: the Hamiltonian is not a scalar (shape "
                         f"{np.shape(h)})")
    H = h[()]
    rhs = [sp.diff(H, pi) for pi in ps] + [-sp.diff(H, qi) for qi in qs]
    return t, qs, ps, H, rhs


def check_equations(problem, t, qs, ps, rhs, rtol: float = 1e-9) -> None:
    """Hamilton's equations (`hamilton_equations`' output) against the term's vector field at
    the initial state, in float64; a `ValueError` where they differ by more than `rtol`
    (relative to the field's largest component, at least 1)."""
    sp = _sympy()
    q0, p0 = _float64_state(problem)
    f = sp.lambdify((t, *qs, *ps), rhs, modules="numpy")
    ours = np.asarray(f(problem.t0, *q0, *p0), np.float64)
    v, force = problem.term.vf(jnp.float64(problem.t0), (jnp.asarray(q0), jnp.asarray(p0)),
                               problem.args)
    theirs = np.concatenate([np.asarray(v, np.float64), np.asarray(force, np.float64)])
    scale = max(float(np.max(np.abs(theirs))), 1.0)
    if not np.all(np.abs(ours - theirs) <= rtol * scale):
        raise ValueError(
            f"{problem.name}: Hamilton's equations of its energy do not match its term's "
            f"vector field at y0 ({ours} against {theirs}); is the energy written in other "
            "coordinates than the term's (q, p)? Give the equations with system=...")
