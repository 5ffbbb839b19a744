"""sympy expressions compiled to JAX, and closed-form derivative kernels of a curve.

- `compile_exprs` turns sympy expressions into one JAX function (common subexpressions
  shared, every constant in the dtype of the inputs), compiled once per expression set.
- `curve_function` builds, from one curve expression `q(τ; p_1..p_P)`, a `jax.custom_jvp`
  function whose derivatives are the sympy ones: the tangent of `q` is `Σ_k ∂q/∂p_k dp_k +
  q' dτ`, the tangent of `q' = ∂q/∂τ` is `Σ_k ∂q'/∂p_k dp_k + q'' dτ`; the parameter
  gradients `∂q/∂p_k`, `∂q'/∂p_k` are compiled closed forms that JAX differentiates further
  (the Newton Jacobian). `symbolic_curve_evaluate` wraps them as `evaluate(θ, τ)` of an
  ansatz.
- `sympy_activation` gives the sympy form of a package activation.

This module sits below the ansätze (their sympy derivative backend, in
`diffrax_vi._ansatz.sympy_kernels`) and below `diffrax_vi.symbolic` (terms and ansätze written
with sympy); it depends on the activations alone. Derivatives of non-smooth functions (`Abs`,
`Max`, `Piecewise`, `sign`, `Heaviside`) are taken almost everywhere, as JAX does: `DiracDelta`
evaluates to zero.
"""

from __future__ import annotations

import functools
import itertools
import linecache
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.special as jsp
import sympy
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array
from sympy.codegen.cfunctions import expm1, log1p

from . import _activations as _act
from ._precision import floating_dtype

__all__ = [
    "CurveKernels",
    "compile_exprs",
    "curve_function",
    "curve_kernels",
    "symbolic_curve_evaluate",
    "sympy_activation",
]


# ---------------------------------------------------------------------------------------------
# sympy -> JAX source
# ---------------------------------------------------------------------------------------------

# Elementwise functions: sympy class -> format string of the JAX call.
_FUNCTIONS: dict[type, str] = {
    sympy.exp: "jnp.exp({0})",
    sympy.log: "jnp.log({0})",
    expm1: "jnp.expm1({0})",
    log1p: "jnp.log1p({0})",
    sympy.sin: "jnp.sin({0})",
    sympy.cos: "jnp.cos({0})",
    sympy.tan: "jnp.tan({0})",
    sympy.cot: "jnp.reciprocal(jnp.tan({0}))",
    sympy.sec: "jnp.reciprocal(jnp.cos({0}))",
    sympy.csc: "jnp.reciprocal(jnp.sin({0}))",
    sympy.asin: "jnp.arcsin({0})",
    sympy.acos: "jnp.arccos({0})",
    sympy.atan: "jnp.arctan({0})",
    sympy.atan2: "jnp.arctan2({0}, {1})",
    sympy.sinh: "jnp.sinh({0})",
    sympy.cosh: "jnp.cosh({0})",
    sympy.tanh: "jnp.tanh({0})",
    sympy.coth: "jnp.reciprocal(jnp.tanh({0}))",
    sympy.sech: "jnp.reciprocal(jnp.cosh({0}))",
    sympy.csch: "jnp.reciprocal(jnp.sinh({0}))",
    sympy.asinh: "jnp.arcsinh({0})",
    sympy.acosh: "jnp.arccosh({0})",
    sympy.atanh: "jnp.arctanh({0})",
    sympy.erf: "jsp.erf({0})",
    sympy.erfc: "jsp.erfc({0})",
    sympy.Abs: "jnp.abs({0})",
    sympy.sign: "jnp.sign({0})",
    sympy.floor: "jnp.floor({0})",
    sympy.ceiling: "jnp.ceil({0})",
    sympy.DiracDelta: "jnp.zeros_like({0})",
}

_RELATIONS: dict[type, str] = {
    sympy.StrictLessThan: "<",
    sympy.LessThan: "<=",
    sympy.StrictGreaterThan: ">",
    sympy.GreaterThan: ">=",
    sympy.Equality: "==",
    sympy.Unequality: "!=",
}

_LOGIC: dict[type, str] = {
    sympy.And: "jnp.logical_and",
    sympy.Or: "jnp.logical_or",
    sympy.Xor: "jnp.logical_xor",
}

_NAMESPACE = {"jnp": jnp, "jsp": jsp}
_counter = itertools.count()


_NAMESPACE["_working_dtype"] = floating_dtype


