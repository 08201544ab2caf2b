"""Setup (raster step 1): per-triangle homogeneous edge functions, culling, screen boxes and
the window counts the visibility pass allocates from."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from diffcloth._math import materialize, materialize_value
from diffcloth.render.camera import Camera, project


def _vertex_table(positions, camera: Camera):
    """(n, 5) per vertex: screen-homogeneous X = x_pix w, Y = y_pix w, w (pixel units; pixel
    centre (j, i) at (j, i), row 0 at the top), view depth, clip x."""
    clip, depth = project(positions, camera)
    w, h = camera.width, camera.height
    cw = clip[:, 3]
    sx = 0.5 * (clip[:, 0] + cw) * w - 0.5 * cw
    sy = 0.5 * (cw - clip[:, 1]) * h - 0.5 * cw
    return jnp.stack([sx, sy, cw, depth, clip[:, 0], clip[:, 1]], axis=-1)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


class _Setup(NamedTuple):
    edge: jax.Array  # (m, 9) signed edge functions E[k, j] at 3k + j (differentiable)
    vdepth: jax.Array  # (m, 3) view depth per vertex (differentiable)
    valid: jax.Array  # (m,) bool: drawable
    front: jax.Array  # (m,) bool: counter-clockwise on screen
    bbox: jax.Array  # (m, 4) int32 x0, y0, x1, y1 inclusive pixel range (clamped)
    origin: jax.Array  # (m, 2) integer pixel origin of the edge functions (no gradient)
    table: jax.Array | None = None  # (m, 14) edge, vdepth, origin in one buffer (`_materialized`)


def setup_table(s: _Setup):
    """(m, 14) per triangle: edge rows (9), vertex depths (3), origin (2, no gradient); the
    buffer `_materialized` keeps, else built (materialized) here. The visibility windows and
    the silhouette walk gather their triangle's row from it."""
    if s.table is not None:
        return s.table
    origin = jax.lax.stop_gradient(s.origin).astype(s.edge.dtype)
    return materialize(jnp.concatenate([s.edge, s.vdepth, origin], axis=-1))


def _materialized(s: _Setup) -> _Setup:
    """`s` computed once into two buffers (floats: edge, vdepth, origin, also kept as `table`
    for the per-pixel and per-window gathers; ints: bbox, valid, front), its fields slices of
    them: XLA's fusion would otherwise recompute the setup inside each consumer, and one
    materialization per field cost two launches and a pass each."""
    table = materialize(jnp.concatenate([s.edge, s.vdepth, s.origin.astype(s.edge.dtype)], -1))
    flags = jnp.stack([s.valid, s.front], axis=-1).astype(jnp.int32)
    ints = materialize(jnp.concatenate([s.bbox, flags], axis=-1))
    origin = jax.lax.stop_gradient(table[:, 12:])  # no tangent (as `_setup`'s): none computed
    valid, front = ints[:, 4] > 0, ints[:, 5] > 0
    return _Setup(table[:, :9], table[:, 9:12], valid, front, ints[:, :4], origin, table)


