"""Dense linear algebra in the working precision (`diffrax_vi._linalg`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

F64 = jnp.float64


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32, jnp.float16])
def test_damped_least_squares_solves_the_regularised_problem(dtype):
    """`d = argmin ‖J d − r‖² + μ‖d‖²`, also for a singular `J`, against the normal equations
    solved in float64, and in the dtype of the right-hand side."""
    from diffrax_vi._linalg import damped_least_squares

    rng = np.random.default_rng(3)
    jac = rng.standard_normal((12, 12))
    jac[:, -1] = jac[:, 0]  # rank-deficient, as the network steps are
    rhs = rng.standard_normal(12)
    mu = 1e-2
    expected = np.linalg.solve(jac.T @ jac + mu * np.eye(12), jac.T @ rhs)
    d = damped_least_squares(jnp.asarray(jac, dtype), jnp.asarray(rhs, dtype),
                             jnp.sqrt(jnp.asarray(mu, dtype)))
    assert d.dtype == dtype
    eps = float(jnp.finfo(dtype).eps)
    tol = 1e-10 if dtype == jnp.float64 else 300 * eps
    np.testing.assert_allclose(np.asarray(d, np.float64), expected, rtol=0,
                               atol=tol * np.max(np.abs(expected)))


@pytest.mark.parametrize("rows", [30, 12, 5, 2])
def test_damped_least_squares_takes_any_shape_and_several_right_hand_sides(rows):
    """Tall, square and wide matrices (the seed fits are tall, the Newton steps square), and a
    matrix of right-hand sides solved column by column, as the seed fits pass them (the
    right-hand sides ride along as columns of the factorised matrix)."""
    from diffrax_vi._linalg import damped_least_squares

    rng = np.random.default_rng(4)
    jac = rng.standard_normal((rows, 12))
    rhs = rng.standard_normal((rows, 3))
    mu = 0.3
    normal = jac.T @ jac + mu * np.eye(12)
    expected = np.linalg.solve(normal, jac.T @ rhs)
    d = damped_least_squares(jnp.asarray(jac), jnp.asarray(rhs), jnp.sqrt(mu))
    assert d.shape == (12, 3)
    np.testing.assert_allclose(np.asarray(d), expected, rtol=0, atol=1e-12)
    for j in range(3):
        one = damped_least_squares(jnp.asarray(jac), jnp.asarray(rhs[:, j]), jnp.sqrt(mu))
        assert one.shape == (12,)
        np.testing.assert_allclose(np.asarray(one), expected[:, j], rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32, jnp.float16])
def test_unpivoted_inverse_in_a_row_order(dtype):
    """Gauss–Jordan without pivoting inverts a matrix whose leading entries vanish in its own
    row order but not in the given one, and works in float32 below 32 bits."""
    from diffrax_vi._linalg import unpivoted_inverse

    rng = np.random.default_rng(5)
    n = 9
    matrix = rng.standard_normal((n, n)) + 6 * np.eye(n)
    # rows 0 and 7 swapped: a zero pivot in the given order, none in the order (7, ..., 0)
    matrix[[0, 7]] = matrix[[7, 0]]
    matrix[0, 0] = 0.0
    order = np.arange(n)
    order[[0, 7]] = [7, 0]
    inverse = unpivoted_inverse(jnp.asarray(matrix, dtype), order)
    work = jnp.float32 if dtype == jnp.float16 else dtype
    assert inverse.dtype == work
    eps = float(jnp.finfo(work).eps)
    rounded = np.asarray(jnp.asarray(matrix, dtype), np.float64)
    np.testing.assert_allclose(np.asarray(inverse, np.float64) @ rounded, np.eye(n), rtol=0,
                               atol=100 * eps)


def test_unpivoted_inverse_is_non_finite_at_a_zero_pivot():
    """A vanishing pivot is not hidden: the caller sees non-finite entries and falls back."""
    from diffrax_vi._linalg import unpivoted_inverse

    matrix = jnp.array([[0.0, 1.0], [1.0, 0.0]])
    assert not bool(jnp.all(jnp.isfinite(unpivoted_inverse(matrix))))
    np.testing.assert_allclose(unpivoted_inverse(matrix, np.array([1, 0])), matrix)


def test_unpivoted_inverse_refuses_what_it_cannot_invert_by_name():
    from diffrax_vi._linalg import unpivoted_inverse

    with pytest.raises(ValueError, match="square matrix"):
        unpivoted_inverse(jnp.ones((2, 3)))
    with pytest.raises(ValueError, match="permutation"):
        unpivoted_inverse(jnp.eye(3), np.array([0, 0, 1]))
    with pytest.raises(ValueError, match="permutation"):
        unpivoted_inverse(jnp.eye(3), np.array([0, 1]))


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32, jnp.float16])
@pytest.mark.parametrize("n", [3, 10, 16])
def test_unpivoted_inverse_under_vmap_is_the_loop_of_single_inverses(dtype, n):
    """Under `vmap` the elimination runs with the members on the last axis (one update over
    all of them per column): the same arithmetic in the same order, so every member's
    inverse is the single one to the bit, in a row order, and under nested `vmap`s (in
    float32 below 32 bits, as the single one)."""
    import jax

    from diffrax_vi._linalg import unpivoted_inverse

    rng = np.random.default_rng(n)
    matrices = jnp.asarray(rng.standard_normal((2, 5, n, n)) + 4 * np.eye(n), dtype)
    order = np.roll(np.arange(n), 1)
    for rows in (None, order):
        def inverse(a, rows=rows):
            return unpivoted_inverse(a, rows)

        single = jax.jit(inverse)
        loop = jnp.stack([jnp.stack([single(a) for a in group]) for group in matrices])
        mapped = jax.jit(jax.vmap(jax.vmap(inverse)))(matrices)
        assert mapped.dtype == loop.dtype == jnp.result_type(dtype, jnp.float32)  # its work
        np.testing.assert_array_equal(mapped, loop)
        np.testing.assert_array_equal(jax.jit(jax.vmap(inverse))(matrices[0]), loop[0])


def test_unpivoted_inverse_differentiates_as_an_inverse_alone_and_under_vmap():
    """Forward and reverse mode, alone and under `vmap` (whose batching rule has no
    derivative of its own): the derivative of the inverse, `−A⁻¹ dA A⁻¹`."""
    import jax

    from diffrax_vi._linalg import unpivoted_inverse

    rng = np.random.default_rng(7)
    matrices = jnp.asarray(rng.standard_normal((4, 6, 6)) + 5 * np.eye(6))
    order = np.array([1, 0, 2, 3, 5, 4])

    def loss(inverse):
        return lambda a: jnp.sum(jnp.sin(inverse(a)))

    ours = loss(lambda a: unpivoted_inverse(a, order))
    lapack = loss(jnp.linalg.inv)
    expected = jax.vmap(jax.grad(lapack))(matrices)
    np.testing.assert_allclose(jax.vmap(jax.grad(ours))(matrices), expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(
        jax.grad(lambda m: jnp.sum(jax.vmap(ours)(m)))(matrices), expected, rtol=0, atol=1e-14
    )
    np.testing.assert_allclose(jax.jacfwd(lambda a: unpivoted_inverse(a, order))(matrices[0]),
                               jax.jacfwd(jnp.linalg.inv)(matrices[0]), rtol=0, atol=1e-14)


@pytest.mark.parametrize("n", [1, 2, 7, 16, 33])
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32, jnp.float16])
def test_elimination_solve_is_backward_stable(n, dtype):
    """Gaussian elimination with partial pivoting: the residual of the computed solution is at
    the rounding of the working precision (float32 below it), relative to `‖A‖ ‖x‖`, and the
    result has the dtype of the right-hand side."""
    from diffrax_vi._linalg import elimination_solve

    rng = np.random.default_rng(n)
    matrix = rng.standard_normal((n, n))
    if n > 1:
        matrix[0, 0] = 0.0  # a zero leading pivot: elimination without row swaps would fail
    rhs = rng.standard_normal(n)
    x = elimination_solve(jnp.asarray(matrix, dtype), jnp.asarray(rhs, dtype))
    assert x.dtype == dtype
    exact_inputs = (np.asarray(jnp.asarray(matrix, dtype), np.float64),
                    np.asarray(jnp.asarray(rhs, dtype), np.float64))
    x64 = np.asarray(x, np.float64)
    residual = np.max(np.abs(exact_inputs[0] @ x64 - exact_inputs[1]))
    scale = np.linalg.norm(exact_inputs[0], np.inf) * np.max(np.abs(x64))
    work_eps = float(jnp.finfo(jnp.float32 if dtype == jnp.float16 else dtype).eps)
    out_eps = float(jnp.finfo(dtype).eps)
    # n eps for the elimination, plus the rounding of the result to its dtype
    bound = 4 * n * work_eps + 2 * out_eps * np.linalg.cond(exact_inputs[0], np.inf)
    assert residual <= bound * scale


def test_elimination_solve_under_vmap_and_its_failures():
    """`vmap` gives each member's own pivots (the loop's answers), a singular matrix gives
    non-finite entries (the caller's check), and shapes that do not fit are named."""
    from diffrax_vi._linalg import elimination_solve

    rng = np.random.default_rng(7)
    matrices = rng.standard_normal((6, 5, 5))
    matrices[::2, 0, 0] = 0.0
    rhs = rng.standard_normal((6, 5))
    batched = jax.vmap(elimination_solve)(jnp.asarray(matrices), jnp.asarray(rhs))
    looped = np.stack([elimination_solve(jnp.asarray(a), jnp.asarray(b))
                       for a, b in zip(matrices, rhs, strict=True)])
    np.testing.assert_allclose(np.asarray(batched), looped, rtol=0, atol=1e-13)
    expected = np.linalg.solve(matrices, rhs[..., None])[..., 0]
    np.testing.assert_allclose(np.asarray(batched), expected, rtol=1e-11, atol=1e-12)
    assert not np.all(np.isfinite(np.asarray(elimination_solve(jnp.zeros((3, 3)), jnp.ones(3)))))
    with pytest.raises(ValueError, match="square matrix and a vector"):
        elimination_solve(jnp.ones((3, 2)), jnp.ones(3))
    with pytest.raises(ValueError, match="square matrix and a vector"):
        elimination_solve(jnp.ones((3, 3)), jnp.ones((3, 1)))


def test_elimination_solve_compiles_without_library_calls():
    """What it exists for: no LAPACK call and no product for the dot library in its program
    (either keeps XLA's CPU backend from compiling a loop around it whole)."""
    from diffrax_vi._linalg import elimination_solve

    program = jax.jit(elimination_solve).lower(jnp.ones((6, 6)) + jnp.eye(6), jnp.ones(6))
    text = program.compile().as_text()
    assert "custom-call" not in text and "kind=kCustom" not in text
