"""The interface every ansatz implements."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree


class AbstractBasis(eqx.Module):
    """A family of curves `q_h(τ; θ)` on the unit step `τ ∈ [0, 1]`, one per degree of freedom.

    For the network and polynomial ansätze the parameters are an array `θ` of shape
    `(num_params, D)`: column `d` parametrises the curve of coordinate `d` (the curves of
    different coordinates share nothing). An ansatz may use any pytree instead (the symbolic
    ansatz keeps one weight vector per coordinate); it then overrides `zeros`.

    `can_advance` says whether `advance` exists (the `PreviousStep` warm start needs it);
    `linear` whether `q_h` is linear in `θ` (a least-squares fit then seeds it exactly).
    """

    can_advance: ClassVar[bool] = False
    linear: ClassVar[bool] = False

    #: Whether coordinate `d` of the curve depends on column `d` of `θ` (shape `(P, D)`)
    #: alone, which lets `FreeEndpoints.jacobian` assemble the step Jacobian by blocks.
    coordinatewise: ClassVar[bool] = False

    def num_params(self) -> int:
        """Number of parameters of the curve of one coordinate."""
        raise NotImplementedError

    def zeros(self, dim: int, dtype) -> PyTree:
        """All-zero parameters for `dim` coordinates (the solver state's placeholder)."""
        return jnp.zeros((self.num_params(), dim), dtype)

    def params_from(self, values, dtype) -> PyTree:
        """Parameters in the working dtype from user-given values (e.g. a VISE `init_w`)."""
        return jnp.asarray(values, dtype)

    def evaluate(self, theta: PyTree, tau) -> Array:
        """`q_h(τ; θ)`, shape `(D,)`."""
        raise NotImplementedError

    def value_and_derivative(self, theta: PyTree, tau) -> tuple[Array, Array]:
        """`(q_h(τ), dq_h/dτ)` at one `τ`, each of shape `(D,)`."""
        dtype = jax.tree_util.tree_leaves(theta)[0].dtype
        tau = jnp.asarray(tau, dtype)
        return jax.jvp(lambda s: self.evaluate(theta, s), (tau,), (jnp.ones_like(tau),))

    def sample_matrices(self, taus) -> tuple[Array, Array] | None:
        """`(V, S)` (NumPy, `(len(taus), num_params)` each) with `q_h(τ_i) = (V θ)_i` and
        `dq_h/dτ(τ_i) = (S θ)_i` for every coordinate, where the curve is that linear in `θ`
        with matrices known when traced; else `None` (the curve is then evaluated). With
        them a step's start at constant points is a product with constants, not an
        evaluation of the basis that the compiled program would keep."""
        del taus
        return None

    def advance(self, theta: PyTree, ratio) -> PyTree:
        """Parameters of the continued curve on the next step.

        Returns `θ'` with `q_h(τ; θ') = q_h(1 + ratio·τ; θ)`: the curve of this step carried
        past its end, in the local time of a next step whose length is `ratio` times this one.
        Only for ansätze with `can_advance`.
        """
        raise NotImplementedError(f"{self!r} cannot be continued past the end of a step")

    def at_step(self, t: Array, h: Array) -> AbstractBasis:
        """The ansatz on the step `[t, t + h]`.

        Ansätze in local time `τ` (all but the symbolic one) do not depend on the step and
        return themselves; an ansatz written in absolute time binds `t` and `h` here.
        """
        del t, h
        return self

    def check(self, dtype) -> None:
        """Raise `ValueError` if the ansatz cannot work in `dtype`."""

    def min_nodes(self) -> int:
        """The fewest quadrature nodes with which the step equations of this ansatz still
        determine the step (`NetworkVI` refuses a rule with fewer)."""
        return 1