def _setup(positions, faces, camera: Camera, cull_backfaces: bool, mask=None) -> _Setup:
    """Per-triangle edge functions, validity (culling), orientation and screen bounding box.

    Edge functions are taken relative to an integer pixel origin near vertex 0, so that a tiny
    triangle's homogeneous columns are well conditioned and the zero-area test is relative to the
    triangle's own size: |det| <= 64 eps |c0| |c1| |c2| counts as degenerate and is skipped.

    Written per (m,) column, with the reductions over a triangle's corners and bounding-box points
    spelled out as elementwise min / max / and: XLA's CPU backend then computes the setup in a
    few loop fusions (reductions over a 3- or 6-long minor axis and the stacked intermediate
    arrays split it into about forty, each a pass over the triangles).
    """
    W, H = camera.width, camera.height
    faces = faces.astype(jnp.int32)
    # materialized: the gather would otherwise recompute the projection (and whatever produced
    # the positions, e.g. the surface collision) per corner, 6x per vertex
    tv = materialize_value(_vertex_table(positions, camera))[faces]  # (m, 3, 6)
    tsg = jax.lax.stop_gradient(tv)
    X, Y, Wc = ([tv[:, k, j] for k in range(3)] for j in range(3))
    Xs, Ys, Ws, ds, xc, yc = ([tsg[:, k, j] for k in range(3)] for j in range(6))
    all3 = lambda f: f(0) & f(1) & f(2)
    ok0 = (Ws[0] > 0) & jnp.isfinite(Xs[0]) & jnp.isfinite(Ys[0])
    lim = float(2 * max(W, H))
    w0 = jnp.where(ok0, Ws[0], 1.0)
    ox = jnp.floor(jnp.clip(jnp.where(ok0, Xs[0] / w0, 0.0), -lim, lim))
    oy = jnp.floor(jnp.clip(jnp.where(ok0, Ys[0] / w0, 0.0), -lim, lim))
    c = [(X[k] - ox * Wc[k], Y[k] - oy * Wc[k], Wc[k]) for k in range(3)]
    adj = [_cross(c[1], c[2]), _cross(c[2], c[0]), _cross(c[0], c[1])]
    det = c[0][0] * adj[0][0] + c[0][1] * adj[0][1] + c[0][2] * adj[0][2]
    det_s = jax.lax.stop_gradient(det)
    norms = [jnp.sqrt(jax.lax.stop_gradient(a * a + b * b + w * w)) for a, b, w in c]
    tol = 64 * jnp.finfo(tv.dtype).eps
    valid = (jnp.abs(det_s) > tol * norms[0] * norms[1] * norms[2]) & jnp.isfinite(det_s)
    sgn = jnp.where(det_s < 0, -1.0, 1.0).astype(tv.dtype)
    edge = jnp.stack([sgn * adj[k][j] for k in range(3) for j in range(3)], axis=-1)
    wsign = jnp.sign(Ws[0]) * jnp.sign(Ws[1]) * jnp.sign(Ws[2])
    front = det_s * wsign < 0
    near, far = jax.lax.stop_gradient(camera.near), jax.lax.stop_gradient(camera.far)
    valid = valid & ~all3(lambda k: ds[k] < near) & ~all3(lambda k: ds[k] > far)
    for q in (xc, yc):  # all three vertices outside one side plane of the frustum
        valid = valid & ~all3(lambda k, q=q: q[k] > Ws[k]) & ~all3(lambda k, q=q: q[k] < -Ws[k])
    if cull_backfaces:
        valid = valid & front
    if mask is not None:
        valid = valid & mask
    # screen bounding box of pixel centres of the part in front of the near plane: the vertices
    # with depth >= near plus the points where edges cross the near plane (w > 0 at all of them).
    nxt = (1, 2, 0)
    dn = [d - near for d in ds]
    crosses = [dn[k] * dn[nxt[k]] < 0 for k in range(3)]
    frac = [
        jnp.where(crosses[k], dn[k] / jnp.where(crosses[k], dn[k] - dn[nxt[k]], 1.0), 0.0)
        for k in range(3)
    ]
    big = float(4 * max(W, H) + 16)
    between = lambda q, k: q[k] + frac[k] * (q[nxt[k]] - q[k])  # on the edge k -> k + 1
    use = [dn[k] >= 0 for k in range(3)] + crosses
    ptw = Ws + [between(Ws, k) for k in range(3)]
    use = [u & (w > 0) for u, w in zip(use, ptw, strict=True)]
    safe_w = [jnp.where(u, w, 1.0) for u, w in zip(use, ptw, strict=True)]
    box = []
    for q in (Xs, Ys):
        pt = q + [between(q, k) for k in range(3)]
        sq = [jnp.clip(p / w, -big, big) for p, w in zip(pt, safe_w, strict=True)]
        lo = [jnp.where(u, v, big) for u, v in zip(use, sq, strict=True)]
        hi = [jnp.where(u, v, -big) for u, v in zip(use, sq, strict=True)]
        box.append(jnp.ceil(functools.reduce(jnp.minimum, lo)))
        box.append(jnp.floor(functools.reduce(jnp.maximum, hi)))
    x0, x1, y0, y1 = box
    finite = all3(lambda k: jnp.isfinite(Xs[k]) & jnp.isfinite(Ys[k]) & jnp.isfinite(Ws[k]))
    valid = valid & functools.reduce(jnp.logical_or, use) & finite
    x0, y0 = jnp.maximum(x0, 0), jnp.maximum(y0, 0)
    x1, y1 = jnp.minimum(x1, W - 1), jnp.minimum(y1, H - 1)
    # each column computed in a loop fusion of its own (materialized): fused into the table's
    # concatenate, the setup ran as one branch per output entry, unvectorized
    bbox = jnp.stack([materialize(v.astype(jnp.int32)) for v in (x0, y0, x1, y1)], axis=-1)
    valid, front = materialize(valid), materialize(front)
    vdepth = jnp.stack([tv[:, k, 3] for k in range(3)], axis=-1)
    return _Setup(edge, vdepth, valid, front, bbox, jnp.stack([ox, oy], axis=-1))


def _tile_counts(s: _Setup, tile: int):
    x0, y0, x1, y1 = (s.bbox[:, k] for k in range(4))
    nx = jnp.maximum(x1 - x0 + tile, 0) // tile
    ny = jnp.maximum(y1 - y0 + tile, 0) // tile
    ntiles = jnp.where(s.valid, nx * ny, 0)
    return nx, ntiles


DIRECT_PIXELS = 2  # triangles with at most this many pixel centres in their box get no windows


def default_max_tiles(num_triangles: int, width: int, height: int, tile_size: int = 2) -> int:
    """Default window budget: one per triangle plus two full screens of windows.

    Shapes: none (Python ints).
    """
    return int(num_triangles + 2 * math.ceil(width / tile_size) * math.ceil(height / tile_size))


def required_tiles(positions, faces, camera: Camera, *, tile_size: int = 2, cull_backfaces=False):
    """Number of pixel windows a scene needs (compare with `max_tiles`): windows of the triangles
    covering more than DIRECT_PIXELS pixel centres.

    Shapes: positions (n, 3) m, faces (m, 3) int -> () int32.
    """
    s = _setup(positions, faces, camera, cull_backfaces)
    direct = _tile_counts(s, 1)[1] <= DIRECT_PIXELS
    return jnp.sum(jnp.where(direct, 0, _tile_counts(s, tile_size)[1]))
