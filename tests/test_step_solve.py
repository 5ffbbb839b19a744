"""The Jacobian a step's nonlinear solve hands its root finder
(`diffrax_vi._step.formulation.jacobian_option`)."""

import jax.numpy as jnp

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._quadrature import GaussLegendre
from diffrax_vi._root_finder.damped_newton import LevenbergMarquardt
from diffrax_vi._seeding.fit import LeastSquaresFit
from diffrax_vi._step.formulation import FreeEndpoints

F64 = jnp.float64


def test_auto_jacobian_hands_the_closed_form_to_the_root_finder():
    """Under `jacobian="auto"` NetworkVI passes its block Jacobian exactly where
    it has a closed form, and the root finder differentiates otherwise."""
    from diffrax_vi._step.formulation import jacobian_option as _jacobian_option

    problem = problems.double_pendulum(dtype=F64)
    auto, fwd = LevenbergMarquardt(jacobian="auto"), LevenbergMarquardt()
    assert fwd.jacobian == "fwd"  # the default
    for basis, closed in [
        (dvi.ShallowNetBasis(dvi.tanh, 4), True),
        (dvi.ShallowNetBasis(dvi.tanh, 4, symmetry=dvi.MirrorPairs()), False),
        (dvi.LagrangeBasis(4), False),
    ]:
        shallow = isinstance(basis, dvi.ShallowNetBasis)
        seed = {} if shallow else dict(seed=dvi.SeedPolicy(initial_guess=LeastSquaresFit()))
        solver = dvi.NetworkVI(basis, GaussLegendre(6), **seed)
        ctx = solver.step_context(problem.term, 0.0, 0.1, problem.y0, problem.args)
        assert (_jacobian_option(auto, FreeEndpoints(), ctx) is not None) == closed
        assert _jacobian_option(fwd, FreeEndpoints(), ctx) is None
        structured = LevenbergMarquardt(jacobian="structured")
        assert _jacobian_option(structured, FreeEndpoints(), ctx) is not None
