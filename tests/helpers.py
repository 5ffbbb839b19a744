"""What several test files share: solves of a reference problem and their error, the solvers
they build (shallow networks, a cheap cGVI), the Hénon–Heiles system, random network
parameters and the OGA's fit data. Tests import it as `tests.helpers`
(the repository root is on `sys.path` through pytest's `pythonpath`)."""

import dataclasses

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np

import diffrax_vi as dvi
from diffrax_vi._quadrature import Simpson


def solve_problem(problem, solver, *, dtype=None, y0=None, saveat=None, **kwargs):
    """`problem` over its span and save times with `solver`, jit-compiled (`eqx.filter_jit`
    over the initial state). With `dtype` the times are cast to it; without, they are passed
    as the problem holds them. Saves the solver state at `problem.ts` unless `saveat`."""
    cast = (lambda x: x) if dtype is None else dtype
    ts = jnp.asarray(problem.ts, dtype)
    saveat = saveat or diffrax.SaveAt(ts=ts, solver_state=True)
    run = eqx.filter_jit(
        lambda y: diffrax.diffeqsolve(
            problem.term,
            solver,
            cast(problem.t0),
            cast(problem.t1),
            cast(problem.dt),
            y,
            args=problem.args,
            saveat=saveat,
            **kwargs,
        )
    )
    return run(problem.y0 if y0 is None else y0)


def solve_adaptive(problem, solver, rtol, atol, ts=None):
    """The states of `problem` at `ts` (default `problem.ts`) by an adaptive solve that steps
    onto the save times, so that no dense output enters a comparison."""
    ts = jnp.asarray(problem.ts if ts is None else ts, dtype=problem.dtype)
    controller = diffrax.PIDController(rtol=rtol, atol=atol)
    sol = diffrax.diffeqsolve(
        problem.term,
        solver,
        t0=problem.t0,
        t1=problem.t1,
        dt0=problem.dt,
        y0=problem.y0,
        args=problem.args,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.ClipStepSizeController(controller, step_ts=ts),
        max_steps=100_000,
    )
    return sol.ys


def check_stored_data(problem, accuracy, max_bytes):
    """A problem's stored reference is the one shipped for it: it matches the default problem,
    covers its span, was verified to `accuracy` by the generator, stays under `max_bytes`, and
    starts at `(q0, p0)` (a time-dependent problem's checkpoints carry the time after them)."""
    from diffrax_vi.problems import StoredFlow
    from diffrax_vi.problems.stored import load_reference_data

    flow = problem.reference_flow
    assert isinstance(flow, StoredFlow) and problem.reference_method == "stored"
    assert flow.data is not None, "the stored data does not match the default problem"
    assert abs(flow.span - (problem.t1 - problem.t0)) <= 1e-6 * abs(problem.t1 - problem.t0)
    assert flow.verified_error < accuracy
    data = load_reference_data(problem.name)
    assert data["qp"].nbytes < max_bytes
    y0 = np.concatenate([np.asarray(x) for x in problem.y0])
    np.testing.assert_array_equal(data["qp"][0, : 2 * problem.dim], y0)


def constrained_convergence_order(term, y0, degree=2):
    """The order of `CGVI(degree)`'s end state at t = 1 on the constrained `term` from `y0`,
    from constant steps 1/20, 1/40, 1/80 (each run's drift checked at round-off)."""

    def end(n):
        # The step as an array and one step cap: the three runs share one compiled program.
        sol = diffrax.diffeqsolve(term, dvi.CGVI(degree), 0.0, 1.0, jnp.asarray(1.0 / n), y0,
                                  saveat=diffrax.SaveAt(t1=True, solver_state=True),
                                  max_steps=88)
        assert np.all(np.asarray(sol.solver_state.holonomic_drift) <= 1e-12)
        return np.concatenate([sol.ys[0][-1], sol.ys[1][-1]])

    a, b, c = end(20), end(40), end(80)
    return np.log2(np.max(np.abs(a - b)) / np.max(np.abs(b - c)))


def max_relative_error(problem, sol):
    """Max over saved times of max|q − q_ref| / max|q_ref| (per time)."""
    ts = np.asarray(sol.ts)
    q_ref, _ = problem.reference(ts)
    q = np.asarray(sol.ys[0], dtype=np.float64)
    return float(np.max(np.max(np.abs(q - q_ref), axis=1) / np.max(np.abs(q_ref), axis=1)))


# The fields of `SeedPolicy`, which `shallow_network` takes as keywords too.
SEED_OPTIONS = {field.name for field in dataclasses.fields(dvi.SeedPolicy)}


def shallow_network(activation, width, nodes, **kwargs):
    """A `NetworkVI` of a shallow network; the seed policy's options (and the OGA
    dictionary's `bias_interval`, `dict_amount`) may be given as keywords too."""
    seed = {name: kwargs.pop(name) for name in list(kwargs) if name in SEED_OPTIONS}
    dictionary = {name: kwargs.pop(name) for name in ("bias_interval", "dict_amount")
                  if name in kwargs}
    if dictionary:
        seed["initial_guess"] = dataclasses.replace(
            seed.get("initial_guess", dvi.oga.OGA1d()), **dictionary)
    if seed:
        kwargs["seed"] = dvi.SeedPolicy(**seed)
    return dvi.NetworkVI(dvi.ShallowNetBasis(activation, width), dvi.GaussLegendre(nodes), **kwargs)


def all_parameter_network(activation, width, nodes, **kwargs):
    """The reference's formulation: every network parameter an unknown (LM root finder)."""
    return shallow_network(activation, width, nodes, formulation=dvi.FreeEndpoints(), **kwargs)


def motionless_cgvi(degree, nodes, **kwargs):
    """A classical cGVI seeded by a motionless trajectory: the solver's paths (and its
    failures) as for a network, at a fraction of the compile time."""
    kwargs.setdefault(
        "seed", dvi.SeedPolicy(dvi.NoExtrapolation(4), initial_guess=dvi.LeastSquaresFit())
    )
    return dvi.NetworkVI(dvi.LagrangeBasis(degree), dvi.GaussLegendre(nodes), **kwargs)


def henon_heiles_lagrangian(t, q, v, args):
    """Hénon–Heiles with λ = 1."""
    return 0.5 * jnp.sum(v**2) - 0.5 * jnp.sum(q**2) - (q[0] ** 2 * q[1] - q[1] ** 3 / 3)


def henon_heiles_energy(q, p):
    """Its energy over the last axis, in NumPy (NaN for the NaN states of a failed run)."""
    q1, q2 = q[..., 0], q[..., 1]
    with np.errstate(invalid="ignore"):  # a failed run leaves NaN/inf states
        return 0.5 * np.sum(p**2, -1) + 0.5 * np.sum(q**2, -1) + q1**2 * q2 - q2**3 / 3


def random_theta(width, dim, seed=0, dtype=jnp.float64):
    """Normal random parameters of a shallow network of `width` neurons, `dim` coordinates."""
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.normal(size=(3 * width, dim)), dtype)


def sqrt_eps(dtype):
    return float(np.sqrt(np.finfo(dtype).eps))


def oga_fixture(dtype, target=lambda t: np.cos(3 * t)):
    """Nodes k/10, Simpson weights and a target, computed in float64 and cast once."""
    t, w = Simpson(10).nodes_weights_np()
    return jnp.asarray(t, dtype), jnp.asarray(w, dtype), jnp.asarray(target(t), dtype)
