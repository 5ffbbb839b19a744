"""The scaled dictionary of an OGA fit, and the checks of a fit's inputs.

Every node's value is multiplied by `sqrt(w_j)` (and by the optional modulation), so weighted
inner products become Euclidean ones, and the whole dictionary by one power of two so that its
largest row norm lies in `[1, 2)`. The dictionary does not depend on the target: with concrete
nodes it is built once and reused as a constant of the compiled fit.
"""

from __future__ import annotations

import collections
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._activations import check_activation
from .._ansatz.symmetry import AbstractSymmetry
from .._precision import as_dtype, norm2, power_of_two_scale, sqrt_eps
from .dictionaries import dictionary_range


class ScaledDictionary(NamedTuple):
    """The scaled dictionary of one fit (independent of the target)."""

    atom_w: Array
    atom_b: Array
    psi_t: Array  # scaled rows, stored transposed; zero for unusable atoms
    norms: Array
    usable: Array
    colscale: Array  # sqrt(weights) * modulation * scale
    scale: Array
    nfloor: Array  # norm floor of usable atoms (scaled units)


def _is_int(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def validate_inputs(
    activation, nodes, weights, y, width, bias_interval, dict_amount, modulation, symmetry
):
    if not isinstance(symmetry, AbstractSymmetry):
        raise ValueError(f"symmetry must be an AbstractSymmetry instance, got {symmetry!r}")
    if not callable(activation):
        raise ValueError(f"activation must be callable, got {activation!r}")

    arrays = {"nodes": nodes, "weights": weights, "y": y}
    if modulation is not None:
        arrays["modulation"] = modulation
    arrays = {name: jnp.asarray(value) for name, value in arrays.items()}
    dtype = arrays["nodes"].dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"nodes must have a floating dtype, got {dtype}")
    for name, value in arrays.items():
        if value.ndim != 1:
            raise ValueError(f"{name} must be one-dimensional, got shape {value.shape}")
        if value.dtype != dtype:
            raise ValueError(
                f"{name} has dtype {value.dtype} but nodes have dtype {dtype}; "
                "all inputs must share the working dtype"
            )
    num_nodes = arrays["nodes"].shape[0]
    if num_nodes < 1:
        raise ValueError("nodes must not be empty")
    for name, value in arrays.items():
        if value.shape[0] != num_nodes:
            raise ValueError(
                f"{name} has length {value.shape[0]} but nodes have length {num_nodes}"
            )
    if not isinstance(arrays["weights"], jax.core.Tracer):
        w = np.asarray(arrays["weights"])
        if not (np.all(np.isfinite(w)) and np.all(w > 0)):
            raise ValueError("quadrature weights must be finite and positive")

    if not _is_int(width) or width < 1:
        raise ValueError(f"width must be a positive integer, got {width!r}")
    symmetry.check_width(int(width))
    lo, hi = dictionary_range(bias_interval, dict_amount)
    check_activation(activation, dtype)
    return arrays["nodes"], arrays["weights"], arrays["y"], arrays.get("modulation"), (lo, hi)


def build_dictionary(
    config,
    activation: Callable,
    nodes: Array,
    weights: Array,
    bias_interval: tuple[float, float],
    dict_amount: int,
    modulation: Array | None,
    symmetry: AbstractSymmetry,
) -> ScaledDictionary:
    dtype = nodes.dtype
    zero = as_dtype(0, dtype)
    colscale = jnp.sqrt(weights)
    if modulation is not None:
        colscale = colscale * modulation
    table = config.dictionary.atoms_np(bias_interval, dict_amount, dtype)
    atom_w = jnp.asarray(table[:, 0], dtype=dtype)
    atom_b = jnp.asarray(table[:, 1], dtype=dtype)
    psi = symmetry.scoring_rows(activation, atom_w, atom_b, nodes, colscale)
    norms = norm2(psi, axis=1)
    finite = jnp.isfinite(norms)
    scale = power_of_two_scale(jnp.max(jnp.where(finite, norms, zero)))
    norms = norms * scale
    finite_max = jnp.max(jnp.where(finite, norms, zero))
    nfloor = sqrt_eps(dtype) * finite_max if config.norm_guard else zero
    usable = finite & (norms > nfloor)
    # Scaling is exact (a power of two); unusable atoms are zeroed so no Inf/NaN reaches a
    # product. Stored one column per atom: `r @ psi_t` streams contiguous memory.
    psi_t = jnp.where(usable[None, :], psi.T * scale, zero)
    return ScaledDictionary(atom_w, atom_b, psi_t, norms, usable, colscale * scale, scale, nfloor)


_DICTIONARY_CACHE: collections.OrderedDict = collections.OrderedDict()
_DICTIONARY_CACHE_SIZE = 16


def cached_dictionary(
    config, activation, raw, dtype, bias_interval, dict_amount, symmetry
) -> ScaledDictionary | None:
    """The scaled dictionary, built once and reused, when the nodes, weights and modulation
    `raw` were given as concrete values (NumPy arrays, or JAX arrays created outside any
    trace); `None` when any of them is traced.

    The dictionary does not depend on the target, so for fixed nodes it is a constant of the
    fit: building it eagerly turns the largest part of a fit with a big dictionary (one
    activation evaluation per atom and node) into an embedded constant of the compiled
    program. An integrator passes its quadrature's nodes as NumPy arrays for this reason.
    With traced nodes it is built inside the program instead. Results are identical.
    """
    arrays = tuple(a for a in raw if a is not None)
    if any(isinstance(a, jax.core.Tracer) for a in arrays):
        return None
    arrays = tuple(np.asarray(a) for a in arrays)
    modulation = arrays[2] if len(arrays) == 3 else None
    key = (
        config.dictionary,
        config.norm_guard,
        activation,
        symmetry,
        tuple(bias_interval),
        int(dict_amount),
        np.dtype(dtype).name,
    ) + tuple(a.tobytes() for a in arrays)
    try:
        hash(key)
    except TypeError:  # an unhashable activation: no caching
        key = None
    if key is not None and key in _DICTIONARY_CACHE:
        _DICTIONARY_CACHE.move_to_end(key)
        return _DICTIONARY_CACHE[key]
    with jax.ensure_compile_time_eval():
        nodes, weights = (jnp.asarray(a, dtype) for a in arrays[:2])
        if modulation is not None:
            modulation = jnp.asarray(modulation, dtype)
        # One compiled program rather than op-by-op dispatch (which compiles each operation
        # on its own: seconds of a solver's compile time).
        dic = eqx.filter_jit(build_dictionary)(
            config, activation, nodes, weights, bias_interval, dict_amount, modulation, symmetry
        )
        dic = ScaledDictionary(*(jax.block_until_ready(jnp.asarray(v)) for v in dic))
    if key is not None:
        _DICTIONARY_CACHE[key] = dic
        if len(_DICTIONARY_CACHE) > _DICTIONARY_CACHE_SIZE:
            _DICTIONARY_CACHE.popitem(last=False)
    return dic
