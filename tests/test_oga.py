"""Tests of the orthogonal greedy seed fit (`diffrax_vi.oga`)."""

import math

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from diffrax_vi._activations import relu_k, tanh  # noqa: E402
from diffrax_vi._quadrature import Simpson  # noqa: E402
from diffrax_vi.oga import (  # noqa: E402
    OGA,
    BiasGrid1d,
    NormalizedProjection,
    OGA1d,
    OGA1dNormalized,
    RawProjection,
    WeightedQR,
    oga_fit,
)
from diffrax_vi.oga._qr import pivoted_lstsq, qr_append, qr_init  # noqa: E402
from diffrax_vi.oga.dictionaries import bias_grid  # noqa: E402
from diffrax_vi.oga.fits import ridged_lstsq  # noqa: E402
from tests.helpers import oga_fixture, sqrt_eps  # noqa: E402

RELU3 = relu_k(3)

# The small kernels, compiled once per dtype (eager fori_loops would compile op by op).
pivoted_lstsq = jax.jit(pivoted_lstsq)
ridged_lstsq = jax.jit(ridged_lstsq)
qr_append = jax.jit(qr_append)

# The reference's regression pin (0-based atom indices).
PIN_ATOMS = [801, 400, 710, 285]
PIN_W = [1.0, -1.0, 1.0, -1.0]
PIN_B = [math.pi, math.pi, 1.7121679962064373, 1.335176877775662]
PIN_C = [-0.49460912014278396, 0.5665083163888716, 1.4395563049941698, -3.5558966254259077]
PIN_RESIDUAL = 0.0029557412009774313


fixture = oga_fixture


def weighted_error(result, activation, target):
    """Float64 weighted L2 error of the returned network against `target` on the nodes."""
    t, w = Simpson(10).nodes_weights_np()
    W, b, c = (np.asarray(a, np.float64) for a in (result.W, result.b, result.c))
    u = np.asarray(activation(jnp.asarray(np.outer(t, W) + b)), np.float64) @ c
    return float(np.sqrt(np.sum(w * (u - target(t)) ** 2)))


def atom_values(activation, W, b, dtype=np.float64):
    """Values of each neuron on the nodes, shape (M, S), in float64."""
    t, _ = Simpson(10).nodes_weights_np()
    W, b = np.asarray(W, np.float64), np.asarray(b, np.float64)
    return np.asarray(activation(jnp.asarray(np.outer(t, W) + b, dtype)), np.float64)


# --------------------------------------------------------------------------------------------
# 1. The reference's numeric pin.


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_reference_pin(dtype):
    nodes, weights, y = fixture(dtype)
    res = oga_fit(OGA1d(), RELU3, nodes, weights, y, 4, dict_amount=400)
    tol = sqrt_eps(dtype)
    assert np.asarray(res.atoms).tolist() == PIN_ATOMS
    assert int(res.placed) == 4
    assert int(res.rejected) == 0
    np.testing.assert_array_equal(np.asarray(res.W), np.asarray(PIN_W, dtype))
    np.testing.assert_allclose(np.asarray(res.b), PIN_B, rtol=8 * tol)
    np.testing.assert_allclose(np.asarray(res.c), PIN_C, rtol=64 * tol)
    np.testing.assert_allclose(float(res.residual), PIN_RESIDUAL, rtol=64 * tol)
    for name in ("W", "b", "c", "residual", "gains"):
        assert getattr(res, name).dtype == dtype, name
    assert res.atoms.dtype == jnp.int32
    assert np.all(np.asarray(res.gains) > 0)
    # The returned network reproduces the reported residual.
    assert weighted_error(res, RELU3, lambda t: np.cos(3 * t)) == pytest.approx(
        PIN_RESIDUAL, rel=64 * tol
    )


def test_float32_stays_float32_end_to_end():
    nodes, weights, y = fixture(np.float32)
    jaxpr = jax.make_jaxpr(
        lambda y: oga_fit(OGA1d(), RELU3, nodes, weights, y, 4, dict_amount=400))(y)
    text = str(jaxpr)
    assert "f32" in text
    assert "f64" not in text


