"""Swing a damped pendulum up by a torque tuned with gradients through the variational solve.

The pendulum `L = v²/2 + cos q` (hanging at `q = 0`) with joint friction `−0.1 v` and a
torque `u(t) = Σ_i a_i sin(iπt/T)` (four parameters). Starting at rest at the bottom, the
torque should leave it at rest at the top (`q(T) = π`, `v(T) = 0`) at `T = 6`. The loss
`(q(T) − π)² + p(T)²` is differentiated through `diffeqsolve` with a `CGVI` solver (the
force enters each step's equations as virtual work; the derivatives are those of the
converged steps) and minimised by Adam.

    .venv/bin/python examples/swing_up.py
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import optax

import diffrax_vi as dvi

jax.config.update("jax_enable_x64", True)

T = 6.0
MODES = jnp.arange(1, 5)
ITERATIONS = 150


def torque(t, amplitudes):
    return jnp.sum(amplitudes * jnp.sin(MODES * jnp.pi * t / T))


term = dvi.LagrangianTerm(
    lambda t, q, v, a: 0.5 * v @ v + jnp.cos(q[0]),
    force=lambda t, q, v, a: -0.1 * v + torque(t, a),
)
solver = dvi.CGVI(4)


def final_state(amplitudes):
    sol = diffrax.diffeqsolve(term, solver, 0.0, T, T / 120, (jnp.zeros(1), jnp.zeros(1)),
                              args=amplitudes, saveat=diffrax.SaveAt(t1=True))
    return sol.ys[0][-1, 0], sol.ys[1][-1, 0]


def loss(amplitudes):
    q, p = final_state(amplitudes)
    return (q - jnp.pi) ** 2 + p**2


def tune(iterations: int = ITERATIONS, learning_rate: float = 0.1):
    """Adam on the torque's amplitudes from zero; returns them and the loss history."""
    optimiser = optax.adam(learning_rate)
    amplitudes = jnp.zeros(MODES.shape[0])
    state = optimiser.init(amplitudes)

    @jax.jit
    def update(amplitudes, state):
        value, grad = jax.value_and_grad(loss)(amplitudes)
        change, state = optimiser.update(grad, state)
        return optax.apply_updates(amplitudes, change), state, value

    history = []
    for _ in range(iterations):
        amplitudes, state, value = update(amplitudes, state)
        history.append(float(value))
    return amplitudes, history


if __name__ == "__main__":
    amplitudes, history = tune()
    q, p = final_state(amplitudes)
    print(f"loss {history[0]:.3e} -> {float(loss(amplitudes)):.3e} in {len(history)} steps")
    print(f"end state q = {float(q):.6f} (pi = {jnp.pi:.6f}), p = {float(p):.2e}")
    print("amplitudes", [round(float(a), 4) for a in amplitudes])
