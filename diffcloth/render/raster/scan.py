"""Log-depth prefix scans and stream compaction used by the rasterizer's allocation passes."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth._math import materialize


def _cumsum(x):
    """Inclusive prefix sum of a 1-D int array (log-depth scan). The input is materialized:
    each level of the scan reads it, and fused the producer (e.g. the window counts from the
    bounding boxes) was recomputed in five of them."""
    # jnp.cumsum / lax.cummax lower to reduce_window on CPU, ~10x slower than a log-depth scan
    return jax.lax.associative_scan(jnp.add, materialize(x))


def _cummax(x):
    """Inclusive prefix maximum of a 1-D int array (log-depth scan, input materialized)."""
    return jax.lax.associative_scan(jnp.maximum, materialize(x))


def _compact(flags, size: int):
    """Indices of the first `size` True entries of a 1-D bool array (padded with 0) and a
    (size,) bool telling which are real.

    The ranks come from the flags packed 32 to a uint32 word: a prefix sum over the words'
    population counts plus the count of the lower bits set in the entry's own word (a prefix
    sum over every entry took 2.4x longer at 131,072 flags).
    """
    n = flags.shape[0]
    rank, total = _ranks(flags, with_total=True)
    idx = (
        jnp.zeros((size,), jnp.int32)
        .at[jnp.where(flags, rank, size)]
        .set(jnp.arange(n, dtype=jnp.int32), mode="drop")
    )
    return idx, jnp.arange(size) < total


def _ranks(flags, with_total: bool = False):
    """(n,) int32 rank of each entry of a 1-D bool array among its True entries (how many come
    before it), from the flags packed 32 to a uint32 word (`_compact`); with with_total, also
    () the number of True entries."""
    n = flags.shape[0]
    nw = -(-n // 32)
    bits = jnp.pad(flags, (0, nw * 32 - n)).reshape(nw, 32).astype(jnp.uint32)
    bit = jnp.left_shift(jnp.uint32(1), jnp.arange(32, dtype=jnp.uint32))
    words = jnp.sum(bits * bit[None], axis=1, dtype=jnp.uint32)  # distinct bits: the sum is the OR
    count = jax.lax.population_count(words).astype(jnp.int32)
    upto = _cumsum(count)  # entries set in the words up to and including this one
    below = jax.lax.population_count(words[:, None] & (bit - 1)[None, :]).astype(jnp.int32)
    rank = ((upto - count)[:, None] + below).reshape(-1)[:n]
    return (rank, upto[-1]) if with_total else rank


def _batch_max(x, batch_axes: tuple):
    """x's maximum over the named vmap axes `batch_axes` (x itself when there are none).

    A work-budget index reduced so is the same for every image of a batch: `lax.switch` on it
    then stays one conditional that runs one branch (the one the batch's largest image needs),
    where a batched index would run every branch and select. Shapes: x () int."""
    return jax.lax.pmax(x, tuple(batch_axes)) if batch_axes else x
