"""Strict JAX in tests: float64 on; rank promotion raises (catches (n,) vs (n, 1) bugs); dtype promotion
is strict (an implicit int/bool/float mix, or float32 with float64, is an error)."""
import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")
