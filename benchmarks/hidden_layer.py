"""How should the hidden layer of a projected network step be chosen? (issue 27)

`VariableProjection` solves each step on the span of a hidden layer `(w, β)`; its accuracy is
that of the span. This script measures, without touching the library, candidate rules for the
hidden layer on the issue's fixtures (oscillator tanh 10 / GL8 at h = 0.1 and 0.5, double
pendulum tanh 10 / GL16 at h = 0.1, pendulum IODE gelu 8 / GL8 at h = 0.1):

- (a) the hidden layer of the solver's own OGA seed (the present behaviour), fitted on every
  step or kept from the first step (`reuse_hidden=True`); and, as the reference of what a span
  of `k` directions can give, the polynomials of degree `k − 1` (the classical cGVI space);
- (b) variable projection proper: from the OGA layer (or a designed one), Gauss-Newton
  (minimal-norm, truncated SVD) or Levenberg-Marquardt updates of `(w, β)` on the
  hidden-parameter equations `∂Φ/∂(w, β) = 0` of the all-parameter system at the projected
  solution, differentiated through the span's SVD and the projected Newton solve;
- (c) fixed, designed layers: `|w| = c`, centres `τ_i = −β_i/w_i` at the Chebyshev or uniform
  points of `[−a, 1 + a]`, signs alternating (or all +), over `c`, `a` and the rank threshold
  `rtol`: one step (with the span's conditioning and its per-degree polynomial defect), then
  10 steps ranked by the worst fixture of each activation;
- (d) the criteria: the smallest kept singular value (`σ_k/σ_1`) against the polynomial defect
  of the kept span weighted by a smooth curve's Legendre decay, correlated with the error.

Each step is solved here by plain Newton on `VariableProjection.reduced_residual` with
`reduced_jacobian` (8 iterations, so every variant does the same work), from the constant curve
`q_n`. Errors are relative to the largest |q| (|p|, at least 1) of the reference over 100 time
units. Determinism: `pert` is the change of the first step when `(w, β)` move by a relative
1e-8 (a smooth map with an accurate span moves by ~1e-16); `jump` is the change when `q_0` is
scaled by `1 + 1e-15` and the layer recomputed by its rule (a continuous step map moves by
~1e-16; a refitted OGA layer jumps, and the step with it by the span's error); the vmap row
solves four oscillators batched and one by one.

    .venv/bin/python -m benchmarks.hidden_layer [--quick]

About 100 s on one core of the 2-core CPU (`--quick`: small grids, 3 steps, ~70 s).
"""

from __future__ import annotations

import argparse
import functools
import math
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.flatten_util  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.ansatz.shallow import ShallowNetBasis  # noqa: E402
from diffrax_vi.projection import ProjectedSpan, feature_span  # noqa: E402

NEWTON = 8  # Newton iterations of each projected solve (1-3 reach round-off)


def make_solver(activation, width, nodes, rtol=None):
    return dvi.NetworkVI(
        dvi.ShallowNetBasis(activation, width), dvi.GaussLegendre(nodes),
        formulation=dvi.VariableProjection(rtol=rtol),
    )


# -- one projected step -----------------------------------------------------------------------
def context(solver, problem, t, h, q0, p0):
    return solver.step_context(problem.term, t, t + h, (q0, p0), problem.args)


def differentiable_span(form, ctx, w, beta):
    """`VariableProjection.span` without its `stop_gradient` (the same SVD construction), so
    that the projected solution can be differentiated in `(w, β)` (variable projection)."""
    dtype = ctx.q0.dtype
    nodes = ctx.nodes.astype(dtype)
    n = nodes.shape[0]
    k = form.span_rank(ctx.basis, n)
    taus = jnp.concatenate([nodes, jnp.array([0.0, 1.0], dtype)])
    z = w * taus[:, None, None] + beta
    value, slope = jax.jvp(ctx.basis.activation, (z,), (jnp.ones_like(z),))
    slope = w * slope
    rtol = form.rtol if form.rtol is not None else float(jnp.finfo(dtype).eps) ** 0.5
    return feature_span(value, slope, ctx.weights, k, rtol, (w, beta))


def projected_solve(solver, ctx, w, beta, differentiable=False):
    """Newton on the span of `(w, β)`: returns `(δc, Δp)`, the span, and the last residual."""
    form = solver.formulation
    if differentiable:
        span = differentiable_span(form, ctx, w, beta)
    else:
        span = form.span(ShallowNetBasis.join(jnp.zeros_like(w), w, beta), ctx)
    # Start: the constant curve q_n (zero increments).
    z = (jnp.zeros_like(span.g0.T), jnp.zeros_like(ctx.p0))
    args = (ctx, span)
    flat, unravel = jax.flatten_util.ravel_pytree(z)

    def residual(v):
        return jax.flatten_util.ravel_pytree(form.reduced_residual(unravel(v), args))[0]

    for _ in range(NEWTON):
        jac = form.reduced_jacobian(unravel(flat), args)
        flat = flat - jnp.linalg.solve(jac, residual(flat))
    return unravel(flat), span, jnp.max(jnp.abs(residual(flat)))


