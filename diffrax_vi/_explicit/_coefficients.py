"""Coefficients of the composition and splitting methods (sub-step fractions).

A symmetric composition `Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}` of a symmetric second-order step `Φ`
has order `p` when the fractions `γ_i` (summing to one, `γ_{s+1-i} = γ_i`) satisfy the order
conditions of symmetric compositions (Hairer, Lubich and Wanner, *Geometric Numerical
Integration*, chapter V.3): `Σ γ_i³ = 0` for order four, and further polynomial conditions for
orders six and eight. The sets below are taken from the papers named in their docstrings; the
tests measure the order each one reaches.
"""

from __future__ import annotations

import math

__all__ = ["composition_gammas", "composition_schemes", "rkn_coefficients"]


def _triple_jump(gammas: tuple[float, ...], order: int) -> tuple[float, ...]:
    """Raise a symmetric composition of order `order` (even) to `order + 2` by composing it
    three times with fractions `(a, 1 - 2a, a)`, `a = 1 / (2 - 2^{1/(order+1)})`."""
    root = 2.0 ** (1.0 / (order + 1))
    outer = 1.0 / (2.0 - root)
    inner = -root / (2.0 - root)
    return tuple(g * outer for g in gammas) + tuple(g * inner for g in gammas) + tuple(
        g * outer for g in gammas
    )


def _fractal(gammas: tuple[float, ...], order: int) -> tuple[float, ...]:
    """Raise a symmetric composition of order `order` (even) to `order + 2` by Suzuki's
    five-fold fractal `(a, a, 1 - 4a, a, a)`, `a = 1 / (4 - 4^{1/(order+1)})`."""
    root = 4.0 ** (1.0 / (order + 1))
    outer = 1.0 / (4.0 - root)
    inner = -root / (4.0 - root)
    out = tuple(g * outer for g in gammas)
    return out + out + tuple(g * inner for g in gammas) + out + out


def _palindrome(half: tuple[float, ...]) -> tuple[float, ...]:
    """The symmetric set `(γ_1, …, γ_m, γ_0, γ_m, …, γ_1)` whose middle fraction `γ_0` makes the
    sum one."""
    middle = 1.0 - 2.0 * math.fsum(half)
    return half + (middle,) + half[::-1]


# Yoshida (1990), "Construction of higher order symplectic integrators", Phys. Lett. A 150:
# the seven-stage sixth-order solution A (outermost fraction first; the middle one is fixed by
# the sum). His fifteen-stage eighth-order solutions are not offered: solution D reaches its
# asymptotic order on the harmonic oscillator only where its error meets round-off (measured
# slopes 7.75 to 7.93 between 40 and 80 steps per ten time units), and Kahan and Li's set
# below is both more accurate and in its regime.
_YOSHIDA_6A = (0.784513610477560, 0.235573213359357, -1.17767998417887)
# Kahan and Li (1997), "Composition constants for raising the orders of unconventional schemes
# for ordinary differential equations", Math. Comp. 66: the nine-stage sixth-order set
# s9odr6a and the seventeen-stage eighth-order set s17odr8a.
_KAHAN_LI_6 = (
    0.39216144400731413928,
    0.33259913678935943860,
    -0.70624617255763935981,
    0.082213596293550800230,
)
_KAHAN_LI_8 = (
    0.13020248308889008088,
    0.56116298177510838456,
    -0.38947496264484728641,
    0.15884190655515560090,
    -0.39590389413323757734,
    0.18453964097831570709,
    0.25837438768632204729,
    0.29501172360931029887,
)


def _recursive(step, order: int) -> tuple[float, ...]:
    gammas: tuple[float, ...] = (1.0,)
    for reached in range(2, order, 2):
        gammas = step(gammas, reached)
    return gammas