def test_normalized_first_atom_is_one_step_optimal():
    # With one neuron the normalised score picks the atom with the smallest single-atom
    # residual (brute force); the raw projection does not (oga_spec §4.9: atom 259 vs 801).
    nodes, weights, y = fixture(np.float64)
    table = BiasGrid1d().atoms_np((-math.pi, math.pi), 400, np.float64)
    phi = atom_values(RELU3, table[:, 0], table[:, 1])
    sw = np.sqrt(np.asarray(weights))
    a, yy = phi * sw[:, None], np.asarray(y) * sw
    nrm2 = np.sum(a * a, axis=0)
    res2 = np.where(nrm2 > 0, yy @ yy - (yy @ a) ** 2 / np.where(nrm2 > 0, nrm2, 1), np.inf)
    best = int(np.argmin(res2))
    assert best == 259
    res = oga_fit(OGA1dNormalized(), RELU3, nodes, weights, y, 4, dict_amount=400)
    assert int(res.atoms[0]) == best
    # oga_spec §4.9: the normalised quartet [260, 599, 212, 540] (1-based), residual 9.80e-2.
    assert np.asarray(res.atoms).tolist() == [259, 598, 211, 539]
    assert float(res.residual) == pytest.approx(9.80e-2, rel=1e-2)


# --------------------------------------------------------------------------------------------
# 2. jit and vmap agree with the eager call.