def polynomial_span(ctx, degree):
    """The span of the polynomials of degree `degree` (shifted Legendre), orthonormalised as
    `VariableProjection.span` does: the classical cGVI space, the reference of what a span of
    that size can give."""
    dtype = ctx.q0.dtype
    nodes = ctx.nodes.astype(dtype)
    dim = ctx.q0.shape[0]
    taus = jnp.concatenate([nodes, jnp.array([0.0, 1.0], dtype)])
    legendre = [np.polynomial.legendre.Legendre.basis(m, domain=[0, 1]) for m in range(degree + 1)]
    value = jnp.stack([jnp.asarray(poly(np.asarray(taus))) for poly in legendre], axis=1)
    slope = jnp.stack([jnp.asarray(poly.deriv()(np.asarray(taus))) for poly in legendre], axis=1)
    k = degree + 1
    rep = lambda a: jnp.repeat(a[:, :, None], dim, axis=2)  # noqa: E731
    zeros = jnp.zeros((k, dim), dtype)
    return feature_span(rep(value), rep(slope), ctx.weights, k, 0.0, (zeros, zeros))


def features_span(ctx, activation, w, beta, exact, k, rtol):
    """The span of the features `σ(w_i τ + β_i)` plus the exact monomials `1, τ, ..,
    τ^(exact−1)` (an output bias, a linear skip connection), orthonormalised and truncated as
    `VariableProjection.span` does."""
    dtype = ctx.q0.dtype
    nodes = ctx.nodes.astype(dtype)
    dim = ctx.q0.shape[0]
    taus = jnp.concatenate([nodes, jnp.array([0.0, 1.0], dtype)])
    z = w * taus[:, None, None] + beta
    value, slope = jax.jvp(activation, (z,), (jnp.ones_like(z),))
    slope = w * slope
    if exact:
        ones = jnp.ones((1, 1, dim), dtype)
        pv = jnp.stack([taus**m for m in range(exact)], axis=1)[:, :, None] * ones
        ps = jnp.stack([m * taus ** max(m - 1, 0) for m in range(exact)], axis=1)[:, :, None]
        value = jnp.concatenate([pv, value], axis=1)
        slope = jnp.concatenate([ps * ones, slope], axis=1)
    return feature_span(value, slope, ctx.weights, k, rtol, (w, beta))


def perturbed_polynomial_span(ctx, k, delta):
    """P_0..P_{k−1}, each plus `delta` times a non-polynomial function
    (`tanh(3τ − 1 + 0.7m)`): a span whose polynomial defect is ~`delta`."""
    nodes = np.asarray(ctx.nodes)
    dim = ctx.q0.shape[0]
    taus = np.concatenate([nodes, [0.0, 1.0]])
    vals, ders = [], []
    for m in range(k):
        poly = np.polynomial.legendre.Legendre.basis(m, domain=[0, 1])
        arg = 3 * taus - 1 + 0.7 * m
        vals.append(poly(taus) + delta * np.tanh(arg))
        ders.append(poly.deriv()(taus) + delta * 3 / np.cosh(arg) ** 2)
    rep = lambda a: jnp.repeat(jnp.asarray(np.stack(a, 1))[:, :, None], dim, axis=2)  # noqa: E731
    zeros = jnp.zeros((k, dim))
    return feature_span(rep(vals), rep(ders), ctx.weights, k, 0.0, (zeros, zeros))


def solve_on_span(solver, ctx, span):
    form = solver.formulation
    z = (jnp.zeros_like(span.g0.T), jnp.zeros_like(ctx.p0))  # the constant curve q_n
    args = (ctx, span)
    flat, unravel = jax.flatten_util.ravel_pytree(z)

    def residual(v):
        return jax.flatten_util.ravel_pytree(form.reduced_residual(unravel(v), args))[0]

    for _ in range(NEWTON):
        flat = flat - jnp.linalg.solve(form.reduced_jacobian(unravel(flat), args), residual(flat))
    return form.projected_end_state(unravel(flat), span, ctx)


def step_end(solver, ctx, w, beta):
    z, span, res = projected_solve(solver, ctx, w, beta)
    q1, p1 = solver.formulation.projected_end_state(z, span, ctx)
    return q1, p1, res, span


def hidden_residual(solver, ctx, w, beta):
    """The all-parameter equations at the projected solution: `∂Φ/∂(w, β)` (2S x D), and the
    output-weight rows `∂Φ/∂α` (S x D), scaled by the residual scale."""
    form = solver.formulation
    z, span, _ = projected_solve(solver, ctx, w, beta, differentiable=True)
    theta = form.expand(form.coefficients(z[0], ctx), span)
    r_theta, cont = dvi.FreeEndpoints().residual((theta, ctx.p0 + z[1]), ctx)
    s = w.shape[0]
    scale = 1 + jnp.maximum(jnp.max(jnp.abs(ctx.q0)), jnp.max(jnp.abs(ctx.p0)))
    return r_theta[s:] / scale, r_theta[:s] / scale