class _Printer:
    """Writes sympy expressions as Python/JAX source, hoisting constants into a table."""

    def __init__(self, names: dict[sympy.Basic, str]):
        self.names = names
        self.constants: dict[float, str] = {}

    def constant(self, value: sympy.Basic) -> str:
        try:
            number = float(sympy.N(value, 30))
        except TypeError as err:
            raise ValueError(f"the constant {value} is not a real number") from err
        key = number if number == number else "nan"
        if key not in self.constants:
            self.constants[key] = f"_k{len(self.constants)}"
        return self.constants[key]

    def __call__(self, e: sympy.Basic) -> str:
        if e in self.names:
            return self.names[e]
        if isinstance(e, sympy.Symbol):
            raise ValueError(f"unknown symbol {e}")
        if isinstance(e, sympy.logic.boolalg.BooleanAtom):
            return "True" if bool(e) else "False"
        if isinstance(e, sympy.Expr) and not e.free_symbols:
            return self.constant(e)
        if isinstance(e, sympy.Add):
            return "(" + " + ".join(self(a) for a in e.args) + ")"
        if isinstance(e, sympy.Mul):
            return self.mul(e)
        if isinstance(e, sympy.Pow):
            return self.pow(e.base, e.exp)
        if isinstance(e, sympy.Piecewise):
            return self.piecewise(e)
        if isinstance(e, (sympy.Max, sympy.Min)):
            fn = "jnp.maximum" if isinstance(e, sympy.Max) else "jnp.minimum"
            out = self(e.args[0])
            for a in e.args[1:]:
                out = f"{fn}({out}, {self(a)})"
            return out
        if isinstance(e, sympy.Heaviside):
            h0 = e.args[1] if len(e.args) > 1 else sympy.S.Half
            return f"jnp.heaviside({self(e.args[0])}, {self.constant(h0)})"
        if type(e) in _RELATIONS:
            return f"({self(e.lhs)} {_RELATIONS[type(e)]} {self(e.rhs)})"
        if type(e) in _LOGIC:
            out = self(e.args[0])
            for a in e.args[1:]:
                out = f"{_LOGIC[type(e)]}({out}, {self(a)})"
            return out
        if isinstance(e, sympy.Not):
            return f"jnp.logical_not({self(e.args[0])})"
        if type(e) in _FUNCTIONS:
            if isinstance(e, sympy.DiracDelta):
                # Zero almost everywhere (also its derivatives), as JAX differentiates kinks.
                return _FUNCTIONS[sympy.DiracDelta].format(self(e.args[0]))
            return _FUNCTIONS[type(e)].format(*(self(a) for a in e.args))
        if isinstance(e, sympy.Function):
            raise ValueError(
                f"cannot compile the function {type(e).__name__} (in {e}) to JAX; supported: "
                + ", ".join(sorted(f.__name__ for f in _FUNCTIONS))
                + ", Max, Min, Heaviside, Piecewise"
            )
        raise ValueError(f"cannot compile {type(e).__name__} expressions to JAX: {e}")

    def mul(self, e: sympy.Mul) -> str:
        coeff = sympy.S.One
        num: list[str] = []
        den: list[str] = []
        for a in e.args:
            if not a.free_symbols:
                coeff *= a
            elif isinstance(a, sympy.Pow) and a.exp.is_number and a.exp.is_negative:
                den.append(self.pow(a.base, -a.exp))
            else:
                num.append(self(a))
        if coeff == -1:
            sign = "-"
        else:
            sign = ""
            if coeff != 1:
                num.insert(0, self.constant(coeff))
        if not num:
            out = f"jnp.reciprocal({' * '.join(den)})"
            return f"(-{out})" if sign else out
        out = " * ".join(num)
        if den:
            out = f"({out}) / ({' * '.join(den)})"
        return f"({sign}{out})"

    def pow(self, base: sympy.Basic, exp: sympy.Basic) -> str:
        if exp.is_number and not exp.free_symbols:
            if exp.is_negative:
                return f"jnp.reciprocal({self.pow(base, -exp)})"
            if exp == 1:
                return self(base)
            b = self(base)
            if exp.is_Integer or (exp.is_Float and float(exp).is_integer()):
                # A Python int exponent: `lax.integer_pow`, exact and safe for negative bases.
                return f"({b} ** {int(exp)})"
            if exp.is_Rational and exp.q == 2:
                root = f"jnp.sqrt({b})"
                return root if exp.p == 1 else f"({root} ** {int(exp.p)})"
            return f"jnp.power({b}, {self.constant(exp)})"
        return f"jnp.power({self(base)}, {self(exp)})"

    def piecewise(self, e: sympy.Piecewise) -> str:
        pieces = list(e.args)
        expr, cond = pieces[-1]
        if cond is sympy.true:
            out = self(expr)
            pieces = pieces[:-1]
        else:
            out = self.constant(sympy.nan)
        for expr, cond in reversed(pieces):
            out = f"jnp.where({self(cond)}, {self(expr)}, {out})"
        return out


