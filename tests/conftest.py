"""Test set-up: float64 by default, rank promotion raises (catches silent broadcasting)."""

import os

import jax

os.environ["DIFFCLOTH_CACHE"] = "off"  # CLI calls in tests leave the user's compilation cache alone
# XLA's small-loop option (diffcloth.runtime.tune_xla_cpu) speeds up runs but lengthens float64
# compiles by about a fifth, and this suite is compile-bound: off here unless asked for
# (`DIFFCLOTH_XLA_TUNING=on pytest`; the whole suite passes with it on). test_runtime checks, in
# fresh processes, that `import diffcloth` sets it and that XLA then compiles small loops as one.
os.environ.setdefault("DIFFCLOTH_XLA_TUNING", "off")

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
