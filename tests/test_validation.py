"""Wrong input is refused early, with a message that names the problem."""

from functools import partial

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from tests.helpers import motionless_cgvi

HO = problems.harmonic_oscillator()
# Python-float times would make diffrax promote a float32 y0 to float64.
F32_TIMES = (jnp.float32(0.0), jnp.float32(0.2), jnp.float32(0.1))


cgvi = partial(motionless_cgvi, 2, 3)


def solve(solver=None, term=HO.term, y0=HO.y0, dt0=0.1, t1=0.2, **kwargs):
    return diffrax.diffeqsolve(term, solver or cgvi(), 0.0, t1, dt0, y0, **kwargs)


def test_odd_width_with_mirrored_pairs():
    for symmetry in (dvi.MirrorPairs(), dvi.SharedMirrorPairs()):
        with pytest.raises(ValueError, match="even width"):
            dvi.ShallowNetBasis(dvi.tanh, 5, symmetry)
    with pytest.raises(ValueError, match="(?i)even"):
        dvi.ShallowNetReversible(dvi.ShallowNetBasis(dvi.tanh, 5), dvi.GaussLegendre(8))


def test_simpson_substeps_not_even():
    for n in (3, 0, -2, 2.0, True):
        with pytest.raises(ValueError, match="even"):
            dvi.Simpson(n)
    for make in (dvi.IntegratorExtrapolation, dvi.NoExtrapolation, dvi.HermiteExtrapolation):
        with pytest.raises(ValueError, match="even"):
            make(7)
    with pytest.raises(ValueError, match="even"):
        dvi.ShallowNet(dvi.ShallowNetBasis(dvi.tanh, 4), dvi.GaussLegendre(4),
                       extrapolation_substep=5)  # fmt: skip


def test_hermite_first_strategy_on_another_label_grid():
    with pytest.raises(ValueError, match="same label grid"):
        dvi.HermiteExtrapolation(first=dvi.IntegratorExtrapolation(20))  # 10 against 20
    traj = dvi.HermiteExtrapolation(20, first=dvi.IntegratorExtrapolation(20))
    assert traj.first.substeps == 20 and dvi.HermiteExtrapolation().first is None


def test_zero_dt0():
    # The first step fails with its own result; `throw=True` raises with its message.
    sol = solve(dt0=jnp.asarray(0.0), throw=False, max_steps=8)
    assert sol.result == diffrax.RESULTS.vi_step_size_invalid
    assert dvi.failure_kind(sol.result) == "step_size"
    assert bool(jnp.all(jnp.isnan(sol.ys[0])))
    with pytest.raises(Exception, match="step size must be finite and non-zero"):
        solve(dt0=jnp.asarray(0.0), max_steps=8).ys[0].block_until_ready()


_CALLBACK_PROBE = """
import diffrax, jax
jax.config.update("jax_enable_x64", True)
import diffrax_vi as dvi
from diffrax_vi import problems

HO = problems.harmonic_oscillator()
solver = dvi.CGVI(3)

def run(y0, t0):
    return diffrax.diffeqsolve(HO.term, solver, t0, 0.2, 0.1, y0, throw=False)

print("callback" in jax.jit(run).lower(HO.y0, 0.0).as_text())
sol = run(HO.y0, float("nan"))
print(int(sol.stats["num_steps"]), sol.result == diffrax.RESULTS.successful)
"""


