"""Parameter seeds: fit the ansatz to an initial trajectory before the Newton solve.

The trajectory is given as targets on the uniform grid `τ_i = i/N` (`N` even), and every fit
works in the composite-Simpson weighted norm on that grid. With `modulated`, the ansatz is
multiplied by `τ(1 − τ)` there (the network term of the interpolating formulation; the targets
are then the deviation from the chord).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from ..ansatz.base import AbstractBasis
from ..ansatz.shallow import ShallowNetBasis
from ..linalg import damped_least_squares, solve
from ..oga import OGA, OGAReference, oga_fit
from ..quadrature import Simpson

__all__ = [
    "AbstractParameterSeed",
    "FitProblem",
    "InitialWeights",
    "LeastSquaresFit",
    "fit_network",
    "fit_problem",
    "with_constant_grid",
]


class FitProblem(NamedTuple):
    """A seed fit: targets `(N + 1, D)` on `τ_i = i/N` with Simpson weights, optionally
    modulated by `τ(1 − τ)`; plus the previous step's converged parameters for seeds that
    warm-start (`fresh` is true before the first step)."""

    nodes: np.ndarray
    weights: np.ndarray
    modulation: np.ndarray | None
    targets: Array
    previous: PyTree
    fresh: Array


def fit_problem(targets: Array, modulated: bool, previous: PyTree, fresh: Array) -> FitProblem:
    """The `FitProblem` of `targets` on the Simpson grid of their length."""
    n = targets.shape[0] - 1
    # NumPy arrays stay compile-time constants, so the OGA builds its dictionary once.
    np_dtype = np.dtype(jnp.dtype(targets.dtype))
    t, w = Simpson(n).nodes_weights_np()
    modulation = (t * (1 - t)).astype(np_dtype) if modulated else None
    return FitProblem(t.astype(np_dtype), w.astype(np_dtype), modulation, targets, previous, fresh)


def with_constant_grid(problem: FitProblem) -> FitProblem:
    """`problem` with its grid (nodes, weights, modulation) as NumPy constants again.

    A problem that travelled through a transformation's arguments (a root find's `args`, a
    loop carry) comes back with its grid traced, and the OGA then rebuilds its dictionary
    inside the compiled program on every call. The grid depends only on the targets' length,
    so it is rebuilt here instead."""
    return fit_problem(
        problem.targets, problem.modulation is not None, problem.previous, problem.fresh
    )


class AbstractParameterSeed(eqx.Module):
    """A way to choose the ansatz parameters that start the Newton solve of a step."""

    def fit(self, basis: AbstractBasis, problem: FitProblem) -> PyTree:
        """Parameters of `basis` for the trajectory in `problem`."""
        raise NotImplementedError

    def check(self, basis: AbstractBasis) -> None:
        """Raise a clear error if this seed cannot fit `basis`."""


def fit_network(
    basis: ShallowNetBasis,
    config: OGA | OGAReference,
    problem: FitProblem,
    bias_interval: tuple[float, float],
    dict_amount: int,
) -> Array:
    """OGA seed: parameters `(num_params, D)` of a shallow network, one greedy fit per
    coordinate, placed with the basis's own mirror symmetry."""
    if not isinstance(basis, ShallowNetBasis):
        raise TypeError(f"the OGA seed fits shallow networks; got {basis!r}")

    def one(y):
        res = oga_fit(
            config,
            basis.activation,
            problem.nodes,
            problem.weights,
            y,
            basis.width,
            bias_interval=bias_interval,
            dict_amount=dict_amount,
            modulation=problem.modulation,
            symmetry=basis.symmetry,
        )
        return basis.from_neurons(res.W, res.b, res.c)

    # One greedy fit after another (a compiled loop over coordinates), not `vmap`: batching
    # the greedy loop costs about a second more of tracing and compiling and runs no faster
    # for a few coordinates (benchmarks page, "Docstrings").
    return jax.lax.map(one, problem.targets.T).T


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

    def fit(self, basis, problem):
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

    def fit(self, basis, problem):
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


def seed_parameters(
    seed, basis: AbstractBasis, problem: FitProblem, bias_interval, dict_amount
) -> PyTree:
    """Dispatch a seed (an `OGA` configuration or an `AbstractParameterSeed`)."""
    if isinstance(seed, OGA | OGAReference):
        return fit_network(basis, seed, problem, bias_interval, dict_amount)
    return seed.fit(basis, problem)
