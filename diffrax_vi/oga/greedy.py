"""The orthogonal greedy fit of a shallow network to sampled data.

`oga_fit` chooses hidden neurons `(w_k, b_k)` one at a time from a dictionary and refits all
output weights after every choice, so that `u(t) = sum_k c_k sigma(w_k t + b_k)` approximates
a target in the quadrature-weighted norm `||f||_w^2 = sum_j w_j f(t_j)^2`. It is the seed
(initial guess) of the network integrators' Newton solve.

The fit works in the scaled space of `_scaled` (weighted inner products as Euclidean ones).
The loop is a `lax.while_loop` with static shapes; selected columns live in a fixed `(M, K)`
design whose unused columns are zero. It stops early once the residual is at rounding level,
so that no atom is picked against rounding noise; the neurons left over become placeholders
drawn from usable atoms, so that none vanishes on the nodes (a dead neuron would give a zero
Jacobian column).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array

from .._ansatz.symmetry import AbstractSymmetry, NoSymmetry
from .._precision import as_dtype, eps, norm2, sqrt_eps
from ._qr import QRState, qr_append, qr_init
from ._scaled import ScaledDictionary, build_dictionary, cached_dictionary, validate_inputs
from .dictionaries import Refined
from .fits import guarded_solve
from .reference import oga_reference_fit
from .result import OGAResult

__all__ = ["OGAResult", "oga_fit"]


class _Carry(NamedTuple):
    attempt: Array
    step: Array
    ncols: Array
    rejected: Array
    stopped: Array
    qr: QRState
    design: Array
    x: Array
    resid: Array
    avail: Array  # usable and not blocked
    pending: Array  # coherence blocking of the last accepted atom not yet applied
    pending_best: Array
    slot_w: Array  # (w, b) of the atom placed at each greedy step
    slot_b: Array
    atoms: Array
    gains: Array


def oga_fit(
    config,
    activation: Callable,
    nodes: Array,
    weights: Array,
    y: Array,
    width: int,
    *,
    bias_interval: tuple[float, float] | None = None,
    dict_amount: int | None = None,
    modulation: Array | None = None,
    symmetry: AbstractSymmetry | None = None,
) -> OGAResult:
    """Fit `u(t) = sum_k c_k activation(W_k t + b_k)` to `y` by orthogonal greedy selection.

    Each greedy step scores every usable, unblocked dictionary atom against the current
    residual (`config.selection`), takes the best one (lowest index on ties), appends its
    column to an incremental QR factorisation (refused, blocked and counted in `rejected` if
    it adds no new direction), refits all output weights (`config.fit`, made finite by a
    ridged fallback), and blocks the atom (and, with `config.coherence`, its near duplicates).
    The loop ends when `width` neurons are placed, when no usable atom is left, after
    `9 G + 8` attempts, or when the residual has dropped to rounding level
    (`<= 8 eps ||sqrt(w) y||`, which includes `y = 0`). Neurons left over are then filled with
    distinct usable atoms at zero output weight (`config.fill_unused`).

    Pure JAX with static shapes: it can be called under `jax.jit` and `jax.vmap` (e.g. over
    a batch of targets). Called eagerly it compiles once per static configuration. Every
    array and constant stays in the dtype `T` of `nodes`.

    **Arguments:**

    - `config`: the `OGA` configuration (static), or the configuration of
        `OGA1dNormalEquations()` (an unguarded normal-equations baseline in float64, which
        takes no `modulation` or `symmetry`).
    - `activation`: the elementwise activation `sigma`; it must keep the dtype `T`
        (checked, a promoting activation raises `ValueError`). Must be hashable.
    - `nodes`: `(M,)` sample points `t_j` in `[0, 1]`; their dtype is the working dtype `T`.
    - `weights`: `(M,)` positive quadrature weights `w_j` (e.g. composite Simpson), dtype `T`.
    - `y`: `(M,)` target values, dtype `T`.
    - `width`: number of neurons `S` (a positive Python int).
    - `bias_interval`: `(lo, hi)` with `lo < hi`, the bias range of grid dictionaries.
        Default `None`: the configuration's own (`config.bias_interval`).
    - `dict_amount`: the dictionary resolution (number of bias intervals for `BiasGrid1d`).
        Default `None`: the configuration's own (`config.dict_amount`).
    - `modulation`: optional `(M,)` factor multiplying every atom (e.g. `t (1 - t)` for an
        ansatz that vanishes at both ends); dtype `T`.
    - `symmetry`: how atoms map to neurons; `None` (the default) means `NoSymmetry()`;
        `MirrorPairs()` and `SharedMirrorPairs()` place mirrored pairs (even `width` only).

    **Returns:**

    An `OGAResult`.
    """
    # Any OGA seed says whether it is the reference's (`AbstractOGA.reference`); the class
    # itself is not imported here, as it fits networks by calling this function.
    if getattr(config, "reference", None) not in (True, False):
        raise ValueError(f"oga_fit needs an OGA configuration, got {config!r}")
    if bias_interval is None:
        bias_interval = config.bias_interval
    if dict_amount is None:
        dict_amount = config.dict_amount
    raw = (nodes, weights, modulation)  # before validation turns them into (traced) arrays
    if config.reference:
        if modulation is not None or not isinstance(symmetry, NoSymmetry | None):
            raise ValueError(
                "the reference seed (OGA1dNormalEquations) takes no modulation and no symmetry"
            )
        args = (nodes, weights, y, width, bias_interval, dict_amount, None, NoSymmetry())
        nodes, weights, y, _, bias_interval = validate_inputs(activation, *args)
        return _reference_jit(activation, nodes, weights, y, width, bias_interval, dict_amount)
    symmetry = NoSymmetry() if symmetry is None else symmetry
    args = (nodes, weights, y, width, bias_interval, dict_amount, modulation, symmetry)
    nodes, weights, y, modulation, bias_interval = validate_inputs(activation, *args)
    dic = cached_dictionary(
        config, activation, raw, nodes.dtype, bias_interval, dict_amount, symmetry
    )
    if dic is not None:
        return _greedy_jit(config, activation, dic, nodes, jnp.sqrt(weights) * y, width, symmetry)
    args = (nodes, weights, y, width, bias_interval, dict_amount, modulation, symmetry)
    return _oga_fit_jit(config, activation, *args)


@eqx.filter_jit
def _reference_jit(activation, nodes, weights, y, width, bias_interval, dict_amount):
    return oga_reference_fit(
        activation, nodes, weights, y, int(width), bias_interval, int(dict_amount)
    )


@eqx.filter_jit
def _first_argmax(x: Array, index: Array) -> Array:
    """`argmax` of a finite vector (first index on ties), as a max and an index min: two
    plain reductions, faster than XLA's CPU argmax on a large dictionary."""
    top = jnp.max(x)
    return jnp.min(jnp.where(x == top, index, jnp.int32(x.shape[0]))).astype(jnp.int32)


