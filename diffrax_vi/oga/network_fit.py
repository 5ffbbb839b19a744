"""The OGA seed of a shallow network: one greedy fit per coordinate, placed with the
network's own mirror symmetry."""

from __future__ import annotations

import jax
from jaxtyping import Array

from .._ansatz.base import AbstractBasis
from .._ansatz.shallow import ShallowNetBasis
from .._parameter_seed import FitProblem
from .greedy import oga_fit

__all__ = ["check_network", "fit_network"]


def check_network(basis: AbstractBasis) -> None:
    """Refuse an ansatz the OGA cannot seed, naming the seeds that can."""
    if not isinstance(basis, ShallowNetBasis):
        raise ValueError(
            f"an OGA seed fits shallow networks; {basis!r} needs another initial_guess "
            "(e.g. LSGD() for DenseNetBasis, LeastSquaresFit() for LagrangeBasis)"
        )


def fit_network(basis: ShallowNetBasis, config, problem: FitProblem) -> Array:
    """Parameters `(num_params, D)` of `basis` fitted to `problem`'s targets by the OGA seed
    `config`."""
    check_network(basis)

    def one(y):
        res = oga_fit(
            config,
            basis.activation,
            problem.nodes,
            problem.weights,
            y,
            basis.width,
            modulation=problem.modulation,
            symmetry=basis.symmetry,
        )
        return basis.from_neurons(res.W, res.b, res.c)

    # One greedy fit after another (a compiled loop over coordinates), not `vmap`: batching
    # the greedy loop costs about a second more of tracing and compiling and runs no faster
    # for a few coordinates (benchmarks page, "Docstrings").
    return jax.lax.map(one, problem.targets.T).T
