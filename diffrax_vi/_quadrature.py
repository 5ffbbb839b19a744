"""Quadrature rules on the unit interval `[0, 1]`, with weights summing to one.

Gauss–Legendre nodes and weights are computed once in extended precision (mpmath, imported
on first use) and rounded straight to the working dtype, so that their symmetries hold
exactly in that dtype: `c_i + c_{n+1-i} == 1`, `b_i == b_{n+1-i}`, and the weights sum to 1
as closely as the dtype allows. A float32 run never sees a float64 constant.
"""

from __future__ import annotations

import functools
from fractions import Fraction

import equinox as eqx
import jax.numpy as jnp
import numpy as np

__all__ = ["AbstractQuadrature", "GaussLegendre", "Simpson"]

# Bits of the extended-precision computations: far more than any rounding below needs.
_MP_BITS = 256
_FLOAT_DTYPES = ("float16", "float32", "float64")


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


# -- extended-precision nodes and weights -----------------------------------------------------


def _legendre(n: int, x):
    """`(P_n(x), P_n'(x), P_n''(x))` by the three-term recurrence (mpmath numbers, |x| < 1)."""
    p0, p1 = 1, x
    for k in range(2, n + 1):
        p0, p1 = p1, ((2 * k - 1) * x * p1 - (k - 1) * p0) / k
    if n == 0:
        p1 = 1
    dp = n * (x * p1 - p0) / (x * x - 1) if n else 0
    ddp = (2 * x * dp - n * (n + 1) * p1) / (1 - x * x)  # Legendre's equation
    return p1, dp, ddp


def _newton(f, x, what: str):
    """Newton's method on `f(x) -> (value, slope)` until the update is negligible."""
    import mpmath

    tol = mpmath.ldexp(1, 24 - _MP_BITS)
    for _ in range(200):
        value, slope = f(x)
        dx = value / slope
        x -= dx
        if abs(dx) < tol:
            return x
    raise RuntimeError(f"Newton's method did not converge on a root of {what}")


def _check_roots(upper, what: str):
    """Refuse a set of upper roots that is not strictly increasing inside `(1/2, 1)`."""
    ok = all(a < b for a, b in zip(upper, upper[1:], strict=False))
    if not ok or (upper and not (upper[0] > 0.5 and upper[-1] < 1)):
        raise RuntimeError(f"{what}: Newton's method missed a root")


