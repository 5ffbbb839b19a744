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
