"""A conditional that stays lazy under `jax.vmap`.

`lax.cond` with a batched predicate becomes a `select` that evaluates both branches for every
member of the batch, so an expensive branch taken by no member is still paid for. A while loop
of at most one iteration runs its body only while some member still needs it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

__all__ = ["unless_all_skip"]


def unless_all_skip(need: Array, expensive: Callable[[], PyTree], cheap: PyTree) -> PyTree:
    """`expensive()` where `need`, else `cheap` (same structure, shapes and dtypes).

    Unbatched this costs what `lax.cond` does. Under `vmap`, `expensive` runs (for every
    member) only if at least one member needs it, and members that do not keep `cheap`.
    """
    # The values `expensive` closes over travel through the loop behind an optimisation
    # barrier: otherwise XLA's loop-invariant code motion hoists the whole of `expensive` out
    # of the loop (its inputs never change), and it runs unconditionally.
    converted, consts = jax.closure_convert(expensive)

    def body(carry):
        _, _, operands = carry
        operands = jax.lax.optimization_barrier(operands)
        return jnp.array(False), converted(*operands), operands

    return jax.lax.while_loop(lambda carry: carry[0], body, (need, cheap, tuple(consts)))[1]
