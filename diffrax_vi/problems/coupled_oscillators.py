"""Two harmonic oscillators with a position-dependent (sigmoid-gated) coupling spring."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._terms import LagrangianTerm
from .base import ClosedFormFlow, Problem, as_vector, make_state, resolve_dtype
from .stored import StoredFlow

__all__ = ["coupled_oscillators"]


class _Params(eqx.Module):
    m1: float = eqx.field(static=True)
    m2: float = eqx.field(static=True)
    k1: float = eqx.field(static=True)
    k2: float = eqx.field(static=True)
    coupling: float = eqx.field(static=True)

    def potential(self, q):
        gate = jax.nn.sigmoid(q[0])
        return (
            0.5 * self.k1 * q[0] ** 2
            + 0.5 * self.k2 * q[1] ** 2
            + 0.5 * self.coupling * gate * (q[1] - q[0]) ** 2
        )


class _Lagrangian(_Params):
    def __call__(self, t, q, v, args):
        return 0.5 * self.m1 * v[0] ** 2 + 0.5 * self.m2 * v[1] ** 2 - self.potential(q)


class _Velocity(_Params):
    def __call__(self, t, q, p, args):
        return jnp.stack([p[0] / self.m1, p[1] / self.m2])


class _Hamiltonian(_Params):
    def __call__(self, t, q, p, args):
        return p[0] ** 2 / (2 * self.m1) + p[1] ** 2 / (2 * self.m2) + self.potential(q)


class _RHS:
    """Hamilton's equations in NumPy, vectorised over leading axes (any float dtype)."""

    def __init__(self, m1: float, m2: float, k1: float, k2: float, coupling: float):
        self.m1, self.m2, self.k1, self.k2, self.coupling = m1, m2, k1, k2, coupling

    def __call__(self, y: np.ndarray) -> np.ndarray:
        q1, q2, p1, p2 = (y[..., i] for i in range(4))
        coupling = self.coupling
        gate = 1 / (1 + np.exp(-q1))
        stretch = q2 - q1
        dv1 = self.k1 * q1 + 0.5 * coupling * gate * (1 - gate) * stretch**2
        dv1 = dv1 - coupling * gate * stretch
        dv2 = self.k2 * q2 + coupling * gate * stretch
        return np.stack([p1 / self.m1, p2 / self.m2, -dv1, -dv2], axis=-1)


def coupled_oscillators(
    m=(2.0, 1.0),
    k=(1.5, 0.3),
    coupling: float = 1.0,
    q0=(1.0, 0.0),
    p0=(2.0, 0.0),
    *,
    t0: float = 0.0,
    t1: float = 100.0,
    dt: float = 0.4,
    dtype=None,
) -> Problem:
    """Two masses on springs to a wall, coupled by a spring gated by `σ(q₁)`.

    `L = m₁ v₁²/2 + m₂ v₂²/2 − V(q)` with `V = k₁ q₁²/2 + k₂ q₂²/2 + κ σ(q₁)(q₂ − q₁)²/2`,
    `σ` the logistic sigmoid and `κ` the `coupling`; energy `H = p₁²/(2m₁) + p₂²/(2m₂) + V(q)`,
    closed-form velocity `v = (p₁/m₁, p₂/m₂)`. (The reference package writes the kinetic part of
    its Lagrangian as `v²/(2m)`, which contradicts its own `v̄ = p/m` and Hamiltonian; the
    consistent `m v²/2` is used here.)

    With `coupling = 0` the oscillators are independent and the reference is exact,
    `qᵢ(t) = q₀ᵢ cos ωᵢτ + p₀ᵢ/(mᵢωᵢ) sin ωᵢτ` with `ωᵢ = √(kᵢ/mᵢ)`; this is the reference's
    two-degree-of-freedom layout test (`q0 = (0.5, −0.3)`, `p0 = (0, 0.4)`, span `(0, 0.3)`,
    step 0.1). Otherwise the reference solves Hamilton's equations: for the default problem it
    is stored with the package over `(t0, t0 + 100)` (extended-precision computation, verified
    to 4e-15 in the max norm); other settings or times use scipy's DOP853.

    **Arguments:**

    - `m`, `k`: the two masses and wall spring constants (positive).
    - `coupling`: the strength `κ ≥ 0` of the coupling spring.
    - `q0`, `p0`: initial positions and momenta.
    - `t0`, `t1`, `dt`: the default span and step (the reference package's `(0, 100)`, 0.4).
    - `dtype`: the floating dtype of `y0` (default: JAX's default float).

    **Returns:** a `Problem` named `"coupled_oscillators"`.
    """
    dtype = resolve_dtype(dtype)
    m1, m2 = (float(x) for x in as_vector(m, 2, "m"))
    k1, k2 = (float(x) for x in as_vector(k, 2, "k"))
    coupling = float(coupling)
    if not (m1 > 0 and m2 > 0 and k1 > 0 and k2 > 0 and coupling >= 0):
        raise ValueError(
            f"masses and spring constants must be positive and coupling >= 0; got m={m}, k={k}, "
            f"coupling={coupling}"
        )
    params = (m1, m2, k1, k2, coupling)
    q0v = as_vector(q0, 2, "q0")
    p0v = as_vector(p0, 2, "p0")
    masses = np.array([m1, m2])
    omegas = np.sqrt(np.array([k1, k2]) / masses)

    if coupling == 0:

        def solution(tau):
            c = np.cos(omegas * tau[:, None])
            s = np.sin(omegas * tau[:, None])
            q = q0v * c + p0v / (masses * omegas) * s
            p = p0v * c - masses * omegas * q0v * s
            return q, p

        flow, method = ClosedFormFlow(solution), "closed form"
    else:
        flow = StoredFlow(
            "coupled_oscillators", _RHS(*params), np.concatenate([q0v, p0v]), np.array(params)
        )
        method = "stored"

    return Problem(
        name="coupled_oscillators",
        term=LagrangianTerm(_Lagrangian(*params), velocity=_Velocity(*params)),
        y0=make_state(q0v, p0v, dtype),
        t0=float(t0),
        t1=float(t1),
        dt=float(dt),
        params={"m1": m1, "m2": m2, "k1": k1, "k2": k2, "coupling": coupling},
        hamiltonian=_Hamiltonian(*params),
        reference_flow=flow,
        reference_method=method,
    )
