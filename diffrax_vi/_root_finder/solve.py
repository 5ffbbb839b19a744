"""One entry point for a step's root find: `step_root_find`, `optimistix.root_find`'s
interface, with the step's derivative rule always the solver's `adjoint`.

A root finder that runs a whole solve in one optimistix step (it reads the hint
`max_iterations`: `RoundoffNewton`, `ChordIteration`, `JacobianFreeIteration`) is run here
without optimistix's outer loop, which would be one more compiled loop around a single
pass; any other root finder goes through `optimistix.root_find`. Either way the adjoint
differentiates the root (implicitly, for `optimistix.ImplicitAdjoint`), not the iteration.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from .step_hints import hints_of, traits_of

__all__ = ["one_step_solve", "step_root_find"]


def one_step_solve(root_finder, fn, y0, args, options, tags=frozenset()):
    """`(y, result, state, aux)` of `root_finder`'s whole solve from `y0`, run as its one
    optimistix step (`fn(y, args) -> (residual, aux)`)."""
    f_struct, aux_struct = jax.eval_shape(lambda: fn(y0, args))
    state = root_finder.init(fn, y0, args, options, f_struct, aux_struct, tags)
    y, state, aux = root_finder.step(fn, y0, args, options, state, tags)
    # a whole solve has ended after its one step (the root finders that run one test the
    # finiteness of their iterates themselves)
    _, result = root_finder.terminate(fn, y, args, options, state, tags)
    y, aux, _ = root_finder.postprocess(fn, y, aux, args, options, state, tags, result)
    return y, result, state, aux


def _primal(inputs):
    fn, root_finder, y0, args, options, *_ = inputs
    y, result, state, aux = one_step_solve(root_finder, fn, y0, args, options)
    return y, (result, state, aux)


def _rewrite(root, _, inputs):
    fn, _, _, args, *_ = inputs
    return fn(root, args)[0]


def step_root_find(fn, root_finder, y0, args, options, *, max_steps: int,
                   adjoint: optx.AbstractAdjoint, has_aux: bool = True) -> optx.Solution:
    """`optimistix.root_find(fn, root_finder, y0, args, options, has_aux=has_aux,
    max_steps=max_steps, adjoint=adjoint, throw=False)`, without the outer loop where
    `root_finder` runs its whole solve in one step (`stats["num_steps"]` is then 1, and the
    root finder's state counts its iterations)."""
    whole = (traits_of(root_finder).reads_hint("max_iterations")
             and hints_of(options).max_iterations is not None)
    if not whole:
        return optx.root_find(fn, root_finder, y0, args, options, has_aux=has_aux,
                              max_steps=max_steps, adjoint=adjoint, throw=False)
    if not has_aux:
        plain = fn
        fn = lambda y, a: (plain(y, a), None)  # noqa: E731
    # closed-over arrays become inputs, as optimistix does: the derivative rule sees them
    fn = eqx.filter_closure_convert(fn, y0, args)
    inputs = (fn, root_finder, y0, args, options, max_steps)
    y, (result, state, aux) = adjoint.apply(_primal, _rewrite, inputs, frozenset())
    return optx.Solution(value=y, result=result, aux=aux, state=state,
                         stats={"num_steps": jnp.array(1), "max_steps": max_steps})
