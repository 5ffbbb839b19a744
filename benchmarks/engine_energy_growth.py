"""Energy error growth of `CGVI(7)` on the oscillator (h = 0.5) over many steps, with the
Jacobian-free engine (`FixedPointIteration(ftol=0, predict=True, picard=True)`) and with the
chord iteration (`picard=False`, the default): largest relative energy error, that after
2·10⁴ steps, and the growth exponent of its running maximum over the last two decades
(Brouwer's law: 0.5).

With several `--h`, each step size in turn: the exponent of one run depends on how the
rounding falls at that step (measured 2026-11-29: from 0.2 to 1.0 over h in 0.4..0.53).

`--random-walks N` first prints the same exponent for `N` random walks of as many steps
(unit Gaussian increments): how far one run's exponent scatters where the growth is a
random walk's.

    .venv/bin/python -m benchmarks.engine_energy_growth [--steps 1000000] [--h 0.5 0.47 ...]
        [--random-walks 60]
"""

from __future__ import annotations

import argparse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--h", type=float, nargs="+", default=[0.5])
    parser.add_argument("--random-walks", type=int, default=0)
    args = parser.parse_args()
    import diffrax
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import diffrax_vi as dvi
    from diffrax_vi import problems
    from diffrax_vi.bench import growth_exponent

    problem = problems.harmonic_oscillator()
    n = args.steps
    if args.random_walks:
        rng = np.random.default_rng(0)
        steps = np.arange(1, n + 1, dtype=np.float64)
        found = np.array([
            growth_exponent(steps, np.maximum.accumulate(np.abs(np.cumsum(rng.standard_normal(n)))))
            for _ in range(args.random_walks)
        ])
        print(f"{args.random_walks} random walks of {n} steps: exponent mean {found.mean():.2f}, "
              f"standard deviation {found.std():.2f}, from {found.min():.2f} to "
              f"{found.max():.2f}; above 0.6 in {np.mean(found > 0.6):.0%}", flush=True)
    e0 = float(problem.energy(0.0, *problem.y0))
    for h, picard in ((h, picard) for h in args.h for picard in (True, False)):
        solver = dvi.CGVI(7, root_finder=dvi.FixedPointIteration(ftol=0.0, predict=True,
                                                                   picard=picard))
        sol = diffrax.diffeqsolve(problem.term, solver, 0.0, n * h, h, problem.y0,
                                  args=problem.args, max_steps=n,
                                  saveat=diffrax.SaveAt(steps=True))
        energy = jax.vmap(lambda q, p: problem.energy(0.0, q, p))(sol.ys[0], sol.ys[1])
        error = np.abs(np.asarray(energy) - e0) / abs(e0)
        envelope = np.maximum.accumulate(error)
        at = min(20_000, n) - 1
        print(f"h={h} picard={picard!s:5s} steps={n}: max {error.max():.2e}, after {at + 1} steps "
              f"{envelope[at]:.2e}, growth exponent "
              f"{growth_exponent(np.asarray(sol.ts), envelope)}", flush=True)


if __name__ == "__main__":
    main()
