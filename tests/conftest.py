import jax

# The library never flips x64 on import; the tests (like the examples) ask for float64.
jax.config.update("jax_enable_x64", True)