def _as_expr(e: Any) -> sympy.Basic:
    out = sympy.sympify(e)
    if not isinstance(out, sympy.Basic):
        raise TypeError(f"not a sympy expression: {e!r}")
    return out


@functools.lru_cache(maxsize=512)
def _compile(exprs: tuple[sympy.Basic, ...], symbols: tuple[sympy.Symbol, ...], cse: bool):
    for s in symbols:
        if not isinstance(s, sympy.Symbol):
            raise TypeError(f"symbols must be sympy Symbols, got {s!r}")
    if len(set(symbols)) != len(symbols):
        raise ValueError(f"repeated symbol in {symbols}")
    known = set(symbols)
    unknown = set().union(*(e.free_symbols for e in exprs)) - known if exprs else set()
    if unknown:
        names = ", ".join(sorted(str(s) for s in unknown))
        raise ValueError(
            f"the expressions contain the symbol(s) {names}, which are not among the inputs "
            f"{tuple(str(s) for s in symbols)}"
        )

    args = [f"_a{i}" for i in range(len(symbols))]
    names: dict[sympy.Basic, str] = dict(zip(symbols, args, strict=True))
    if cse:
        tmp = sympy.numbered_symbols("_cse", cls=sympy.Dummy)
        replacements, reduced = sympy.cse(list(exprs), symbols=tmp)
    else:
        replacements, reduced = [], list(exprs)

    printer = _Printer(names)
    body: list[str] = []
    for i, (sym, sub) in enumerate(replacements):
        code = printer(sub)
        names[sym] = f"_s{i}"
        body.append(f"    _s{i} = {code}")
    outputs = [printer(e) for e in reduced]

    arglist = ", ".join(args)
    lines = [f"def _compiled({arglist}):"]
    lines.append(f"    _dt = _working_dtype({arglist})")
    lines.append(f"    _shape = jnp.broadcast_shapes({''.join(f'jnp.shape({a}), ' for a in args)})")
    lines.extend(f"    {a} = jnp.asarray({a}, _dt)" for a in args)
    for value, name in printer.constants.items():
        lines.append(f"    {name} = jnp.asarray(float({str(float(value))!r}), _dt)")
    lines.extend(body)
    lines.append("    return (")
    lines.extend(f"        jnp.broadcast_to({o}, _shape)," for o in outputs)
    lines.append("    )")
    source = "\n".join(lines) + "\n"

    filename = f"<diffrax_vi.symbolic-{next(_counter)}>"
    namespace = dict(_NAMESPACE)
    exec(compile(source, filename, "exec"), namespace)  # noqa: S102 - generated from sympy
    # Keep the source visible to tracebacks and `inspect`.
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    fn = namespace["_compiled"]
    fn.source = source
    return fn


def compile_exprs(
    exprs: Sequence[Any], symbols: Sequence[sympy.Symbol], *, cse: bool = True
) -> Callable[..., tuple[Array, ...]]:
    """Compile sympy expressions into one JAX function of the symbol values.

    **Arguments:**

    - `exprs`: the expressions (anything `sympy.sympify` accepts).
    - `symbols`: the inputs, in call order; every free symbol of `exprs` must be one of them.
    - `cse`: share common subexpressions (`sympy.cse`) across all of `exprs`.

    **Returns:**

    `f(*values) -> tuple` of the expression values. Inputs broadcast against each other; every
    output has the broadcast shape and the common floating dtype of the inputs (integer inputs
    give the default float). Constants (rationals, floats, `π`, ...) are cast to that dtype,
    so a float32 or float16 call stays in its precision. The generated code calls only
    `jax.numpy` (and `jax.scipy.special.erf`); its source is `f.source`.

    Supported: `+ − × /`, integer, half-integer and real powers, `exp log expm1 log1p`, the
    trigonometric and hyperbolic functions and their inverses, `erf erfc sqrt Abs sign floor
    ceiling`, `Max Min Heaviside Piecewise`, relations and `And Or Not`. Non-smooth functions
    are differentiated almost everywhere (`DiracDelta` is zero).

    Compiled functions are cached: compiling the same expressions again is free.
    """
    exprs_t = tuple(_as_expr(e) for e in exprs)
    symbols_t = tuple(symbols)
    return _compile(exprs_t, symbols_t, bool(cse))


