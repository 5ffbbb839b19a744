"""What a parameter seed is: a fit of the ansatz's parameters to a trajectory estimate over
the step (`FitProblem`), which starts the step's nonlinear solve.

The trajectory is given as targets on the uniform grid `τ_i = i/N` (`N` even), and every fit
works in the composite-Simpson weighted norm on that grid. With `modulated`, the ansatz is
multiplied by `τ(1 − τ)` there (the network term of the interpolating formulation; the targets
are then the deviation from the chord). The seeds themselves are in `diffrax_vi._seeding` and
`diffrax_vi.oga`.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PyTree

from ._ansatz.base import AbstractBasis
from ._quadrature import Simpson

__all__ = ["AbstractParameterSeed", "FitProblem", "fit_problem", "with_constant_grid"]


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
    """A way to choose the ansatz parameters that start the Newton solve of a step (the
    solver's `initial_guess`): the OGA, `LSGD`, `TrainingMethod`, `LeastSquaresFit`,
    `InitialWeights`, `TrajectoryFit`."""

    def parameters(self, basis: AbstractBasis, problem: FitProblem) -> PyTree:
        """Parameters of `basis` for the trajectory in `problem`."""
        raise NotImplementedError

    def check(self, basis: AbstractBasis) -> None:
        """Raise a clear error if this seed cannot fit `basis`."""

    def with_dictionary(self, **options) -> AbstractParameterSeed:
        """This seed with other dictionary options (`bias_interval`, `dict_amount`): only the
        OGA has a dictionary."""
        raise TypeError(
            f"{', '.join(sorted(options))} configure the OGA's dictionary; the seed {self!r} "
            "has none"
        )
