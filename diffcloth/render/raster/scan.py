"""Log-depth prefix scans and stream compaction used by the rasterizer's allocation passes."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _cumsum(x):
    # jnp.cumsum / lax.cummax lower to reduce_window on CPU, ~10x slower than a log-depth scan
    return jax.lax.associative_scan(jnp.add, x)


def _cummax(x):
    return jax.lax.associative_scan(jnp.maximum, x)


def _compact(flags, size: int):
    """Indices of the first `size` True entries of a 1-D bool array (padded with 0) and a
    (size,) bool telling which are real."""
    n = flags.shape[0]
    rank = _cumsum(flags.astype(jnp.int32)) - 1
    idx = (
        jnp.zeros((size,), jnp.int32)
        .at[jnp.where(flags, rank, size)]
        .set(jnp.arange(n, dtype=jnp.int32), mode="drop")
    )
    return idx, jnp.arange(size) <= rank[-1]


def _batch_max(x, batch_axes: tuple):
    """x's maximum over the named vmap axes `batch_axes` (x itself when there are none).

    A work-budget index reduced so is the same for every image of a batch: `lax.switch` on it
    then stays one conditional that runs one branch (the one the batch's largest image needs),
    where a batched index would run every branch and select. Shapes: x () int."""
    return jax.lax.pmax(x, tuple(batch_axes)) if batch_axes else x
