"""A conditional that stays lazy under `vmap` (`diffrax_vi._lazy`)."""

import jax.numpy as jnp
import numpy as np


def test_lazy_conditional_skips_the_expensive_branch_under_vmap():
    """`unless_all_skip` must not run `expensive` when no member needs it, even though
    `expensive` depends only on values fixed before the loop (which XLA's loop-invariant code
    motion would otherwise hoist out of it and run unconditionally: 4x slower ensembles)."""
    import time

    import jax

    from diffrax_vi._lazy import unless_all_skip

    def member(x, need):
        def expensive():  # ~3 Gflop, all of it loop-invariant
            m = jnp.outer(x, x) / (1 + jnp.dot(x, x))
            return jax.lax.fori_loop(0, 40, lambda i, a: jnp.tanh(a @ m), m)[0]

        return unless_all_skip(need, expensive, x)

    run = jax.jit(jax.vmap(member))
    x = jnp.linspace(0.0, 1.0, 4 * 400).reshape(4, 400)

    def timed(need):
        jax.block_until_ready(run(x, need))
        start = time.perf_counter()
        out = jax.block_until_ready(run(x, need))
        return out, time.perf_counter() - start

    skipped, t_skip = timed(jnp.zeros(4, bool))
    ran, t_ran = timed(jnp.array([False, True, False, False]))
    np.testing.assert_array_equal(skipped, x)
    np.testing.assert_array_equal(ran[0], x[0])
    assert not np.allclose(ran[1], x[1])
    assert t_skip < 0.1 * t_ran, (t_skip, t_ran)
