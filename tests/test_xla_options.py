"""`compile_loops_whole`: XLA's whole-loop compilation as an explicit opt-in.

XLA reads `XLA_FLAGS` once per process, when JAX starts its backend, so each behaviour is run
in a fresh interpreter; the text of the flags is also checked here, where it costs nothing.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffrax_vi import _xla_options
from diffrax_vi._xla_options import threshold_in, with_threshold

jax.config.update("jax_enable_x64", True)

MODULE = Path(_xla_options.__file__)
OPTION = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000"

# A loop whose one pass touches a few kilobytes: above XLA's own threshold, below the opt-in's.
LOOP = textwrap.dedent(
    """
    import jax, jax.numpy as jnp

    def loop(x):
        def body(carry):
            i, x = carry
            return i + 1, 0.5 * jnp.sin(x) + 0.25 * jnp.cos(x) + 0.1 * x
        return jax.lax.while_loop(lambda c: c[0] < 50, body, (0, x))[1]
    """
)
# The module alone, without the package's import time (it needs nothing of the package).
ALONE = textwrap.dedent(
    f"""
    import importlib.util
    spec = importlib.util.spec_from_file_location("xla_options", {str(MODULE)!r})
    dvi = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(dvi)
    """
)


def _run(code: str, xla_flags: str | None = None) -> dict:
    """Runs `code` in a fresh interpreter; its last printed line is a JSON object."""
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _loop_here(x):
    namespace = {}
    exec(LOOP, namespace)
    return np.asarray(jax.jit(namespace["loop"])(jnp.asarray(x)))


def test_opt_in_from_a_fresh_process():
    got = _run(
        LOOP
        + """
import json, os
import numpy as np
import diffrax_vi as dvi

before = dvi.loops_compiled_whole()
dvi.compile_loops_whole()
jax.config.update("jax_enable_x64", True)
y = jax.jit(loop)(jnp.linspace(0.0, 1.0, 512))
dvi.compile_loops_whole()  # again, with the same threshold: nothing to change, no error
print(json.dumps({"flags": os.environ["XLA_FLAGS"], "before": before,
                  "after": dvi.loops_compiled_whole(), "y": np.asarray(y).tolist()}))
"""
    )
    assert got["flags"] == OPTION
    assert got["before"] is False and got["after"] is True
    # Compiled whole, XLA may order the arithmetic differently: equal to rounding.
    expected = _loop_here(np.linspace(0.0, 1.0, 512))
    np.testing.assert_allclose(got["y"], expected, rtol=1e-14, atol=1e-15)


def test_after_a_computation_it_raises_and_says_what_to_do():
    got = _run(
        ALONE
        + """
import json, os
import jax.numpy as jnp

(jnp.ones(2) + 1).block_until_ready()
try:
    dvi.compile_loops_whole()
except RuntimeError as error:
    message = str(error)
else:
    message = None
print(json.dumps({"message": message, "flags": os.environ.get("XLA_FLAGS")}))
"""
    )
    message = got["message"]
    assert message is not None, "no error after the backend had started"
    assert "before the first JAX computation" in message
    assert f'XLA_FLAGS="{OPTION}"' in message
    assert got["flags"] is None  # the environment is left as it was


def test_merges_with_existing_flags():
    existing = (
        "--xla_force_host_platform_device_count=2 "
        "--xla_backend_extra_options=xla_llvm_disable_expensive_passes,"
        "xla_cpu_small_while_loop_byte_threshold=2048"
    )
    got = _run(
        LOOP
        + ALONE
        + """
import json, os

dvi.compile_loops_whole(5_000_000)
y = jax.jit(loop)(jnp.linspace(0.0, 1.0, 512))
print(json.dumps({"flags": os.environ["XLA_FLAGS"], "devices": jax.device_count()}))
""",
        xla_flags=existing,
    )
    assert got["flags"] == (
        "--xla_force_host_platform_device_count=2 "
        "--xla_backend_extra_options=xla_llvm_disable_expensive_passes,"
        "xla_cpu_small_while_loop_byte_threshold=5000000"
    )
    assert got["devices"] == 2  # the other flag still reached XLA


@pytest.mark.parametrize(
    "flags, expected",
    [
        ("", OPTION),
        ("--xla_cpu_enable_fast_math=false", f"--xla_cpu_enable_fast_math=false {OPTION}"),
        (
            '--xla_backend_extra_options="xla_cpu_disable_loop_unrolling"',
            "--xla_backend_extra_options=xla_cpu_disable_loop_unrolling,"
            "xla_cpu_small_while_loop_byte_threshold=100000000",
        ),
        (
            "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=7 --a=1 "
            "--xla_backend_extra_options=xla_llvm_disable_expensive_passes",
            "--a=1 --xla_backend_extra_options=xla_llvm_disable_expensive_passes,"
            "xla_cpu_small_while_loop_byte_threshold=100000000",
        ),
    ],
)
def test_the_flags_text(flags, expected):
    merged = with_threshold(flags, 100_000_000)
    assert merged == expected
    assert threshold_in(merged) == 100_000_000
    assert with_threshold(merged, 100_000_000) == merged


def test_a_threshold_must_be_a_non_negative_integer():
    import diffrax_vi as dvi

    with pytest.raises(TypeError, match="integer"):
        dvi.compile_loops_whole(1.5)
    with pytest.raises(ValueError, match="non-negative"):
        dvi.compile_loops_whole(-1)