@eqx.filter_jit
def _greedy_jit(config, activation, dic, nodes, yhat, width, symmetry):
    # Jitted so that a solver whose step is traced several times (diffrax traces its loop
    # body more than once) traces the greedy loop once.
    return _greedy(config, activation, dic, nodes, yhat, int(width), symmetry)


@eqx.filter_jit
def _oga_fit_jit(
    config, activation, nodes, weights, y, width, bias_interval, dict_amount, modulation, symmetry
):
    # The dictionary is built inside the program here: some of its inputs are traced.
    dic = build_dictionary(
        config, activation, nodes, weights, bias_interval, int(dict_amount), modulation, symmetry
    )
    yhat = jnp.sqrt(weights) * y
    return _greedy(config, activation, dic, nodes, yhat, int(width), symmetry)


def _greedy(
    config,
    activation: Callable,
    dic: ScaledDictionary,
    nodes: Array,
    yhat: Array,
    width: int,
    symmetry: AbstractSymmetry,
) -> OGAResult:
    dtype = yhat.dtype
    nsteps = width // symmetry.neurons_per_atom
    maxcols = nsteps * symmetry.columns_per_atom
    maxattempts = 9 * nsteps + 8
    cap = as_dtype(1, dtype) - sqrt_eps(dtype)
    psi_t, norms = dic.psi_t, dic.norms
    atom_index = jnp.arange(norms.shape[0], dtype=jnp.int32)

    # Rounding-level residual test, on max-abs-normalised vectors (no overflow).
    ymax = jnp.max(jnp.abs(yhat))
    ysafe = jnp.where(ymax > 0, ymax, as_dtype(1, dtype))
    tol = as_dtype(8, dtype) * eps(dtype) * norm2(yhat / ysafe)

    def negligible(resid):
        return (ymax == 0) | (norm2(resid / ysafe) <= tol)

    def coherent(dots, best):
        """Atoms whose |cosine| with atom `best` exceeds the cap."""
        return jnp.abs(dots) > cap * norms * norms[best]

    def cond(c: _Carry):
        return (c.attempt < maxattempts) & (c.step < nsteps) & ~c.stopped

    def body(c: _Carry) -> _Carry:
        # One pass over the dictionary gives the projections of the residual and, when the
        # previous attempt accepted an atom, its coherence products (blocking deferred to here).
        if config.coherence:
            prods = jnp.stack([c.resid, psi_t[:, c.pending_best]]) @ psi_t
            proj, dots = jnp.abs(prods[0]), prods[1]
            avail = c.avail & ~(c.pending & coherent(dots, c.pending_best))
        else:
            proj, avail = jnp.abs(c.resid @ psi_t), c.avail
        scores = config.selection.scores(proj, norms, psi_t, c.qr)
        ok = avail & jnp.isfinite(proj) & jnp.isfinite(scores)
        scores = jnp.where(ok, scores, as_dtype(-1, dtype))
        best = _first_argmax(scores, atom_index)
        stop = (scores[best] < 0) | negligible(c.resid)
        wa, ba, columns = _atom_columns(config, activation, dic, nodes, c, best, symmetry)
        qr, gain, good = _append_columns(config, c.qr, columns)
        accept = ~stop & good

        # Tentative accepted state; kept only if `accept` (all small arrays).
        design = c.design
        for j in range(columns.shape[1]):
            at = jnp.arange(maxcols) == c.ncols + j
            design = jnp.where(at[None, :], columns[:, j : j + 1], design)
        ncols = c.ncols + columns.shape[1]
        x = guarded_solve(config.fit, design, yhat, qr, ncols)
        at_step = accept & (jnp.arange(nsteps) == c.step)

        def keep(new, old):
            return jnp.where(accept, new, old)

        return _Carry(
            attempt=c.attempt + 1,
            step=c.step + accept.astype(jnp.int32),
            ncols=keep(ncols, c.ncols),
            rejected=c.rejected + (~stop & ~good).astype(jnp.int32),
            stopped=stop,
            qr=QRState(*(keep(n, o) for n, o in zip(qr, c.qr, strict=True))),
            design=keep(design, c.design),
            x=keep(x, c.x),
            resid=keep(yhat - design @ x, c.resid),
            avail=avail & (stop | (atom_index != best)),
            pending=accept,
            pending_best=keep(best, c.pending_best),
            slot_w=jnp.where(at_step, wa, c.slot_w),
            slot_b=jnp.where(at_step, ba, c.slot_b),
            atoms=jnp.where(at_step, best, c.atoms),
            gains=jnp.where(at_step, gain, c.gains),
        )

    out = lax.while_loop(cond, body, _initial_carry(dic, yhat, nsteps, maxcols))
    return _result(config, dic, out, nsteps, width, symmetry)