@pytest.mark.parametrize("on_error, has_callback", [("raise", "True"), ("nan", "False")])
def test_time_check_is_the_only_host_callback_of_a_throw_false_solve(on_error, has_callback):
    """With equinox's default `EQX_ON_ERROR=raise` the run-time check of the times is a host
    callback; with `EQX_ON_ERROR=nan` a `throw=False` solve has none (JAX's persistent
    compilation cache needs that), and a NaN time then takes no step, as the choosing page says."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, EQX_ON_ERROR=on_error, JAX_PLATFORMS="cpu")
    run = subprocess.run(
        [sys.executable, "-c", _CALLBACK_PROBE], env=env, capture_output=True, text=True,
        timeout=300,
    )
    if on_error == "raise":
        assert "t0 and t1 must be finite times" in run.stderr
        assert run.stdout.split() == [has_callback]
    else:
        assert run.returncode == 0, run.stderr
        assert run.stdout.split() == [has_callback, "0", "True"]


def test_negative_dt0():
    with pytest.raises(Exception, match=r"\(t1 - t0\) \* dt0 >= 0"):
        solve(dt0=-0.1)


@pytest.mark.parametrize(
    "y0, match",
    [
        (jnp.array([0.5, 0.0]), "pair"),
        ((jnp.array([0.5]),), "pair"),
        ((jnp.array([0.5]), jnp.array([0.0]), jnp.array([0.0])), "pair"),
        ((jnp.array([0.5, 0.1]), jnp.array([0.0])), "same shape"),
        ((jnp.array([[0.5]]), jnp.array([[0.0]])), "1-D"),
        ((jnp.array([0.5]), jnp.array([0.0], jnp.float32)), "dtype"),
        ((jnp.array([1]), jnp.array([0])), "floating"),
    ],
)
def test_bad_initial_state(y0, match):
    # Directly at the solver (diffrax may first trip over the term with some of these).
    with pytest.raises(ValueError, match=match):
        cgvi().init(HO.term, 0.0, 0.1, y0, None)


def test_bad_initial_state_through_diffeqsolve():
    with pytest.raises(ValueError, match="pair"):
        solve(y0=jnp.array([0.5, 0.0]))
    # (A float32/float64 mix never reaches the solver through diffeqsolve: diffrax promotes
    # y0 to one dtype first. That case is refused by `init` above.)


def test_lagrangian_not_scalar_or_wrong_dtype():
    vector = dvi.LagrangianTerm(lambda t, q, v, a: 0.5 * v * v - 0.25 * q * q)
    with pytest.raises(ValueError, match="scalar"):
        solve(term=vector)
    promoting = dvi.LagrangianTerm(
        lambda t, q, v, a: (0.5 * v @ v - 0.25 * q @ q).astype(jnp.float64)
    )
    y32 = (jnp.array([0.5], jnp.float32), jnp.array([0.0], jnp.float32))
    with pytest.raises(ValueError, match="dtype float64 for float32"):
        diffrax.diffeqsolve(promoting, cgvi(), *F32_TIMES, y32)


def test_iode_maps_with_wrong_shape_or_dtype():
    bad_shape = dvi.IODETerm(lambda t, q, v, a: jnp.concatenate([v, v]), lambda t, q, v, a: -q)
    with pytest.raises(ValueError, match="momentum map returned shape"):
        cgvi().step(bad_shape, 0.0, 0.1, HO.y0, None, cgvi().init(HO.term, 0.0, 0.1, HO.y0, None),
                    False)  # fmt: skip


def test_activation_that_promotes():
    def tanh64(x):
        return jnp.tanh(x) * np.float64(1.0)  # a float64 constant promotes float32 input

    y32 = (jnp.array([0.5], jnp.float32), jnp.array([0.0], jnp.float32))
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(tanh64, 4), dvi.GaussLegendre(4))
    with pytest.raises(ValueError, match="promotes float32 input to float64"):
        diffrax.diffeqsolve(HO.term, solver, *F32_TIMES, y32)
    with pytest.raises(ValueError, match="elementwise"):
        dvi.ShallowNetBasis(lambda x: jnp.stack([x, x]), 4).check(jnp.float64)


def test_quadrature_with_too_few_nodes():
    with pytest.raises(ValueError, match="at least 2 nodes"):
        dvi.NetworkVI(dvi.LagrangeBasis(2), dvi.GaussLegendre(1),
                      seed=dvi.SeedPolicy(initial_guess=dvi.LeastSquaresFit()))  # fmt: skip
    with pytest.raises(ValueError, match="nodes"):
        dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(4))
    with pytest.raises(ValueError, match="at least 3 nodes"):
        dvi.NetworkVI(dvi.DenseNetBasis(dvi.tanh, 4, 6), dvi.GaussLegendre(2),
                      seed=dvi.SeedPolicy(initial_guess=dvi.LSGD()))  # fmt: skip
    # The reference's settings pass.
    dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10), dvi.GaussLegendre(8))


def test_degenerate_term_given_to_an_explicit_solver():
    pendulum = problems.pendulum()
    term = dvi.IODETerm(pendulum.term.momentum_map, pendulum.term.force_map)
    # The missing velocity map fails when Tsit5 evaluates the vector field (an equinox
    # runtime error), not when diffeqsolve traces it for its shapes.
    with pytest.raises(RuntimeError, match="only be integrated by the variational solvers"):
        diffrax.diffeqsolve(term, diffrax.Tsit5(), 0.0, 0.2, 0.1, pendulum.y0)
    # The same system as a Lagrangian linear in the velocity: ∂²L/∂v² is singular.
    linear = dvi.LagrangianTerm(lambda t, q, v, a: q[1] * v[0] - 0.5 * q[1] ** 2 + jnp.cos(q[0]))
    y0 = (jnp.array([0.3, 0.1]), jnp.array([0.1, 0.0]))
    with pytest.raises(Exception, match="degenerate Lagrangian"):
        diffrax.diffeqsolve(linear, diffrax.Tsit5(), 0.0, 0.2, 0.1, y0).ys[0].block_until_ready()


def test_unknown_option_names():
    with pytest.raises(TypeError, match="root_find_maxsteps"):
        dvi.NetworkVI(dvi.LagrangeBasis(2), root_find_maxsteps=5)
    with pytest.raises(TypeError, match="dict_ammount"):
        dvi.ShallowNet(dvi.ShallowNetBasis(dvi.tanh, 4), dvi.GaussLegendre(4), dict_ammount=10)
    with pytest.raises(TypeError):
        dvi.LevenbergMarquardt(lamda=1e-3)


def test_bad_option_values():
    basis = dvi.ShallowNetBasis(dvi.tanh, 4)
    for kwargs, match in [
        (dict(root_find_max_steps=0), "root_find_max_steps"),
        (dict(seed=dvi.oga.OGA1d()), "seed must be a SeedPolicy"),
        (dict(initial_guess=dvi.oga.OGA1d()), "initial_guess"),
        (dict(error_estimate=0), "error_estimate"),
        (dict(iteration_log=-1), "iteration_log"),
        (dict(quadrature="gauss"), "quadrature"),
    ]:
        with pytest.raises((TypeError, ValueError), match=match):
            dvi.NetworkVI(basis, **kwargs)
    # the OGA's dictionary options are the OGA's
    for kwargs, match in [
        (dict(dict_amount=0), "dict_amount"),
        (dict(dict_amount=2.5), "dict_amount"),
        (dict(bias_interval=(1.0, -1.0)), "bias_interval"),
        (dict(bias_interval=(0.0, float("inf"))), "bias_interval"),
        (dict(bias_interval="wide"), "bias_interval"),
    ]:
        with pytest.raises(ValueError, match=match):
            dvi.oga.OGA1d(**kwargs)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="positive integer node count"):
            dvi.GaussLegendre(bad)
