"""Single-hidden-layer network ansatz (the reference's `ShallowNetBasis`), optionally with
mirrored neuron pairs (the reference's reversible variants)."""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._activations import activation_name, check_activation, package_activation
from .base import AbstractBasis
from .symmetry import AbstractSymmetry, MirrorPairs, NoSymmetry, SharedMirrorPairs, mirror

__all__ = ["ShallowNetBasis", "NetworkJet"]


def network_min_nodes(width: int) -> int:
    """Nodes a network with `width` output weights needs: each node shows the action the
    value and the slope of the curve, so `2R >= width`. Measured on the harmonic oscillator
    (5 steps of 0.1, tanh): width 10 fails with 1 to 4 Gauss nodes and works with 5. The rule
    only refuses what fails: width 4 with 2 nodes fails too, but loudly (a failed step)."""
    return (width + 1) // 2


def _interleave(a: Array, b: Array) -> Array:
    """Rows `a_0, b_0, a_1, b_1, ...` (along axis 0)."""
    return jnp.stack([a, b], axis=1).reshape((-1,) + a.shape[1:])


def _activation_derivatives(activation: Callable, z: Array) -> tuple[Array, Array, Array, Array]:
    """`σ, σ', σ'', σ'''` of an elementwise activation at `z`, by nested forward mode."""
    one = jnp.ones_like(z)

    def d1(x):
        return jax.jvp(activation, (x,), (one,))[1]

    s0, s1 = jax.jvp(activation, (z,), (one,))
    s2, s3 = jax.jvp(lambda x: jax.jvp(d1, (x,), (one,))[1], (z,), (one,))
    return s0, s1, s2, s3


class NetworkJet(eqx.Module):
    """A network `q_d(τ) = Σ_i α_id σ(w_id τ + β_id)` and its derivatives at points `τ_k`, in
    closed form: values and τ-slopes, their gradients in each coordinate's parameters
    `θ_d = (α_d, w_d, β_d)`, and weighted sums of their Hessians, which are 3×3 blocks per
    neuron (a neuron touches only its own three parameters).

    This is what the Newton Jacobian of a step needs (`FreeEndpoints.jacobian`): a few
    elementwise passes over `(points, neurons, coordinates)` instead of nested automatic
    differentiation through the network.
    """

    alpha: Array  # (S, D)
    w: Array  # (S, D)
    beta: Array  # (S, D)
    taus: Array  # (K,)
    s: tuple[Array, Array, Array, Array]  # σ and its first three derivatives, each (K, S, D)

    def values(self) -> tuple[Array, Array]:
        """`q_d(τ_k)` and `q_d'(τ_k)`, each `(K, D)`."""
        s0, s1 = self.s[0], self.s[1]
        return jnp.sum(self.alpha * s0, axis=1), jnp.sum(self.alpha * self.w * s1, axis=1)

    def gradients(self) -> tuple[Array, Array]:
        """`∂q_d(τ_k)/∂θ_d` and `∂q_d'(τ_k)/∂θ_d`, each `(K, D, 3S)` in the order `(α, w, β)`."""
        s0, s1, s2, _ = self.s
        tau = self.taus[:, None, None]
        a, w = self.alpha, self.w
        value = (s0, a * tau * s1, a * s1)
        slope = (w * s1, a * (s1 + w * tau * s2), a * w * s2)

        def join(parts):
            return jnp.concatenate([jnp.swapaxes(part, 1, 2) for part in parts], axis=2)

        return join(value), join(slope)

    def weighted_hessian(self, u: Array, v: Array) -> Array:
        """`∇²_θd Σ_k (u_kd q_d(τ_k) + v_kd q_d'(τ_k))` for every coordinate `d`: `(D, 3S, 3S)`
        (`u`, `v` of shape `(K, D)`)."""
        _, s1, s2, s3 = self.s
        tau = self.taus[:, None, None]
        u, v = u[:, None, :], v[:, None, :]
        a, w = self.alpha, self.w

        def total(x):  # over the points: (S, D)
            return jnp.sum(x, axis=0)

        aw = total(u * tau * s1 + v * (s1 + w * tau * s2))
        ab = total(u * s1 + v * w * s2)
        ww = a * total(u * tau**2 * s2 + v * (2 * tau * s2 + w * tau**2 * s3))
        wb = a * total(u * tau * s2 + v * (s2 + w * tau * s3))
        bb = a * total(u * s2 + v * w * s3)
        zero = jnp.zeros_like(aw)
        blocks = jnp.stack(
            [jnp.stack([zero, aw, ab]), jnp.stack([aw, ww, wb]), jnp.stack([ab, wb, bb])]
        )  # (3, 3, S, D)
        n_s, dim = a.shape
        eye = jnp.eye(n_s, dtype=a.dtype)
        return jnp.einsum("abid,ij->daibj", blocks, eye).reshape(dim, 3 * n_s, 3 * n_s)