# ---------------------------------------------------------------------------------------------
# Activations
# ---------------------------------------------------------------------------------------------


def _gelu_tanh(x):
    inner = sympy.sqrt(2 / sympy.pi) * (x + sympy.Rational(44715, 1000000) * x**3)
    return x / 2 * (1 + sympy.tanh(inner))


def _gelu_erf(x):
    return x / 2 * (1 + sympy.erf(x / sympy.sqrt(2)))


_SYMPY_ACTIVATIONS: dict[Any, Callable[[sympy.Symbol], sympy.Expr]] = {
    _act.tanh: sympy.tanh,
    _act.sigmoid: lambda x: 1 / (1 + sympy.exp(-x)),
    _act.sin: sympy.sin,
    _act.gelu: _gelu_tanh,
    _act.gelu_exact: _gelu_erf,
    _act.elu: lambda x: sympy.Piecewise((x, x > 0), (expm1(x), True)),
    jnp.tanh: sympy.tanh,
    jnp.sin: sympy.sin,
    jax.nn.sigmoid: lambda x: 1 / (1 + sympy.exp(-x)),
}


def sympy_activation(activation: Callable) -> sympy.Lambda:
    """The sympy form `x ↦ σ(x)` of an activation of `diffrax_vi._activations`.

    Knows `tanh`, `sigmoid`, `sin`, `gelu` (tanh approximation, as
    `jax.nn.gelu(approximate=True)`), `gelu_exact` (with `erf`), `elu` and `relu_k(k)` (a
    `Piecewise`, so its derivatives are exact piecewise polynomials). Any other activation may
    provide a method `sympy_form(x)` returning its expression in the sympy symbol `x`.

    Raises `ValueError` for an activation with no known sympy form.
    """
    x = sympy.Symbol("x", real=True)
    if isinstance(activation, _act.ReLUk):
        k = activation.k
        expr = sympy.Piecewise((x**k, x > 0), (sympy.S.Zero, True))
    elif hasattr(activation, "sympy_form"):
        expr = _as_expr(activation.sympy_form(x))
    else:
        try:
            form = _SYMPY_ACTIVATIONS.get(activation)
        except TypeError:  # unhashable callable
            form = None
        if form is None:
            raise ValueError(
                f"no sympy form is known for the activation {_act.activation_name(activation)}; "
                "sympy derivatives support tanh, sigmoid, sin, gelu, gelu_exact, elu and "
                "relu_k(k) (or an activation with a `sympy_form(x)` method). Use "
                "derivatives='autodiff' instead."
            )
        expr = form(x)
    return sympy.Lambda(x, expr)


# ---------------------------------------------------------------------------------------------
# Closed-form derivative kernels of a curve q(τ; p_1..p_P)
# ---------------------------------------------------------------------------------------------


class CurveKernels(NamedTuple):
    """Compiled kernels of a curve `q(τ; p_1..p_P)`, each a function of `(p_1..p_P, τ)`:
    `value` → `(q,)`, `velocity` → `(q',)`, `acceleration` → `(q'',)` (`' = ∂/∂τ`),
    `d_value` → `(∂q/∂p_k)_k`, `d_velocity` → `(∂q'/∂p_k)_k`."""

    value: Callable[..., tuple[Array, ...]]
    velocity: Callable[..., tuple[Array, ...]]
    acceleration: Callable[..., tuple[Array, ...]]
    d_value: Callable[..., tuple[Array, ...]]
    d_velocity: Callable[..., tuple[Array, ...]]


@functools.lru_cache(maxsize=256)
def _curve_kernels(expr, tau, params, cse) -> CurveKernels:
    symbols = (*params, tau)
    velocity = sympy.diff(expr, tau)
    return CurveKernels(
        value=compile_exprs([expr], symbols, cse=cse),
        velocity=compile_exprs([velocity], symbols, cse=cse),
        acceleration=compile_exprs([sympy.diff(velocity, tau)], symbols, cse=cse),
        d_value=compile_exprs([sympy.diff(expr, p) for p in params], symbols, cse=cse),
        d_velocity=compile_exprs([sympy.diff(velocity, p) for p in params], symbols, cse=cse),
    )


