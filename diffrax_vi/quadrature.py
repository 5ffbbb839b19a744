"""Quadrature rules on the unit interval `[0, 1]`, with weights summing to one.

Nodes and weights are computed once in float64 with NumPy and handed out in the working
dtype, so a float32 run never sees a float64 constant.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax.numpy as jnp
import numpy as np

__all__ = ["AbstractQuadrature", "GaussLegendre", "Simpson"]


class AbstractQuadrature(eqx.Module):
    """A rule `(c_j, b_j)` on `[0, 1]`: `∫_0^1 f ≈ Σ_j b_j f(c_j)`."""

    def nodes_weights_np(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def nodes_weights(self, dtype) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Nodes and weights as arrays of `dtype`."""
        c, b = self.nodes_weights_np()
        return jnp.asarray(c, dtype=dtype), jnp.asarray(b, dtype=dtype)

    @property
    def num_nodes(self) -> int:
        return len(self.nodes_weights_np()[0])


@functools.cache
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    c, b = 0.5 * (x + 1.0), 0.5 * w
    c.setflags(write=False)
    b.setflags(write=False)
    return c, b


class GaussLegendre(AbstractQuadrature):
    """Gauss–Legendre rule with `n` nodes on `[0, 1]`: exact for polynomials of degree `2n-1`.

    **Arguments:**

    - `n`: number of nodes (the reference's `GaussLegendreQuadrature(T, n)`).
    """

    n: int = eqx.field(static=True)

    def __check_init__(self):
        if not isinstance(self.n, int) or isinstance(self.n, bool) or self.n < 1:
            raise ValueError(f"GaussLegendre needs a positive integer node count, got {self.n!r}")

    def nodes_weights_np(self):
        return _gauss_legendre(self.n)

    @property
    def order(self) -> int:
        """Polynomial exactness plus one: the rule is exact up to degree `2n - 1`."""
        return 2 * self.n


@functools.cache
def _simpson(n: int) -> tuple[np.ndarray, np.ndarray]:
    c = np.arange(n + 1, dtype=np.float64) / n
    b = np.full(n + 1, 2.0)
    b[1::2] = 4.0
    b[0] = b[-1] = 1.0
    b /= 3.0 * n
    c.setflags(write=False)
    b.setflags(write=False)
    return c, b


class Simpson(AbstractQuadrature):
    """Composite Simpson rule on the uniform grid `i/n`, `i = 0..n` (`n` even).

    This is the weight set of the OGA seed fit (on the sub-step grid of the initial
    trajectory).

    **Arguments:**

    - `n`: number of sub-intervals; must be even and positive.
    """

    n: int = eqx.field(static=True)

    def __check_init__(self):
        if not isinstance(self.n, int) or isinstance(self.n, bool) or self.n < 2 or self.n % 2:
            raise ValueError(
                f"Simpson needs an even, positive number of sub-intervals, got {self.n!r}"
            )

    def nodes_weights_np(self):
        return _simpson(self.n)
