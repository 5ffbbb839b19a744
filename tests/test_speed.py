"""Speed options keep results: the Newton Jacobian by reverse mode equals forward mode."""

import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import diffrax_vi as dvi


def test_jacobian_modes_agree():
    def fn(x, _):
        return jnp.array([x[0] ** 2 + x[1] - 2.0, jnp.sin(x[0]) * x[1] - jnp.sin(1.0)])

    x0 = jnp.array([1.3, 0.6])
    roots = []
    for mode in ("fwd", "rev"):
        sol = optx.root_find(fn, dvi.LevenbergMarquardt(jacobian=mode), x0, max_steps=50)
        roots.append(np.asarray(sol.value))
        assert int(sol.stats["num_steps"]) <= 10
    np.testing.assert_allclose(roots[0], [1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(roots[0], roots[1], atol=1e-14)


def test_jacobian_mode_is_checked():
    with pytest.raises(ValueError, match="jacobian must be"):
        dvi.LevenbergMarquardt(jacobian="central")


def test_lazy_conditional_skips_the_expensive_branch_under_vmap():
    """`unless_all_skip` must not run `expensive` when no member needs it, even though
    `expensive` depends only on values fixed before the loop (which XLA's loop-invariant code
    motion would otherwise hoist out of it and run unconditionally: 4x slower ensembles)."""
    import time

    import jax

    from diffrax_vi.lazy import unless_all_skip

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
