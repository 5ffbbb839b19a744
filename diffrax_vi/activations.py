"""Activation functions for network ansätze, and the working-precision check.

Every activation here maps an array of dtype T to an array of dtype T, for T in float16,
float32 and float64. Activations are hashable (they sit in static fields of solvers), so
parametrised ones are small frozen dataclasses rather than closures.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

__all__ = [
    "tanh",
    "sigmoid",
    "sin",
    "gelu",
    "elu",
    "relu_k",
    "ReLUk",
    "check_activation",
    "activation_name",
]


def tanh(x):
    """Hyperbolic tangent."""
    return jnp.tanh(x)


def sigmoid(x):
    """Logistic sigmoid `1 / (1 + exp(-x))`."""
    return jax.nn.sigmoid(x)


def sin(x):
    """Sine (a periodic, smooth activation)."""
    return jnp.sin(x)


def gelu(x):
    """Gaussian error linear unit, tanh approximation (as in the reference's benchmarks)."""
    return jax.nn.gelu(x, approximate=True)


def elu(x):
    """Exponential linear unit with unit scale."""
    return jax.nn.elu(x)


@dataclasses.dataclass(frozen=True)
class ReLUk:
    """`max(0, x)^k`: C^(k-1), positively homogeneous of degree `k`.

    The Newton Jacobian of a variational step differentiates the activation three times,
    so `k >= 3` keeps it continuous; `k = 2` still works away from the kinks.
    """

    k: int

    def __post_init__(self):
        if not isinstance(self.k, int) or isinstance(self.k, bool) or self.k < 1:
            raise ValueError(f"relu_k needs an integer power k >= 1, got {self.k!r}")

    def __call__(self, x):
        return jnp.maximum(x, jnp.zeros((), x.dtype)) ** self.k

    def __repr__(self):
        return f"relu_k({self.k})"


def relu_k(k: int) -> ReLUk:
    """The rectified power unit `max(0, x)^k` (the reference's `relu_k`)."""
    return ReLUk(k)


def activation_name(activation: Callable) -> str:
    """A readable name for an activation, for error messages and reports."""
    if isinstance(activation, ReLUk):
        return repr(activation)
    return getattr(activation, "__name__", repr(activation))


def check_activation(activation: Callable, dtype) -> None:
    """Refuse an activation that does not stay in the working precision.

    Evaluates `activation(T(1/3))` for the working dtype `T` (eagerly, also while tracing)
    and raises `ValueError` if the result is not a finite scalar of dtype `T`: an activation
    written with a float64 constant silently promotes float16/float32 runs to float64.
    """
    dtype = jnp.dtype(dtype)
    name = activation_name(activation)
    with jax.ensure_compile_time_eval():
        try:
            out = activation(jnp.asarray(1.0 / 3.0, dtype=dtype))
        except Exception as err:  # noqa: BLE001 - re-raised with context
            raise ValueError(
                f"activation {name} cannot be evaluated at dtype {dtype}: {err}"
            ) from err
        out_dtype = jnp.result_type(out)
        if jnp.shape(out) != ():
            raise ValueError(
                f"activation {name} must act elementwise; a scalar input gave shape "
                f"{jnp.shape(out)}"
            )
        if out_dtype != dtype:
            raise ValueError(
                f"activation {name} promotes {dtype} input to {out_dtype}; write it so that it "
                f"keeps the input dtype (e.g. no float64 constants)"
            )
        if not bool(jnp.isfinite(out)):
            raise ValueError(f"activation {name} is not finite at x = 1/3 in {dtype}")
