"""The typed interface between NetworkVI and its root finder
(`diffrax_vi._root_finder.step_hints`)."""

import diffrax
import jax
import jax.numpy as jnp
import optimistix as optx
import pytest
from jax.flatten_util import ravel_pytree

import diffrax_vi as dvi
from diffrax_vi._root_finder.step_hints import (
    HINT_FEATURES,
    AbstractStepRootFinder,
    StepHints,
    hints_of,
    missing_hints,
    step_options,
)

jax.config.update("jax_enable_x64", True)

TERM = dvi.LagrangianTerm(lambda t, q, v, args: 0.5 * v @ v - 0.5 * q @ q)
Y0 = (jnp.array([0.5]), jnp.array([0.0]))


def test_what_each_root_finder_reads():
    assert missing_hints(dvi.LevenbergMarquardt()) == {}
    assert missing_hints(dvi.RegularisedNewton()) == {}
    assert set(missing_hints(dvi.RoundoffNewton())) == {"outputs", "fallback"}
    assert set(missing_hints(dvi.ChordIteration())) == {"outputs", "fallback"}
    assert missing_hints(optx.Newton(rtol=1e-8, atol=1e-8)) == HINT_FEATURES
    # a class attribute alone does not make a root finder read the hints
    class Pretends(optx.Newton):
        hints_read = frozenset(HINT_FEATURES)

    assert missing_hints(Pretends(rtol=1e-8, atol=1e-8)) == HINT_FEATURES


def test_hints_travel_in_the_options_under_one_key():
    hints = StepHints(scale=2.0)
    assert hints_of(step_options(hints)) is hints
    assert hints_of(None) == StepHints() and hints_of({}) == StepHints()


def test_a_plain_optimistix_root_finder_is_told_what_it_lacks():
    with pytest.warns(UserWarning, match="does not read NetworkVI's step hints") as record:
        dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 4), formulation=dvi.FreeEndpoints(),
                      root_finder=optx.Newton(rtol=1e-8, atol=1e-8))
    message = str(record[0].message)
    for feature in HINT_FEATURES.values():
        assert feature in message
    assert record[0].filename == __file__  # the warning points at the user's line
    with pytest.raises(TypeError, match="root_finder must be an optimistix root finder"):
        dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 4), root_finder="newton")


def _captured_hints(monkeypatch, solver) -> list[StepHints]:
    # every step's root find passes through optimistix's entry point or through the
    # package's own (`step_root_find`, for a root finder that runs a whole solve in one step)
    from diffrax_vi._step import projected_solve

    seen = []
    root_find = optx.root_find
    step_root_find = projected_solve.step_root_find

    def spy(*args, options=None, **kwargs):
        seen.append(hints_of(options))
        assert set(options) == {"step"}
        return root_find(*args, options=options, **kwargs)

    def step_spy(fn, root_finder, y0, args, options, **kwargs):
        seen.append(hints_of(options))
        assert set(options) == {"step"}
        return step_root_find(fn, root_finder, y0, args, options, **kwargs)

    monkeypatch.setattr(optx, "root_find", spy)
    monkeypatch.setattr(projected_solve, "step_root_find", step_spy)
    sol = diffrax.diffeqsolve(TERM, solver, 0.0, 0.2, 0.1, Y0)
    assert sol.result == diffrax.RESULTS.successful
    return seen


def test_the_projected_step_hands_its_root_finder_typed_hints(monkeypatch):
    # Newton's iteration (not the Jacobian-free one, which takes no hints)
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 6),
                           root_finder=dvi.RoundoffNewton(confirm=False))
    seen = _captured_hints(monkeypatch, solver)
    assert seen
    for hints in seen:
        assert isinstance(hints, StepHints)
        assert hints.jacobian is not None and hints.kinetic is not None
        assert hints.restart is not None and hints.outputs is None
        assert jnp.asarray(hints.scale).shape == ()


def test_the_all_parameter_step_hands_its_root_finder_typed_hints(monkeypatch):
    solver = dvi.NetworkVI(
        dvi.ShallowNetBasis(dvi.tanh, 6), formulation=dvi.FreeEndpoints(),
        seed=dvi.SeedPolicy(reuse_neurons=True),
        root_finder=dvi.LevenbergMarquardt(jacobian="auto"),
    )
    seen = _captured_hints(monkeypatch, solver)
    assert seen
    for hints in seen:
        assert hints.outputs is not None and hints.jacobian is not None
        # refits are carried seeds: the fresh fit is the fallback
        assert hints.fallback is not None and hints.start_at_fallback is not None


