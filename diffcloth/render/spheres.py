"""Analytic spheres: per-pixel ray casting (exact silhouettes, no tessellation) into a GBuffer.

The GBuffer composites with rasterized meshes by depth (`raster.composite`) and antialiases
with the same pixel-pair blending (`raster.antialias`): the silhouette crossing between a sphere
pixel and its neighbour is where the signed ray-to-surface distance g = r - |ray - centre|
(linear across the rim to first order) changes sign, so silhouette gradients w.r.t. centre,
radius and camera exist.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth._math import safe_div, safe_normalize, safe_sqrt
from diffcloth.render.camera import Camera, pixel_rays
from diffcloth.render.coverage import pair_share
from diffcloth.render.raster import BACKGROUND_DEPTH, GBuffer
from diffcloth.render.rays import ray_sphere
from diffcloth.shapes import Sphere


def raycast_spheres(spheres: Sphere, camera: Camera, attributes: dict | None = None) -> GBuffer:
    """Ray-cast one or more spheres through every pixel centre.

    Args:
      spheres: Sphere with center (3,) or (s, 3), radius () or (s,), in m; differentiable.
      camera: Camera.
      attributes: optional dict name -> (s, C) per-sphere values (e.g. colour), broadcast to
        the pixels each sphere covers.
    Returns:
      GBuffer with attributes "position" (world hit point), "normal" (unit outward normal) and
      the given ones; surface_id = sphere index; depth = view depth of the hit (m). Only hits
      between the near and far planes count.
    """
    sp = spheres.batched()
    dtype = camera.view.dtype
    origins, dirs = pixel_rays(camera)
    centers, radii = sp.center.astype(dtype), sp.radius.astype(dtype)
    t, hit, disc = jax.vmap(lambda c, r: ray_sphere(origins, dirs, c[None, None], r))(
        centers, radii
    )
    pts = origins[None] + t[..., None] * dirs[None]  # (s, H, W, 3)
    vdepth = -(jnp.einsum("k,shwk->shw", camera.view[2, :3], pts) + camera.view[2, 3])
    hit = hit & (jax.lax.stop_gradient(vdepth) <= jax.lax.stop_gradient(camera.far))
    vdepth = jnp.where(hit, vdepth, BACKGROUND_DEPTH)
    which = jnp.argmin(jax.lax.stop_gradient(vdepth), axis=0)  # (H, W)
    mask = jnp.any(hit, axis=0)

    def take(x):  # (s, H, W, ...) -> (H, W, ...)
        idx = which.reshape((1,) + which.shape + (1,) * (x.ndim - 3))
        return jnp.take_along_axis(x, idx, axis=0)[0]

    depth = jnp.where(mask, take(vdepth), BACKGROUND_DEPTH)
    pos = jnp.where(mask[..., None], take(pts), 0.0)
    normal = jnp.where(mask[..., None], safe_normalize(pos - centers[which]), 0.0)
    attrs = {"position": pos, "normal": normal}
    for name, val in (attributes or {}).items():
        val = jnp.asarray(val)
        attrs[name] = jnp.where(mask[..., None], val[which], 0.0)
    # signed distance of each pixel ray from each sphere's surface (> 0 inside the silhouette)
    g = radii[:, None, None] - safe_sqrt(radii[:, None, None] ** 2 - disc)
    sid = jnp.where(mask, which, -1).astype(jnp.int32)
    cross = _sphere_crossings(g, which, mask, jax.lax.stop_gradient(depth), sid)
    return GBuffer(
        attributes=attrs,
        depth=depth,
        mask=mask,
        surface_id=sid,
        crossings=cross.astype(dtype),
        front_facing=mask,
    )


def _sphere_crossings(g, which, mask, depth, sid):
    """(H, W, 12) crossings on the nearer pixel of each pair showing different surfaces, (zero)
    edge slopes and the pair directions' shares, as `raster.Fragments`."""
    gs = jnp.take_along_axis(g, which[None], axis=0)[0]  # own sphere at own pixel
    # gradient direction of the own sphere's g: a rim point is shared between the two pair
    # directions by how perpendicular it is to each (coverage.pair_share; as the triangle edges)
    gp = jnp.pad(g, ((0, 0), (1, 1), (1, 1)), mode="edge")
    own = lambda x: jnp.take_along_axis(x, which[None], axis=0)[0]
    gx = jnp.abs(own(gp[:, 1:-1, 2:] - gp[:, 1:-1, :-2]))
    gy = jnp.abs(own(gp[:, 2:, 1:-1] - gp[:, :-2, 1:-1]))
    share = {1: pair_share(gx, gy), 0: pair_share(gy, gx)}
    prefer = {a: jax.lax.stop_gradient(v) > 0 for a, v in share.items()}
    out, shares = [], []
    for axis in (1, 0):
        n = g.shape[axis + 1]
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, n - 1), slice(1, n)
        lo, hi = tuple(lo), tuple(hi)
        glo = (slice(None),) + lo
        ghi = (slice(None),) + hi
        a_front = depth[lo] < depth[hi]
        differ = sid[lo] != sid[hi]
        # own sphere's g at the partner pixel
        g_a_at_b = jnp.take_along_axis(g[ghi], which[lo][None], axis=0)[0]
        g_b_at_a = jnp.take_along_axis(g[glo], which[hi][None], axis=0)[0]
        ok_a = (
            differ & a_front & mask[lo] & (jax.lax.stop_gradient(g_a_at_b) <= 0) & prefer[axis][lo]
        )
        ok_b = (
            differ & ~a_front & mask[hi] & (jax.lax.stop_gradient(g_b_at_a) <= 0) & prefer[axis][hi]
        )
        t_a = safe_div(gs[lo], gs[lo] - g_a_at_b)
        t_b = safe_div(gs[hi], gs[hi] - g_b_at_a)
        t_a = jnp.where(ok_a, jnp.clip(t_a, 0.0, 1.0), -1.0)
        t_b = jnp.where(ok_b, jnp.clip(t_b, 0.0, 1.0), -1.0)
        pad_lo = [(0, 0)] * 2
        pad_hi = [(0, 0)] * 2
        pad_lo[axis], pad_hi[axis] = (0, 1), (1, 0)
        out.append(jnp.pad(t_a, pad_lo, constant_values=-1.0))
        out.append(jnp.pad(t_b, pad_hi, constant_values=-1.0))
        shares.append(jnp.pad(jnp.where(ok_a, share[axis][lo], 0.0), pad_lo))
        shares.append(jnp.pad(jnp.where(ok_b, share[axis][hi], 0.0), pad_hi))
    # slopes 0 (rim taken perpendicular to the pair, as nvdiffrast): the rasterizer's (12,) layout
    zeros = jnp.zeros(g.shape[1:] + (4,), g.dtype)
    return jnp.concatenate([jnp.stack(out, axis=-1), zeros, jnp.stack(shares, axis=-1)], -1)
