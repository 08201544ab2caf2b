"""Mesh topology for the silhouette search: the triangle across each edge."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def edge_neighbors(faces):
    """(m, 3) int32: the triangle across edge k (opposite vertex k) of each triangle, -1 if none.

    Runs in numpy when `faces` is concrete (precompute it once per mesh and pass it as
    `neighbors=`), in jnp (a sort) when traced.
    """
    if isinstance(faces, jax.core.Tracer):
        return _edge_neighbors_jnp(faces)
    f = np.asarray(faces, np.int64)
    m = f.shape[0]
    a = np.stack([f[:, 1], f[:, 2], f[:, 0]], axis=1).reshape(-1)
    b = np.stack([f[:, 2], f[:, 0], f[:, 1]], axis=1).reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((hi, lo))
    same = (lo[order][1:] == lo[order][:-1]) & (hi[order][1:] == hi[order][:-1])
    nbr = np.full(3 * m, -1, np.int64)
    k = np.nonzero(same)[0]
    nbr[order[k]] = order[k + 1] // 3
    nbr[order[k + 1]] = order[k] // 3
    return jnp.asarray(nbr.reshape(m, 3), jnp.int32)


def _edge_neighbors_jnp(faces):
    f = faces.astype(jnp.int32)
    m = f.shape[0]
    a = jnp.stack([f[:, 1], f[:, 2], f[:, 0]], axis=1).reshape(-1)
    b = jnp.stack([f[:, 2], f[:, 0], f[:, 1]], axis=1).reshape(-1)
    lo, hi = jnp.minimum(a, b), jnp.maximum(a, b)
    order = jnp.lexsort((hi, lo))
    slo, shi = lo[order], hi[order]
    same = (slo[1:] == slo[:-1]) & (shi[1:] == shi[:-1])
    nbr = jnp.full(3 * m, -1, jnp.int32)
    nxt = jnp.where(same, order[1:] // 3, -1).astype(jnp.int32)
    prv = jnp.where(same, order[:-1] // 3, -1).astype(jnp.int32)
    nbr = nbr.at[order[:-1]].max(nxt)
    nbr = nbr.at[order[1:]].max(prv)
    return nbr.reshape(m, 3)