def _atom_columns(config, activation, dic, nodes, c: _Carry, best, symmetry):
    """The atom `(w, b)` taken at index `best` (refined if the dictionary asks for it) and
    its fit columns."""
    wa, ba = dic.atom_w[best], dic.atom_b[best]
    if isinstance(config.dictionary, Refined):
        found = (c.resid, c.qr, wa, ba, symmetry)
        wa, ba = _refine(config.dictionary, config.selection, activation, dic, nodes, *found)
        row = symmetry.scoring_rows(activation, wa[None], ba[None], nodes, dic.colscale)[0]
    else:
        row = dic.psi_t[:, best]
    return wa, ba, symmetry.fit_columns(activation, wa, ba, nodes, dic.colscale, row)


def _append_columns(config, qr: QRState, columns: Array):
    """Append an atom's columns to the QR factorisation: the new factorisation, the smallest
    gain and whether every column added a new direction."""
    min_gain = config.selection.min_gain(columns.dtype)
    gain = as_dtype(0, columns.dtype)
    good = jnp.ones((), bool)
    for j in range(columns.shape[1]):
        qr, rho, accepted = qr_append(qr, columns[:, j], min_gain)
        gain = rho if j == 0 else jnp.minimum(gain, rho)
        good = good & accepted
    return qr, gain, good


def _initial_carry(dic: ScaledDictionary, yhat: Array, nsteps: int, maxcols: int) -> _Carry:
    dtype, num_nodes = yhat.dtype, yhat.shape[0]
    int0 = jnp.zeros((), jnp.int32)
    return _Carry(
        attempt=int0,
        step=int0,
        ncols=int0,
        rejected=int0,
        stopped=jnp.zeros((), bool),
        qr=qr_init(num_nodes, maxcols, dtype),
        design=jnp.zeros((num_nodes, maxcols), dtype),
        x=jnp.zeros((maxcols,), dtype),
        resid=yhat,
        avail=dic.usable,
        pending=jnp.zeros((), bool),
        pending_best=int0,
        slot_w=jnp.zeros((nsteps,), dtype),
        slot_b=jnp.zeros((nsteps,), dtype),
        atoms=jnp.full((nsteps,), -1, jnp.int32),
        gains=jnp.zeros((nsteps,), dtype),
    )


