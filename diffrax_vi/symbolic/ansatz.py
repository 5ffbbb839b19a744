"""A user-written ansatz in absolute time (`SymbolicAnsatz`, also named `VISEBasis`)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import sympy
from jaxtyping import Array

from .._ansatz.base import AbstractBasis
from .._codegen import curve_function

__all__ = ["SymbolicAnsatz", "VISEBasis"]


def _sympify(expr: Any, where: str) -> sympy.Expr:
    try:
        out = sympy.sympify(expr)
    except (sympy.SympifyError, TypeError) as err:
        raise TypeError(f"{where} is not a sympy expression: {expr!r}") from err
    if not isinstance(out, sympy.Expr):
        raise TypeError(f"{where} must be a sympy expression, got {type(out).__name__}: {out}")
    return out


@functools.lru_cache(maxsize=256)
def _coordinate_curve(expr: sympy.Expr, t: sympy.Symbol, weights: tuple[sympy.Symbol, ...]):
    """The compiled curve `q(W_1..W_n, t)` of one coordinate, with sympy derivatives.

    The symbols are replaced by real ones first, so that sympy differentiates `Abs`, `sign`
    etc. as real functions."""
    real = {s: sympy.Dummy(s.name, real=True) for s in (t, *weights)}
    return curve_function(expr.xreplace(real), real[t], tuple(real[w] for w in weights))


class SymbolicAnsatz(AbstractBasis):
    """A trial trajectory written by hand as sympy expressions in absolute time.

    Coordinate `d` follows `q_d(t; W_d)`, an expression in the time symbol `t` and its own
    weights `W_d = (W_{d,1}, .., W_{d,n_d})` (the counts may differ between coordinates), e.g.
    `W1*cos(W2*t + W3)`. The derivatives the solve needs (`∂q/∂t`, `∂q/∂W_k`, `∂²q/∂t∂W_k`)
    are taken by sympy and compiled to JAX once per expression (`diffrax_vi._codegen`), then
    used as closed-form derivatives by JAX's `custom_jvp`. With it the solver is a VISE
    (variational integrator with a symbolic ansatz): use it with the free-endpoint formulation
    (the default) and `InitialWeights` as the seed.

    The expressions are in absolute time, not in the local time `τ ∈ [0, 1]` of the other
    ansätze: the solver binds each step with `at_step(t_n, h)`, after which `evaluate(θ, τ)` is
    `q(W, t_n + τh)`. Unbound, `evaluate(θ, t)` reads its second argument as the absolute
    time. Since the curve does not depend on the step, the previous step's weights are
    themselves the continuation to the next step (`advance` is the identity), so
    `PreviousStep` warm starts work as well.

    The parameters are a tuple of `D` one-dimensional arrays, `θ[d]` holding `W_d` in the order
    of `weights[d]`.

    **Arguments:**

    - `exprs`: `D` sympy expressions, one per coordinate.
    - `weights`: `D` sequences of sympy symbols, the weights of each coordinate (with `D = 1`
      a single flat sequence of symbols also works).
    - `t`: the time symbol.

    Every symbol of `exprs[d]` must be `t` or one of `weights[d]`.
    """

    exprs: tuple[sympy.Expr, ...] = eqx.field(static=True)
    weights: tuple[tuple[sympy.Symbol, ...], ...] = eqx.field(static=True)
    t: sympy.Symbol = eqx.field(static=True)
    t_start: Array | None = None
    h: Array | None = None

    can_advance: ClassVar[bool] = True

    def __init__(
        self,
        exprs: Sequence[Any],
        weights: Sequence[Sequence[sympy.Symbol]] | Sequence[sympy.Symbol],
        t: sympy.Symbol,
        t_start: Array | None = None,
        h: Array | None = None,
    ):
        if isinstance(exprs, str | sympy.Basic) or not isinstance(exprs, Sequence):
            raise TypeError(
                "exprs must be a sequence of sympy expressions, one per coordinate; got "
                f"{type(exprs).__name__}"
            )
        self.exprs = tuple(_sympify(e, f"exprs[{d}]") for d, e in enumerate(exprs))
        if isinstance(weights, sympy.Basic) or not isinstance(weights, Sequence):
            raise TypeError(
                f"weights must be a sequence of weight-symbol sequences; got {weights!r}"
            )
        weights = tuple(weights)
        if weights and all(isinstance(w, sympy.Symbol) for w in weights):
            if len(self.exprs) != 1:
                raise ValueError(
                    f"{len(self.exprs)} expressions need {len(self.exprs)} weight sequences "
                    "(one per coordinate); got one flat sequence of symbols"
                )
            weights = (weights,)
        out = []
        for d, w in enumerate(weights):
            if isinstance(w, sympy.Basic) or not isinstance(w, Sequence | sympy.MatrixBase):
                raise TypeError(f"weights[{d}] must be a sequence of sympy symbols, got {w!r}")
            out.append(tuple(w))
        self.weights = tuple(out)
        self.t = t
        self.t_start = t_start
        self.h = h

    def __check_init__(self):
        if not isinstance(self.t, sympy.Symbol):
            raise TypeError(f"t must be a sympy Symbol, got {self.t!r}")
        dim = len(self.exprs)
        if dim == 0:
            raise ValueError("SymbolicAnsatz needs at least one expression")
        if len(self.weights) != dim:
            raise ValueError(
                f"got {dim} expression(s) but {len(self.weights)} weight sequence(s); give one "
                "weight sequence per coordinate"
            )
        owner = {}
        for d, w in enumerate(self.weights):
            for s in w:
                if not isinstance(s, sympy.Symbol):
                    raise TypeError(f"weights[{d}] must hold sympy Symbols; got {s!r}")
                owner.setdefault(s, d)
            if not w:
                raise ValueError(f"coordinate {d} has no weights")
            if len(set(w)) != len(w):
                raise ValueError(f"weights[{d}] repeats a symbol: {w}")
            if self.t in w:
                raise ValueError(
                    f"the time symbol {self.t} cannot also be a weight (coordinate {d})"
                )
        for d, (expr, w) in enumerate(zip(self.exprs, self.weights, strict=True)):
            extra = expr.free_symbols - {self.t} - set(w)
            if extra:
                notes = []
                for s in sorted(extra, key=str):
                    other = owner.get(s)
                    if other is None:
                        notes.append(f"{s} (neither the time symbol {self.t} nor a weight)")
                    else:
                        notes.append(f"{s} (a weight of coordinate {other}, not of {d})")
                raise ValueError(
                    f"the expression of coordinate {d}, {expr}, contains the unknown symbol(s) "
                    + ", ".join(notes)
                )

    # -- parameters -----------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        """Number of coordinates `D`."""
        return len(self.exprs)

    def num_params(self) -> int:
        """Total number of weights over all coordinates."""
        return sum(len(w) for w in self.weights)

    def zeros(self, dim: int, dtype) -> tuple[Array, ...]:
        self._check_dim(dim)
        return tuple(jnp.zeros(len(w), dtype) for w in self.weights)

    def params_from(self, values, dtype) -> tuple[Array, ...]:
        """Weights from nested sequences `((W_{1,1}, ..), (W_{2,1}, ..), ..)` (with `D = 1` a
        flat sequence also works)."""
        if isinstance(values, tuple | list) and len(values) and np.ndim(values[0]) == 0:
            values = (values,)
        if not isinstance(values, tuple | list) or len(values) != self.dim:
            n = len(values) if isinstance(values, tuple | list) else type(values).__name__
            raise ValueError(
                f"initial weights need one sequence per coordinate ({self.dim}); got {n}"
            )
        out = []
        for d, (v, w) in enumerate(zip(values, self.weights, strict=True)):
            arr = jnp.asarray(v, dtype)
            if arr.shape != (len(w),):
                raise ValueError(
                    f"coordinate {d} has {len(w)} weights {w}; got initial values of shape "
                    f"{arr.shape}"
                )
            out.append(arr)
        return tuple(out)

    def _check_dim(self, dim: int) -> None:
        if dim != self.dim:
            raise ValueError(f"the ansatz has {self.dim} coordinate(s) but the state has {dim}")

    # -- curve ----------------------------------------------------------------------------------
    def _curves(self) -> tuple[Callable[..., Array], ...]:
        return tuple(
            _coordinate_curve(e, self.t, w) for e, w in zip(self.exprs, self.weights, strict=True)
        )

    def at_step(self, t, h) -> SymbolicAnsatz:
        return SymbolicAnsatz(self.exprs, self.weights, self.t, t_start=t, h=h)

    def time(self, tau) -> Array:
        """The absolute time of local time `τ` on the bound step (`τ` itself if unbound)."""
        if self.t_start is None:
            return tau
        return self.t_start + tau * self.h

    def evaluate(self, theta, tau) -> Array:
        if not isinstance(theta, tuple | list) or len(theta) != self.dim:
            raise ValueError(
                f"SymbolicAnsatz parameters are a tuple of {self.dim} weight arrays; got "
                f"{type(theta).__name__}"
                + (f" of length {len(theta)}" if isinstance(theta, tuple | list) else "")
            )
        dtype = theta[0].dtype
        t = self.time(jnp.asarray(tau, dtype))
        return jnp.stack([curve(*w, t) for curve, w in zip(self._curves(), theta, strict=True)])

    def advance(self, theta, ratio):
        # Absolute time: the same weights describe the curve on the next step.
        del ratio
        return theta

    def check(self, dtype) -> None:
        zeros = self.zeros(self.dim, dtype)
        out = jax.eval_shape(self.evaluate, zeros, jnp.zeros((), dtype))
        if out.dtype != jnp.dtype(dtype):
            raise ValueError(f"{self!r} evaluates to {out.dtype} for {jnp.dtype(dtype)} weights")

    def __repr__(self):
        exprs = ", ".join(str(e) for e in self.exprs)
        return f"SymbolicAnsatz([{exprs}], t={self.t})"


VISEBasis = SymbolicAnsatz
