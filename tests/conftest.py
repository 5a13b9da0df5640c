"""Test configuration: float64 (references are compared to 1e-6 and tighter) and
strict rank promotion, so accidental broadcasting fails loudly."""

import jax

import selfid_jax  # noqa: F401  (sets the CPU XLA flags before JAX initialises)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