# -- hidden layers ----------------------------------------------------------------------------
def oga_hidden(solver, problem, t, h, q0, p0):
    """The hidden layer of the solver's OGA seed for this step (a fresh fit, as on every step
    of the default `NetworkVI`)."""
    return _oga(solver, problem.term, problem.args, h)(jnp.asarray(t, q0.dtype), q0, p0)


@functools.cache
def _oga(solver, term, args, h):
    def fit(t, q0, p0):
        state = solver.init(term, t, t + h, (q0, p0), args)
        ctx = solver.step_context(term, t, t + h, (q0, p0), args)
        (theta, _), _, _ = solver.seeder.cold_seed(
            ctx, state.theta, state.fresh, state.history
        )
        _, w, beta = ctx.basis.split(theta)
        return w, beta

    return jax.jit(fit)


def centres(kind, n, a):
    if kind == "chebyshev":  # Chebyshev points of the first kind
        x = np.cos((2 * np.arange(n) + 1) * np.pi / (2 * n))[::-1]
    elif kind == "gauss":
        x = np.polynomial.legendre.leggauss(n)[0]
    else:  # uniform, ends included
        x = np.linspace(-1.0, 1.0, n)
    return -a + (1 + 2 * a) * (x + 1) / 2


def designed_hidden(width, dim, c, a, kind="chebyshev", sign="alternate"):
    """`|w| = c`, centres at `kind` points of `[−a, 1 + a]` (neuron i: `w_i (τ − τ_i)`);
    signs alternate (tanh is odd, so the sign only matters for non-odd activations)."""
    tau = centres(kind, width, a)
    w = np.full(width, float(c))
    if sign == "alternate":
        w[1::2] *= -1
    beta = -w * tau
    return jnp.asarray(np.tile(w[:, None], (1, dim))), jnp.asarray(np.tile(beta[:, None], (1, dim)))


# -- variable projection proper (b) -----------------------------------------------------------
def varpro(solver, ctx, w, beta, outer, mode="gn", cut=1e-10):
    """`outer` updates of `(w, β)` on the hidden-parameter residual `G` at the projected
    solution (re-solved, and differentiated through the span's SVD and the Newton solve, at
    each update): Gauss-Newton with minimal-norm steps over the singular values above `cut`
    times the largest (`mode="gn"`), or Levenberg-Marquardt with damping `cut·s_max²`
    (`"lm"`). Returns the new layer, `max|G|` before each update and at the end."""
    shape = w.shape
    history = []
    gj = _varpro_jacobian(solver, shape)
    v = jnp.concatenate([w.ravel(), beta.ravel()])
    for _ in range(outer):
        r, jac = gj(ctx, v)
        history.append(float(jnp.max(jnp.abs(r))))
        u, s, vt = jnp.linalg.svd(jac, full_matrices=False)
        if mode == "gn":
            inv = jnp.where(s > cut * s[0], 1 / jnp.where(s > 0, s, 1), 0)
        else:
            inv = s / (s**2 + cut * s[0] ** 2)
        v = v - vt.T @ (inv * (u.T @ r))
    history.append(float(jnp.max(jnp.abs(gj(ctx, v)[0]))))
    n = w.size
    return v[:n].reshape(shape), v[n:].reshape(shape), history


@functools.cache
def _varpro_jacobian(solver, shape):
    n = shape[0] * shape[1]

    def g(ctx, v):
        return hidden_residual(solver, ctx, v[:n].reshape(shape), v[n:].reshape(shape))[0].ravel()

    return jax.jit(lambda ctx, v: (g(ctx, v), jax.jacfwd(g, argnums=1)(ctx, v)))


# -- measurements -----------------------------------------------------------------------------
@functools.cache
def reference_scale(problem):
    q, p = problem.reference(problem.t0 + 0.5 * np.arange(201))
    return float(np.max(np.abs(q))), float(max(np.max(np.abs(p)), 1.0))


def rel_error(problem, t, q, p):
    """Errors of `(q, p)` at time `t`, relative to the largest |q| and |p| of the reference
    over [t0, t0 + 100]."""
    q_ref, p_ref = problem.reference(np.array([t]))
    sq, sp = reference_scale(problem)
    return (float(np.max(np.abs(np.asarray(q) - q_ref[0]))) / sq,
            float(np.max(np.abs(np.asarray(p) - p_ref[0]))) / sp)


@functools.cache
def jitted_step(solver):
    return jax.jit(lambda ctx, w, beta: step_end(solver, ctx, w, beta))


@functools.cache
def jitted_features_span(activation, exact, k, rtol):
    return jax.jit(lambda ctx, w, beta: features_span(ctx, activation, w, beta, exact, k, rtol))


@functools.cache
def jitted_poly_step(solver):
    return jax.jit(lambda ctx, span: solve_on_span(solver, ctx, span))