def test_jit_and_vmap_match_eager():
    nodes, weights, _ = fixture(np.float64)
    t, _ = Simpson(10).nodes_weights_np()
    targets = np.stack([np.cos(3 * t), np.exp(2 * t) / 4, np.sin(5 * t + 1), np.zeros_like(t)])

    def fit(y):
        return oga_fit(OGA1d(), RELU3, nodes, weights, y, 4, dict_amount=400)

    eager = [fit(jnp.asarray(y)) for y in targets]
    batched = jax.jit(jax.vmap(fit))(jnp.asarray(targets))

    def check(got, want):
        np.testing.assert_array_equal(np.asarray(got.atoms), np.asarray(want.atoms))
        np.testing.assert_array_equal(np.asarray(got.W), np.asarray(want.W))
        np.testing.assert_array_equal(np.asarray(got.b), np.asarray(want.b))
        np.testing.assert_allclose(np.asarray(got.c), np.asarray(want.c), rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(float(got.residual), float(want.residual), rtol=1e-9)
        assert int(got.placed) == int(want.placed)
        assert int(got.rejected) == int(want.rejected)

    assert batched.W.shape == (len(targets), 4)
    for i, want in enumerate(eager):
        check(jax.tree.map(lambda a, i=i: a[i], batched), want)


# --------------------------------------------------------------------------------------------
# 3. Reduced precision and the activation check.


def test_float16_is_finite_and_float16():
    nodes, weights, y = fixture(np.float16)
    res = oga_fit(OGA1d(), RELU3, nodes, weights, y, 4, dict_amount=400)
    for name in ("W", "b", "c", "residual", "gains"):
        value = getattr(res, name)
        assert value.dtype == np.float16, name
        assert np.all(np.isfinite(np.asarray(value, np.float64))), name
    assert int(res.placed) == 4
    # Distinct neurons and a useful fit (float16 is coarse: a loose bound).
    pairs = {(float(w), float(b)) for w, b in zip(res.W, res.b, strict=True)}
    assert len(pairs) == 4
    assert float(res.residual) < 0.2


def test_float16_relu4_fill_avoids_selected_atoms():
    # At float16 the coherence guard (cap 1 - 2^-5) blocks wide neighbourhoods: on this
    # problem every usable ReLU^4 atom is blocked after three picks, so the loop stops early
    # and the fill falls back to usable atoms that were not selected.
    nodes, weights, y = fixture(np.float16)
    relu4 = relu_k(4)
    res = oga_fit(OGA1d(), relu4, nodes, weights, y, 4, dict_amount=400)
    for name in ("W", "b", "c", "residual", "gains"):
        value = getattr(res, name)
        assert value.dtype == np.float16, name
        assert np.all(np.isfinite(np.asarray(value, np.float64))), name
    placed = int(res.placed)
    assert 1 <= placed < 4
    check_placeholders(res, relu4, first=placed, dtype=np.float16)


def test_promoting_activation_is_refused():
    nodes, weights, y = fixture(np.float32)

    def promoting(x):
        return jnp.maximum(x, 0.0) ** 3 * jnp.float64(1)

    with pytest.raises(ValueError, match="promotes"):
        oga_fit(OGA1d(), promoting, nodes, weights, y, 4, dict_amount=400)
    nodes16, weights16, y16 = fixture(np.float16)
    with pytest.raises(ValueError, match="promotes"):
        oga_fit(OGA1d(), promoting, nodes16, weights16, y16, 4, dict_amount=400)


# --------------------------------------------------------------------------------------------
# 4. Placeholders (fill_unused) and fit quality.


def check_placeholders(res, activation, first, dtype=np.float64):
    W, b, c = (np.asarray(a) for a in (res.W, res.b, res.c))
    width = W.shape[0]
    pairs = {(float(w), float(bb)) for w, bb in zip(W, b, strict=True)}
    assert len(pairs) == width, "neurons must be pairwise distinct"
    np.testing.assert_array_equal(c[first:], 0)
    _, weights = Simpson(10).nodes_weights_np()
    values = atom_values(activation, W[first:], b[first:], dtype)
    norms = np.sqrt(weights @ values**2)
    # Not numerically zero on the nodes: the reference's fill could pick (w, b) = (-1, -pi),
    # which vanishes on [0, 1] for a ReLU power.
    assert np.all(norms > 1e-3), norms


def test_fill_unused_for_zero_target():
    nodes, weights, _ = fixture(np.float64)
    res = oga_fit(OGA1d(), RELU3, nodes, weights, jnp.zeros_like(nodes), 4, dict_amount=400)
    assert int(res.placed) == 0
    assert np.asarray(res.atoms).tolist() == [-1, -1, -1, -1]
    assert float(res.residual) == 0.0
    check_placeholders(res, RELU3, first=0)


def test_fill_unused_for_single_atom_target():
    # y is exactly the dictionary atom 600 = (+1, b_199); the greedy fit recovers it with
    # one neuron and stops (residual at rounding level); the rest are placeholders.
    table = BiasGrid1d().atoms_np((-math.pi, math.pi), 400, np.float64)
    w0, b0 = table[600]
    nodes, weights, _ = fixture(np.float64)
    y = RELU3(w0 * nodes + b0)
    res = oga_fit(OGA1dNormalized(), RELU3, nodes, weights, y, 4, dict_amount=400)
    assert int(res.placed) == 1
    assert np.asarray(res.atoms).tolist() == [600, -1, -1, -1]
    assert float(res.c[0]) == pytest.approx(1.0, rel=1e-12)
    assert float(res.residual) < 1e-14
    check_placeholders(res, RELU3, first=1)


def test_modulation_multiplies_every_atom():
    # With the boundary ansatz modulation t(1 - t), a modulated dictionary atom is recovered
    # exactly by one neuron with unit output weight.
    table = BiasGrid1d().atoms_np((-math.pi, math.pi), 400, np.float64)
    w0, b0 = table[600]
    nodes, weights, _ = fixture(np.float64)
    modulation = nodes * (1 - nodes)
    y = modulation * RELU3(w0 * nodes + b0)
    res = oga_fit(OGA1dNormalized(), RELU3, nodes, weights, y, 4, modulation=modulation,
                  dict_amount=400)
    assert int(res.placed) == 1
    assert int(res.atoms[0]) == 600
    assert float(res.c[0]) == pytest.approx(1.0, rel=1e-12)
    assert float(res.residual) < 1e-14


@pytest.mark.parametrize(("dtype", "bound"), [(np.float64, 1e-7), (np.float32, 1e-4)])
def test_tanh_smooth_target_fit(dtype, bound):
    # Measured: 6.1e-9 (float64) and 1.3e-5 (float32) for cos(3t), width 10, dict 400.
    nodes, weights, y = fixture(dtype)
    res = oga_fit(OGA1d(), tanh, nodes, weights, y, 10, dict_amount=400)
    assert int(res.placed) == 10
    assert float(res.residual) < bound
    assert weighted_error(res, tanh, lambda t: np.cos(3 * t)) < 2 * bound
    pairs = {(float(w), float(b)) for w, b in zip(res.W, res.b, strict=True)}
    assert len(pairs) == 10


# --------------------------------------------------------------------------------------------
# 5. Input validation.


def test_input_validation():
    nodes, weights, y = fixture(np.float64)
    fit = OGA1d()
    with pytest.raises(ValueError, match="length"):
        oga_fit(fit, RELU3, nodes, weights[:-1], y, 4, dict_amount=400)
    with pytest.raises(ValueError, match="length"):
        oga_fit(fit, RELU3, nodes, weights, y, 4, modulation=nodes[:-2], dict_amount=400)
    with pytest.raises(ValueError, match="one-dimensional"):
        oga_fit(fit, RELU3, nodes, weights, y[None, :], 4, dict_amount=400)
    with pytest.raises(ValueError, match="width"):
        oga_fit(fit, RELU3, nodes, weights, y, 0, dict_amount=400)
    with pytest.raises(ValueError, match="width"):
        oga_fit(fit, RELU3, nodes, weights, y, 2.0, dict_amount=400)
    with pytest.raises(ValueError, match="dict_amount"):
        oga_fit(fit, RELU3, nodes, weights, y, 4, dict_amount=0)
    with pytest.raises(ValueError, match="bias_interval"):
        oga_fit(fit, RELU3, nodes, weights, y, 4, bias_interval=(1.0, 1.0), dict_amount=400)
    with pytest.raises(ValueError, match="bias_interval"):
        oga_fit(fit, RELU3, nodes, weights, y, 4, bias_interval=(2.0, -2.0), dict_amount=400)
    with pytest.raises(ValueError, match="bias_interval"):
        oga_fit(fit, RELU3, nodes, weights, y, 4, bias_interval=(0.0, math.inf), dict_amount=400)
    with pytest.raises(ValueError, match="dtype"):
        oga_fit(fit, RELU3, nodes, weights.astype(jnp.float32), y, 4, dict_amount=400)
    with pytest.raises(ValueError, match="dtype"):
        oga_fit(fit, RELU3, nodes, weights, y.astype(jnp.float32), 4, dict_amount=400)
    with pytest.raises(ValueError, match="floating"):
        oga_fit(fit, RELU3, jnp.arange(11), weights, y, 4, dict_amount=400)
    with pytest.raises(ValueError, match="positive"):
        oga_fit(fit, RELU3, nodes, weights.at[3].set(0.0), y, 4, dict_amount=400)
    with pytest.raises(ValueError, match="OGA configuration"):
        oga_fit(RawProjection(), RELU3, nodes, weights, y, 4, dict_amount=400)
    with pytest.raises(ValueError, match="selection"):
        OGA(BiasGrid1d(), WeightedQR(), WeightedQR())
    with pytest.raises(ValueError, match="bool"):
        OGA(coherence=1)


# --------------------------------------------------------------------------------------------
# Configuration objects and kernels.


def test_configs_are_static_and_labelled():
    assert OGA1d() == OGA()
    assert hash(OGA1d()) == hash(OGA())
    assert OGA1d().label == "grid1d/raw/qr"
    assert OGA1dNormalized().label == "grid1d/normalized/qr"
    assert OGA1dNormalized() == OGA(BiasGrid1d(), NormalizedProjection(), WeightedQR())
    assert OGA1d(coherence=False) != OGA1d()
    assert jax.tree_util.tree_leaves(OGA1d()) == []


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_bias_grid(dtype):
    grid = bias_grid(-math.pi, math.pi, 8, dtype)
    assert grid.dtype == dtype and grid.shape == (9,)
    assert grid[0] == dtype(-math.pi) and grid[-1] == dtype(math.pi)
    assert np.all(np.diff(grid.astype(np.float64)) > 0)
    fine = bias_grid(-math.pi, math.pi, 70000, dtype)
    assert fine.shape == (70001,) and np.all(np.isfinite(fine))
    table = BiasGrid1d().atoms_np((-1.0, 1.0), 4, dtype)
    assert table.shape == (BiasGrid1d().size(4), 2) == (10, 2)
    np.testing.assert_array_equal(table[:, 0], [-1] * 5 + [1] * 5)
    np.testing.assert_array_equal(table[:5, 1], table[5:, 1])


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_pivoted_lstsq_and_ridge(dtype):
    tol = 32 * sqrt_eps(dtype)
    eps = float(np.finfo(dtype).eps)
    # Exact recovery with an unused (zero) column.
    a = np.array([[1, 0, 0], [0, 1, 0], [1, 1, 0], [1, -1, 0]], np.float64)
    x_true = np.array([0.5, 0.25, 0.0])
    x = pivoted_lstsq(
        jnp.asarray(a, dtype), jnp.asarray(a @ x_true, dtype), jnp.asarray(4 * eps, dtype)
    )
    assert x.dtype == dtype
    np.testing.assert_allclose(np.asarray(x, np.float64), x_true, rtol=tol, atol=tol)
    # Rank-deficient design: the dependent column gets a zero coefficient.
    a = np.array([[1, 0, 1], [0, 1, 0], [1, 1, 1], [2, 0, 2]], np.float64)
    y = np.array([1.0, 2.0, 3.0, 4.0])
    x = np.asarray(
        pivoted_lstsq(jnp.asarray(a, dtype), jnp.asarray(y, dtype), jnp.asarray(4 * eps, dtype)),
        np.float64,
    )
    assert np.count_nonzero(x) == 2
    best = np.linalg.norm(a @ np.linalg.pinv(a) @ y - y)
    assert np.linalg.norm(a @ x - y) == pytest.approx(best, rel=64 * sqrt_eps(dtype))
    # The ridged fallback is finite, close to the plain solution, and zero at unused columns.
    a = np.array([[1, 0, 0], [0, 1, 0], [1, 1, 0], [1, -1, 0]], np.float64)
    xr = ridged_lstsq(jnp.asarray(a, dtype), jnp.asarray(a @ x_true, dtype), jnp.int32(2))
    assert xr.dtype == dtype and float(xr[2]) == 0.0
    np.testing.assert_allclose(np.asarray(xr, np.float64), x_true, rtol=tol, atol=tol)


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_incremental_qr(dtype):
    state = qr_init(5, 3, dtype)
    gain_floor = jnp.asarray(sqrt_eps(dtype), dtype)
    cols = np.array([[1, 0, 0, 0, 0], [1, 1, 0, 0, 0], [0, 0, 1, 1, 0]], np.float64)
    for col in cols:
        state, rho, accepted = qr_append(state, jnp.asarray(col, dtype), gain_floor)
        assert bool(accepted) and float(rho) > 0
    assert int(state.k) == 3
    q, r = np.asarray(state.q, np.float64), np.asarray(state.r, np.float64)
    np.testing.assert_allclose(q.T @ q, np.eye(3), atol=32 * sqrt_eps(dtype))
    np.testing.assert_allclose(q @ r, cols.T, atol=32 * sqrt_eps(dtype))
    # A column in the span is refused and leaves the state unchanged.
    new, rho, accepted = qr_append(state, jnp.asarray([2, 2, 0, 0, 0], dtype), gain_floor)
    assert not bool(accepted) and float(rho) <= 3 * sqrt_eps(dtype)
    assert int(new.k) == 3
    np.testing.assert_array_equal(np.asarray(new.q), np.asarray(state.q))