class ShallowNetBasis(AbstractBasis):
    """`q_h(τ) = Σ_{i=1..S} α_i σ(w_i τ + β_i)` per coordinate, with no output bias.

    A network does not pass through prescribed endpoints: the free-endpoint formulation adds
    continuity `q_h(0) = q_n` as an equation, the interpolating one multiplies the network by
    `τ(1 − τ)` and adds the chord.

    With a mirrored `symmetry` the neurons come in pairs `(w, β)` and `(−w, w + β)`; the second
    neuron `σ(w(1 − τ) + β)` is the first reflected about `τ = 1/2`, so the family of curves
    is closed under time reversal of the step. Only the first neuron of each pair has free
    hidden parameters, and the solve differentiates through the mirror map (the residual is
    the exact gradient of the action on the reduced family). Parameter layout of coordinate
    `d` (column `θ[:, d]`):

    - `NoSymmetry()`: `[α_1..α_S, w_1..w_S, β_1..β_S]` (`3S` parameters);
    - `MirrorPairs()`: `[α_1..α_S, w_1, w_3, .., w_{S−1}, β_1, β_3, .., β_{S−1}]` (`2S`),
      every neuron with its own output weight;
    - `SharedMirrorPairs()`: `[α_1, α_3, .., α_{S−1}, w_1, w_3, .., β_1, β_3, ..]` (`3S/2`),
      one output weight per pair, shared in the solve itself.

    **Arguments:**

    - `activation`: elementwise `σ`, e.g. `diffrax_vi.tanh` or `diffrax_vi.relu_k(3)`. It must
      be smooth enough for Newton (the Jacobian differentiates it three times) and keep the
      dtype of its input. JAX's own functions become the package's activation they compute
      (`diffrax_vi._activations.package_activation`): `jnp.tanh` and `jax.nn.tanh` are `tanh`,
      `jax.nn.sigmoid` is `sigmoid`, `jax.nn.gelu` is `gelu` and
      `functools.partial(jax.nn.gelu, approximate=False)` is `gelu_exact`, `jnp.sin` is `sin`,
      `jax.nn.elu` is `elu`, `jax.nn.relu` is `relu_k(1)`; so the basis, its repr and the
      solver's default step are the same whichever name is written. `tanh`, `sigmoid`,
      `gelu`, `gelu_exact` and `relu_k(k)` with `k >= 2` get the projected step
      (`VariableProjection`) by default; any other activation the all-parameter step, with an
      `AllParameterFallbackWarning` unless the formulation is chosen.
    - `width`: number of neurons `S` per coordinate (even with a mirrored symmetry).
    - `symmetry`: `NoSymmetry()` (default), `MirrorPairs()` or `SharedMirrorPairs()`.
    - `derivatives`: `"autodiff"` (default: JAX differentiates the network) or `"sympy"`: the
      neuron `α σ(wτ + β)` and its first derivatives in `(α, w, β, τ)` (and those of its
      τ-derivative) are taken by sympy and compiled to JAX once, as the reference's symbolic
      kernels; higher derivatives (the Newton Jacobian) differentiate that compiled code.
      Both give the same solution.
    """

    activation: Callable = eqx.field(static=True, converter=package_activation)
    width: int = eqx.field(static=True)
    symmetry: AbstractSymmetry = eqx.field(static=True, default=NoSymmetry())
    derivatives: str = eqx.field(static=True, default="autodiff")
    coordinatewise: ClassVar[bool] = True

    def __check_init__(self):
        if not callable(self.activation):
            raise TypeError(f"activation must be callable, got {type(self.activation).__name__}")
        if not isinstance(self.width, int) or isinstance(self.width, bool) or self.width < 1:
            raise ValueError(f"width must be a positive integer, got {self.width!r}")
        if not isinstance(self.symmetry, AbstractSymmetry):
            raise TypeError(
                "symmetry must be NoSymmetry(), MirrorPairs() or SharedMirrorPairs(), got "
                f"{self.symmetry!r}"
            )
        if self.derivatives not in ("autodiff", "sympy"):
            raise ValueError(f"derivatives must be 'autodiff' or 'sympy', got {self.derivatives!r}")
        if self.derivatives == "sympy":
            from .._codegen import sympy_activation  # sympy only when asked for

            sympy_activation(self.activation)  # refuses an activation with no sympy form
        if self.mirrored and self.width % 2:
            raise ValueError(
                f"mirrored neuron pairs need an even width; got width={self.width} with "
                f"{type(self.symmetry).__name__}()"
            )

    @property
    def mirrored(self) -> bool:
        return isinstance(self.symmetry, MirrorPairs | SharedMirrorPairs)

    @property
    def can_advance(self) -> bool:  # type: ignore[override]
        # A continued mirrored pair is no longer a mirrored pair.
        return not self.mirrored

    def num_params(self) -> int:
        s = self.width
        if isinstance(self.symmetry, MirrorPairs):
            return 2 * s
        if isinstance(self.symmetry, SharedMirrorPairs):
            return 3 * s // 2
        return 3 * s

    def split(self, theta: Array) -> tuple[Array, Array, Array]:
        """`(α, w, β)` of all `S` neurons, each of shape `(S, D)` (mirror pairs expanded)."""
        s = self.width
        if not self.mirrored:
            return theta[:s], theta[s : 2 * s], theta[2 * s :]
        k = s // 2
        n_alpha = s if isinstance(self.symmetry, MirrorPairs) else k
        alpha, w, beta = theta[:n_alpha], theta[n_alpha : n_alpha + k], theta[n_alpha + k :]
        if n_alpha == k:
            alpha = jnp.repeat(alpha, 2, axis=0)
        mw, mb = mirror(w, beta)
        return alpha, _interleave(w, mw), _interleave(beta, mb)

    def from_neurons(self, w: Array, b: Array, c: Array) -> Array:
        """The parameter column of one coordinate from per-neuron `(W, b, c)` (each `(S,)`),
        e.g. an OGA fit placed with this basis's symmetry."""
        if not self.mirrored:
            return jnp.concatenate([c, w, b])
        alpha = c if isinstance(self.symmetry, MirrorPairs) else c[0::2]
        return jnp.concatenate([alpha, w[0::2], b[0::2]])

    def num_output_weights(self) -> int:
        """Number of output weights `α` per coordinate (they lead the parameter column)."""
        return self.width // 2 if isinstance(self.symmetry, SharedMirrorPairs) else self.width

    @staticmethod
    def join(alpha: Array, w: Array, beta: Array) -> Array:
        """Parameters of an unmirrored network from `(α, w, β)`."""
        return jnp.concatenate([alpha, w, beta], axis=0)

    def evaluate(self, theta, tau):
        if self.derivatives == "sympy":
            from .sympy_kernels import symbolic_shallow_evaluate

            return symbolic_shallow_evaluate(self)(theta, tau)
        alpha, w, beta = self.split(theta)
        return jnp.sum(alpha * self.activation(w * tau + beta), axis=0)

    @property
    def has_jet(self) -> bool:
        """Whether `jet` applies: not with mirrored pairs (the parameters reach the neurons
        through the mirror map) nor with sympy-compiled derivatives."""
        return not self.mirrored and self.derivatives == "autodiff"

    def jet(self, theta: Array, taus: Array) -> NetworkJet | None:
        """The network's closed-form derivatives at the points `taus` (`NetworkJet`), or
        `None` where they do not apply (`has_jet`)."""
        if not self.has_jet:
            return None
        alpha, w, beta = self.split(theta)
        z = w * taus[:, None, None] + beta
        return NetworkJet(alpha, w, beta, taus, _activation_derivatives(self.activation, z))

    def advance(self, theta, ratio):
        if self.mirrored:
            return super().advance(theta, ratio)
        alpha, w, beta = self.split(theta)
        return self.join(alpha, w * ratio, beta + w)

    def check(self, dtype) -> None:
        check_activation(self.activation, dtype)

    def min_nodes(self) -> int:
        return network_min_nodes(self.width)

    def __repr__(self):
        extra = "" if not self.mirrored else f", symmetry={type(self.symmetry).__name__}()"
        if self.derivatives != "autodiff":
            extra += f", derivatives={self.derivatives!r}"
        return f"ShallowNetBasis({activation_name(self.activation)}, width={self.width}{extra})"
