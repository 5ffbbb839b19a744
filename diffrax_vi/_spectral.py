"""Spectral variational integrators: keep a large step and raise the polynomial degree.

Hall and Leok (2015) observe that for a fixed step `h` the error of a Galerkin variational
integrator falls geometrically in the degree of its polynomial space when the solution is
analytic. `SpectralCGVI` uses that: given the step and the time scale of the motion it picks,
in Python before anything is traced, the smallest degree whose estimated one-step error is
below a tolerance, and returns the continuous-Galerkin integrator `CGVI` of that degree.

Two error models (`model=`), both as functions of `x = dt / timescale`:

- `"analytic"` (default): the solution is taken to be analytic in the strip `|Im t| <
  timescale` around the real time axis. Then it is analytic inside the Bernstein ellipse of
  each step with semi-minor axis `timescale`, whose parameter is
  `ρ = 2/x + sqrt(1 + 4/x²)`; polynomials of degree `s` approximate it to `O(ρ^-s)` and the
  Galerkin end values converge like the square of that. The estimate is `8 x ρ^(-2s)`: the
  rate follows from analyticity, the factor `8 x` is set so that the estimate bounds the
  oscillator's exact error below and the errors measured on Kepler orbits
  (`docs/studies.md`).
- `"oscillator"`: the exact one-step error of `CGVI(s)` on the harmonic oscillator with
  `ω = 1/timescale`, computed in extended precision from the Galerkin action. Exact for
  linear oscillations, whose error falls faster than geometrically; it underestimates the
  error of motions with singularities in complex time (orbits, large swings).

The estimates assume a regular Lagrangian, where `CGVI(s)` has order `2s`. For degenerate
(first-order) Lagrangians given as an `IODETerm` the error falls about half as fast in `s`.
"""

from __future__ import annotations

import functools
import math
from typing import Any

from ._methods import CGVI
from ._quadrature import GaussLegendre, gauss_legendre_exact
from ._root_finder.chord import ChordIteration
from ._solver import NetworkVI

__all__ = ["SpectralCGVI", "large_step_root_finder", "spectral_degree", "spectral_step_error"]

#: The largest degree `spectral_degree` considers unless told otherwise.
DEFAULT_MAX_DEGREE = 40
#: The default one-step tolerance: float64's machine epsilon.
DEFAULT_RTOL = 2.0**-52
#: The smallest tolerance accepted: the extended-precision estimate resolves errors down
#: to far below it.
SMALLEST_RTOL = 1e-30
MODELS = ("analytic", "oscillator")
_DIGITS = 60  # decimal digits of the extended-precision oscillator estimate


def _positive_real(name: str, value) -> float:
    number = value.item() if hasattr(value, "item") and getattr(value, "ndim", 1) == 0 else value
    if isinstance(number, bool) or not isinstance(number, int | float):
        raise ValueError(f"{name} must be a positive real number, got {value!r}")
    number = float(number)
    if not (math.isfinite(number) and number > 0):
        raise ValueError(f"{name} must be a positive, finite number, got {value!r}")
    return number


