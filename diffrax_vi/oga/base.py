"""What every OGA seed is: a parameter seed of a shallow network with its dictionary's bias
range and resolution, which says whether it runs the reference's verbatim algorithm (which
`oga_fit` dispatches on)."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
from jaxtyping import Array

from .._ansatz.base import AbstractBasis
from .._parameter_seed import AbstractParameterSeed, FitProblem
from .dictionaries import bias_pair, dictionary_range
from .network_fit import check_network, fit_network

__all__ = ["DEFAULT_BIAS_INTERVAL", "DEFAULT_DICT_AMOUNT", "AbstractOGA"]

DEFAULT_BIAS_INTERVAL = (-math.pi, math.pi)
DEFAULT_DICT_AMOUNT = 4000


class AbstractOGA(AbstractParameterSeed):
    """An OGA seed (`OGA`, `OGAReference`): `bias_interval` (default `(-π, π)`) and
    `dict_amount` (default 4000) size its dictionary; `reference` says whether it runs the
    reference's verbatim algorithm."""

    bias_interval: tuple[float, float] = eqx.field(
        static=True, default=DEFAULT_BIAS_INTERVAL, kw_only=True, converter=bias_pair
    )
    dict_amount: int = eqx.field(static=True, default=DEFAULT_DICT_AMOUNT, kw_only=True)
    reference: eqx.AbstractClassVar[bool]

    def __check_init__(self):
        dictionary_range(self.bias_interval, self.dict_amount)

    def parameters(self, basis: AbstractBasis, problem: FitProblem) -> Array:
        return fit_network(basis, self, problem)

    def check(self, basis: AbstractBasis) -> None:
        check_network(basis)

    def with_dictionary(self, **options) -> AbstractOGA:
        return dataclasses.replace(self, **options)
