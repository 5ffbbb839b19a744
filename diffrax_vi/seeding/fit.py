"""Fit the seed network to an initial trajectory with the Orthogonal Greedy Algorithm."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..ansatz.base import AbstractBasis
from ..ansatz.shallow import ShallowNetBasis
from ..oga import OGA, AbstractSymmetry, oga_fit
from ..quadrature import Simpson

__all__ = ["fit_network"]


def fit_network(
    basis: AbstractBasis,
    config: OGA,
    labels: Array,
    bias_interval: tuple[float, float],
    dict_amount: int,
    *,
    modulated: bool = False,
    symmetry: AbstractSymmetry | None = None,
) -> Array:
    """Parameters `θ` (shape `(num_params, D)`) of `basis` fitted to `labels` `(N + 1, D)`.

    The labels sit on `τ_i = i/N`; the fit is in the composite-Simpson weighted norm, one
    greedy fit per coordinate. With `modulated`, every atom is multiplied by `τ(1 − τ)` (for
    an ansatz whose network term vanishes at both ends; the labels are then the deviation
    from the chord); `symmetry` places mirrored neuron pairs (`MirrorPairs`,
    `SharedMirrorPairs`).
    """
    if not isinstance(basis, ShallowNetBasis):
        raise TypeError(f"the OGA seed fits shallow networks; got {basis!r}")
    dtype = labels.dtype
    n = labels.shape[0] - 1
    # NumPy inputs stay constants under jit, so the OGA builds its dictionary once.
    np_dtype = np.dtype(jnp.dtype(dtype))
    t, w = Simpson(n).nodes_weights_np()
    nodes, weights = t.astype(np_dtype), w.astype(np_dtype)
    modulation = (t * (1 - t)).astype(np_dtype) if modulated else None

    def one(y):
        res = oga_fit(
            config,
            basis.activation,
            nodes,
            weights,
            y,
            basis.width,
            bias_interval=bias_interval,
            dict_amount=dict_amount,
            modulation=modulation,
            symmetry=symmetry,
        )
        return jnp.concatenate([res.c, res.W, res.b])

    return jax.vmap(one, in_axes=1, out_axes=1)(labels)
