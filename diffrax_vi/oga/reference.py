"""The reference implementation's original greedy seed, kept as a numerical baseline.

This reproduces the seed of the original paper's code on purpose *without* any of the fixes
of `oga_fit`: the dictionary and the normal equations live in float64, the residual is
evaluated through the network with parameters rounded to the working dtype, nothing stops
the argmax from picking an atom again, there is no ridge, no rank detection, no norm floor,
no coherence guard, no placeholder fill and no power-of-two scaling. It breaks the precision
discipline deliberately (float64 inside a float16/float32 fit) and needs `jax_enable_x64`.

Where the reference throws on a singular Gram matrix (e.g. a repeated atom), this version
cannot raise under `jit`: the output weights then come out non-finite.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array

from ._qr import lu_solve
from .dictionaries import BiasGrid1d
from .result import OGAResult

__all__ = ["oga_reference_fit"]


def oga_reference_fit(
    activation: Callable,
    nodes: Array,
    weights: Array,
    y: Array,
    width: int,
    bias_interval: tuple[float, float],
    dict_amount: int,
) -> OGAResult:
    """The reference's seed (validated inputs; normally reached through `oga_fit`).

    For `k = 1..width`: evaluate the current network in the working dtype `T` (parameters
    rounded to `T`, initially all zero), score every `±1`-grid atom by the squared weighted
    projection of `u - y` (float64), take the first maximiser, and solve the `k x k` normal
    equations of the selected atoms in float64 by LU without ridge; round the output weights
    to `T`. `residual` is the weighted residual of the returned network (evaluated in `T`);
    `gains` are zero and `rejected` is zero (no QR is maintained).
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "the reference seed (OGA1dNormalEquations) computes in float64, which needs "
            "jax.config.update('jax_enable_x64', True)"
        )
    dtype = nodes.dtype
    f64 = jnp.float64
    table = BiasGrid1d().atoms_np(bias_interval, dict_amount, f64)
    atom_w, atom_b = jnp.asarray(table[:, 0]), jnp.asarray(table[:, 1])
    t64, w64, y64 = nodes.astype(f64), weights.astype(f64), y.astype(f64)
    phi = activation(atom_w[:, None] * t64[None, :] + atom_b[:, None])  # (N, M), float64
    slots = jnp.arange(width)
    rhs_all = phi @ (w64 * y64)

    def network(W, b, c):
        return activation(nodes[:, None] * W[None, :] + b[None, :]) @ c

    def step(k, carry):
        W, b, c, atoms = carry
        u = network(W, b, c).astype(f64)
        score = (phi @ (w64 * (u - y64))) ** 2
        best = jnp.argmax(score).astype(jnp.int32)
        atoms = jnp.where(slots == k, best, atoms)
        W = jnp.where(slots == k, atom_w[best].astype(dtype), W)
        b = jnp.where(slots == k, atom_b[best].astype(dtype), b)
        used = slots <= k
        sel = phi[jnp.where(used, atoms, 0)]  # (S, M); unused rows masked below
        gram = (sel * w64[None, :]) @ sel.T
        eye = jnp.eye(width, dtype=bool)
        both = used[:, None] & used[None, :]
        gram = jnp.where(both, gram, jnp.where(eye, 1.0, 0.0))
        rhs = jnp.where(used, rhs_all[jnp.where(used, atoms, 0)], 0.0)
        x = lu_solve(gram, rhs)
        c = jnp.where(used, x.astype(dtype), jnp.zeros_like(c))
        return W, b, c, atoms

    zeros = jnp.zeros((width,), dtype)
    init = (zeros, zeros, zeros, jnp.full((width,), -1, jnp.int32))
    W, b, c, atoms = lax.fori_loop(0, width, step, init)
    resid = jnp.sqrt(weights) * (network(W, b, c) - y)
    return OGAResult(
        W=W,
        b=b,
        c=c,
        atoms=atoms,
        placed=jnp.asarray(width, jnp.int32),
        residual=jnp.sqrt(jnp.sum(resid * resid)),
        gains=zeros,
        rejected=jnp.zeros((), jnp.int32),
    )
