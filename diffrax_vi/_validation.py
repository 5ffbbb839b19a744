"""Checks of what the user hands in: the state `y0 = (q, p)` and the times.

They run at trace time (shapes, dtypes and container types are static), so a malformed input is
refused with one readable `ValueError` before any JAX code trips over it. They are called by the
terms' `vf` (which diffrax evaluates before any solver sees the state) and by `NetworkVI`. Times
are values, which `diffeqsolve` has traced before any solver sees them: `refuse_nonfinite_times`
checks them when the program runs.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

__all__ = ["check_state", "check_times", "describe_value", "refuse_nonfinite_times"]



def _expected(what: str) -> str:
    return (
        f"{what} must be a pair (a tuple) of two 1-D real floating arrays of the same shape "
        "and dtype, e.g. (jnp.array([0.5, 0.0]), jnp.array([0.0, 1.0]))"
    )


def describe_value(x: Any) -> str:
    """A short description of `x` for an error message: `float64[2]` for an array (traced or
    not), `a tuple (float64[2], float64[3])` for a container, else the type's name."""
    if isinstance(x, tuple | list):
        inner = ", ".join(describe_value(a) for a in x)
        return f"a {type(x).__name__} ({inner})"
    if isinstance(x, dict):
        return f"a dict with keys {sorted(map(str, x))}"
    if isinstance(x, bool | int | float | complex):
        return f"a Python {type(x).__name__} {x!r}"
    shape, dtype = getattr(x, "shape", None), getattr(x, "dtype", None)
    if shape is not None and dtype is not None:
        return f"{np.dtype(dtype).name}{list(shape)}"
    return f"a {type(x).__name__}"


def check_state(y: Any, what: str = "y0 = (q, p)") -> tuple[Array, Array]:
    """Return `(q, p)` as arrays if `y` is a valid state, else raise a `ValueError`.

    A valid state is a tuple of two 1-D arrays of one shape and one real floating dtype (the
    working precision). Only static properties are checked, so this works on traced values
    (under `jit`, `vmap`, `grad`) and costs nothing at run time. Integers are refused rather
    than converted: the dtype of the state is the working precision, and a silent choice of
    it would hide a mistake. `what` names the pair in the message.
    """
    expected = _expected(what)
    if not (isinstance(y, tuple) and len(y) == 2):
        raise ValueError(f"{expected}; got {_what(y)}")
    parts = []
    for x in y:
        if isinstance(x, bool | int | float | complex) or not hasattr(x, "dtype"):
            raise ValueError(f"{expected}; got {_what(y)}")
        parts.append(jnp.asarray(x))
    q, p = parts
    if q.ndim != 1 or p.ndim != 1 or q.shape != p.shape:
        raise ValueError(f"{expected}; got {_what(y)}")
    for x in (q, p):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            kind = "complex" if jnp.issubdtype(x.dtype, jnp.complexfloating) else "not floating"
            raise ValueError(f"{expected}; got {_what(y)} ({x.dtype} is {kind})")
    if q.dtype != p.dtype:
        raise ValueError(
            f"{expected}; got {_what(y)} (its two arrays differ in dtype: the dtype of the "
            "state is the working precision, so it must be one)"
        )
    return q, p


def _what(y: Any) -> str:
    if hasattr(y, "shape") and hasattr(y, "dtype"):
        return f"a single array {describe_value(y)}"
    return describe_value(y)


def check_times(**times: Any) -> None:
    """Raise a `ValueError` naming the first of `times` that is concretely NaN or infinite.

    Each keyword is a time (`t0=..., t1=..., dt0=...`); `None` is skipped. Only concrete values
    (Python numbers, NumPy or concrete JAX arrays) can be checked at trace time; a traced value
    is left alone (inside `diffrax.diffeqsolve` every time is traced by the time a solver or
    term sees it, see the failures page).
    """
    for name, value in times.items():
        number = _concrete_float(value)
        if number is not None and not math.isfinite(number):
            raise ValueError(
                f"{name} must be a finite time; got {name} = {number!r}. A NaN or infinite "
                "t0, t1 or dt0 gives no meaningful step."
            )


NONFINITE_TIME_MESSAGE = (
    "t0 and t1 must be finite times: diffeqsolve was given a NaN or infinite t0 or t1 (or a NaN "
    "dt0), which gives no meaningful step. Check the times where they are computed."
)


def refuse_nonfinite_times(t0: Any, t1: Any) -> Any:
    """`t0`, with a run-time error (equinox's `error_if`) where `t0` or `t1` is NaN or infinite.

    `NetworkVI.init` sees the solve's `t0` and the end of its first step (diffrax clips that to
    the solve's `t1`, so a NaN `t1` or `dt0` shows there); without this a NaN time makes
    `diffeqsolve` take no step and report success. The returned `t0` must be used for the check
    to stay in the program. It is a host callback, unless `EQX_ON_ERROR=nan` or `off` is set
    (then a NaN time takes no step, as without the check).
    """
    t0 = jnp.asarray(t0)
    bad = ~(jnp.isfinite(t0) & jnp.isfinite(jnp.asarray(t1)))
    return eqx.error_if(t0, bad, NONFINITE_TIME_MESSAGE)


def _concrete_float(value: Any) -> float | None:
    """`value` as a Python float if it is a concrete real scalar, else `None`."""
    if value is None or isinstance(value, jax.core.Tracer):
        return None
    try:
        array = np.asarray(value)
    except Exception:  # e.g. an object no array can be made of: not ours to judge here
        return None
    if array.shape != () or not np.issubdtype(array.dtype, np.number):
        return None
    if np.iscomplexobj(array):
        return None
    return float(array)
