"""What an OGA fit returns (shared by the greedy fit and the reference's baseline)."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array

__all__ = ["OGAResult"]


class OGAResult(eqx.Module):
    """The outcome of `oga_fit`: a shallow network plus diagnostics.

    All arrays are in the working dtype `T` of the fit (or int32). With `G` the number of
    greedy steps (`width` divided by the neurons per atom of the symmetry, i.e. `width` for
    `NoSymmetry`):

    **Arguments:**

    - `W`: `(width,)` hidden weights.
    - `b`: `(width,)` biases.
    - `c`: `(width,)` output weights; zero for placeholder neurons.
    - `atoms`: `(G,)` 0-based dictionary indices accepted by the greedy loop, in order, and
        `-1` for steps that were not taken.
    - `placed`: number of neurons placed by the greedy loop (placeholders excluded).
    - `residual`: the weighted residual norm `sqrt(sum_j w_j (u(t_j) - y_j)^2)` of the greedy
        fit, in true (unscaled) units.
    - `gains`: `(G,)` rank gain of each accepted atom (norm of the part of its column
        orthogonal to the previously selected ones, in the dictionary's power-of-two scaled
        units); zero for steps not taken.
    - `rejected`: number of chosen atoms refused when appending their column to the QR
        factorisation.
    """

    W: Array
    b: Array
    c: Array
    atoms: Array
    placed: Array
    residual: Array
    gains: Array
    rejected: Array
