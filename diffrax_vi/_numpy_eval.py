"""A small program evaluated in NumPy while a solve is being traced.

What a step decides when it is traced (a constant kinetic matrix's value, whether a varying
one is regular at a random state) needs the values of a few derivatives of the Lagrangian at
known inputs. Compiling a program for them costs tens of milliseconds of every first call;
evaluating its jaxpr equation by equation in NumPy costs well under one. Only the common
elementwise, shape and contraction primitives are known here: a program that uses any other
raises `Unsupported`, and the caller compiles it instead.
"""

from __future__ import annotations

import numpy as np
from jax.extend import core as jex_core

__all__ = ["Unsupported", "evaluate_jaxpr"]


class Unsupported(Exception):
    """The program uses a primitive that this evaluator does not know."""


def _broadcast_in_dim(x, *, shape, broadcast_dimensions, **_):
    expanded = np.reshape(x, [x.shape[broadcast_dimensions.index(d)]
                              if d in broadcast_dimensions else 1 for d in range(len(shape))])
    return np.broadcast_to(expanded, shape).copy()


def _iota(*, dtype, shape, dimension, **_):
    ramp = np.arange(shape[dimension], dtype=dtype)
    return _broadcast_in_dim(ramp, shape=shape, broadcast_dimensions=(dimension,))


def _pad(x, value, *, padding_config):
    for axis, (low, high, interior) in enumerate(padding_config):
        if interior:
            n = x.shape[axis]
            shape = list(x.shape)
            shape[axis] = n + (n - 1) * interior if n else 0
            spread = np.full(shape, value, x.dtype)
            index = [slice(None)] * x.ndim
            index[axis] = slice(None, None, interior + 1)
            spread[tuple(index)] = x
            x = spread
        index = [slice(None)] * x.ndim
        index[axis] = slice(max(-low, 0), x.shape[axis] - max(-high, 0))
        x = x[tuple(index)]
        widths = [(0, 0)] * x.ndim
        widths[axis] = (max(low, 0), max(high, 0))
        x = np.pad(x, widths, constant_values=value)
    return x


def _slice(x, *, start_indices, limit_indices, strides, **_):
    strides = strides or (1,) * x.ndim
    return x[tuple(slice(a, b, s) for a, b, s in
                   zip(start_indices, limit_indices, strides, strict=True))]


def _split(x, *, sizes, axis):
    return np.split(x, np.cumsum(sizes)[:-1], axis=axis)


def _reshape(x, *, new_sizes, dimensions=None, **_):
    if dimensions is not None:
        raise Unsupported("reshape with dimensions")
    return np.reshape(x, new_sizes)


def _dot_general(a, b, *, dimension_numbers, preferred_element_type=None, **_):
    (a_contract, b_contract), (a_batch, b_batch) = dimension_numbers
    letters = iter("abcdefghijklmnopqrstuvwxyz")
    a_sub = [next(letters) for _ in range(a.ndim)]
    b_sub = [None] * b.ndim
    for i, j in zip(a_contract, b_contract, strict=True):
        b_sub[j] = a_sub[i]
    for i, j in zip(a_batch, b_batch, strict=True):
        b_sub[j] = a_sub[i]
    b_sub = [s if s is not None else next(letters) for s in b_sub]
    batch = [a_sub[i] for i in a_batch]
    free_a = [s for i, s in enumerate(a_sub) if i not in a_contract and i not in a_batch]
    free_b = [s for j, s in enumerate(b_sub) if j not in b_contract and j not in b_batch]
    spec = f"{''.join(a_sub)},{''.join(b_sub)}->{''.join(batch + free_a + free_b)}"
    out = np.einsum(spec, a, b)
    dtype = preferred_element_type or np.result_type(a, b)
    return np.asarray(out, dtype)


def _select_n(which, *cases):
    return np.choose(np.asarray(which, np.int64), cases)


def _reduce(fn):
    def reduce(x, *, axes, **_):
        return np.asarray(fn(x, axis=tuple(axes)), x.dtype)

    return reduce


def _same_dtype(fn):
    def apply(*args, **_):
        return np.asarray(fn(*args), args[0].dtype)

    return apply