def _degree_count(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return value


def _check_model(model) -> str:
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    return model


@functools.cache
def _galerkin_matrices(degree: int, digits: int = _DIGITS):
    """Stiffness and mass matrices of the continuous-Galerkin space of `degree` on `[0, 1]`.

    Basis: the two hat functions `1 − τ`, `τ` (the end values) and the bubbles
    `φ_j(τ) = ∫_0^τ P_j(2t − 1) dt`, `j = 1 .. degree − 1`, which vanish at both ends and have
    orthogonal derivatives: the stiffness matrix is diagonal, and the system stays well
    conditioned at any degree. The mass matrix is integrated exactly by Gauss–Legendre.
    Returns `(K_ends, M_ends, M_cross, K_bubbles, M_bubbles)` as mpmath matrices."""
    import mpmath

    with mpmath.workdps(digits):
        nodes, weights = gauss_legendre_exact(degree + 2)
        odd = (degree + 2) % 2
        c = [1 - v for v in reversed(nodes[odd:])] + list(nodes)
        w = list(reversed(weights[odd:])) + list(weights)
        values = []  # basis values at the nodes, one row per basis function
        values.append([1 - t for t in c])
        values.append(list(c))
        for j in range(1, degree):
            row = []
            for t in c:
                y = 2 * t - 1
                row.append((mpmath.legendre(j + 1, y) - mpmath.legendre(j - 1, y)) / (4 * j + 2))
            values.append(row)
        n = degree + 1
        mass = mpmath.matrix(n, n)
        for a in range(n):
            for b in range(a, n):
                mass[a, b] = mass[b, a] = mpmath.fsum(
                    wk * va * vb for wk, va, vb in zip(w, values[a], values[b], strict=True)
                )
        k_ends = mpmath.matrix([[1, -1], [-1, 1]])
        m_ends = mass[0:2, 0:2]
        if degree == 1:
            return k_ends, m_ends, None, None, None
        m_cross = mass[2:n, 0:2]
        k_bubbles = mpmath.diag([mpmath.mpf(1) / (2 * j + 1) for j in range(1, degree)])
        m_bubbles = mass[2:n, 2:n]
        return k_ends, m_ends, m_cross, k_bubbles, m_bubbles


def oscillator_map(degree: int, x, digits: int = _DIGITS):
    """The one-step map of `CGVI(degree)` (any quadrature exact for polynomials of degree
    `2·degree`) on the oscillator at `x = ω h`, in the coordinates `(q, p/ω)`, and the exact
    rotation, as mpmath 2×2 matrices.

    The discrete Lagrangian is the action of the stationary polynomial with end values
    `q0`, `q1`: `h L_d = ½ α (q0² + q1²) − β q0 q1`, with `α`, `β` from the Schur complement
    of the bubbles in `K − x² M`. Its discrete Euler–Lagrange equations give the map."""
    import mpmath

    with mpmath.workdps(digits):
        x = mpmath.mpf(x)
        k_ends, m_ends, m_cross, k_bub, m_bub = _galerkin_matrices(degree, digits)
        reduced = k_ends - x**2 * m_ends
        if degree > 1:
            coupling = -(x**2) * m_cross
            block = k_bub - x**2 * m_bub
            solved = mpmath.matrix(degree - 1, 2)
            for col in range(2):
                column = mpmath.lu_solve(block, coupling[:, col])
                for row in range(degree - 1):
                    solved[row, col] = column[row]
            reduced = reduced - coupling.T * solved
        alpha, beta = reduced[0, 0], -reduced[0, 1]
        discrete = mpmath.matrix(
            [[alpha / beta, x / beta], [(alpha**2 - beta**2) / (x * beta), alpha / beta]]
        )
        exact = mpmath.matrix([[mpmath.cos(x), mpmath.sin(x)], [-mpmath.sin(x), mpmath.cos(x)]])
    return discrete, exact


@functools.cache
def _step_error(degree: int, x: float) -> float:
    import mpmath

    try:
        discrete, exact = oscillator_map(degree, x)
    except ZeroDivisionError:  # exactly at a resonance of the bubbles
        return math.inf
    with mpmath.workdps(_DIGITS):
        difference = discrete - exact
        # Spectral norm of a 2×2 matrix: the largest singular value.
        a, b, c, d = difference[0, 0], difference[0, 1], difference[1, 0], difference[1, 1]
        frob = a * a + b * b + c * c + d * d
        det = a * d - b * c
        norm = mpmath.sqrt((frob + mpmath.sqrt(max(frob * frob - 4 * det * det, 0))) / 2)
    value = float(norm)
    return value if math.isfinite(value) else math.inf


def _analytic_error(degree: int, x: float) -> float:
    rho = 2 / x + math.sqrt(1 + 4 / (x * x))
    return 8 * x * math.exp(-2 * degree * math.log(rho))


def _estimate(model: str, degree: int, x: float) -> float:
    if model == "analytic":
        return _analytic_error(degree, x)
    return _step_error(degree, x)


def spectral_step_error(degree: int, dt, timescale, model: str = "analytic") -> float:
    """Estimated one-step error of `CGVI(degree)` at step `dt` for a motion of time scale
    `timescale`, relative to the size of the state, by `model` (`"analytic"` or
    `"oscillator"`, see the module's description).

    The `"oscillator"` value is the distance (spectral norm, coordinates `(q, p/ω)`) between
    the method's one-step map and the exact flow of the oscillator with `ω = 1/timescale`.
    Global errors over `n` steps grow like `n` times the phase part of it."""
    degree = _degree_count("degree", degree)
    dt = _positive_real("dt", dt)
    timescale = _positive_real("timescale", timescale)
    return _estimate(_check_model(model), degree, dt / timescale)


def spectral_degree(
    dt, timescale, rtol=None, max_degree: int = DEFAULT_MAX_DEGREE, model: str = "analytic"
) -> int:
    """The smallest polynomial degree whose estimated one-step error
    (`spectral_step_error`) at step `dt`, for a motion of time scale `timescale`, is at most
    `rtol`.

    **Arguments:**

    - `dt`: the (constant) step size.
    - `timescale`: the shortest time scale of the motion: `1/ω` for an oscillation of
      angular frequency `ω`; for an orbit the pericentre passage `r_p / |v_p|`. With
      `model="analytic"` any lower bound of the distance from the real axis to the nearest
      singularity of the solution in complex time is safe (smaller is more conservative).
    - `rtol`: the one-step error allowed, relative to the size of the state; in
      `[SMALLEST_RTOL, 1)`. Default `DEFAULT_RTOL` (float64's machine epsilon). The realised
      error also carries rounding, a few units of roundoff per step that grow with the degree.
    - `max_degree`: the largest degree to consider (default `DEFAULT_MAX_DEGREE`).
    - `model`: `"analytic"` (default, conservative) or `"oscillator"` (exact for linear
      oscillations).

    **Raises:** `ValueError` for invalid arguments, and when no degree up to `max_degree`
    meets `rtol` (the message names the best one).
    """
    dt = _positive_real("dt", dt)
    timescale = _positive_real("timescale", timescale)
    rtol = DEFAULT_RTOL if rtol is None else _positive_real("rtol", rtol)
    if not SMALLEST_RTOL <= rtol < 1:
        raise ValueError(
            f"rtol must lie in [{SMALLEST_RTOL:g}, 1) (a relative error per step), got {rtol!r}"
        )
    max_degree = _degree_count("max_degree", max_degree)
    model = _check_model(model)
    x = dt / timescale
    best = (math.inf, 0)
    for degree in range(1, max_degree + 1):
        error = _estimate(model, degree, x)
        if error <= rtol:
            return degree
        best = min(best, (error, degree))
    raise ValueError(
        f"no degree up to max_degree={max_degree} resolves dt={dt:g} for timescale="
        f"{timescale:g} (dt/timescale = {x:.3g}) to rtol={rtol:.3g} by the {model!r} model: "
        f"the best is degree {best[1]} with an estimated one-step error of {best[0]:.2e}; "
        "take a smaller step, a larger rtol or max_degree"
        + (", or model='oscillator' for a linear oscillation" if model == "analytic" else "")
    )


def SpectralCGVI(
    dt,
    timescale,
    rtol=None,
    max_degree: int = DEFAULT_MAX_DEGREE,
    *,
    model: str = "analytic",
    **options: Any,
) -> NetworkVI:
    """A continuous-Galerkin variational integrator whose degree resolves a given step.

    The degree is `spectral_degree(dt, timescale, rtol, max_degree, model)`, chosen in
    Python before anything is traced; the solver is `CGVI(degree, GaussLegendre(degree + 1))`,
    of order `2·degree`, with `options` passed on to `CGVI`. Use it with constant steps of
    `dt`: the estimate is for that step. More quadrature nodes than `degree + 1` do not
    change the error measurably (Kepler orbits), so the rule is fixed.

    **Arguments:** as `spectral_degree`; `**options` go to `CGVI` (not `quadrature`).

    **Returns:** a configured `NetworkVI`.
    """
    if "quadrature" in options:
        raise ValueError(
            "SpectralCGVI chooses its own quadrature (Gauss–Legendre with degree + 1 nodes); "
            "use CGVI(degree, quadrature) for another rule"
        )
    degree = spectral_degree(dt, timescale, rtol, max_degree, model)
    options.setdefault("root_finder", large_step_root_finder())
    return CGVI(degree, GaussLegendre(degree + 1), **options)


def large_step_root_finder() -> ChordIteration:
    """`SpectralCGVI`'s root finder: the chord iteration, restarted inside the step from the
    trajectory seed with Newton's updates where it cannot contract. The Jacobian-free
    iteration of `CGVI`'s default contracts at a rate of order `(hω)²`, which the steps this
    method is for exceed."""
    return ChordIteration(ftol=0.0, predict=True, picard=False, restart=True)
