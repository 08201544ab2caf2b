"""Test set-up: float64 by default, rank promotion raises (catches silent broadcasting)."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
