"""Strict JAX in tests: float64 on, rank promotion raises (catches (n,) vs (n, 1) bugs)."""
import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