def _result(config, dic: ScaledDictionary, out: _Carry, nsteps, width, symmetry) -> OGAResult:
    slot_w, slot_b = out.slot_w, out.slot_b
    if config.fill_unused:
        # If the loop ran out of attempts right after accepting an atom, that atom's coherence
        # block is still pending; the fill excludes the atom itself but may take a close
        # neighbour. (Applying the block here costs a dictionary pass, slow under `vmap`.)
        def fill(wb):
            return _fill_unused(*wb, out.step, out.avail, out.atoms, dic)

        slot_w, slot_b = lax.cond(out.step < nsteps, fill, lambda wb: wb, (slot_w, slot_b))
    W, B = symmetry.neurons(slot_w, slot_b)
    return OGAResult(
        W=W,
        b=B,
        c=symmetry.coefficients(out.x * dic.scale, width),
        atoms=out.atoms,
        placed=out.step * symmetry.neurons_per_atom,
        residual=norm2(out.resid),
        gains=out.gains,
        rejected=out.rejected,
    )


def _fill_unused(slot_w, slot_b, step, avail, atoms, dic):
    """Give the atom slots `step..G-1` distinct atoms, spread over the candidates.

    Candidates are the available atoms: usable (not numerically zero on the nodes) and not
    blocked (neither selected, refused, nor coherent with a selected atom). If there are fewer
    of them than slots (e.g. float16, where the coherence guard blocks wide neighbourhoods),
    the usable atoms not selected by the loop are candidates, and failing that all atoms not
    selected. The `f`-th of `n` fills takes the candidate of rank `floor((2f + 1) ncand / (2n))`,
    the centre of the `f`-th of `n` equal parts of the candidate list, so fills are distinct
    when `ncand >= n`.
    """
    nsteps = slot_w.shape[0]
    nfill = nsteps - step
    num_atoms = avail.shape[0]
    index = jnp.where(atoms >= 0, atoms, num_atoms)  # untaken steps point out of range
    unselected = jnp.ones((num_atoms,), bool).at[index].set(False, mode="drop")
    usable = dic.usable & unselected
    cand = jnp.where(
        jnp.sum(avail, dtype=jnp.int32) >= nfill,
        avail,
        jnp.where(jnp.sum(usable, dtype=jnp.int32) >= nfill, usable, unselected),
    )
    counts = jnp.cumsum(cand, dtype=jnp.int32)
    ncand = counts[-1]
    f = jnp.arange(nsteps, dtype=jnp.int32) - step
    rank = ((2 * f + 1) * ncand) // (2 * jnp.maximum(nfill, 1))
    # The candidate of rank r sits at the first position whose running count exceeds r.
    idx = jnp.searchsorted(counts, rank + 1, side="left").astype(jnp.int32)
    idx = jnp.minimum(idx, counts.shape[0] - 1)
    live = f >= 0
    return (
        jnp.where(live, dic.atom_w[idx], slot_w),
        jnp.where(live, dic.atom_b[idx], slot_b),
    )


def _refine(refined, selection, activation, dic, nodes, resid, qr, w, b, symmetry):
    """Compass search of `(w, b)` on the normalised candidate score (see `Refined`)."""
    dtype = resid.dtype
    e = eps(dtype)
    zero = as_dtype(0, dtype)
    one = as_dtype(1, dtype)
    neg_inf = as_dtype(-jnp.inf, dtype)
    shrink = as_dtype(refined.shrink, dtype)

    def score(wc, bc):
        g = symmetry.scoring_rows(activation, wc[None], bc[None], nodes, dic.colscale)[0]
        n = norm2(g)
        p = jnp.abs(g @ resid)
        usable = jnp.isfinite(p) & jnp.isfinite(n) & (n > dic.nfloor)
        g = jnp.where(usable, g, zero)
        denom = selection.candidate_denominator(jnp.where(usable, n, one), g, qr)
        ok = usable & (denom > 0)
        return jnp.where(ok, p / jnp.where(ok, denom, one), neg_inf)

    best = score(w, b)
    h = (sqrt_eps(dtype) + jnp.abs(w) + jnp.abs(b)) / as_dtype(8, dtype)
    active = jnp.isfinite(best) & jnp.isfinite(h) & (h > e)

    def sweep(_, carry):
        w, b, best, h, active = carry
        improved = jnp.zeros((), bool)
        for move in range(4):
            if move == 0:
                cw, cb = w + h, b
            elif move == 1:
                cw, cb = w - h, b
            elif move == 2:
                cw, cb = w, b + h
            else:
                cw, cb = w, b - h
            s = score(cw, cb)
            take = active & jnp.isfinite(s) & (s > best)
            w, b = jnp.where(take, cw, w), jnp.where(take, cb, b)
            best = jnp.where(take, s, best)
            improved = improved | take
        h = jnp.where(active & ~improved, h * shrink, h)
        return w, b, best, h, active & (h > e)

    w, b, _, _, _ = lax.fori_loop(0, refined.iterations, sweep, (w, b, best, h, active))
    return w, b
