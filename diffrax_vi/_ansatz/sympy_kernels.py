"""The sympy derivative backend of the network ansätze (`derivatives="sympy"`).

A shallow network's neuron `α σ(w τ + β)`, or a two-hidden-layer network's whole curve, is
differentiated by sympy and compiled once (per activation and widths) by
`diffrax_vi._codegen`; `ShallowNetBasis` and `DenseNetBasis` import this module only when
asked for sympy derivatives, so sympy is not loaded otherwise.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax.numpy as jnp
import sympy
from jaxtyping import Array

from .._codegen import curve_function, symbolic_curve_evaluate, sympy_activation

__all__ = [
    "dense_expression",
    "shallow_neuron_expression",
    "symbolic_dense_evaluate",
    "symbolic_shallow_evaluate",
]

_TAU = sympy.Symbol("tau", real=True)


@functools.lru_cache(maxsize=64)
def shallow_neuron_expression(activation: Callable) -> tuple[sympy.Expr, tuple[sympy.Symbol, ...]]:
    """One neuron's contribution `α σ(w τ + β)` and its parameter symbols `(α, w, β)`; the
    curve symbol is `τ` (`sympy.Symbol("tau", real=True)`)."""
    sigma = sympy_activation(activation)
    alpha, w, beta = sympy.symbols("alpha w beta", real=True)
    return alpha * sigma(w * _TAU + beta), (alpha, w, beta)


def symbolic_shallow_evaluate(basis) -> Callable[[Array, Array], Array]:
    """`evaluate(θ, τ)` of a `ShallowNetBasis` with sympy derivatives.

    The neuron `α σ(w τ + β)` is differentiated by sympy and compiled once per activation; the
    network sums it over the neurons of `basis.split(θ)` (mirrored pairs are expanded there,
    and JAX differentiates through that map). `τ` is a scalar.
    """
    expr, params = shallow_neuron_expression(basis.activation)
    network = curve_function(expr, _TAU, params, reduce=True)

    def evaluate(theta: Array, tau) -> Array:
        alpha, w, beta = basis.split(theta)
        return network(alpha, w, beta, jnp.asarray(tau, theta.dtype))

    return evaluate


@functools.lru_cache(maxsize=64)
def dense_expression(
    activation: Callable, width1: int, width2: int
) -> tuple[sympy.Expr, tuple[sympy.Symbol, ...]]:
    """The curve `Σ_k γ_k σ(Σ_i A_ki σ(a_i τ + e_i) + g_k)` of a two-hidden-layer network and
    its `2S₁ + S₂S₁ + 2S₂` parameter symbols in `DenseNetBasis`'s flat order
    `[a | e | A column-major | g | γ]`; the curve symbol is `τ`."""
    sigma = sympy_activation(activation)
    s1, s2 = width1, width2
    a = sympy.symbols(f"a0:{s1}", real=True)
    e = sympy.symbols(f"e0:{s1}", real=True)
    big_a = [[sympy.Symbol(f"A{k}_{i}", real=True) for i in range(s1)] for k in range(s2)]
    g = sympy.symbols(f"g0:{s2}", real=True)
    gamma = sympy.symbols(f"gamma0:{s2}", real=True)
    first = [sigma(a[i] * _TAU + e[i]) for i in range(s1)]
    expr = sympy.Add(
        *(
            gamma[k] * sigma(sympy.Add(*(big_a[k][i] * first[i] for i in range(s1))) + g[k])
            for k in range(s2)
        )
    )
    columns = tuple(big_a[k][i] for i in range(s1) for k in range(s2))
    return expr, (*a, *e, *columns, *g, *gamma)


def symbolic_dense_evaluate(basis) -> Callable[[Array, Array], Array]:
    """`evaluate(θ, τ)` of a `DenseNetBasis` with sympy derivatives (`θ` of shape `(NP, D)`).

    The whole curve of one coordinate is one expression in its `NP` parameters, differentiated
    and compiled once per `(activation, width1, width2)`; sympy's time grows quickly with the
    widths.
    """
    expr, params = dense_expression(basis.activation, basis.width1, basis.width2)
    return symbolic_curve_evaluate(expr, _TAU, params)
