"""Selection rules: how the greedy loop scores every atom against the current residual.

Every rule starts from the absolute projections `s_i = |<psi_i, r>|` of the scaled residual on
the scaled dictionary rows and the row norms `n_i`. The greedy loop marks unusable and blocked
atoms afterwards (score `-1`), so a rule only has to produce non-negative scores for the
usable ones.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from .numerics import as_dtype
from .qr import QRState

__all__ = ["AbstractSelection", "RawProjection", "NormalizedProjection"]


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

    @property
    def label(self) -> str:
        """A short name used in configuration labels."""
        return type(self).__name__


class RawProjection(AbstractSelection):
    """Score `|<psi_i, r>|`: the plain projection, not invariant to the scale of an atom.

    Atoms with a large norm are favoured. On the `±1` bias grid the norms are comparable and
    this is the reference's default (its selected atoms are pinned by a regression test); on
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
