"""Regenerate the stored reference solutions `problems/data/*.npz`.

Run `python -m diffrax_vi.problems.data.generate` (a few minutes; needs scipy only for the
DOP853 cross-check). For each problem below the default float64 problem is integrated in
extended precision (`np.longdouble`, 64-bit mantissa on x86) with Gragg–Bulirsch–Stoer steps of
order 16, checkpoints `(q, p)` are saved every `spacing` time units and rounded to float64. A
time-dependent problem is integrated as the autonomous system of `(q, p, t)` (see
`problems.stored`); its checkpoints carry the time as a last column.

Recorded in each file next to the data (errors in the max norm over `q` and `p`):

- `verified_error`: max-norm error of the shipped `StoredFlow` (float64 checkpoints plus a
  float64 GBS hop) at 400 random times of the span, measured against extended-precision hops
  from the extended-precision checkpoints (the number quoted in the problems' docstrings);
- `self_check`: max-norm difference at the checkpoints between the extended-precision solution
  and a second one with twice as many steps (the truncation error of the data itself);
- `dop853_difference`: max-norm difference at the checkpoints to scipy's DOP853 at
  `rtol = 2.3e-14`, `atol = 1e-16` (an independent float64 cross-check, limited by float64).
"""

from __future__ import annotations

import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from diffrax_vi.problems import (  # noqa: E402
    charged_particle,
    coupled_oscillators,
    double_pendulum,
    fermi_pasta_ulam,
    henon_heiles,
    modulated_oscillator,
    outer_solar_system,
    pendulum,
    perturbed_pendulum,
    toda_lattice,
)
from diffrax_vi.problems.stored import checkpoint_count, gbs_integrate  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent

# name: (factory, checkpoint spacing, GBS steps per hop at run time, extended-precision steps
# per spacing)
SETTINGS = {
    "henon_heiles": (henon_heiles, 0.25, 1, 8),
    "perturbed_pendulum": (perturbed_pendulum, 0.25, 1, 8),
    "toda_lattice": (toda_lattice, 0.5, 1, 8),
    "outer_solar_system": (outer_solar_system, 2.0, 1, 4),
    "pendulum": (pendulum, 0.25, 1, 8),
    "double_pendulum": (double_pendulum, 0.0625, 1, 4),
    "coupled_oscillators": (coupled_oscillators, 0.25, 1, 8),
    # time-dependent: the flow's state is (q, p, t), so the checkpoints carry their time
    "modulated_oscillator": (modulated_oscillator, 0.25, 1, 8),
    "charged_particle": (charged_particle, 0.0625, 1, 4),  # gyration period ≈ 0.79
    "fermi_pasta_ulam": (fermi_pasta_ulam, 0.125, 4, 32),  # stiff period 2π/50 ≈ 0.126
}


def _march(rhs, y0: np.ndarray, spacing: float, count: int, steps: int) -> np.ndarray:
    y = y0.astype(np.longdouble)[None, :]
    out = [y[0]]
    tau = np.full(1, spacing, dtype=np.longdouble)
    for _ in range(count):
        y = gbs_integrate(rhs, y, tau, steps)
        out.append(y[0])
    return np.array(out)


def generate(name: str, seed: int = 0) -> dict[str, float]:
    factory, spacing, hop_steps, steps = SETTINGS[name]
    problem = factory(dtype=np.float64)
    flow = problem.reference_flow
    span = problem.t1 - problem.t0
    count = checkpoint_count(span, spacing)
    start = time.perf_counter()
    fine = _march(flow.rhs, flow.y0, spacing, count, steps)
    finer = _march(flow.rhs, flow.y0, spacing, count, 2 * steps)
    qp = slice(0, 2 * flow.dim)  # the errors are measured on (q, p), not on an appended time
    self_check = float(np.max(np.abs(fine - finer)[:, qp]))

    # the shipped flow against extended-precision hops from extended-precision checkpoints
    rng = np.random.default_rng(seed)
    tau = np.sort(rng.uniform(0.0, span, 400))
    index = np.clip(np.rint(tau / spacing).astype(np.int64), 0, count)
    hop = (tau - index * spacing).astype(np.longdouble)
    exact = gbs_integrate(flow.rhs, finer[index], hop, 4)
    checkpoints = finer.astype(np.float64)
    shipped = gbs_integrate(flow.rhs, checkpoints[index], tau - index * spacing, hop_steps)
    verified_error = float(np.max(np.abs(shipped - exact)[:, qp]))

    dop853 = float("nan")
    try:
        from scipy.integrate import solve_ivp

        grid = spacing * np.arange(count + 1)
        sol = solve_ivp(
            lambda _, y: flow.rhs(y),
            (0.0, grid[-1]),
            flow.y0,
            method="DOP853",
            t_eval=grid,
            rtol=2.3e-14,
            atol=1e-16,
        )
        dop853 = float(np.max(np.abs(sol.y.T - finer)[:, qp]))
    except ImportError:  # pragma: no cover
        pass

    np.savez_compressed(
        HERE / f"{name}.npz",
        qp=checkpoints,
        spacing=np.float64(spacing),
        hop_steps=np.int64(hop_steps),
        y0=flow.y0,
        key=flow.key,
        verified_error=np.float64(verified_error),
        self_check=np.float64(self_check),
        dop853_difference=np.float64(dop853),
    )
    return {
        "scale": float(np.max(np.abs(checkpoints[:, qp]))),
        "verified_error": verified_error,
        "self_check": self_check,
        "dop853_difference": dop853,
        "seconds": time.perf_counter() - start,
        "bytes": (HERE / f"{name}.npz").stat().st_size,
    }


def main(names: list[str]) -> None:
    for name in names or list(SETTINGS):
        print(name, generate(name), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