def span_quality(solver, ctx, span, degree):
    """Per degree m <= `degree`: the relative distance of the data (weighted node values and
    slopes, end values) of the shifted Legendre polynomial P_m from the kept span
    (coordinate 0). A span that holds P_0..P_{k-1} exactly gives the classical cGVI step."""
    nodes, weights = (np.asarray(a) for a in solver.quadrature.nodes_weights_np())
    taus = np.concatenate([nodes, [0.0, 1.0]])
    n = nodes.shape[0]
    rb = np.sqrt(weights)
    live = np.asarray(span.live)[:, 0]
    u = np.concatenate([rb[:, None] * np.asarray(span.gq[0]), rb[:, None] * np.asarray(span.gv[0]),
                        np.asarray(span.g0[0])[None], np.asarray(span.g1[0])[None]])[:, live]
    defects = []
    for m in range(degree + 1):
        poly = np.polynomial.legendre.Legendre.basis(m, domain=[0, 1])
        val, der = poly(taus), poly.deriv()(taus)
        x = np.concatenate([rb * val[:n], rb * der[:n], val[n:]])
        defects.append(np.linalg.norm(x - u @ (u.T @ x)) / np.linalg.norm(x))
    return np.array(defects)


def defect_string(defects):
    """log10 of the per-degree defects, as one string of digits (`-16` written as `g`...)."""
    return " ".join(f"{int(np.floor(np.log10(max(d, 1e-17))))}" for d in defects)


def weighted_defect(defects, rho):
    """The defect weighted by the decay `rho^m / m!` of a smooth curve's Legendre content."""
    return max(d * rho**m / math.factorial(m) for m, d in enumerate(defects))


def feature_singular_values(ctx, w, beta):
    """Singular values of the weighted feature data, per coordinate, over the largest."""
    nodes = ctx.nodes
    taus = jnp.concatenate([nodes, jnp.array([0.0, 1.0])])
    z = w * taus[:, None, None] + beta
    value, slope = jax.jvp(ctx.basis.activation, (z,), (jnp.ones_like(z),))
    rb = jnp.sqrt(ctx.weights)[:, None, None]
    n = nodes.shape[0]
    data = jnp.concatenate([rb * value[:n], rb * w * slope[:n], value[n:]])
    s = jnp.linalg.svd(jnp.moveaxis(data, 2, 0), compute_uv=False)
    return np.asarray(s / s[:, :1])


def perturbation(solver, ctx, w, beta, size=1e-8, seed=0):
    """Largest change of (q1, p1) when (w, β) move by a relative `size` (3 random draws)."""
    q1, p1, _, _ = jitted_step(solver)(ctx, w, beta)
    worst = 0.0
    rng = np.random.default_rng(seed)
    for _ in range(3):
        dw = 1 + size * rng.standard_normal(w.shape)
        db = 1 + size * rng.standard_normal(beta.shape)
        q2, p2, _, _ = jitted_step(solver)(ctx, w * dw, beta * db)
        worst = max(worst, float(jnp.max(jnp.abs(q2 - q1))), float(jnp.max(jnp.abs(p2 - p1))))
    return worst


def run_steps(fx, solver, n_steps, rule):
    """`n_steps` projected steps from `y0`; `rule(ctx, t, q, p, n)` gives `(w, β)` per step
    (or a `ProjectedSpan`). Largest relative errors of q and p over the step ends."""
    problem, h = fx.problem, fx.h
    q, p = problem.y0
    worst = [0.0, 0.0]
    for n in range(n_steps):
        t = problem.t0 + n * h
        ctx = context(solver, problem, t, h, q, p)
        hidden = rule(ctx, t, q, p, n)
        if isinstance(hidden, ProjectedSpan):
            q, p = jitted_poly_step(solver)(ctx, hidden)
        else:
            q, p, _, _ = jitted_step(solver)(ctx, *hidden)
        eq, ep = rel_error(problem, problem.t0 + (n + 1) * h, q, p)
        worst = [max(worst[0], eq), max(worst[1], ep)]
    return worst


def step_jump(fx, solver, rule, factor=1 + 1e-15):
    """Largest change of the first step when q0 is scaled by `factor`, the layer (or span)
    recomputed by `rule`: a continuous step map moves by about 1e-16."""
    q0, p0 = fx.problem.y0
    out = []
    for q in (q0, q0 * factor):
        ctx = context(solver, fx.problem, fx.problem.t0, fx.h, q, p0)
        layer = rule(ctx, fx.problem.t0, q, p0, 0)
        if isinstance(layer, ProjectedSpan):
            out.append(jitted_poly_step(solver)(ctx, layer))
        else:
            out.append(jitted_step(solver)(ctx, *layer)[:2])
    return max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(out[0], out[1], strict=True))


# -- fixtures and rules -----------------------------------------------------------------------
class Fixture:
    def __init__(self, name, problem, activation, width, nodes, h):
        self.name, self.problem, self.activation = name, problem, activation
        self.width, self.nodes, self.h = width, nodes, h
        self.dim = problem.dim

    def solver(self, rtol=None):
        return _solver(self.activation, self.width, self.nodes, rtol)

    def first_context(self, solver):
        q0, p0 = self.problem.y0
        return context(solver, self.problem, self.problem.t0, self.h, q0, p0)


