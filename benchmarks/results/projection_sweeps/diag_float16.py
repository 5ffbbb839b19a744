"""Two diagnostics of the projected step's quick stability sweep (issue 27).

1. float16, oscillator, GELU 10, GL8, 10 steps of 0.1: the error of each step end and the
   total Newton iterations, with the default `RoundoffNewton()` (ftol = 64 eps), a tight
   `RoundoffNewton(ftol=1, floor=64)`, and a smaller span cut-off `VariableProjection(rtol=1e-6)`.
2. float64, pendulum (IODE), tanh, 10 steps of 0.1: the final error against width S and nodes R.

Run: taskset -c 1 .venv/bin/python benchmarks/results/projection_sweeps/diag_float16.py
"""

import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import diffrax_vi as dvi  # noqa: E402
from diffrax_vi import problems  # noqa: E402
from diffrax_vi.bench.harness import relative_error  # noqa: E402
from diffrax_vi.bench.stability import StabilityCase, run_case  # noqa: E402


def run(dtype, formulation, root_finder, dt=0.1, steps=10):
    prob = problems.harmonic_oscillator(dtype=np.dtype(dtype))
    solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.gelu, 10), dvi.GaussLegendre(8),
                           formulation=formulation, root_finder=root_finder)
    ts = prob.t0 + dt * np.arange(steps + 1)
    tsd = jnp.asarray(ts, np.dtype(dtype))
    sol = diffrax.diffeqsolve(
        prob.term, solver, tsd[0], tsd[-1], None, prob.y0, args=prob.args,
        saveat=diffrax.SaveAt(t0=True, steps=True, solver_state=True),
        stepsize_controller=diffrax.StepTo(tsd), max_steps=steps, throw=False)
    q = np.asarray(sol.ys[0], np.float64)
    q_ref = prob.reference(ts)[0]
    errs = [relative_error(q[k], q_ref[k]) for k in range(1, steps + 1)]
    ok = sol.result == diffrax.RESULTS.successful
    return ("ok" if ok else "failed"), int(sol.solver_state.iterations), errs


start = time.perf_counter()
tight = dvi.RoundoffNewton(ftol=1.0, floor=64.0)
for label, form, rf in [
    ("default", dvi.VariableProjection(), dvi.RoundoffNewton()),
    ("ftol=1 floor=64", dvi.VariableProjection(), tight),
    ("rtol=1e-6", dvi.VariableProjection(rtol=1e-6), dvi.RoundoffNewton()),
    ("rtol=1e-6 ftol=1 floor=64", dvi.VariableProjection(rtol=1e-6), tight),
]:
    status, its, errs = run("float16", form, rf)
    print(f"HO float16 gelu10 GL8 dt=0.1 [{label}]: {status}, total iterations {its}, "
          "error per step end " + " ".join(f"{e:.2g}" for e in errs), flush=True)
for width, nodes in [(8, 8), (10, 8), (12, 8), (8, 16), (10, 16)]:
    row = run_case(StabilityCase("pendulum", 0.1, "float64", nodes, width, "tanh",
                                 "projection"))
    print(f"pendulum float64 tanh S{width} R{nodes} dt=0.1: {row['status']}, "
          f"ref_err {row.get('ref_err', float('nan')):.3g}, last-step iterations "
          f"{row['iterations']}", flush=True)
print(f"{time.perf_counter() - start:.0f} s")