@functools.cache
def gauss_legendre_exact(n: int) -> tuple[tuple, tuple]:
    """The Gauss–Legendre rule on `[0, 1]` in extended precision, upper half only.

    Returns `(nodes, weights)`, mpmath numbers in increasing node order: the middle node 1/2
    first when `n` is odd, then the nodes above 1/2. The nodes below are `1 - c` with the same
    weights.
    """
    import mpmath

    with mpmath.workprec(_MP_BITS):
        nodes, weights = [], []
        for i in range(n // 2, 0, -1):
            # Tricomi's estimate of the i-th largest root of P_n on [-1, 1], then Newton.
            guess = mpmath.cos(mpmath.pi * (4 * i - 1) / (4 * n + 2))
            x = _newton(lambda x: _legendre(n, x)[:2], guess, f"P_{n}")
            dp = _legendre(n, x)[1]
            nodes.append((1 + x) / 2)
            weights.append(1 / ((1 - x * x) * dp * dp))  # half the weight on [-1, 1]
        _check_roots(nodes, f"GaussLegendre({n})")
        if n % 2:
            dp = _legendre(n, mpmath.mpf(0))[1]
            nodes.insert(0, mpmath.mpf(1) / 2)
            weights.insert(0, 1 / (dp * dp))
    return tuple(nodes), tuple(weights)


@functools.cache
def gauss_lobatto_upper(degree: int) -> tuple:
    """The interior Gauss–Lobatto points of `degree` (roots of `P'_degree`) on `[0, 1]` that
    lie above 1/2, increasing, in extended precision."""
    import mpmath

    with mpmath.workprec(_MP_BITS):
        points = []
        for i in range((degree - 1) // 2, 0, -1):
            # The Chebyshev–Lobatto point is close enough for Newton to find the same root.
            guess = mpmath.cos(mpmath.pi * i / degree)
            x = _newton(lambda x: _legendre(degree, x)[1:], guess, f"P'_{degree}")
            points.append((1 + x) / 2)
        _check_roots(points, f"Gauss–Lobatto points of degree {degree}")
    return tuple(points)


# -- rounding to a binary format --------------------------------------------------------------


def _split(x, dtype) -> tuple[int, int, object]:
    """For positive mpmath `x`: the exponent `e` of the spacing `2**e` of `dtype` around `x`
    (subnormals included), `k = floor(x / 2**e)`, and the remainder `x / 2**e - k`."""
    import mpmath

    info = np.finfo(dtype)
    with mpmath.workprec(_MP_BITS):
        _, exponent = mpmath.frexp(x)  # x = m · 2**exponent with 1/2 <= m < 1
        shift = max(int(exponent) - 1, int(info.minexp)) - int(info.nmant)
        scaled = mpmath.ldexp(x, -shift)
        k = int(mpmath.floor(scaled))
        rest = scaled - k
    return shift, k, rest


def _round_nearest(x, dtype) -> Fraction:
    """`x` (positive, mpmath) rounded to the nearest number of `dtype`, ties to even."""
    shift, k, rest = _split(x, dtype)
    if rest > 0.5 or (rest == 0.5 and k % 2):
        k += 1
    return k * Fraction(2) ** shift


def _balanced_weights(exact, multiplicity, dtype) -> list[Fraction]:
    """Round each weight down or up in `dtype` (so within one unit in the last place) such
    that the exact sum `Σ multiplicity_i · b_i` is as close to 1 as these choices allow;
    among the best, the one that departs least often from rounding to nearest."""
    nearest = [_round_nearest(x, dtype) for x in exact]
    options = []
    for x in exact:
        shift, k, rest = _split(x, dtype)
        spacing = Fraction(2) ** shift
        options.append((k * spacing,) if rest == 0 else (k * spacing, (k + 1) * spacing))
    gaps = [m * (o[-1] - o[0]) for m, o in zip(multiplicity, options, strict=True)]
    unit = min((g for g in gaps if g), default=Fraction(1))
    steps = [int(g / unit) for g in gaps]  # powers of two times the finest gap
    base = sum((m * o[0] for m, o in zip(multiplicity, options, strict=True)), Fraction(0))
    target = (1 - base) / unit
    if sum(steps) > 1 << 16:
        return nearest  # too many sums to search
    # Dynamic programme over the reachable sums, in units of the finest gap: for each sum,
    # the fewest departures from nearest rounding and the choices that give it.
    reach: dict[int, tuple[int, tuple[int, ...]]] = {0: (0, ())}
    for opts, near, step in zip(options, nearest, steps, strict=True):
        following: dict[int, tuple[int, tuple[int, ...]]] = {}
        for total, (cost, picks) in reach.items():
            for j, value in enumerate(opts):
                key, entry = total + j * step, (cost + (value != near), picks + (j,))
                if key not in following or entry[0] < following[key][0]:
                    following[key] = entry
        reach = following
    best = min(reach, key=lambda s: (abs(s - target), reach[s][0], s))
    return [o[j] for o, j in zip(options, reach[best][1], strict=True)]


def _to_array(values, dtype) -> np.ndarray:
    """Exactly representable fractions as a read-only array of `dtype` (via float64, exact)."""
    out = np.array([float(v) for v in values], dtype=np.float64).astype(dtype)
    out.setflags(write=False)
    return out


def symmetric_points(upper, dtype, *, middle: bool, ends: bool = False) -> np.ndarray:
    """Points on `[0, 1]`, symmetric about 1/2 exactly in `dtype`, from the extended-precision
    points `upper` above 1/2: those are rounded to nearest and their mirror images are
    `1 - c`, which is exact in binary floating point for `c` in `[1/2, 1]` (Sterbenz), so
    every pair sums to 1 exactly and the lower points are accurate to half a unit in the
    last place of their partners. `middle` adds 1/2, `ends` adds 0 and 1."""
    dtype = np.dtype(dtype)
    top = [_round_nearest(c, dtype) for c in upper] + [Fraction(1)] * ends
    half = [Fraction(1, 2)] * middle
    return _to_array([1 - c for c in reversed(top)] + half + top, dtype)


@functools.cache
def _gauss_legendre(n: int, dtype_name: str = "float64") -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on `[0, 1]` in a binary float dtype, rounded once
    from extended precision: nodes exactly symmetric (`symmetric_points`), each weight pair
    rounded once (so equal) in the direction that brings the sum closest to 1."""
    dtype = np.dtype(dtype_name)
    nodes, weights = gauss_legendre_exact(n)
    odd = n % 2
    c = symmetric_points(nodes[odd:], dtype, middle=bool(odd))
    w = _balanced_weights(weights, [1] * odd + [2] * (n // 2), dtype)
    b = _to_array(list(reversed(w[odd:])) + w, dtype)
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

    def nodes_weights(self, dtype) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Nodes and weights as arrays of `dtype`, rounded once from extended precision
        (not via float64) with their symmetries exact in `dtype`."""
        name = jnp.dtype(dtype).name
        if name in _FLOAT_DTYPES:
            c, b = _gauss_legendre(self.n, name)
            return jnp.asarray(c, dtype=dtype), jnp.asarray(b, dtype=dtype)
        return super().nodes_weights(dtype)

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
