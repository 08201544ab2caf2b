"""Test set-up: float64 by default, rank promotion raises (catches silent broadcasting)."""

import os

import jax

os.environ["DIFFCLOTH_CACHE"] = "off"  # CLI calls in tests leave the user's compilation cache alone

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
