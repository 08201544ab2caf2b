"""Differentiable resolve (raster step 3): barycentrics, depth and silhouette crossings of the
visible triangle per pixel; `rasterize` runs the whole pipeline, `interpolate` reads attributes."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth._math import materialize, materialize_grad, materialize_value, safe_div
from diffcloth.render.camera import Camera
from diffcloth.render.raster.buffers import BACKGROUND_DEPTH, Fragments
from diffcloth.render.raster.silhouette import _crossings, _pairs, default_silhouette_budget
from diffcloth.render.raster.topology import edge_neighbors
from diffcloth.render.raster.triangle_setup import (
    _materialized,
    _Setup,
    _setup,
    default_max_tiles,
)
from diffcloth.render.raster.visibility import _visibility


def _resolve(
    s: _Setup, ids, camera: Camera, neighbors, walk: int, budget: int | None, batch_axes=()
):
    H, W = camera.height, camera.width
    dtype = s.edge.dtype
    ids = ids.reshape(H, W)
    mask = ids >= 0
    tri = jnp.maximum(ids, 0)
    E = s.edge[tri]  # (H, W, 9)
    dv = s.vdepth[tri]  # (H, W, 3)
    o = s.origin[tri]
    Y, X = jnp.meshgrid(jnp.arange(H, dtype=dtype), jnp.arange(W, dtype=dtype), indexing="ij")
    lx, ly = X - o[..., 0], Y - o[..., 1]
    # the edge functions' cotangent is computed once per pixel (materialize_grad): the per-pixel
    # cotangent of the 9 edge coefficients is built from it, and XLA's CPU fusion otherwise
    # re-derives the whole barycentric / depth backward chain for each of the 9
    e3 = materialize_grad(
        jnp.stack(
            [E[..., 3 * k] * lx + E[..., 3 * k + 1] * ly + E[..., 3 * k + 2] for k in range(3)],
            axis=-1,
        )
    )
    e = [e3[..., k] for k in range(3)]
    total = e[0] + e[1] + e[2]
    ok = mask & (jax.lax.stop_gradient(total) > 0)
    inv = safe_div(jnp.ones((), dtype), jnp.where(ok, total, 1.0))
    # materialized before any use: every consumer (the silhouette pairs, interpolate per
    # attribute and channel, antialias's shifted reads, compositing) would otherwise redo the
    # per-pixel gathers and edge functions, e.g. once per output channel of the crossings
    bary = materialize(jnp.stack([jnp.where(ok, ek * inv, 0.0) for ek in e], axis=-1))
    depth = bary[..., 0] * dv[..., 0] + bary[..., 1] * dv[..., 1] + bary[..., 2] * dv[..., 2]
    depth = materialize(jnp.where(ok, depth, BACKGROUND_DEPTH))
    ok = materialize(ok)
    cross, weights = _crossings(
        s, tri, ok, jax.lax.stop_gradient(depth), X, Y, neighbors, walk, budget, batch_axes
    )
    return Fragments(
        triangle_id=materialize(jnp.where(ok, ids, -1).astype(jnp.int32)),
        barycentric=bary,
        depth=depth,
        crossings=materialize(cross.astype(dtype)),
        front_facing=materialize(ok & s.front[tri]),
        weights=weights.astype(dtype),
    )


def rasterize(
    positions,
    faces,
    camera: Camera,
    *,
    neighbors=None,
    cull_backfaces: bool = False,
    triangle_mask=None,
    tile_size: int = 2,
    max_tiles: int | None = None,
    silhouette_walk: int = 8,
    silhouette_budget: int | None = None,
    batch_axes: tuple = (),
) -> Fragments:
    """Visible triangle, perspective-correct barycentrics and depth for every pixel.

    Args:
      positions: (n, 3) world vertex positions in m; differentiable (through barycentrics, depth
        and silhouette crossings).
      faces: (m, 3) int vertex indices, counter-clockwise = front.
      camera: Camera.
      neighbors: (m, 3) from `edge_neighbors(faces)`; computed here if None (numpy when faces is
        concrete, a jnp sort when traced: pass it precomputed inside jit for speed).
      cull_backfaces: drop triangles that are clockwise on screen (cloth is two-sided: default off).
      triangle_mask: optional (m,) bool, False drops a triangle (e.g. frustum-culled objects).
      tile_size, max_tiles: static raster window size and window budget (see module doc).
      silhouette_walk: how many triangles beyond the visible one the silhouette search may cross
        along each neighbour segment (static). Default 8: near a contour seen at a grazing
        angle the triangles are foreshortened to slivers and a 1-pixel segment crosses many
        (walk 1-2 missed most of the drape's contour crossings at 128 x 128, walk 8 finds them).
      silhouette_budget: static size of the compacted list of pixel pairs searched for
        silhouettes (default `default_silhouette_budget`: H W / 16 from 128 x 128 up); when a
        frame needs more, a list of 4 x the budget, then a full-image search runs instead (same
        result, slower; under vmap all run). >= 2 H W: always the full-image search (compiles
        once, not three times).
      batch_axes: names of the `vmap` axes this call runs under (e.g. `pipeline.render_frames`'
        frames and cameras; static). Each work budget (windows, silhouette list) is then the
        smallest that holds every image of the batch (`lax.pmax` over these axes), so one branch
        of each `lax.switch` runs for the batch; unnamed, a batched switch runs every branch.
        Images are the same either way.
    Returns:
      Fragments.
    """
    faces = jnp.asarray(faces).astype(jnp.int32)
    if faces.shape[0] == 0:  # empty scene: background everywhere
        H, W = camera.height, camera.width
        dtype = jnp.result_type(positions)
        return Fragments(
            triangle_id=jnp.full((H, W), -1, jnp.int32),
            barycentric=jnp.zeros((H, W, 3), dtype),
            depth=jnp.full((H, W), BACKGROUND_DEPTH, dtype),
            crossings=jnp.concatenate(
                [jnp.full((H, W, 4), -1.0, dtype), jnp.zeros((H, W, 8), dtype)], axis=-1
            ),
            front_facing=jnp.zeros((H, W), bool),
        )
    if neighbors is None:
        neighbors = edge_neighbors(faces)
    if max_tiles is None:
        max_tiles = default_max_tiles(faces.shape[0], camera.width, camera.height, tile_size)
    s = _materialized(_setup(positions, faces, camera, cull_backfaces, triangle_mask))
    batch_axes = tuple(batch_axes)
    ids = _visibility(s, camera, tile_size, max_tiles, batch_axes)
    if silhouette_budget is None:
        silhouette_budget = default_silhouette_budget(camera.width, camera.height)
    if int(silhouette_budget) < 0:
        raise ValueError(f"silhouette_budget must be >= 0, got {silhouette_budget}")
    return _resolve(s, ids, camera, neighbors, silhouette_walk, silhouette_budget, batch_axes)


def silhouette_pairs(
    positions,
    faces,
    camera: Camera,
    *,
    neighbors=None,
    cull_backfaces: bool = False,
    tile_size: int = 2,
    max_tiles: int | None = None,
    silhouette_walk: int = 8,
):
    """Number of pixel pairs the silhouette search needs (compare with `silhouette_budget`:
    above it, the slower full-image search runs)."""
    faces = jnp.asarray(faces).astype(jnp.int32)
    if neighbors is None:
        neighbors = edge_neighbors(faces)
    if max_tiles is None:
        max_tiles = default_max_tiles(faces.shape[0], camera.width, camera.height, tile_size)
    s = _setup(positions, faces, camera, cull_backfaces)
    ids = _visibility(s, camera, tile_size, max_tiles)
    fr = _resolve(s, ids, camera, neighbors, 0, None)
    tri = jnp.maximum(fr.triangle_id, 0)
    return jnp.sum(_pairs(s, tri, fr.triangle_id >= 0, fr.depth, neighbors, silhouette_walk)[3])


def interpolate(attributes, fragments: Fragments, faces):
    """Interpolate per-vertex attributes (n, C) to pixels: (H, W, C), zero on background.

    Differentiable w.r.t. the attributes and (through the barycentrics) the vertex positions.
    """
    tri = jnp.maximum(fragments.triangle_id, 0)
    faces = jnp.asarray(faces).astype(jnp.int32)
    if faces.shape[0] == 0:
        return jnp.zeros(tri.shape + attributes.shape[1:], attributes.dtype)
    # the attributes of each triangle's corners (m, 3, ...) computed once, then one gather per
    # pixel (a gather of the pixel's vertex ids and one per corner cost four passes)
    corners = materialize_value(attributes[faces])[tri]  # (H, W, 3, ...)
    b = fragments.barycentric.astype(attributes.dtype)
    # a sum over the corner axis: its transpose is one broadcast product per corner and
    # channel (summed slices transposed to pads, which XLA's CPU loops evaluate branch by branch)
    b = b.reshape(b.shape + (1,) * (corners.ndim - 3))
    out = jnp.sum(b * corners, axis=2)
    return jnp.where((fragments.triangle_id >= 0)[..., None], out, 0.0)
