"""Visibility (raster step 2, no gradient): direct per-triangle tests and prefix-sum allocated
pixel windows, z-buffer scatter-min and id scatter-max."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from diffcloth._math import materialize
from diffcloth.render.camera import Camera
from diffcloth.render.raster.scan import _batch_max, _cummax, _cumsum
from diffcloth.render.raster.triangle_setup import DIRECT_PIXELS, _Setup, _tile_counts, setup_table


def _candidate_depth(E, dep, org, px, py, keep, near, far):
    """View depth of candidate pixels (px, py) (int32) of triangles with edge rows E (..., 9),
    vertex depths dep (..., 3) and origins org (..., 2) (shapes broadcast); +inf where rejected."""
    dtype = E.dtype
    fx = (px - org[..., 0].astype(jnp.int32)).astype(dtype)
    fy = (py - org[..., 1].astype(jnp.int32)).astype(dtype)
    e = [E[..., 3 * k] * fx + E[..., 3 * k + 1] * fy + E[..., 3 * k + 2] for k in range(3)]
    total = e[0] + e[1] + e[2]
    num = e[0] * dep[..., 0] + e[1] * dep[..., 1] + e[2] * dep[..., 2]
    depth = num / jnp.where(total > 0, total, 1.0)
    keep = keep & (e[0] >= 0) & (e[1] >= 0) & (e[2] >= 0) & (total > 0)
    keep = keep & (depth >= near) & (depth <= far)
    return jnp.where(keep, depth, jnp.inf)


def _windows(ftab, itab, ends, W: int, tile: int, budget: int, near, far):
    """Candidates of the first `budget` tile x tile windows, allocated to triangles by the prefix
    sum `ends` of their window counts: flat depth (+inf rejected), flat pixel index and triangle
    id. ftab (m, 14): edge rows, vertex depths, origin; itab (m, 5): bounding box, windows per
    row."""
    m = ftab.shape[0]
    ntiles = ends - jnp.concatenate([jnp.zeros(1, ends.dtype), ends[:-1]])
    owner = jnp.full((budget,), -1, jnp.int32)
    owner = owner.at[jnp.where(ntiles > 0, ends - ntiles, budget)].max(
        jnp.arange(m, dtype=jnp.int32), mode="drop"
    )
    owner = _cummax(owner)
    slot = jnp.arange(budget, dtype=jnp.int32)
    tri = jnp.maximum(owner, 0)
    # one gather per table, materialized: fused into the per-pixel code it would run per pixel
    f = materialize(ftab[tri])[:, None, None]
    i = materialize(itab[tri])
    local = slot - (ends[tri] - ntiles[tri])
    ntx = jnp.maximum(i[:, 4], 1)
    ox = i[:, 0] + tile * (local % ntx)
    oy = i[:, 1] + tile * (local // ntx)
    u = jnp.arange(tile, dtype=jnp.int32)
    px = ox[:, None, None] + u[None, None, :]  # (S, T, T), columns vary fastest
    py = oy[:, None, None] + u[None, :, None]
    keep = (px <= i[:, 2, None, None]) & (py <= i[:, 3, None, None])
    keep = keep & ((owner >= 0) & (local < ntiles[tri]))[:, None, None]
    depth = _candidate_depth(f[..., :9], f[..., 9:12], f[..., 12:], px, py, keep, near, far)
    pix = jnp.broadcast_to(py * W + px, keep.shape).reshape(-1)
    tid = jnp.broadcast_to(tri[:, None, None], keep.shape).reshape(-1)
    return depth.reshape(-1), pix, tid


def window_budgets(width: int, height: int, max_tiles: int, tile_size: int = 2) -> tuple:
    """Static window budgets of the visibility pass, smallest first: a quarter and one screen of
    windows, then `max_tiles`; a frame runs the smallest that holds its windows. (An eighth of a
    screen, 2,048 windows at 256 x 256, was 50 short for the draped cloth of
    benchmarks/peers/mitsuba_render.py, which then evaluated 8 x the windows it needs.)
    Below 128 x 128 pixels only `max_tiles` (as cheap there, and compiled once; also for a
    batch: on the main job's ten 64^2 images the ladder ran the render forward 0.69x and its
    gradient 0.78x, the fit step 0.90x, but compiled the step in 44 instead of 35 s of CPU,
    more than 57 LM steps win back)."""
    screen = math.ceil(width / tile_size) * math.ceil(height / tile_size)
    if width * height < 128 * 128:
        return (int(max_tiles),)
    small = [b for b in (screen // 4, screen) if b < int(max_tiles)]
    return tuple(sorted(set(small))) + (int(max_tiles),)


def _visibility(s: _Setup, camera: Camera, tile: int, max_tiles: int, batch_axes: tuple = ()):
    """(H * W,) int32 visible triangle per pixel (-1 background). No gradient.

    Triangles whose clamped bounding box holds at most `DIRECT_PIXELS` pixel centres (nearly all
    of a finely tessellated cloth) are tested at those pixels directly, per triangle; the others
    get tile x tile windows from the smallest of `window_budgets` that holds the frame's windows
    (lax.switch; under vmap with `batch_axes` named, the smallest that holds every image's
    windows, else every budget runs). A z-buffer scatter-min of the candidates'
    depths, then a scatter-max of the ids of those equal to it (ties: larger id).
    """
    W, H = camera.width, camera.height
    m = s.edge.shape[0]
    E = jax.lax.stop_gradient(s.edge)
    dep = jax.lax.stop_gradient(s.vdepth)
    near, far = jax.lax.stop_gradient(camera.near), jax.lax.stop_gradient(camera.far)
    nx1, n1 = _tile_counts(s, 1)
    direct = n1 <= DIRECT_PIXELS
    k = jnp.arange(DIRECT_PIXELS, dtype=jnp.int32)[None, :]
    nxd = jnp.maximum(nx1, 1)[:, None]
    dpx = s.bbox[:, 0, None] + k % nxd
    dpy = s.bbox[:, 1, None] + k // nxd
    col = lambda a: a[:, None]
    d_keep = k < n1[:, None]
    d_depth = _candidate_depth(col(E), col(dep), col(s.origin), dpx, dpy, d_keep, near, far)
    d_pix = (dpy * W + dpx).reshape(-1)
    d_tid = jnp.broadcast_to(jnp.arange(m, dtype=jnp.int32)[:, None], dpx.shape).reshape(-1)

    nx, ntiles = _tile_counts(s, tile)
    ends = _cumsum(jnp.where(direct, 0, ntiles))
    ftab = jax.lax.stop_gradient(setup_table(s))
    itab = materialize(jnp.concatenate([s.bbox, nx[:, None]], axis=-1))

    def pass_(budget):
        w = _windows(ftab, itab, ends, W, tile, budget, near, far)
        # the direct and the window candidates scattered one set after the other (concatenated,
        # each of depth, pixel and id cost a pass); their depths computed once (materialized),
        # so that the edge functions are not re-evaluated inside every consumer fusion
        parts = []
        for depth, pix, tid in ((d_depth.reshape(-1), d_pix, d_tid), w):
            depth = materialize(depth)
            keep = depth < jnp.inf
            parts.append((depth, keep, jnp.where(keep, pix, H * W), tid))
        zbuf = jnp.full((H * W,), jnp.inf, d_depth.dtype)
        for depth, _, pix, _ in parts:
            zbuf = zbuf.at[pix].min(depth, mode="drop")
        ids = jnp.full((H * W,), -1, jnp.int32)
        for depth, keep, pix, tid in parts:
            win = keep & (depth == zbuf.at[pix].get(mode="fill", fill_value=-1.0))
            ids = ids.at[jnp.where(win, pix, H * W)].max(tid, mode="drop")
        return ids

    budgets = window_budgets(W, H, max_tiles, tile)
    if len(budgets) == 1:
        return pass_(budgets[0])
    level = _batch_max(jnp.sum(ends[-1] > jnp.asarray(budgets[:-1])), batch_axes)
    return jax.lax.switch(level, [lambda b=b: pass_(b) for b in budgets])