_RULES = {
    "add": _same_dtype(np.add),
    "add_any": _same_dtype(np.add),
    "sub": _same_dtype(np.subtract),
    "mul": _same_dtype(np.multiply),
    "div": lambda a, b: np.asarray(a / b if a.dtype.kind in "fc" else np.trunc(a / b), a.dtype),
    "neg": _same_dtype(np.negative),
    "max": _same_dtype(np.maximum),
    "min": _same_dtype(np.minimum),
    "abs": _same_dtype(np.abs),
    "sign": _same_dtype(np.sign),
    "sqrt": _same_dtype(np.sqrt),
    "rsqrt": _same_dtype(lambda x: 1 / np.sqrt(x)),
    "exp": _same_dtype(np.exp),
    "log": _same_dtype(np.log),
    "log1p": _same_dtype(np.log1p),
    "expm1": _same_dtype(np.expm1),
    "exp2": _same_dtype(np.exp2),
    "sin": _same_dtype(np.sin),
    "cos": _same_dtype(np.cos),
    "tan": _same_dtype(np.tan),
    "tanh": _same_dtype(np.tanh),
    "sinh": _same_dtype(np.sinh),
    "cosh": _same_dtype(np.cosh),
    "asin": _same_dtype(np.arcsin),
    "acos": _same_dtype(np.arccos),
    "atan": _same_dtype(np.arctan),
    "atan2": _same_dtype(np.arctan2),
    "logistic": _same_dtype(lambda x: 1 / (1 + np.exp(-x))),
    "integer_pow": lambda x, *, y: np.asarray(x**y, x.dtype),
    "pow": _same_dtype(np.power),
    "square": _same_dtype(np.square),
    "eq": lambda a, b: np.equal(a, b),
    "ne": lambda a, b: np.not_equal(a, b),
    "lt": lambda a, b: np.less(a, b),
    "le": lambda a, b: np.less_equal(a, b),
    "gt": lambda a, b: np.greater(a, b),
    "ge": lambda a, b: np.greater_equal(a, b),
    "and": _same_dtype(np.bitwise_and),
    "or": _same_dtype(np.bitwise_or),
    "not": _same_dtype(np.invert),
    "select_n": _select_n,
    "convert_element_type": lambda x, *, new_dtype, **_: np.asarray(x, new_dtype),
    "broadcast_in_dim": _broadcast_in_dim,
    "iota": _iota,
    "reshape": _reshape,
    "squeeze": lambda x, *, dimensions: np.squeeze(x, tuple(dimensions)),
    "expand_dims": lambda x, *, dimensions: np.expand_dims(x, tuple(dimensions)),
    "transpose": lambda x, *, permutation: np.transpose(x, permutation),
    "slice": _slice,
    "pad": _pad,
    "concatenate": lambda *xs, dimension: np.concatenate(xs, axis=dimension),
    "split": _split,
    "stack": lambda *xs, axis: np.stack(xs, axis=axis),
    "unstack": lambda x, *, axis: list(np.moveaxis(x, axis, 0)),
    "reduce_sum": _reduce(np.sum),
    "reduce_max": _reduce(np.max),
    "reduce_min": _reduce(np.min),
    "dot_general": _dot_general,
    "copy": lambda x: np.array(x),
}

# Primitives that call a program of their own, found in this parameter.
_CALLS = {"pjit": "jaxpr", "jit": "jaxpr", "closed_call": "call_jaxpr",
          "custom_jvp_call": "call_jaxpr", "custom_vjp_call": "call_jaxpr",
          "remat": "jaxpr", "checkpoint": "jaxpr"}


def _run(jaxpr, consts, args):
    env = {}

    def read(atom):
        if isinstance(atom, jex_core.Literal):
            return np.asarray(atom.val, atom.aval.dtype)
        return env[atom]

    for var, value in zip(jaxpr.constvars, consts, strict=True):
        env[var] = np.asarray(value)
    for var, value in zip(jaxpr.invars, args, strict=True):
        env[var] = np.asarray(value)
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        ins = [np.asarray(read(v)) for v in eqn.invars]
        if name in _CALLS:
            inner = eqn.params[_CALLS[name]]
            closed = getattr(inner, "jaxpr", inner)
            inner_consts = getattr(inner, "consts", ())
            outs = _run(closed, inner_consts, ins)
        elif name in _RULES:
            params = {k: v for k, v in eqn.params.items() if k not in ("sharding", "accuracy")}
            try:
                outs = _RULES[name](*ins, **params)
            except TypeError as error:  # parameters this rule does not read
                raise Unsupported(f"{name}: {error}") from error
        else:
            raise Unsupported(name)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for var, value in zip(eqn.outvars, outs, strict=True):
            value = np.asarray(value)
            if value.shape != var.aval.shape:
                raise Unsupported(f"{name}: shape {value.shape} where {var.aval.shape}")
            env[var] = value.astype(var.aval.dtype, copy=False)
    return [np.asarray(read(v)) for v in jaxpr.outvars]


def evaluate_jaxpr(closed, *args) -> list[np.ndarray]:
    """The outputs of the closed jaxpr `closed` at the NumPy arrays `args` (its flat inputs),
    computed in NumPy; raises `Unsupported` where a primitive is not known here."""
    with np.errstate(all="ignore"):
        return _run(closed.jaxpr, closed.consts, args)