@functools.cache
def _solver(activation, width, nodes, rtol):
    return make_solver(activation, width, nodes, rtol)


def fixtures():
    ho = problems.harmonic_oscillator()
    return [
        Fixture("HO h=0.1 tanh10/GL8", ho, dvi.tanh, 10, 8, 0.1),
        Fixture("HO h=0.5 tanh10/GL8", ho, dvi.tanh, 10, 8, 0.5),
        Fixture("DP h=0.1 tanh10/GL16", problems.double_pendulum(t1=1.0, dt=0.1), dvi.tanh, 10,
                16, 0.1),
        Fixture("pend h=0.1 gelu8/GL8", problems.pendulum(), dvi.gelu, 8, 8, 0.1),
    ]


def oga_rule(fx, solver):
    return lambda ctx, t, q, p, n: oga_hidden(solver, fx.problem, t, fx.h, q, p)


def oga_reused_rule(fx, solver):
    first = oga_hidden(solver, fx.problem, fx.problem.t0, fx.h, *fx.problem.y0)
    return lambda ctx, t, q, p, n: first


def design_rule(fx, c, a, kind="chebyshev", sign="alternate"):
    layer = designed_hidden(fx.width, fx.dim, c, a, kind, sign)
    return lambda ctx, t, q, p, n: layer


def varpro_rule(fx, solver, outer, start="oga"):
    def rule(ctx, t, q, p, n):
        w, beta = oga_hidden(solver, fx.problem, t, fx.h, q, p)
        return varpro(solver, ctx, w, beta, outer)[:2]
    return rule


def poly_rule(degree):
    return lambda ctx, t, q, p, n: polynomial_span(ctx, degree)


def fmt(x):
    return f"{x:.1e}"


# -- the experiments --------------------------------------------------------------------------
C_GRID = (0.25, 0.5, 1.0, 2.0)
A_GRID = (0.0, 0.5, 1.0, 2.0, 4.0)
RTOLS = (None, 1e-10, 1e-12)