class _PlainNewton(AbstractStepRootFinder):
    """A root finder from outside the package that follows the interface: Newton with the
    solver's Jacobian where it gives one, stopping at a residual relative to its scale."""

    hints_read = frozenset({"jacobian", "scale"})
    jacobian: str = "auto"  # asks the solver for the Jacobian in closed form
    rtol: float = 1e-12
    atol: float = 1e-12
    norm = staticmethod(optx.max_norm)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return jnp.array(jnp.inf)

    def step(self, fn, y, args, options, state, tags):
        hints = hints_of(options)
        flat, unravel = ravel_pytree(y)

        def residual(v):
            return ravel_pytree(fn(unravel(v), args)[0])[0]

        given = hints.jacobian
        jac = jax.jacfwd(residual)(flat) if given is None else given(y, args)
        new = flat - jnp.linalg.solve(jac, residual(flat))
        fmax = jnp.max(jnp.abs(residual(new)))
        return unravel(new), fmax / hints.scale, fn(unravel(new), args)[1]

    def terminate(self, fn, y, args, options, state, tags):
        return state <= 64 * jnp.finfo(jnp.float64).eps, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


def test_a_root_finder_outside_the_package_gets_the_hints_it_reads(recwarn):
    def cgvi(root_finder):
        return dvi.NetworkVI(dvi.LagrangeBasis(3), dvi.GaussLegendre(4),
                             formulation=dvi.FreeEndpoints(),
                             seed=dvi.SeedPolicy(initial_guess=dvi.LeastSquaresFit()),
                             root_finder=root_finder)

    own = diffrax.diffeqsolve(TERM, cgvi(_PlainNewton()), 0.0, 1.0, 0.1, Y0)
    ours = diffrax.diffeqsolve(TERM, cgvi(dvi.LevenbergMarquardt()), 0.0, 1.0, 0.1, Y0)
    assert not [w for w in recwarn if "step hints" in str(w.message)]
    assert own.result == diffrax.RESULTS.successful
    # both stop each step at a residual of 64 eps times the scale (0.5 of 1 + |q|): ten
    # steps apart by a few such residuals
    assert jnp.max(jnp.abs(own.ys[0] - ours.ys[0])) <= 1e-13
    assert missing_hints(_PlainNewton()) == {
        k: v for k, v in HINT_FEATURES.items() if k not in ("jacobian", "scale")}


def test_a_restart_hint_needs_the_iteration_cap():
    # The restart sits between the loops of a whole solve, which needs the solver's cap.
    hints = StepHints(restart=(4, lambda args: jnp.zeros(2)))
    with pytest.raises(ValueError, match="max_iterations"):
        optx.root_find(lambda y, args: y - 1.0, dvi.RoundoffNewton(), jnp.zeros(2),
                       options=step_options(hints), max_steps=10, throw=False)


def test_each_root_finder_answers_the_steps_questions():
    """What the step asks its root finder beyond optimistix's interface (`traits_of`): any
    optimistix root finder gets the answers of one that reads no hint; ours answer for
    themselves."""
    from diffrax_vi._root_finder.step_hints import traits_of

    foreign = traits_of(optx.Newton(rtol=1e-8, atol=1e-8))
    assert not any(foreign.reads_hint(name) for name in HINT_FEATURES)
    assert foreign.jacobian_mode() is None and foreign.companion() is None
    assert foreign.final_residual(None, jnp.float64) is None
    assert not foreign.allows_picard() and not bool(foreign.was_restarted(None))
    assert traits_of(dvi.ChordIteration(picard=True)).allows_picard()
    assert not traits_of(dvi.ChordIteration()).allows_picard()
    assert isinstance(traits_of(dvi.RoundoffNewton()).companion(), dvi.LevenbergMarquardt)
    assert traits_of(dvi.LevenbergMarquardt()).companion() is None
    assert traits_of(dvi.LevenbergMarquardt(jacobian="structured")).jacobian_mode() == (
        "structured")
    assert traits_of(dvi.RoundoffNewton()).reads_hint("max_iterations")
