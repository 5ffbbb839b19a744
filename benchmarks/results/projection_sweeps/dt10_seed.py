"""The stability sweep's dt = 10 cells with ever more accurate restart seeds (issue 27).

The pendulum (IODE, width 8, GL8) and the double pendulum (width 10, GL16), 10 steps of 10, the
default projected step, with `initial_trajectory=IntegratorExtrapolation(substeps=N)`: the
trajectory seed the step restarts from, for N = 10 (the default), 100 and 400 sub-steps.
Columns: problem, activation, N, success, steps taken, max relative error of q if successful.

    taskset -c 1 .venv/bin/python benchmarks/results/projection_sweeps/dt10_seed.py
"""
import jax
jax.config.update("jax_enable_x64", True)
import diffrax, jax.numpy as jnp, numpy as np
import diffrax_vi as dvi
from diffrax_vi import problems
from diffrax_vi.bench.stability import QUICK_WIDTH, QUICK_NODES
for pname in ("pendulum", "double_pendulum"):
    prob = getattr(problems, pname)()
    for act in (dvi.tanh, dvi.gelu):
        for sub in (10, 100, 400):
            solver = dvi.NetworkVI(dvi.ShallowNetBasis(act, QUICK_WIDTH[pname]), dvi.GaussLegendre(QUICK_NODES[pname]),
                                   initial_trajectory=dvi.IntegratorExtrapolation(substeps=sub))
            sol = diffrax.diffeqsolve(prob.term, solver, 0.0, 100.0, 10.0, prob.y0, args=prob.args, throw=False,
                                      saveat=diffrax.SaveAt(ts=jnp.arange(0.0, 101.0, 10.0), solver_state=True))
            ok = sol.result == diffrax.RESULTS.successful
            err = None
            if ok:
                qr, _ = prob.reference(np.asarray(sol.ts))
                err = float(np.max(np.abs(np.asarray(sol.ys[0]) - qr)) / np.max(np.abs(qr)))
            print(pname, act.__name__ if hasattr(act,'__name__') else act, sub, ok, int(sol.stats["num_steps"]), err, flush=True)
