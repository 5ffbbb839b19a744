"""`dvi.ensemble`: batched solves over initial conditions and parameters, on one device and
sharded over 8 virtual CPU devices (in a subprocess, since the device count is fixed when JAX
starts)."""

import importlib
import os
import subprocess
import sys
import textwrap

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffrax_vi as dvi

TERM = dvi.LagrangianTerm(lambda t, q, v, k: 0.5 * v @ v - 0.5 * k * q @ q)
# The helper does not care which solver runs; the polynomial cGVI compiles fastest. (Batched
# network solves are checked in tests/test_solver.py.)
SOLVER = dvi.CGVI(3)


def solve_one(y0, k):
    sol = diffrax.diffeqsolve(
        TERM, SOLVER, 0.0, 0.3, 0.1, y0, args=k, saveat=diffrax.SaveAt(t1=True), throw=False
    )
    return sol.ys, sol.result == diffrax.RESULTS.successful


def initial_conditions(n):
    q = jnp.linspace(0.2, 0.8, n)[:, None]
    return q, jnp.zeros_like(q)


@pytest.mark.parametrize("batch_size", [
    None, 1,
    pytest.param(2, marks=pytest.mark.slow),  # the compiled loop over chunks: batch_size=1
])
def test_ensemble_matches_single_solves(batch_size):
    """Every way of sharing the device (full vmap, a compiled loop over members or over
    chunks of 2, which leaves a remainder of 1) gives each member its single solve."""
    y0 = initial_conditions(3)
    k = jnp.array([0.5, 1.0, 2.0])
    (q, p), result = dvi.ensemble(solve_one, y0, k, batch_size=batch_size)
    assert q.shape == (3, 1, 1) and p.shape == (3, 1, 1)
    assert np.all(np.asarray(result))
    for i in range(3):
        (qi, pi), ri = jax.jit(solve_one)((y0[0][i], y0[1][i]), k[i])
        assert ri
        np.testing.assert_allclose(q[i], qi, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(p[i], pi, rtol=1e-13, atol=1e-15)
    # the amplitude scales the solution (linear problem), so members really differ
    expected = 4.0 * np.cos(np.sqrt(2.0) * 0.3) / np.cos(np.sqrt(0.5) * 0.3)
    np.testing.assert_allclose(q[2, 0, 0] / q[0, 0, 0], expected, rtol=1e-6)


def test_bad_input_is_refused():
    y0 = initial_conditions(3)
    with pytest.raises(ValueError, match="ensemble size"):
        dvi.ensemble(solve_one, y0, jnp.ones(2))
    with pytest.raises(ValueError, match="in_axes has"):
        dvi.ensemble(solve_one, y0, jnp.ones(3), in_axes=(0,))
    with pytest.raises(ValueError, match="scalar"):
        dvi.ensemble(solve_one, y0, jnp.asarray(1.0))
    with pytest.raises(ValueError, match="mapped argument"):
        dvi.ensemble(solve_one, y0, jnp.ones(3), in_axes=None)
    with pytest.raises(ValueError, match="one-axis"):
        dvi.ensemble(solve_one, y0, jnp.ones(3), mesh="cpu")
    with pytest.raises(TypeError, match="callable"):
        dvi.ensemble(3, y0)
    for bad in (0, -2, 1.5, True, "all", "auto"):
        with pytest.raises(ValueError, match="batch_size"):
            dvi.ensemble(solve_one, y0, jnp.ones(3), batch_size=bad)


def test_cpu_compiler_options_fall_back_where_xla_lacks_them(monkeypatch):
    module = importlib.import_module("diffrax_vi._ensemble")

    # this jaxlib knows the option, so CPU ensembles compile with it
    if jax.default_backend() == "cpu":
        assert dict(module.cpu_compiler_options()) == module._CPU_OPTIONS
    # an XLA without it: no options, and the ensemble still runs
    monkeypatch.setattr(module, "_CPU_OPTIONS", {"xla_cpu_no_such_option": "1"})
    module.cpu_compiler_options.cache_clear()
    module._compiled.cache_clear()
    try:
        assert module.cpu_compiler_options() == ()
        (q, _), result = dvi.ensemble(solve_one, initial_conditions(2), jnp.ones(2))
        assert np.all(np.asarray(result)) and np.all(np.isfinite(np.asarray(q)))
    finally:
        module.cpu_compiler_options.cache_clear()
        module._compiled.cache_clear()


SHARDED = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np
    import diffrax_vi as dvi
    from tests.test_ensemble import initial_conditions, solve_one

    assert jax.device_count() == 8, jax.devices()
    y0 = initial_conditions(13)          # not a multiple of 8: padded, then trimmed
    k = jnp.asarray(1.0)                 # shared by all members (replicated on every device)
    mesh = dvi.ensemble_mesh()
    (q, p), result = dvi.ensemble(solve_one, y0, k, in_axes=(0, None), mesh=mesh)
    (q1, p1), result1 = dvi.ensemble(solve_one, y0, k, in_axes=(0, None))
    assert q.shape == q1.shape == (13, 1, 1), q.shape
    assert np.all(np.asarray(result)) and np.all(np.asarray(result1))
    # the sharded run used all 8 devices
    (qs, _), _ = dvi.ensemble(solve_one, initial_conditions(16), k, in_axes=(0, None), mesh=mesh)
    assert len(qs.sharding.device_set) == 8, qs.sharding
    np.testing.assert_allclose(q[:, 0, 0], y0[0][:, 0] * np.cos(0.3), rtol=1e-6)  # q0 cos t
    dq = float(np.max(np.abs(np.asarray(q) - np.asarray(q1))))
    dp = float(np.max(np.abs(np.asarray(p) - np.asarray(p1))))
    print("max difference sharded - unsharded:", dq, dp)
    # vmap over 2 members per device vs 16 on one: same code, rounding may differ in the last bit
    assert dq <= 1e-13 and dp <= 1e-13
    # each device's slice vmapped at once, or solved member by member
    for batch_size in (None, 1):
        (qb, _), rb = dvi.ensemble(
            solve_one, y0, k, in_axes=(0, None), mesh=mesh, batch_size=batch_size
        )
        assert np.all(np.asarray(rb))
        assert float(np.max(np.abs(np.asarray(qb) - np.asarray(q1)))) <= 1e-13
    """
)


@pytest.mark.long
def test_sharded_over_8_devices_matches_unsharded():
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run(
        [sys.executable, "-c", SHARDED],
        env=env,
        cwd=root,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "max difference" in proc.stdout
