"""Parameter seeds that fit in one solve (`LeastSquaresFit`, `InitialWeights`), and the refit
of the previous step's output weights. The seed interface is `diffrax_vi._parameter_seed`."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from .._ansatz.shallow import ShallowNetBasis
from .._linalg import damped_least_squares, solve
from .._parameter_seed import AbstractParameterSeed, FitProblem

__all__ = ["InitialWeights", "LeastSquaresFit", "frozen_values", "refit_output_weights"]


def refit_output_weights(basis: ShallowNetBasis, problem: FitProblem) -> tuple[Array, Array]:
    """The previous step's neurons with their output weights refitted to this step's targets.

    The hidden weights and biases of `problem.previous` are kept; the output weights (in which
    the network is linear) solve the Simpson-weighted least-squares fit to the targets, per
    coordinate, with a tiny Tikhonov term that keeps redundant neurons' weights bounded.
    Returns the parameters and the relative misfit `‖N − y‖ / (1 + max|y|)` (weighted `L²`
    norm on `[0, 1]`, largest over coordinates), which decides whether the fit is good enough
    to replace a fresh OGA seed.
    """
    targets = problem.targets
    dtype = targets.dtype
    nodes = jnp.asarray(problem.nodes, dtype)
    sw = jnp.sqrt(jnp.asarray(problem.weights, dtype))
    k = basis.num_output_weights()

    def one(theta, y):
        def curve(alpha, tau):
            return basis.evaluate(theta.at[:k].set(alpha)[:, None], tau)[0]

        design = jax.vmap(lambda tau: jax.grad(curve)(theta[:k], tau))(nodes)
        if problem.modulation is not None:
            design = design * jnp.asarray(problem.modulation, dtype)[:, None]
        a = design * sw[:, None]
        reg = jnp.sqrt(jnp.finfo(dtype).eps) * jnp.max(jnp.abs(a))
        alpha = damped_least_squares(a, y * sw, reg)
        misfit = jnp.sqrt(jnp.sum((a @ alpha - y * sw) ** 2)) / (1 + jnp.max(jnp.abs(y)))
        return theta.at[:k].set(alpha), misfit

    theta, misfit = jax.vmap(one, in_axes=(1, 1), out_axes=(1, 0))(problem.previous, targets)
    return theta, jnp.max(misfit)


class LeastSquaresFit(AbstractParameterSeed):
    """Weighted least-squares fit of an ansatz that is linear in its parameters (the
    polynomial cGVI basis): exact in one solve, no greedy selection."""

    def check(self, basis):
        if not basis.linear:
            raise ValueError(f"LeastSquaresFit needs an ansatz linear in its parameters; {basis!r}")

    def parameters(self, basis, problem):
        dtype = problem.targets.dtype
        nodes = jnp.asarray(problem.nodes, dtype)
        zeros = jnp.zeros((basis.num_params(), 1), dtype)
        # Design matrix Φ[i, k] = ∂q_h(τ_i)/∂θ_k of one coordinate.
        design = jax.vmap(lambda t: jax.jacfwd(lambda th: basis.evaluate(th, t)[0])(zeros))(nodes)
        design = design[:, :, 0]
        if problem.modulation is not None:
            design = design * jnp.asarray(problem.modulation, dtype)[:, None]
        sw = jnp.sqrt(jnp.asarray(problem.weights, dtype))[:, None]
        a, y = design * sw, problem.targets * sw
        # Normal equations of a small, well-conditioned basis (Lagrange polynomials).
        return solve(a.T @ a, a.T @ y)


def frozen_values(values):
    """Nested sequences of numbers as nested tuples of floats (hashable, for static fields)."""
    if isinstance(values, int | float):
        return float(values)
    try:
        return tuple(frozen_values(v) for v in values)
    except TypeError:
        return float(values)


class InitialWeights(AbstractParameterSeed):
    """Fixed starting parameters, then the previous step's converged ones (VISE's seed).

    The first step starts from `init`; each later step from the previous converged
    parameters, unless they have drifted more than `restart_radius` (Euclidean norm over all
    parameters) from `init`, in which case the step restarts from `init` (the reference's
    rule, with its radius 1 as default). The trajectory labels are not used.

    **Arguments:**

    - `init`: the parameters, in the layout of the ansatz (for `SymbolicAnsatz`, one weight
      sequence per coordinate).
    - `restart_radius`: see above; `None` never restarts.
    """

    init: PyTree = eqx.field(static=True, converter=frozen_values)
    restart_radius: float | None = eqx.field(static=True, default=1.0)

    def parameters(self, basis, problem):
        dtype = problem.targets.dtype
        init = basis.params_from(self.init, dtype)
        previous = problem.previous
        if self.restart_radius is None:
            drift_ok = jnp.array(True)
        else:
            leaves = jax.tree_util.tree_leaves(
                jax.tree_util.tree_map(lambda a, b: jnp.sum((a - b) ** 2), previous, init)
            )
            drift_ok = jnp.sqrt(sum(leaves)) <= self.restart_radius
        use_init = problem.fresh | ~drift_ok
        return jax.tree_util.tree_map(lambda a, b: jnp.where(use_init, a, b), init, previous)
