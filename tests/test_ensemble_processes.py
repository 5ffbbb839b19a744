"""One ensemble sharded over the devices of two JAX processes (`jax.distributed`, CPU
collectives through gloo) gives exactly the members of one process with as many devices.

The processes are this file run as a script: `python test_ensemble_processes.py ID COUNT PORT
DEVICES SOLVER OUT` joins a run of COUNT processes whose coordinator listens on PORT, with
DEVICES CPU devices of its own, solves the ensemble with SOLVER (`tsit5`: the Lagrangian term
through its Legendre transform, cheap to compile; `networkvi`) and saves the gathered members
to OUT."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import numpy as np
import pytest

MEMBERS = 5  # not a multiple of the device count: the padding is exercised too


def _solve_ensemble(solver_name: str):
    import diffrax
    import jax.numpy as jnp

    import diffrax_vi as dvi

    # L = v²/2 − k q²/2: the initial position and the stiffness k vary over the members
    term = dvi.LagrangianTerm(lambda t, q, v, k: 0.5 * v @ v - 0.5 * k * q @ q)
    if solver_name == "networkvi":
        solver = dvi.NetworkVI(dvi.ShallowNetBasis(dvi.tanh, 4), dvi.GaussLegendre(4))
    else:
        solver = diffrax.Tsit5()
    q0 = jnp.linspace(0.1, 1.0, MEMBERS)[:, None]
    k = jnp.linspace(0.5, 2.0, MEMBERS)

    def solve_one(q, k):
        sol = diffrax.diffeqsolve(term, solver, 0.0, 0.5, 0.1, (q, jnp.zeros_like(q)), args=k,
                                  throw=False)
        return sol.ys, sol.result == diffrax.RESULTS.successful

    return dvi.ensemble_gather(dvi.ensemble(solve_one, q0, k, mesh=dvi.ensemble_mesh()))


def _process(process_id: int, count: int, port: int, devices: int, solver: str,
             out: str) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_num_cpu_devices", devices)
    if count > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}",
                                   num_processes=count, process_id=process_id)
    assert jax.process_count() == count and jax.device_count() == 2
    (q, p), ok = _solve_ensemble(solver)
    np.savez(out, q=q, p=p, ok=ok)
    if count > 1:
        jax.distributed.shutdown()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    "solver", ["tsit5", pytest.param("networkvi", marks=pytest.mark.long)])
def test_two_processes_give_the_members_of_one(solver, tmp_path):
    port = _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)

    def start(process_id, count, devices, name):
        args = [sys.executable, __file__, str(process_id), str(count), str(port), str(devices),
                solver, str(tmp_path / name)]
        return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True)

    # two processes of one device each, and one process of two devices, side by side
    procs = [start(0, 2, 1, "rank0.npz"), start(1, 2, 1, "rank1.npz"),
             start(0, 1, 2, "single.npz")]
    for proc in procs:
        output, _ = proc.communicate(timeout=240)
        assert proc.returncode == 0, output[-3000:]
    single = np.load(tmp_path / "single.npz")
    assert single["q"].shape[0] == MEMBERS and single["ok"].all()
    for rank in ("rank0.npz", "rank1.npz"):  # every process holds every member, bit for bit
        got = np.load(tmp_path / rank)
        for key in ("q", "p", "ok"):
            np.testing.assert_array_equal(got[key], single[key])
    # and the members differ from each other: the comparison is not vacuous
    assert not np.allclose(single["q"][0], single["q"][-1])


if __name__ == "__main__":
    _process(*(int(a) for a in sys.argv[1:5]), *sys.argv[5:7])
