"""Tabulated high-accuracy reference solutions shipped with the package.

Problems without a closed-form solution carry a precomputed trajectory of their nominal (default)
float64 problem: checkpoints `(q, p)` every `spacing` time units over the default span, computed
once by `problems/data/generate.py` in extended precision and stored in `problems/data/*.npz`.
Between checkpoints the flow is evaluated by integrating a short hop (at most half a spacing) from
the nearest checkpoint with a Gragg–Bulirsch–Stoer extrapolation step of order 16, vectorised over
the requested times in NumPy. No scipy is needed at run time.

Times outside the stored span, or a problem whose parameters or initial data differ from the
stored ones, fall back to a `DOP853Flow` (scipy) of the same equations.

A time-dependent problem (a Lagrangian with an explicit `t`) is stored as the autonomous system
of the augmented state `concat(q, p, [t])` with `dt/dt = 1`: its checkpoints carry their
absolute time, the extrapolation steps integrate the time exactly, and its stored data applies
only to the start time it was generated for (`StoredFlow(..., t0=...)`).
"""

from __future__ import annotations

import importlib.resources
import math
from collections.abc import Callable

import numpy as np

from .base import DOP853Flow

__all__ = ["StoredFlow", "gbs_step", "gbs_integrate", "load_reference_data"]

# Step-number sequence of the extrapolation (harmonic sequence of even numbers): order 16.
GBS_SEQUENCE = (2, 4, 6, 8, 10, 12, 14, 16)


def gbs_step(rhs: Callable[[np.ndarray], np.ndarray], y: np.ndarray, h: np.ndarray) -> np.ndarray:
    """One Gragg–Bulirsch–Stoer step of order 16 for an autonomous ODE `y' = rhs(y)`.

    (A time-dependent ODE enters with the time as a last state component, see above.)

    Modified-midpoint solutions with `n = 2, 4, ..., 16` substeps are combined by
    Aitken–Neville extrapolation in `h²`. Vectorised: `y` has shape `(M, n)`, `h` shape `(M, 1)`
    (one step size per row, zero allowed); works in any floating dtype (e.g. `np.longdouble`).
    """
    # The midpoint recursions and the extrapolation run on the increment `z − y`, which keeps
    # the rounding errors (amplified by the extrapolation) at the scale of the increment.
    f0 = rhs(y)
    previous: list[np.ndarray] = []
    for j, n in enumerate(GBS_SEQUENCE):
        hs = h / n
        d0, d1 = np.zeros_like(y), hs * f0
        for _ in range(n - 1):
            d0, d1 = d1, d0 + 2 * hs * rhs(y + d1)
        row = [d1]
        for k in range(1, j + 1):
            m = GBS_SEQUENCE[j - k]
            row.append(row[k - 1] + (row[k - 1] - previous[k - 1]) * (m * m) / (n * n - m * m))
        previous = row
    return y + previous[-1]


def gbs_integrate(
    rhs: Callable[[np.ndarray], np.ndarray], y: np.ndarray, tau: np.ndarray, n_steps: int
) -> np.ndarray:
    """Integrate each row of `y` (shape `(M, n)`) over its own time `tau[i]` in `n_steps` steps."""
    h = (tau / n_steps)[:, None].astype(y.dtype)
    for _ in range(n_steps):
        y = gbs_step(rhs, y, h)
    return y


def load_reference_data(name: str) -> dict[str, np.ndarray] | None:
    """The stored reference data `data/<name>.npz` as a dict of arrays, or `None` if absent."""
    resource = importlib.resources.files(__package__).joinpath("data", f"{name}.npz")
    if not resource.is_file():
        return None
    with resource.open("rb") as f, np.load(f) as data:
        return {key: np.array(data[key]) for key in data.files}