def curve_kernels(
    expr: Any, tau: sympy.Symbol, params: Sequence[sympy.Symbol], *, cse: bool = True
) -> CurveKernels:
    """Differentiate the curve `expr` in `tau` and in each of `params` with sympy and compile
    the kernels (once per expression, cached)."""
    return _curve_kernels(_as_expr(expr), tau, tuple(params), bool(cse))


def _is_zero(tangent) -> bool:
    return isinstance(tangent, SymbolicZero)


def _sum0(x: Array) -> Array:
    return jnp.sum(x, axis=0)


def _identity(x: Array) -> Array:
    return x


@functools.lru_cache(maxsize=256)
def _curve_function(expr, tau, params, cse, reduce) -> Callable[..., Array]:
    kernels = _curve_kernels(expr, tau, params, cse)
    red = _sum0 if reduce else _identity

    def tangent(d_params, d_tau, primals, tangents):
        *dps, dt = tangents
        out = None
        active = [k for k, dp in enumerate(dps) if not _is_zero(dp)]
        if active:
            partials = d_params(*primals)
            terms = [partials[k] * dps[k] for k in active]
            out = red(functools.reduce(jnp.add, terms))
        if not _is_zero(dt):
            term = d_tau(*primals) * dt
            out = term if out is None else out + term
        return out

    def acceleration(*args):
        # q'' is only differentiated further by plain autodiff of its compiled code.
        return red(kernels.acceleration(*args)[0])

    @jax.custom_jvp
    def velocity(*args):
        return red(kernels.velocity(*args)[0])

    @jax.custom_jvp
    def value(*args):
        return red(kernels.value(*args)[0])

    def value_jvp(primals, tangents):
        out = value(*primals)
        dq = tangent(kernels.d_value, velocity, primals, tangents)
        return out, jnp.zeros_like(out) if dq is None else dq

    def velocity_jvp(primals, tangents):
        out = velocity(*primals)
        dv = tangent(kernels.d_velocity, acceleration, primals, tangents)
        return out, jnp.zeros_like(out) if dv is None else dv

    value.defjvp(value_jvp, symbolic_zeros=True)
    velocity.defjvp(velocity_jvp, symbolic_zeros=True)
    value.velocity = velocity  # type: ignore[attr-defined]
    value.kernels = kernels  # type: ignore[attr-defined]
    return value


def curve_function(
    expr: Any,
    tau: sympy.Symbol,
    params: Sequence[sympy.Symbol],
    *,
    cse: bool = True,
    reduce: bool = False,
) -> Callable[..., Array]:
    """The curve `q(τ; p_1..p_P)` as a JAX function `f(p_1, .., p_P, τ)` with sympy derivatives.

    `f` is a `jax.custom_jvp` function: its tangent is `Σ_k ∂q/∂p_k dp_k + q' dτ` with the
    compiled closed forms, where `q' = f.velocity` is again a `custom_jvp` function (tangent
    `Σ_k ∂q'/∂p_k dp_k + q'' dτ`). So `jax.jvp` in `τ` gives `q'`, a vector-Jacobian product in
    the parameters uses `∂q/∂p_k` and `∂q'/∂p_k`, and JAX differentiates those compiled
    gradients for anything of higher order (the Newton Jacobian of the action gradient).

    The inputs broadcast against each other (e.g. per-neuron arrays `(S, D)` and a scalar `τ`).
    With `reduce=True` the broadcast values are summed over their first axis (over the
    neurons of a network whose `expr` is one neuron's contribution); `τ` must then be a
    scalar. Built once per expression (cached).
    """
    return _curve_function(_as_expr(expr), tau, tuple(params), bool(cse), bool(reduce))


def symbolic_curve_evaluate(
    expr: Any, tau_symbol: sympy.Symbol, param_symbols: Sequence[sympy.Symbol], *, cse: bool = True
) -> Callable[[Array, Array], Array]:
    """`evaluate(θ, τ)` of an ansatz whose curve, the same for every coordinate, is `expr`.

    `θ` has one row per entry of `param_symbols` (shape `(P, D)`, or `(P,)` for one curve);
    returns `q(τ; θ[:, d])` for every `d`, shape `(D,)`, with the sympy derivatives of
    `curve_function`. `τ` is a scalar (vmap for many).
    """
    f = curve_function(expr, tau_symbol, param_symbols, cse=cse)
    n = len(param_symbols)

    def evaluate(theta: Array, tau) -> Array:
        if theta.shape[0] != n:
            raise ValueError(f"expected {n} parameter rows, got an array of shape {theta.shape}")
        return f(*theta, jnp.asarray(tau, theta.dtype))

    return evaluate
