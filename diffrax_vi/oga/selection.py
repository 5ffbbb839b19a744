"""Selection rules: how the greedy loop scores every atom against the current residual.

Every rule starts from the absolute projections `s_i = |<psi_i, r>|` of the scaled residual on
the scaled dictionary rows and the row norms `n_i`. The greedy loop marks unusable and blocked
atoms afterwards (score `-1`), so a rule only has to produce non-negative scores for the
usable ones.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from .._precision import as_dtype, sqrt_eps, sumsq
from ._qr import QRState

__all__ = [
    "AbstractSelection",
    "RawProjection",
    "NormalizedProjection",
    "OrthogonalProjection",
]


class AbstractSelection(eqx.Module):
    """Base class of selection rules.

    Subclasses implement `scores`; a rule that refuses atoms whose new direction is too small
    (a rank-gain floor) also overrides `min_gain`, which the incremental QR append enforces.
    """

    @abc.abstractmethod
    def scores(
        self,
        proj: Array,
        norms: Array,
        psi_t: Array,
        qr: QRState,
    ) -> Array:
        """Scores of all atoms (only the entries of usable atoms are used).

        **Arguments:**

        - `proj`: absolute projections `|<psi_i, r>|` of the residual.
        - `norms`: the row norms `||psi_i||` (positive for usable atoms).
        - `psi_t`: the scaled dictionary, one column per atom (zero for unusable atoms).
        - `qr`: the incremental QR factorisation of the columns selected so far.
        """

    def min_gain(self, dtype) -> Array:
        """Relative rank-gain floor for accepting a column; zero refuses only null gains."""
        return as_dtype(0, dtype)

    def candidate_denominator(self, norm: Array, column: Array, qr: QRState) -> Array:
        """Denominator of the normalised score of one off-grid candidate (used by `Refined`).

        The candidate's score is `|<g, r>| / denominator`; a non-positive denominator marks
        the candidate as unusable. The default is the norm `||g||` (normalised projection,
        whatever the rule: maximising a raw projection over continuous `(w, b)` would only
        inflate the atom).
        """
        del column, qr
        return norm

    @property
    def label(self) -> str:
        """A short name used in configuration labels."""
        return type(self).__name__


class RawProjection(AbstractSelection):
    """Score `|<psi_i, r>|`: the plain projection, not invariant to the scale of an atom.

    Atoms with a large norm are favoured. On the `±1` bias grid the norms are comparable and
    this is `OGA1d`'s rule (its selected atoms are pinned by a regression test); on
    grids that mix weight magnitudes a scale-invariant rule is needed.
    """

    def scores(self, proj, norms, psi_t, qr):
        del norms, psi_t, qr
        return proj

    @property
    def label(self) -> str:
        return "raw"


class NormalizedProjection(AbstractSelection):
    """Score `|<psi_i, r>| / ||psi_i||`: the cosine-like, scale-invariant projection.

    For the first atom this is exactly the choice that minimises the one-atom residual; later
    it ignores the overlap with atoms already selected.
    """

    def scores(self, proj, norms, psi_t, qr):
        del psi_t, qr
        safe = jnp.where(norms > 0, norms, jnp.ones_like(norms))
        return proj / safe

    @property
    def label(self) -> str:
        return "normalized"


class OrthogonalProjection(AbstractSelection):
    """Score `|<psi_i, r>| / ||psi_i^perp||`, the exact one-step optimum of the greedy refit.

    `psi_i^perp` is the part of the atom orthogonal to the columns selected so far, read from
    the maintained incremental QR factorisation: `||psi_i^perp||^2 = ||psi_i||^2 -
    ||Q^T psi_i||^2` (clamped at zero; rounding can make it negative for an atom already in
    the span). The numerator needs no projection because the residual is already orthogonal
    to the selected span. With no column selected yet this is `NormalizedProjection`.

    Atoms whose orthogonal part is at most `min_gain * ||psi_i||` are refused (score `-1`);
    the same relative floor is applied when the chosen column is appended to the QR, so a
    nearly dependent atom is never accepted. Costs one extra `(K, M) x (M, N)` product per
    step.

    **Arguments:**

    - `min_gain`: the relative rank-gain floor (a positive Python float), or `None` (default)
        for `sqrt(eps(T))` of the working dtype.
    """

    min_gain_value: float | None = eqx.field(static=True, default=None)

    def __init__(self, min_gain: float | None = None):
        if min_gain is not None:
            if isinstance(min_gain, bool) or not isinstance(min_gain, int | float):
                raise ValueError(f"min_gain must be a real number or None, got {min_gain!r}")
            min_gain = float(min_gain)
            if not (math.isfinite(min_gain) and 0 <= min_gain < 1):
                raise ValueError(f"min_gain must lie in [0, 1), got {min_gain!r}")
        self.min_gain_value = min_gain

    def min_gain(self, dtype) -> Array:
        if self.min_gain_value is None:
            return sqrt_eps(dtype)
        return as_dtype(self.min_gain_value, dtype)

    def _gains(self, norms, explained):
        res2 = norms * norms - explained
        return jnp.sqrt(jnp.where(res2 > 0, res2, jnp.zeros_like(res2)))

    def scores(self, proj, norms, psi_t, qr):
        # Columns of Q past k are zero, so the full product needs no mask (and at k = 0 the
        # gain is the norm: the normalised projection).
        explained = sumsq(qr.q.T @ psi_t, axis=0)
        gains = self._gains(norms, explained)
        floor = self.min_gain(norms.dtype)
        ok = gains > floor * norms
        safe = jnp.where(ok, gains, jnp.ones_like(gains))
        return jnp.where(ok, proj / safe, as_dtype(-1, proj.dtype))

    def candidate_denominator(self, norm, column, qr):
        gain = self._gains(norm, sumsq(qr.q.T @ column))
        floor = self.min_gain(norm.dtype)
        return jnp.where(gain > floor * norm, gain, jnp.zeros_like(gain))

    @property
    def label(self) -> str:
        return "orthogonal"
