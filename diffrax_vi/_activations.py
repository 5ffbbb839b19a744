"""Activation functions for network ansätze, and the working-precision check.

Every activation here maps an array of dtype T to an array of dtype T, for T in float16,
float32 and float64. Activations are hashable (they sit in static fields of solvers), so
parametrised ones are small frozen dataclasses rather than closures.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "tanh",
    "sigmoid",
    "sin",
    "gelu",
    "gelu_exact",
    "elu",
    "relu_k",
    "ReLUk",
    "check_activation",
    "activation_name",
    "package_activation",
    "numpy_value_and_slope",
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


def gelu_exact(x):
    """Gaussian error linear unit, exact form `x Φ(x)` with the error function (as
    `jax.nn.gelu(approximate=False)`)."""
    return jax.nn.gelu(x, approximate=False)


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


def _jax_activations() -> tuple[tuple[Callable, Callable], ...]:
    """JAX's functions that compute one of this module's activations, and that activation.
    Each JAX function is exactly what the package's one evaluates (`jax.nn.tanh` is
    `jnp.tanh`, `jax.nn.sigmoid` is `lax.logistic`), so recognising it changes no value."""
    return (
        (jnp.tanh, tanh),
        (jax.nn.tanh, tanh),
        (jax.lax.tanh, tanh),
        (jax.nn.sigmoid, sigmoid),
        (jax.lax.logistic, sigmoid),
        (jnp.sin, sin),
        (jax.lax.sin, sin),
        (jax.nn.gelu, gelu),  # approximate=True is jax.nn.gelu's default
        (jax.nn.elu, elu),  # alpha=1.0, its default
        (jax.nn.relu, ReLUk(1)),
    )


def package_activation(activation: Callable) -> Callable:
    """This module's activation that `activation` is, else `activation` itself.

    Recognises JAX's own functions by identity: `jnp.tanh`, `jax.nn.tanh` and `lax.tanh` are
    `tanh`; `jax.nn.sigmoid` and `lax.logistic` are `sigmoid`; `jnp.sin` and `lax.sin` are
    `sin`; `jax.nn.gelu` is `gelu` (its default `approximate=True`) and
    `functools.partial(jax.nn.gelu, approximate=False)` is `gelu_exact`; `jax.nn.elu` is `elu`;
    `jax.nn.relu` is `relu_k(1)`. `ShallowNetBasis` applies it to its activation, so that the
    solver's defaults (which step a network gets) are the same whichever name a user writes.
    Any other function (a lambda, a composition, a power of `jax.nn.relu`) is returned as it
    is: it cannot be compared with a package activation without evaluating it.
    """
    if isinstance(activation, functools.partial):
        if activation.func is jax.nn.gelu and not activation.args:
            keywords = activation.keywords or {}
            approximate = keywords.get("approximate", True)
            if set(keywords) <= {"approximate"} and isinstance(approximate, bool):
                return gelu if approximate else gelu_exact
        return activation
    for jax_function, ours in _jax_activations():
        if activation is jax_function:
            return ours
    return activation


def activation_name(activation: Callable) -> str:
    """A readable name for an activation, for error messages and reports."""
    if isinstance(activation, ReLUk):
        return repr(activation)
    return getattr(activation, "__name__", repr(activation))


def check_activation(activation: Callable, dtype) -> None:
    """Refuse an activation that does not stay in the working precision.

    Evaluates `activation(T(1/3))` for the working dtype `T` and raises `ValueError` if the
    result is not a finite scalar of dtype `T`: an activation written with a float64
    constant silently promotes float16/float32 runs to float64. The shape and dtype come from
    tracing it (`jax.eval_shape`); the value from its NumPy form where it has one
    (`numpy_value_and_slope`: nothing is compiled), else from JAX, eagerly (also while a step
    is being traced).
    """
    dtype = jnp.dtype(dtype)
    name = activation_name(activation)
    x = np.asarray(1.0 / 3.0, dtype)
    try:
        out = jax.eval_shape(activation, jax.ShapeDtypeStruct((), dtype))
        if isinstance(out, jax.ShapeDtypeStruct) and out.shape == () and out.dtype == dtype:
            twin = numpy_value_and_slope(activation)
            if twin is not None:
                value = twin(x)[0]
            else:
                with jax.ensure_compile_time_eval():
                    value = np.asarray(activation(jnp.asarray(x)))
    except Exception as err:  # noqa: BLE001 - re-raised with context
        raise ValueError(
            f"activation {name} cannot be evaluated at dtype {dtype}: {err}"
        ) from err
    if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != ():
        shape = getattr(out, "shape", type(out).__name__)
        raise ValueError(
            f"activation {name} must act elementwise; a scalar input gave shape {shape}"
        )
    if out.dtype != dtype:
        raise ValueError(
            f"activation {name} promotes {dtype} input to {out.dtype}; write it so that it "
            f"keeps the input dtype (e.g. no float64 constants)"
        )
    if not np.all(np.isfinite(value)):
        raise ValueError(f"activation {name} is not finite at x = 1/3 in {dtype}")


def _numpy_tanh(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.tanh(z)
    return y, (1 + y) * (1 - y)


def _numpy_sigmoid(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = 1 / (1 + np.exp(-z))
    return y, y * (1 - y)


_NUMPY_TWINS: dict[Callable, Callable] = {tanh: _numpy_tanh, sigmoid: _numpy_sigmoid}


def numpy_value_and_slope(activation: Callable) -> Callable | None:
    """`z ↦ (σ(z), σ'(z))` in NumPy for an activation of this module that has a closed form
    there (`tanh`, `sigmoid`), else `None`: features at points known when a step is traced
    are then constants, with no program to compile for them."""
    try:
        return _NUMPY_TWINS.get(package_activation(activation))
    except TypeError:  # an unhashable activation
        return None