class StoredFlow:
    """A reference flow read from the package's stored data, with a DOP853 fallback.

    **Arguments:**

    - `name`: the data set, `data/<name>.npz`.
    - `rhs`: the vectorised Hamiltonian vector field, `rhs(y) -> dy/dt` on float arrays of shape
      `(..., 2D)` holding `concat(q, p)` (NumPy only, so it also runs in `np.longdouble`). With
      `t0`, the field of the augmented state `concat(q, p, [t])`, shape `(..., 2D + 1)`, whose
      last component (the absolute time) has derivative 1.
    - `y0`: the flat float64 initial state `concat(q0, p0)` of this problem.
    - `key`: float64 vector of the problem's parameters; the stored data is used only when `y0`
      and `key` (and `t0`) equal the stored ones bit for bit.
    - `t0`: the start time of a time-dependent problem; `None` (default) for an autonomous one,
      whose flow depends on the elapsed time only. Then `self.y0` is `concat(q0, p0, [t0])`.

    The data holds `qp` (checkpoints, shape `(K + 1, 2D)`, or `(K + 1, 2D + 1)` with the
    absolute time last for a time-dependent problem, at `tau = 0, spacing, ...`),
    `spacing`, `hop_steps` (GBS steps per hop), `y0`, `key` and `verified_error` (the max-norm
    error of this flow measured by the generator against an extended-precision solution).
    """

    def __init__(
        self,
        name: str,
        rhs: Callable[[np.ndarray], np.ndarray],
        y0: np.ndarray,
        key: np.ndarray,
        *,
        t0: float | None = None,
    ):
        self.name = name
        self.rhs = rhs
        y0 = np.array(y0, dtype=np.float64)
        self.dim = y0.shape[0] // 2
        self.t0 = None if t0 is None else float(t0)
        self.y0 = y0 if t0 is None else np.append(y0, self.t0)
        self.key = np.array(key, dtype=np.float64)
        self.fallback = DOP853Flow(rhs, self.y0)
        self._data: dict[str, np.ndarray] | None = None
        self._loaded = False

    @property
    def time_dependent(self) -> bool:
        """Whether the vector field depends on the time (the state is augmented by `t`)."""
        return self.t0 is not None

    def vector_field(self, t: float, y: np.ndarray) -> np.ndarray:
        """Hamilton's equations `d concat(q, p)/dt` at the absolute time `t` (scipy's `fun(t, y)`
        convention), for autonomous and time-dependent problems alike."""
        y = np.asarray(y)
        if not self.time_dependent:
            return self.rhs(y)
        t = np.broadcast_to(np.asarray(t, dtype=y.dtype), y.shape[:-1])[..., None]
        return self.rhs(np.concatenate([y, t], axis=-1))[..., : 2 * self.dim]

    @property
    def data(self) -> dict[str, np.ndarray] | None:
        """The stored data if it matches this problem, else `None` (loaded once)."""
        if not self._loaded:
            data = load_reference_data(self.name)
            if data is not None and not (
                np.array_equal(data["y0"], self.y0) and np.array_equal(data["key"], self.key)
            ):
                data = None
            self._data = data
            self._loaded = True
        return self._data

    @property
    def span(self) -> float | None:
        """The elapsed time covered by the stored data (`None` if no matching data)."""
        data = self.data
        return None if data is None else float(data["spacing"]) * (data["qp"].shape[0] - 1)

    @property
    def verified_error(self) -> float | None:
        """The max-norm error of the stored flow measured by the generator, if stored data."""
        data = self.data
        return None if data is None else float(data["verified_error"])

    def __call__(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tau = np.asarray(tau, dtype=np.float64)
        if not np.all(np.isfinite(tau)):
            raise ValueError("reference times must be finite")
        span = self.span
        if span is None:
            return self._fallback(tau, "no stored data matches its parameters and initial data")
        inside = (tau >= 0) & (tau <= span)
        out = np.empty((tau.shape[0], self.y0.shape[0]), dtype=np.float64)
        if np.any(inside):
            out[inside] = self._interpolate(tau[inside])
        if not np.all(inside):
            q, p = self._fallback(
                tau[~inside], f"times outside the stored span [0, {span}] (relative to t0)"
            )
            out[~inside, : 2 * self.dim] = np.concatenate([q, p], axis=1)
        return out[:, : self.dim], out[:, self.dim : 2 * self.dim]

    def _interpolate(self, tau: np.ndarray) -> np.ndarray:
        data = self.data
        spacing = float(data["spacing"])
        checkpoints = data["qp"]
        index = np.clip(np.rint(tau / spacing).astype(np.int64), 0, checkpoints.shape[0] - 1)
        hop = tau - index * spacing
        return gbs_integrate(self.rhs, checkpoints[index], hop, int(data["hop_steps"]))

    def _fallback(self, tau: np.ndarray, why: str) -> tuple[np.ndarray, np.ndarray]:
        try:
            return self.fallback(tau)
        except ImportError as e:
            raise ImportError(
                f"the reference of {self.name!r} is stored only for its default problem over its "
                f"default span; the request needs a DOP853 solve ({why}), which needs scipy "
                "(e.g. `pip install diffrax_vi[test]`)"
            ) from e


def checkpoint_count(span: float, spacing: float) -> int:
    """The number of spacings in a span (an error if `spacing` does not divide it)."""
    ratio = span / spacing
    n = round(ratio)
    if n < 1 or not math.isclose(ratio, n, rel_tol=1e-12):
        raise ValueError(f"spacing {spacing} does not divide the span {span}")
    return n
