"""Rasterizer output pytrees: per-pixel Fragments (one mesh) and GBuffers (composited)."""

from __future__ import annotations

from typing import NamedTuple

import jax

BACKGROUND_DEPTH = (
    1e10  # view depth stored where nothing is drawn (finite, so arithmetic stays finite)
)


class Fragments(NamedTuple):
    """Per-pixel visibility. All (H, W, ...).

    triangle_id: int32, -1 for background.
    barycentric: perspective-correct barycentrics (3,), zeros on background; differentiable in
      the vertex positions.
    depth: view depth (-z_view) in m, BACKGROUND_DEPTH on background; differentiable.
    crossings: (12,) fraction of the way to the (+x, -x, +y, -y) neighbour's centre where the
      visible triangle's silhouette edge is crossed, -1 where there is none; then that edge's
      slope k in [0, 1] relative to the pair direction (0: perpendicular; `edge_coverage`); then
      this pair direction's share of the edge's blend (`coverage.pair_share`); differentiable.
      (A (4,) array without the slopes is read as k = 0, an (8,) one as share 1.)
    front_facing: bool, True where the visible triangle is counter-clockwise on screen.
    weights: (4, H, W) `antialias_weights` of these crossings, computed by the silhouette search
      per pair (cheaper than from the per-pixel crossings: `antialias` reads them when present;
      jit then drops the unused crossings), or None.
    """

    triangle_id: jax.Array
    barycentric: jax.Array
    depth: jax.Array
    crossings: jax.Array
    front_facing: jax.Array
    weights: jax.Array | None = None


class GBuffer(NamedTuple):
    """Per-pixel surface attributes of one or several composited objects. All (H, W, ...).

    attributes: dict name -> (H, W, C), zero on background.
    depth: view depth in m, BACKGROUND_DEPTH on background.
    mask: bool coverage.
    surface_id: int32 id of the visible element (unique across composited objects), -1 background.
    crossings: (12,) silhouette crossings toward (+x, -x, +y, -y) neighbours, the edges'
      slopes and the pair directions' shares (see Fragments).
    front_facing: bool, True where the visible side faces the camera.
    weights: (4, H, W) antialiasing weights of one rasterized mesh (see Fragments) or None
      (composited buffers: `antialias` computes them from the crossings).
    """

    attributes: dict
    depth: jax.Array
    mask: jax.Array
    surface_id: jax.Array
    crossings: jax.Array
    front_facing: jax.Array
    weights: jax.Array | None = None
