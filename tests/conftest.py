import jax

# The library never flips x64 on import; the tests (like the examples) ask for float64.
jax.config.update("jax_enable_x64", True)


import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code():
    """Drop jit caches after each test module: one process compiles hundreds of solves, and
    keeping every executable alive exhausted LLVM's memory (a segfault while compiling)."""
    yield
    jax.clear_caches()
    gc.collect()