_SCHEMES = {
    # name: {order: fractions}
    "triple_jump": {p: (lambda p=p: _recursive(_triple_jump, p)) for p in (2, 4, 6, 8)},
    # At order eight the fractal has 125 sub-steps and, on Kepler's problem, is still above its
    # asymptotic regime where its error meets double precision's round-off: not offered.
    "suzuki": {p: (lambda p=p: _recursive(_fractal, p)) for p in (2, 4, 6)},
    "yoshida": {2: lambda: (1.0,), 6: lambda: _palindrome(_YOSHIDA_6A)},
    "kahan_li": {
        2: lambda: (1.0,),
        6: lambda: _palindrome(_KAHAN_LI_6),
        8: lambda: _palindrome(_KAHAN_LI_8),
    },
}


def composition_schemes(order: int) -> tuple[str, ...]:
    """The scheme names that have a set of fractions of order `order`."""
    return tuple(name for name, sets in _SCHEMES.items() if order in sets)


def composition_gammas(order: int, scheme: str = "triple_jump") -> tuple[float, ...]:
    """The sub-step fractions `γ_i` (summing to one, symmetric) of a composition of order
    `order` of a symmetric second-order step, by the scheme named `scheme`.

    **Arguments:**

    - `order`: 2, 4, 6 or 8 (order 2 is the base step itself, `(1.0,)`).
    - `scheme`: `"triple_jump"` (Yoshida's and Suzuki's recursive triple jump, `3^{p/2-1}`
      stages), `"suzuki"` (Suzuki's recursive five-fold fractal, `5^{p/2-1}` stages, orders
      four and six),
      `"yoshida"` (Yoshida's solution A, order six) or `"kahan_li"` (Kahan and Li's optimised
      sets at orders six and eight).
    """
    if scheme not in _SCHEMES:
        raise ValueError(
            f"unknown composition scheme {scheme!r}: choose one of {sorted(_SCHEMES)}"
        )
    sets = _SCHEMES[scheme]
    if order not in sets:
        raise ValueError(
            f"composition scheme {scheme!r} has no set of order {order!r}: it has orders "
            f"{sorted(sets)}; the schemes of order {order!r} are "
            f"{list(composition_schemes(order)) if order in (2, 4, 6, 8) else 'none'}"
        )
    return sets[order]()


# Blanes and Moan (2002), "Practical symplectic partitioned Runge-Kutta and Runge-Kutta-Nyström
# methods", J. Comput. Appl. Math. 142: the RKN splittings SRKN_6^b (order four, six drifts)
# and SRKN_11^b (order six, eleven drifts), kick first. Only the independent coefficients are
# listed; the middle ones follow from the sums (kicks and drifts each sum to one).
_BLANES_MOAN = {
    4: (
        (0.0829844064174052, 0.396309801498368, -0.0390563049223486),
        (0.245298957184271, 0.604872665711080),
    ),
    6: (
        (0.0414649985182624, 0.198128671918067, -0.0400061921041533, 0.0752539843015807,
         -0.0115113874206879),
        (0.123229775946271, 0.290553797799558, -0.127049212625417, -0.246331761062075,
         0.357208872795928),
    ),
}


def rkn_coefficients(order: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """`(kicks, drifts)` of Blanes and Moan's symmetric RKN splitting of order `order` (4 or
    6): `K(b_0) D(a_1) K(b_1) … D(a_m) K(b_m)`, `m` drifts and `m + 1` kicks, fractions of
    the step.

    These splittings reach their order only for `q̈ = g(t, q)` (a kinetic energy quadratic in
    `p`, forces of the position and time alone), where the brackets `[B, [B, [B, A]]]` of the
    kick `B` and the drift `A` vanish and fewer order conditions remain.
    """
    if order not in _BLANES_MOAN:
        raise ValueError(f"BlanesMoan has orders 4 and 6, got order={order!r}")
    b, a = _BLANES_MOAN[order]
    if order == 4:
        kicks = b + (1.0 - 2.0 * math.fsum(b),) + b[::-1]
        a_mid = 0.5 - math.fsum(a)
        drifts = a + (a_mid, a_mid) + a[::-1]
    else:
        b_mid = 0.5 - math.fsum(b)
        kicks = b + (b_mid, b_mid) + b[::-1]
        drifts = a + (1.0 - 2.0 * math.fsum(a),) + a[::-1]
    return kicks, drifts
