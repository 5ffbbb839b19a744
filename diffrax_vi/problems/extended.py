"""Reference flows computed when asked, in extended precision, in other coordinates.

A constrained problem is integrated in Cartesian coordinates with multipliers; its reference
comes from the same system in coordinates that satisfy the constraints (angles), integrated
by the order-16 Gragg–Bulirsch–Stoer steps of `problems.stored` in `np.longdouble` and mapped
back to the Cartesian state.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable

import numpy as np

from .stored import gbs_integrate

__all__ = ["ExtendedPrecisionFlow", "spd_solve"]


def spd_solve(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """`x` with `matrix @ x = rhs` for stacks of symmetric positive definite matrices
    (`(..., N, N)` and `(..., N)`), by elimination without pivoting (stable for such
    matrices); works in any floating dtype, `np.longdouble` included, which `np.linalg`
    does not."""
    a = np.array(matrix, copy=True)
    b = np.array(rhs, copy=True)
    n = a.shape[-1]
    for k in range(n):
        factor = a[..., k + 1 :, k] / a[..., k : k + 1, k]
        a[..., k + 1 :, :] -= factor[..., None] * a[..., k : k + 1, :]
        b[..., k + 1 :] -= factor * b[..., k : k + 1]
    x = np.zeros_like(b)
    for k in range(n - 1, -1, -1):
        x[..., k] = (b[..., k] - np.sum(a[..., k, k + 1 :] * x[..., k + 1 :], axis=-1)) / a[
            ..., k, k
        ]
    return x


class ExtendedPrecisionFlow:
    """The flow of `y' = rhs(y)` from `y0`, integrated in `np.longdouble` and mapped to
    `(q, p)` by `to_state`.

    **Arguments:**

    - `rhs`: the vector field on rows `(M, n)` of the state in the integration's coordinates
      (NumPy only, so that it runs in `np.longdouble`).
    - `y0`: the float64 initial state in those coordinates.
    - `to_state`: `(M, n) -> (q, p)`, each `(M, D)`: the state in the problem's coordinates.
    - `steps_per_unit`: extrapolation steps per unit of time (each of order 16).
    """

    def __init__(
        self,
        rhs: Callable[[np.ndarray], np.ndarray],
        y0: np.ndarray,
        to_state: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
        *,
        steps_per_unit: float = 40.0,
        cache_size: int = 16,
    ):
        self.rhs = rhs
        self.y0 = np.asarray(y0, np.float64)
        self.to_state = to_state
        self.steps_per_unit = steps_per_unit
        self.cache_size = cache_size
        self._cache: collections.OrderedDict[bytes, tuple] = collections.OrderedDict()

    def __call__(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tau = np.asarray(tau, np.float64)
        if tau.ndim != 1 or not np.all(np.isfinite(tau)):
            raise ValueError("reference times must be a finite 1-D array")
        key = tau.tobytes()
        if key not in self._cache:
            longest = float(np.max(np.abs(tau), initial=0.0))
            steps = max(1, math.ceil(self.steps_per_unit * longest))
            start = np.tile(self.y0.astype(np.longdouble), (tau.shape[0], 1))
            ys = gbs_integrate(self.rhs, start, tau.astype(np.longdouble), steps)
            q, p = self.to_state(ys)
            self._cache[key] = (np.asarray(q, np.float64), np.asarray(p, np.float64))
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        q, p = self._cache[key]
        return q.copy(), p.copy()
