"""Parameter seeds that train the network on the initial trajectory (the reference's
`LSGD` and `TrainingMethod`).

Both fit each coordinate separately, from a deterministic initialisation drawn from an explicit
PRNG key, in the working precision, with the Simpson weights of the fit grid in the loss and
with the `τ(1 − τ)` modulation of the interpolating formulation honoured. They run entirely in
`lax` loops, so they compile once and work inside the solver's `jit`. Float16 fits run their
arithmetic in float32 (as `diffrax_vi._linalg` does for LAPACK; Adam's second moment would
underflow in half precision) and return float16 parameters.

Differences from the reference, all deliberate: the explicit key replaces reseeding the global
RNG with 42; training happens in the working dtype instead of always in float64; the stopping
tolerances scale with the dtype and with the size of the targets instead of fixed float64
numbers; the box initialisation puts each unit's hyperplane through its box point (the
reference has the sign of the bias flipped) and gives every unit a moderate, dtype-dependent
steepness (`box_layer`, `default_init_scale`); the default loss of `TrainingMethod` is the smooth
mean-square error; and the default epoch counts are measured to give a seed Newton converges
from, not 50 000 per coordinate per step.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, PyTree

from .._ansatz.base import AbstractBasis
from .._ansatz.dense import DenseNetBasis
from .._ansatz.shallow import ShallowNetBasis
from .._linalg import damped_least_squares
from .._parameter_seed import AbstractParameterSeed, FitProblem
from .._precision import lapack_dtype

__all__ = ["LSGD", "TrainingMethod", "box_layer", "default_init_scale"]


# ------------------------------------------------------------------------------------------------
# Networks as (hidden layers, output weights), one coordinate at a time.


def _check_network(seed: AbstractParameterSeed, basis: AbstractBasis) -> None:
    name = type(seed).__name__
    if isinstance(basis, DenseNetBasis):
        return
    if isinstance(basis, ShallowNetBasis):
        if basis.mirrored:
            raise ValueError(
                f"{name} trains every neuron independently and cannot keep the mirrored neuron "
                f"pairs of {basis!r}; use an OGA seed (e.g. OGA1d()) for mirrored shallow "
                "networks"
            )
        return
    raise ValueError(
        f"{name} trains network ansätze (DenseNetBasis, ShallowNetBasis); it cannot fit {basis!r}"
    )


def default_init_scale(dtype) -> float:
    """Default `scale` of `box_layer` in `dtype`: `eps^(1/16)`, i.e. 0.105 for float64, 0.37
    for float32, 0.65 for float16.

    Small scales keep every unit in the nearly linear part of a sigmoidal activation, which
    on the short, gently curved trajectory of one step gives well-conditioned seeds; but the
    curvature the units contribute, of order `scale²` and beyond, must stay resolvable in the
    working precision. On the harmonic-oscillator fixture (DenseNet 8×8, tanh) float64 runs
    were accurate for scales 0.03–0.3 and failed for ≥ 2; float32 needed about 0.3–0.6.
    """
    return float(jnp.finfo(dtype).eps) ** (1 / 16)


def box_layer(key: Array, inputs: Array, width: int, scale: float) -> tuple[Array, Array]:
    """Box initialisation of one layer `x ↦ W x + b` with `width` units.

    Each unit gets a random direction `n` (uniform on the sphere) and a random point `p` in the
    box `[lo, hi]` spanned by the layer's `inputs` (shape `(M, n_in)`: the values the layer
    sees on the fit grid), and its hyperplane passes through `p`: `W = k n`, `b = −W·p`. So the
    kinks or centres of the units are spread over the region where the layer's inputs actually
    lie (Cyr, Gulian, Patel, Perego, Trask, "Robust training and initialization of deep neural
    networks: an adaptive basis viewpoint", 2020).

    The steepness differs from that paper: there `k = 1/(n·(p_max − p))` makes the
    pre-activation 1 at the far corner, so a unit whose point lies near that corner is
    arbitrarily steep, and such seeds made the Newton solve of a step fail. Here
    `k = scale / extent`, with `extent = Σ_j |n_j| (hi_j − lo_j)` the width of the box along
    `n`: over the box every unit's pre-activation sweeps an interval of length `scale` that
    contains 0.

    **Arguments:**

    - `key`: a `jax.random` key.
    - `inputs`: `(M, n_in)` sample of the layer's inputs.
    - `width`: number of units.
    - `scale`: length of the pre-activation interval of each unit over the box.

    **Returns:** `W` of shape `(width, n_in)` and `b` of shape `(width,)`, in the dtype of
    `inputs`.
    """
    dtype = inputs.dtype
    n_in = inputs.shape[1]
    lo, hi = jnp.min(inputs, axis=0), jnp.max(inputs, axis=0)
    kp, kn = jax.random.split(key)
    zero, one = jnp.zeros((), dtype), jnp.ones((), dtype)  # no float64 bounds in float32 runs
    p = lo + jax.random.uniform(kp, (width, n_in), dtype, zero, one) * (hi - lo)
    n = jax.random.normal(kn, (width, n_in), dtype)
    n = n / jnp.maximum(jnp.linalg.norm(n, axis=1, keepdims=True), jnp.finfo(dtype).tiny)
    extent = jnp.sum(jnp.abs(n) * (hi - lo), axis=1)
    extent = jnp.maximum(extent, jnp.sqrt(jnp.finfo(dtype).eps) * (1 + jnp.max(hi - lo)))
    k = jnp.asarray(scale, dtype) / extent
    w = k[:, None] * n
    b = -jnp.sum(w * p, axis=1)
    return w, b


def _init_hidden(basis: AbstractBasis, key: Array, nodes: Array, scale: float) -> PyTree:
    """Box-initialised hidden layers of one coordinate's network."""
    x = nodes[:, None]
    if isinstance(basis, DenseNetBasis):
        k1, k2 = jax.random.split(key)
        w1, b1 = box_layer(k1, x, basis.width1, scale)
        a = w1[:, 0]
        first = basis.activation(x * a + b1)
        big_a, g = box_layer(k2, first, basis.width2, scale)
        return a, b1, big_a, g
    w, b = box_layer(key, x, basis.width, scale)
    return w[:, 0], b


def _features(basis: AbstractBasis, hidden: PyTree, nodes: Array) -> Array:
    """Last hidden layer on the nodes, `(M, S)`; the network is `features @ output_weights`."""
    x = nodes[:, None]
    if isinstance(basis, DenseNetBasis):
        a, e, big_a, g = hidden
        first = basis.activation(x * a + e)
        return basis.activation(first @ big_a.T + g)
    w, b = hidden
    return basis.activation(x * w + b)


def _column(basis: AbstractBasis, hidden: PyTree, out: Array) -> Array:
    """The basis's flat parameter column from hidden layers and output weights."""
    if isinstance(basis, DenseNetBasis):
        a, e, big_a, g = hidden
        return basis.join(a, e, big_a, g, out)
    w, b = hidden
    return basis.join(out, w, b)


def _output_width(basis: AbstractBasis) -> int:
    return basis.width2 if isinstance(basis, DenseNetBasis) else basis.width


class _Grid(eqx.Module):
    """The fit grid in the work dtype: nodes, Simpson weights, modulation (ones if none)."""

    nodes: Array
    weights: Array
    modulation: Array


def _grid(problem: FitProblem, work) -> _Grid:
    nodes = jnp.asarray(problem.nodes, work)
    weights = jnp.asarray(problem.weights, work)
    if problem.modulation is None:
        modulation = jnp.ones_like(nodes)
    else:
        modulation = jnp.asarray(problem.modulation, work)
    return _Grid(nodes, weights, modulation)


def _setup(tolerance: float | None, problem: FitProblem):
    """What a training run starts from: the targets' dtype, the dtype it computes in, the
    sample grid, and the loss tolerance in that dtype."""
    dtype = problem.targets.dtype
    work = lapack_dtype(dtype)
    tol = _scaled_tolerance(tolerance, dtype, problem.targets).astype(work)
    return dtype, work, _grid(problem, work), tol


def _scaled_tolerance(tolerance: float | None, dtype, targets: Array) -> Array:
    """Absolute loss tolerance: `tolerance` (default `sqrt(eps)` of the working dtype) times
    the largest target magnitude."""
    rel = math.sqrt(float(jnp.finfo(dtype).eps)) if tolerance is None else tolerance
    return jnp.asarray(rel, targets.dtype) * jnp.max(jnp.abs(targets))


def _per_coordinate(fit_one, key: int, problem: FitProblem, work) -> Array:
    targets = problem.targets
    dim = targets.shape[1]
    keys = jax.random.split(jax.random.PRNGKey(key), dim)
    y = targets.astype(work)
    theta = jax.vmap(fit_one, in_axes=(0, 1), out_axes=1)(keys, y)
    return theta.astype(targets.dtype)


def _tuple_if_sequence(value):
    """Lists become tuples, so that static fields stay hashable."""
    return tuple(value) if isinstance(value, list) else value


def _check_count(name: str, value) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")


def _check_positive_float(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")


def _check_key(value) -> None:
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"key must be an integer seed for jax.random.PRNGKey, got {value!r}")


# ------------------------------------------------------------------------------------------------
# LSGD


def _output_least_squares(design: Array, target: Array, weights: Array) -> Array:
    """Output weights `argmin Σ_i w_i (design_i·γ − y_i)²`, with a tiny ridge so that the
    nearly collinear features of a random network give moderate weights."""
    sw = jnp.sqrt(weights)
    scaled = design * sw[:, None]
    eps = jnp.finfo(design.dtype).eps
    sqrt_mu = jnp.sqrt(eps) * jnp.max(jnp.abs(scaled))
    return damped_least_squares(scaled, target * sw, sqrt_mu)


class LSGD(AbstractParameterSeed):
    """Least squares for the output layer alternated with gradient descent on the hidden
    layers (the reference's default seed of `DenseNet`).

    Per coordinate, the hidden layers are box-initialised from `key` (`box_layer`; each
    layer's box is the range of its inputs on the fit grid; with several `init_scale`s the
    same draw is tried at each steepness and the one with the best least-squares fit is kept).
    Then each epoch

    1. sets the output weights to the Simpson-weighted least-squares fit of the targets on the
       features of the last hidden layer (a tiny ridge keeps them bounded when the features
       are nearly collinear);
    2. takes one gradient-descent step of size `learning_rate` on the hidden parameters for the
       weighted RMS error `sqrt(Σ_i w_i (m_i q_h(τ_i) − y_i)²)` (`m_i` the modulation, or 1);

    until the RMS error is at most `tolerance · max|y|` or `epochs` epochs have run. The best
    epoch is returned (plain gradient descent may overshoot). Supports `DenseNetBasis` and
    (unmirrored) `ShallowNetBasis`.

    On a step-sized trajectory the first least-squares fit usually meets the tolerance already
    and the loop does not run; the gradient steps matter for strongly curved trajectories, and
    improve the fit there only modestly (about 2× in 100 epochs). The reference's 50 000 epochs
    per coordinate and step buy nothing measurable.

    **Arguments:**

    - `epochs`: most epochs per coordinate and step. Default 100.
    - `learning_rate`: gradient-descent step on the hidden layers. Default 0.1.
    - `tolerance`: early-stop RMS error relative to the largest target magnitude; `None`
      (default) uses `sqrt(eps)` of the working dtype.
    - `key`: integer seed of `jax.random.PRNGKey` for the initialisation (the same every
      step, so a step's seed depends only on its targets).
    - `init_scale`: steepness of the initial units (`box_layer`'s `scale`), or a tuple of
      candidates; `None` (default) uses `default_init_scale` of the working dtype.
    """

    epochs: int = eqx.field(static=True, default=100)
    learning_rate: float = eqx.field(static=True, default=1e-1)
    tolerance: float | None = eqx.field(static=True, default=None)
    key: int = eqx.field(static=True, default=0)
    init_scale: float | tuple[float, ...] | None = eqx.field(
        static=True, default=None, converter=_tuple_if_sequence
    )

    def __check_init__(self):
        _check_count("epochs", self.epochs)
        _check_positive_float("learning_rate", self.learning_rate)
        if self.tolerance is not None:
            _check_positive_float("tolerance", self.tolerance)
        _check_key(self.key)
        if isinstance(self.init_scale, tuple):
            if not self.init_scale:
                raise ValueError("init_scale must not be an empty tuple")
            for scale in self.init_scale:
                _check_positive_float("init_scale", scale)
        elif self.init_scale is not None:
            _check_positive_float("init_scale", self.init_scale)

    def check(self, basis: AbstractBasis) -> None:
        _check_network(self, basis)

    def _scales(self, dtype) -> tuple[float, ...]:
        if self.init_scale is None:
            return (default_init_scale(dtype),)
        if isinstance(self.init_scale, tuple):
            return tuple(float(x) for x in self.init_scale)
        return (float(self.init_scale),)

    def parameters(self, basis: AbstractBasis, problem: FitProblem) -> Array:
        self.check(basis)
        dtype, work, grid, tol = _setup(self.tolerance, problem)
        lr = jnp.asarray(self.learning_rate, work)
        scales = self._scales(dtype)

        def design(hidden):
            return _features(basis, hidden, grid.nodes) * grid.modulation[:, None]

        def fit_one(key, y):
            def mse(hidden, out):
                r = design(hidden) @ out - y
                return jnp.sum(grid.weights * r**2)

            def evaluate(hidden):
                out = _output_least_squares(design(hidden), y, grid.weights)
                value, grad = jax.value_and_grad(mse)(hidden, out)
                rmse = jnp.sqrt(value)
                # d sqrt(E) = dE / (2 sqrt(E)); a zero error has nothing left to descend.
                factor = jnp.where(rmse > 0, 1 / (2 * jnp.where(rmse > 0, rmse, 1)), 0)
                grad = jax.tree_util.tree_map(lambda g: g * factor, grad)
                return out, rmse, grad

            def cond(carry):
                i, _, _, rmse, (_, _, best_rmse) = carry
                return (i < self.epochs) & (best_rmse > tol) & jnp.isfinite(rmse)

            def body(carry):
                i, hidden, grad, _, best = carry
                hidden = jax.tree_util.tree_map(lambda p, g: p - lr * g, hidden, grad)
                out, rmse, grad = evaluate(hidden)
                # Plain gradient descent has no line search: keep the best epoch seen.
                better = rmse < best[2]
                best = jax.tree_util.tree_map(
                    lambda new, old: jnp.where(better, new, old), (hidden, out, rmse), best
                )
                return i + 1, hidden, grad, rmse, best

            # One box draw at several steepnesses; keep the one whose least-squares fit is best.
            candidates = [_init_hidden(basis, key, grid.nodes, s) for s in scales]
            if len(candidates) == 1:
                hidden = candidates[0]
            else:
                errors = []
                for hidden in candidates:
                    out = _output_least_squares(design(hidden), y, grid.weights)
                    err = jnp.sqrt(mse(hidden, out))
                    errors.append(jnp.where(jnp.isfinite(err), err, jnp.asarray(jnp.inf, work)))
                choice = jnp.argmin(jnp.stack(errors))
                hidden = jax.tree_util.tree_map(lambda *c: jnp.stack(c)[choice], *candidates)
            out, rmse, grad = evaluate(hidden)
            carry = (jnp.array(0, jnp.int32), hidden, grad, rmse, (hidden, out, rmse))
            *_, (hidden, out, _) = jax.lax.while_loop(cond, body, carry)
            return _column(basis, hidden, out)

        return _per_coordinate(fit_one, self.key, problem, work)


# ------------------------------------------------------------------------------------------------
# TrainingMethod


class TrainingMethod(AbstractParameterSeed):
    """Adam training of all network parameters on the initial trajectory (the reference's
    `TrainingMethod`).

    Per coordinate: hidden layers box-initialised from `key` (as `LSGD`), output weights zero;
    then Adam (`b1 = 0.9`, `b2 = 0.99`, `eps = 1e-8`, the reference's constants) with a step
    size decaying exponentially from `learning_rate[0]` to `learning_rate[1]` over `epochs`
    epochs, on the Simpson-weighted loss of `m_i q_h(τ_i) − y_i` (`m_i` the modulation, or
    1). Training stops early once the loss — as an RMS error for `"mse"`, a mean absolute error
    for `"mae"` — is at most `tolerance · max|y|`. The same key gives bit-identical seeds.
    Supports `DenseNetBasis` and (unmirrored) `ShallowNetBasis`.

    **Arguments:**

    - `epochs`: most Adam steps per coordinate and step. Default 2000.
    - `learning_rate`: `(η₁, η₂)`, the step sizes of the first and the last epoch. Default
      `(1e-3, 5e-5)` (the reference's); a single number keeps the step size constant.
    - `loss`: `"mse"` (default; smooth) or `"mae"` (the reference's mean absolute error).
    - `tolerance`: early-stop loss relative to the largest target; `None` (default) uses
      `sqrt(eps)` of the working dtype.
    - `key`: integer seed of `jax.random.PRNGKey` for the initialisation (the same every step).
    - `init_scale`: steepness of the initial hidden units (`box_layer`'s `scale`); `None`
      (default) uses `default_init_scale` of the working dtype.

    Adam moves every parameter by about the step size per epoch whatever the gradient, so the
    fit stalls at an error near the last step size, far above what a least-squares fit
    reaches. Newton then needs many more iterations than from `LSGD`'s seed, and the
    converged trajectory is less accurate; `LSGD` is the better seed.
    """

    epochs: int = eqx.field(static=True, default=2000)
    learning_rate: tuple[float, float] | float = eqx.field(
        static=True, default=(1e-3, 5e-5), converter=_tuple_if_sequence
    )
    loss: str = eqx.field(static=True, default="mse")
    tolerance: float | None = eqx.field(static=True, default=None)
    key: int = eqx.field(static=True, default=0)
    init_scale: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check_count("epochs", self.epochs)
        if self.init_scale is not None:
            _check_positive_float("init_scale", self.init_scale)
        rates = self.learning_rate
        if isinstance(rates, tuple | list):
            if len(rates) != 2:
                raise ValueError(
                    f"learning_rate must be a number or a pair (first, last), got {rates!r}"
                )
            for r in rates:
                _check_positive_float("learning_rate", r)
        else:
            _check_positive_float("learning_rate", rates)
        if self.loss not in ("mse", "mae"):
            raise ValueError(f'loss must be "mse" or "mae", got {self.loss!r}')
        if self.tolerance is not None:
            _check_positive_float("tolerance", self.tolerance)
        _check_key(self.key)

    def check(self, basis: AbstractBasis) -> None:
        _check_network(self, basis)

    def _rates(self) -> tuple[float, float]:
        if isinstance(self.learning_rate, tuple | list):
            return float(self.learning_rate[0]), float(self.learning_rate[1])
        return float(self.learning_rate), float(self.learning_rate)

    def parameters(self, basis: AbstractBasis, problem: FitProblem) -> Array:
        self.check(basis)
        dtype, work, grid, tol = _setup(self.tolerance, problem)
        eta1, eta2 = self._rates()
        # η_k = η₁ (η₂/η₁)^(k/epochs), computed in the work dtype (no float64 in float32 runs).
        log_ratio = jnp.asarray(math.log(eta2 / eta1) / max(self.epochs, 1), work)
        eta1 = jnp.asarray(eta1, work)

        def schedule(count):
            return eta1 * jnp.exp(log_ratio * count.astype(work))

        optimiser = optax.chain(
            optax.scale_by_adam(
                b1=jnp.asarray(0.9, work), b2=jnp.asarray(0.99, work), eps=jnp.asarray(1e-8, work)
            ),
            optax.scale_by_schedule(schedule),
            optax.scale(-1.0),
        )
        mae = self.loss == "mae"
        scale = default_init_scale(dtype) if self.init_scale is None else self.init_scale

        def fit_one(key, y):
            def loss(params):
                hidden, out = params
                design = _features(basis, hidden, grid.nodes) * grid.modulation[:, None]
                r = design @ out - y
                if mae:
                    return jnp.sum(grid.weights * jnp.abs(r))
                return jnp.sum(grid.weights * r**2)

            def as_error(value):
                return value if mae else jnp.sqrt(value)

            def cond(carry):
                i, _, _, value, _ = carry
                return (i < self.epochs) & (as_error(value) > tol)

            def body(carry):
                i, params, state, _, grad = carry
                updates, state = optimiser.update(grad, state, params)
                params = optax.apply_updates(params, updates)
                value, grad = jax.value_and_grad(loss)(params)
                return i + 1, params, state, value, grad

            hidden = _init_hidden(basis, key, grid.nodes, scale)
            params = (hidden, jnp.zeros(_output_width(basis), work))
            value, grad = jax.value_and_grad(loss)(params)
            state = optimiser.init(params)
            carry = (jnp.array(0, jnp.int32), params, state, value, grad)
            _, (hidden, out), _, _, _ = jax.lax.while_loop(cond, body, carry)
            return _column(basis, hidden, out)

        return _per_coordinate(fit_one, self.key, problem, work)
