"""A start whose singular kinetic matrix leaves coordinates the equations of motion do not see
is refused by name (`diffrax_vi._step.kinetic_check`), and the degenerate Lagrangians the solvers
do integrate (first order, or mixing first- and second-order coordinates) are not."""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi._step.kinetic_check import (
    DEGENERATE_START_MESSAGE,
    SINGULAR_AT_START,
    blind_directions,
    refuse_degenerate_start,
)

jax.config.update("jax_enable_x64", True)

SOLVERS = {
    "CGVI(4)": lambda: dvi.CGVI(4),
    "NetworkVI": lambda: dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 10)),
}
# q[1] appears nowhere: neither in the kinetic term nor in the potential.
BLIND = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v[0] ** 2 - 0.5 * q[0] ** 2)
# the same, with a potential that depends on q[0]'s value: known only when the solve runs
BLIND_LATER = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v[0] ** 2 + jnp.cos(q[0]))
Y0 = (jnp.array([0.3, 0.5]), jnp.array([0.1, 0.0]))


def _solve(term, solver, y0=Y0, t1=0.2, **kwargs):
    return diffrax.diffeqsolve(term, solver, 0.0, t1, 0.1, y0, **kwargs)


@pytest.mark.parametrize("name", SOLVERS)
def test_a_coordinate_nothing_sees_is_named_when_traced(name):
    with pytest.raises(ValueError) as error:
        _solve(BLIND, SOLVERS[name]())
    message = str(error.value)
    assert message.startswith(SINGULAR_AT_START)
    assert "direction(s) q[1]" in message and "Remove those coordinates" in message


def test_a_combination_of_coordinates_is_named():
    # L sees only q0 - q1: the direction q0 + q1 is free.
    term = dvi.LagrangianTerm(
        lambda t, q, v, args: 0.5 * (v[0] - v[1]) ** 2 - 0.5 * (q[0] - q[1]) ** 2
    )
    with pytest.raises(ValueError, match=r"direction\(s\) \(1·q\[0\] \+ 1·q\[1\]\)"):
        _solve(term, dvi.CGVI(4))


def test_a_first_order_lagrangian_with_an_unseen_coordinate():
    # The rotation L = q0 v1 - (q0² + q1²)/2 is integrable; a third coordinate it never reads
    # is not.
    term = dvi.LagrangianTerm(lambda t, q, v, args: q[0] * v[1] - 0.5 * (q[0] ** 2 + q[1] ** 2))
    y0 = (jnp.array([0.5, 0.2, 0.1]), jnp.array([0.0, 0.5, 0.0]))
    with pytest.raises(ValueError, match=r"direction\(s\) q\[2\]"):
        _solve(term, dvi.CGVI(4), y0)


@pytest.mark.parametrize("name", SOLVERS)
def test_known_only_at_the_start_it_fails_when_the_solve_runs(name):
    with pytest.raises(Exception) as error:  # equinox's run-time error, from inside the jit
        _solve(BLIND_LATER, SOLVERS[name](), t1=0.1)
    assert DEGENERATE_START_MESSAGE in str(error.value)
    assert "NaN" not in str(error.value)


def _context(term, y0, solver=None):
    solver = solver or dvi.CGVI(4)
    return solver.step_context(term, jnp.asarray(0.0), jnp.asarray(0.1), y0, None)


def test_nothing_is_added_where_nothing_needs_checking():
    regular = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 0.5 * q @ q)
    rotation = dvi.LagrangianTerm(lambda t, q, v, args: q[0] * v[1] - 0.5 * q @ q)
    for term in (regular, rotation):
        ctx = _context(term, Y0)
        assert refuse_degenerate_start(ctx) is ctx
    # a kinetic matrix that varies with the state, regular at a random state
    pendulum = problems.double_pendulum()
    ctx = _context(pendulum.term, pendulum.y0)
    assert refuse_degenerate_start(ctx) is ctx
    # known only from the start's values: checked on them (here at once, as they are concrete)
    with pytest.raises(Exception, match="singular at the start"):
        refuse_degenerate_start(_context(BLIND_LATER, Y0))


def test_supported_degenerate_lagrangians_still_integrate():
    # First order (a rotation; its kinetic matrix is zero), exact solution known.
    rotation = dvi.LagrangianTerm(lambda t, q, v, args: q[0] * v[1] - 0.5 * q @ q)
    y0 = (jnp.array([0.5, 0.2]), jnp.array([0.0, 0.5]))
    sol = _solve(rotation, dvi.CGVI(4), y0, t1=0.3)
    t = 0.3
    exact = [0.5 * np.cos(t) - 0.2 * np.sin(t), 0.2 * np.cos(t) + 0.5 * np.sin(t)]
    np.testing.assert_allclose(np.asarray(sol.ys[0][-1]), exact, atol=1e-10)
    # A second-order oscillator beside a first-order rotation: a singular, nonzero kinetic
    # matrix whose null space the momentum and the force see.
    mixed = dvi.LagrangianTerm(
        lambda t, q, v, args: 0.5 * v[0] ** 2 - 0.5 * q[0] ** 2
        + q[1] * v[2] - 0.5 * (q[1] ** 2 + q[2] ** 2)
    )
    y0 = (jnp.array([0.3, 0.4, 0.5]), jnp.array([0.1, 0.0, 0.4]))
    sol = _solve(mixed, dvi.CGVI(4), y0, t1=0.3)
    q = np.asarray(sol.ys[0][-1])
    np.testing.assert_allclose(q[0], 0.3 * np.cos(t) + 0.1 * np.sin(t), atol=1e-10)
    np.testing.assert_allclose(np.hypot(q[1], q[2]), np.hypot(0.4, 0.5), atol=1e-10)


def test_blind_directions():
    eye = np.eye(3)
    mass = np.diag([1.0, 0.0, 0.0])
    force = np.diag([-1.0, -1.0, 0.0])
    found = blind_directions([mass, force], eye, 1e-12)
    assert found.shape == (3, 1) and abs(abs(found[2, 0]) - 1) < 1e-12
    assert blind_directions([mass, -np.eye(3)], eye, 1e-12).shape == (3, 0)
    # zero blocks see nothing; a restricted basis stays within its span
    assert blind_directions([np.zeros((3, 3))], eye, 1e-12).shape == (3, 3)
    assert blind_directions([mass], eye[:, 1:], 1e-12).shape == (3, 2)