def sweep(fx, quick):
    """(c): one step on designed layers over (c, a) and rtol; returns the rows."""
    c_grid, a_grid = ((0.5, 1.0), (0.5, 2.0)) if quick else (C_GRID, A_GRID)
    signs = ("alternate", "same") if fx.activation is dvi.gelu else ("alternate",)
    rows = []
    for sign in signs:
        for c in c_grid:
            for a in a_grid:
                w, beta = designed_hidden(fx.width, fx.dim, c, a, "chebyshev", sign)
                errs = []
                for rtol in RTOLS:
                    solver = fx.solver(rtol)
                    ctx = fx.first_context(solver)
                    q1, p1, _, span = jitted_step(solver)(ctx, w, beta)
                    errs.append(max(rel_error(fx.problem, fx.problem.t0 + fx.h, q1, p1)))
                    if rtol is None:
                        live = int(np.asarray(span.live).sum(axis=0).min())
                        sv = feature_singular_values(ctx, w, beta)
                        k = solver.formulation.span_rank(ctx.basis, fx.nodes)
                        kept = float(sv[:, live - 1].min())
                        defects = span_quality(solver, ctx, span, k - 1)
                rows.append(dict(sign=sign, c=c, a=a, errs=errs, live=live, kept=kept,
                                 defects=defects))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small grids, 3 steps")
    args = parser.parse_args(argv)
    quick = args.quick
    n_steps = 3 if quick else 10
    start = time.perf_counter()
    fxs = fixtures()
    print(f"# Hidden layers for the projected step (jax {jax.__version__}, float64)\n")

    # (a) baseline and the polynomial reference, one step
    print("## (a) One step: the OGA seed's hidden layer, and the polynomial span P_R\n")
    print("Errors relative to max|q| (max|p|, at least 1) of the reference. `hidden res`: "
          "max |dPhi/d(w, beta)| of the all-parameter equations at the projected solution "
          "(over the residual scale). `jump`: largest change of (q1, p1) when q0 is scaled by "
          "1 + 1e-15 (the OGA refits its layer; a continuous step map moves ~1e-16). `pert`: "
          "largest change of (q1, p1) when (w, beta) move by a relative 1e-8.\n")
    print("| fixture | layer | live | sigma_k/sigma_1 | log10 P_m defect | q error | p error | "
          "hidden res | jump | pert |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for fx in fxs:
        solver = fx.solver()
        ctx = fx.first_context(solver)
        q0, p0 = fx.problem.y0
        k = solver.formulation.span_rank(ctx.basis, fx.nodes)
        w, beta = oga_hidden(solver, fx.problem, fx.problem.t0, fx.h, q0, p0)
        q1, p1, _, span = jitted_step(solver)(ctx, w, beta)
        eq, ep = rel_error(fx.problem, fx.problem.t0 + fx.h, q1, p1)
        hres = float(jnp.max(jnp.abs(jax.jit(
            lambda c, w, b, s=solver: hidden_residual(s, c, w, b)[0])(ctx, w, beta))))
        w2, b2 = oga_hidden(solver, fx.problem, fx.problem.t0, fx.h, q0 * (1 + 1e-15), p0)
        ctx2 = context(solver, fx.problem, fx.problem.t0, fx.h, q0 * (1 + 1e-15), p0)
        q2, p2, _, _ = jitted_step(solver)(ctx2, w2, b2)
        jump = max(float(jnp.max(jnp.abs(q2 - q1))), float(jnp.max(jnp.abs(p2 - p1))))
        live = int(np.asarray(span.live).sum(axis=0).min())
        kept = float(feature_singular_values(ctx, w, beta)[:, live - 1].min())
        print(f"| {fx.name} | OGA | {live} | {fmt(kept)} | "
              f"{defect_string(span_quality(solver, ctx, span, k - 1))} | {fmt(eq)} | {fmt(ep)} | "
              f"{fmt(hres)} | {fmt(jump)} | {fmt(perturbation(solver, ctx, w, beta))} |")
        pq, pp = jitted_poly_step(solver)(ctx, polynomial_span(ctx, k - 1))
        eq, ep = rel_error(fx.problem, fx.problem.t0 + fx.h, pq, pp)
        print(f"| {fx.name} | P_{k - 1} (k = {k}) | {k} | | | {fmt(eq)} | {fmt(ep)} | | | |")
    print(f"\n({time.perf_counter() - start:.0f} s)\n")

    # (c) designed layers
    print("## (c) One step on designed layers: |w| = c, centres at the Chebyshev points of "
          "[-a, 1 + a], signs alternating (gelu: also all +)\n")
    print("max(q, p) error of one step for rtol = sqrt(eps) (default), 1e-10, 1e-12; `live`, "
          "`sigma_k/sigma_1` (smallest kept) and the P_R defect at the default rtol.\n")
    best = {}
    for fx in fxs:
        rows = sweep(fx, quick)
        print(f"### {fx.name}\n")
        print("| sign | c | a | err (default) | err (1e-10) | err (1e-12) | live | "
              "sigma_k/sigma_1 | log10 P_m defect, m = 0..k-1 |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            e = r["errs"]
            print(f"| {r['sign']} | {r['c']} | {r['a']} | {fmt(e[0])} | {fmt(e[1])} | "
                  f"{fmt(e[2])} | {r['live']} | {fmt(r['kept'])} | "
                  f"{defect_string(r['defects'])} |")
        errors = np.log10([max(r["errs"][0], 1e-17) for r in rows])
        kept = np.log10([r["kept"] for r in rows])
        corr = [f"sigma_k/sigma_1 {np.corrcoef(kept, errors)[0, 1]:+.2f}"]
        for rho in (0.1, 0.3, 1.0):
            score = np.log10([max(weighted_defect(r["defects"], rho), 1e-17) for r in rows])
            corr.append(f"defect weighted by rho^m/m!, rho = {rho}: "
                        f"{np.corrcoef(score, errors)[0, 1]:+.2f}")
        print("\ncorrelation of log10 error (default rtol) with log10 of: " + "; ".join(corr)
              + "\n")
        for r in rows:
            for rtol, e in zip(RTOLS, r["errs"], strict=True):
                key = (fx.activation, r["sign"], r["c"], r["a"], rtol)
                best.setdefault(key, []).append(e)
    print(f"({time.perf_counter() - start:.0f} s)\n")
    rules = {}
    for act in (dvi.tanh, dvi.gelu):
        ranked = sorted(((max(v), k[1:]) for k, v in best.items() if k[0] is act),
                        key=lambda x: x[0])
        default = [k for _, k in ranked if k[3] is None]
        rules[act] = [("chebyshev",) + k for k in [ranked[0][1]] + default[:1]]
        print(f"best (sign, c, a, rtol) for {act.__name__} (largest one-step error over its "
              f"fixtures): " + ", ".join(f"{k}: {fmt(v)}" for v, k in ranked[:4]))
    print()

    # (c2) the same rules over 10 steps, ranked by the worst fixture of each activation
    print(f"## (c2) Designed layers over {n_steps} steps: rules ranked by the largest error "
          f"(q or p, over the step ends) of the activation's fixtures\n")
    grids = {dvi.tanh: dict(c=(0.35, 0.5, 0.7, 1.0), a=(1.0, 2.0, 3.0, 4.0, 6.0),
                            rtol=(None, 1e-10, 1e-12), sign=("alternate",)),
             dvi.gelu: dict(c=(0.25, 0.35, 0.5, 0.7, 1.0), a=(0.5, 1.0, 1.5, 2.0, 3.0),
                            rtol=(None, 1e-10), sign=("alternate", "same"))}
    if quick:
        grids = {act: dict(c=(0.5,), a=(2.0, 4.0), rtol=(None, 1e-10), sign=("alternate",))
                 for act in grids}
    for act, grid in grids.items():
        group = [fx for fx in fxs if fx.activation is act]
        ranked = []
        for kind in ("chebyshev", "uniform"):
            for sign in grid["sign"]:
                for c in grid["c"]:
                    for a in grid["a"]:
                        for rtol in grid["rtol"]:
                            errs = [max(run_steps(fx, fx.solver(rtol), n_steps,
                                                  design_rule(fx, c, a, kind, sign)))
                                    for fx in group]
                            ranked.append((max(errs), (kind, sign, c, a, rtol), errs))
        ranked.sort(key=lambda x: x[0])
        names = " | ".join(fx.name for fx in group)
        print(f"### {act.__name__}: {len(ranked)} rules\n")
        print(f"| rank | centres | sign | c | a | rtol | worst | {names} |")
        print("|---|---|---|---|---|---|---|" + "---|" * len(group))
        for i, (worst, (kind, sign, c, a, rtol), errs) in enumerate(ranked):
            if i < 8 or i == len(ranked) - 1:
                print(f"| {i + 1} | {kind} | {sign} | {c} | {a} | {rtol or 'default'} | "
                      f"{fmt(worst)} | " + " | ".join(fmt(e) for e in errs) + " |")
        print()
        rules[act] = [(kind, sign, c, a, rtol) for _, (kind, sign, c, a, rtol), _ in ranked[:2]]
    print(f"({time.perf_counter() - start:.0f} s)\n")

    # (d) how the error depends on the span's polynomial defect
    print("## (d) Sensitivity of one step to the span's polynomial defect\n")
    print("The span of P_0..P_{k-1}, each plus delta * tanh(3 tau - 1 + 0.7 m) (a defect of "
          "size ~delta); max(q, p) error of one step, per quadrature.\n")
    deltas = (0.0, 1e-2, 1e-4, 1e-6)
    print("| fixture | nodes | k | " + " | ".join(f"delta = {d:g}" for d in deltas) + " |")
    print("|---|---|---|" + "---|" * len(deltas))
    for base in (fxs[0], fxs[2], fxs[3]):
        for nodes in ((8, 16) if quick else (8, 12, 16)):
            fx = Fixture(base.name.split(" ")[0], base.problem, base.activation, base.width,
                         nodes, base.h)
            solver = fx.solver()
            ctx = fx.first_context(solver)
            k = min(fx.width, 9)
            errs = []
            for delta in deltas:
                q1, p1 = jitted_poly_step(solver)(ctx, perturbed_polynomial_span(ctx, k, delta))
                errs.append(max(rel_error(fx.problem, fx.problem.t0 + fx.h, q1, p1)))
            print(f"| {fx.name} h={fx.h} | GL{nodes} | {k} | "
                  + " | ".join(fmt(e) for e in errs) + " |")
    print()
    print(f"Designed layers plus exact monomials 1, .., tau^(e-1) in the span (an output bias "
          f"e = 1, a linear skip connection e = 2): {n_steps} steps, best and median over the "
          f"(c2) grid of the activation (rtol default and 1e-10).\n")
    print("| fixture | e = 0 best | e = 0 median | e = 1 best | e = 1 median | e = 2 best | "
          "e = 2 median |")
    print("|---|---|---|---|---|---|---|")
    for fx in fxs:
        grid = grids[fx.activation]
        cells = []
        for exact in (0, 1, 2):
            solver = fx.solver()
            k = solver.formulation.span_rank(solver.basis, fx.nodes)
            errs = []
            for kind in ("chebyshev", "uniform"):
                for c in grid["c"]:
                    for a in grid["a"]:
                        for rtol in (math.sqrt(np.finfo(float).eps), 1e-10):
                            w, beta = designed_hidden(fx.width, fx.dim, c, a, kind)

                            def rule(ctx, t, q, p, n, w=w, beta=beta, rtol=rtol, exact=exact,
                                     k=k):
                                return jitted_features_span(fx.activation, exact, k, rtol)(
                                    ctx, w, beta)

                            errs.append(max(run_steps(fx, solver, n_steps, rule)))
            cells += [fmt(min(errs)), fmt(float(np.median(errs)))]
        print(f"| {fx.name} | " + " | ".join(cells) + " |")
    print(f"\n({time.perf_counter() - start:.0f} s)\n")

    # (b) variable projection proper
    print("## (b) Variable projection: Gauss-Newton on dPhi/d(w, beta) at the projected "
          "solution, one step\n")
    print("max |dPhi/d(w, beta)| before each of 4 outer updates and after; the error after; "
          "how far the layer moved. GN: minimal-norm steps over singular values above cut "
          "* s_max; LM: damping cut * s_max^2.\n")
    print("| fixture | start | update | hidden res history | error before | error after | "
          "max move |")
    print("|---|---|---|---|---|---|---|")
    for fx in fxs[:2] + fxs[3:] if quick else fxs:
        solver = fx.solver()
        ctx = fx.first_context(solver)
        q0, p0 = fx.problem.y0
        starts = {"OGA": oga_hidden(solver, fx.problem, fx.problem.t0, fx.h, q0, p0)}
        kind, sign, c, a, _ = rules[fx.activation][0]
        starts[f"design {kind} c={c} a={a}"] = designed_hidden(fx.width, fx.dim, c, a, kind,
                                                                sign)
        for label, (w, beta) in starts.items():
            q1, p1, _, _ = jitted_step(solver)(ctx, w, beta)
            before = max(rel_error(fx.problem, fx.problem.t0 + fx.h, q1, p1))
            updates = [("gn", 1e-10), ("lm", 1e-8)] if not quick else [("gn", 1e-10)]
            for mode, cut in updates:
                w2, b2, hist = varpro(solver, ctx, w, beta, 2 if quick else 4, mode, cut)
                q1, p1, _, _ = jitted_step(solver)(ctx, w2, b2)
                after = max(rel_error(fx.problem, fx.problem.t0 + fx.h, q1, p1))
                move = max(float(jnp.max(jnp.abs(w2 - w))), float(jnp.max(jnp.abs(b2 - beta))))
                print(f"| {fx.name} | {label} | {mode} {cut:g} | "
                      f"{' '.join(fmt(x) for x in hist)} | {fmt(before)} | {fmt(after)} | "
                      f"{fmt(move)} |")
    print(f"\n({time.perf_counter() - start:.0f} s)\n")

    # 10 steps
    print(f"## {n_steps} steps: largest relative error of q (p) over the step ends\n")
    print("`pert`: change of step 1 when (w, beta) move by a relative 1e-8; `jump`: change of "
          "step 1 when q0 is scaled by 1 + 1e-15 (the layer recomputed by its rule).\n")
    print("| fixture | layer | q error | p error | pert (step 1) | jump (step 1) |")
    print("|---|---|---|---|---|---|")
    for fx in fxs:
        solver = fx.solver()
        ctx = fx.first_context(solver)
        k = solver.formulation.span_rank(ctx.basis, fx.nodes)
        cases = {"OGA every step": oga_rule(fx, solver),
                 "OGA first step, reused": oga_reused_rule(fx, solver)}
        cases = {label: (rule, solver) for label, rule in cases.items()}
        for kind, sign, c, a, rtol in rules[fx.activation]:
            cases[f"design {kind} {sign} c={c} a={a} rtol={rtol or 'default'}"] = (
                design_rule(fx, c, a, kind, sign), fx.solver(rtol))
        cases[f"P_{k - 1}"] = (poly_rule(k - 1), solver)
        if fx.activation is dvi.tanh and fx.dim == 1 and not quick:
            cases["OGA + 3 GN (varpro)"] = (varpro_rule(fx, solver, 3), solver)
        for label, (rule, slv) in cases.items():
            eq, ep = run_steps(fx, slv, n_steps, rule)
            layer = rule(ctx, fx.problem.t0, *fx.problem.y0, 0)
            pert = "" if isinstance(layer, ProjectedSpan) else fmt(perturbation(
                slv, fx.first_context(slv), *layer))
            print(f"| {fx.name} | {label} | {fmt(eq)} | {fmt(ep)} | {pert} | "
                  f"{fmt(step_jump(fx, slv, rule))} |")
    print(f"\n({time.perf_counter() - start:.0f} s)\n")

    # determinism under vmap
    print(f"## vmap against a loop: four oscillators (amplitudes 0.3, 0.5, 0.7, 0.9), "
          f"{n_steps} steps of 0.1, tanh 10 / GL8\n")
    fx = fxs[0]
    solver = fx.solver()
    amplitudes = jnp.array([0.3, 0.5, 0.7, 0.9])
    kind, sign, c, a, rtol = rules[dvi.tanh][0]
    layers = {"OGA every step": (None, solver),
              f"design {kind} c={c} a={a} rtol={rtol or 'default'}": (
                  designed_hidden(fx.width, fx.dim, c, a, kind, sign), fx.solver(rtol))}
    term, pargs = fx.problem.term, fx.problem.args
    for label, (layer, solver) in layers.items():
        def one(t, q, p, layer=layer, solver=solver):
            ctx = solver.step_context(term, t, t + fx.h, (q, p), pargs)
            if layer is None:
                state = solver.init(term, t, t + fx.h, (q, p), pargs)
                (theta, _), _, _ = solver.seeder.cold_seed(ctx, state.theta, state.fresh,
                                                     state.history)
                _, w, beta = ctx.basis.split(theta)
            else:
                w, beta = layer
            q1, p1, _, _ = step_end(solver, ctx, w, beta)
            return q1, p1

        single = jax.jit(one)
        batched = jax.jit(jax.vmap(one, in_axes=(None, 0, 0)))
        qs, ps = amplitudes[:, None], jnp.zeros((4, 1))
        ql, pl = [qs[i] for i in range(4)], [ps[i] for i in range(4)]
        diff = 0.0
        for n in range(n_steps):
            t = jnp.asarray(n * fx.h)
            qs, ps = batched(t, qs, ps)
            for i in range(4):
                ql[i], pl[i] = single(t, ql[i], pl[i])
            diff = max(diff, float(jnp.max(jnp.abs(qs - jnp.stack(ql)))),
                       float(jnp.max(jnp.abs(ps - jnp.stack(pl)))))
        print(f"- {label}: max |vmap - loop| = {diff:.1e}")
    print(f"\n(total {time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
