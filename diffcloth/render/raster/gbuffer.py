"""Analytic silhouette antialiasing, G-buffers (rasterize + interpolate, depth compositing) and
the unlit `render_mesh`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth._math import materialize, materialize_grad, materialize_value, safe_normalize
from diffcloth.render.camera import Camera
from diffcloth.render.coverage import edge_coverage
from diffcloth.render.mesh import vertex_normals
from diffcloth.render.raster.buffers import Fragments, GBuffer
from diffcloth.render.raster.resolve import interpolate, rasterize


def antialias(color, buffer, weights=None):
    """Analytic silhouette antialiasing; gives gradients w.r.t. silhouette and occlusion edges.

    Args:
      color: (H, W, C) image computed from the buffer (e.g. interpolated or shaded colour,
        with background filled in).
      buffer: Fragments or GBuffer (its `weights` when the rasterizer computed them, else the
        id, depth and crossings); unused when `weights` is given.
      weights: optional (4, H, W) `antialias_weights(buffer, color.dtype)`, computed once for
        a static geometry and camera (e.g. by `render.prepare_frame`).
    Returns:
      (H, W, C) colour where each pixel pair straddling a silhouette is blended by how far the edge
      lies from the pixel midline. Converges to `color` as pixels shrink.
    """
    w = antialias_weights(buffer, color.dtype) if weights is None else weights.astype(color.dtype)
    nb = [
        jnp.pad(color[:, 1:], ((0, 0), (0, 1), (0, 0))),
        jnp.pad(color[:, :-1], ((0, 0), (1, 0), (0, 0))),
        jnp.pad(color[1:], ((0, 1), (0, 0), (0, 0))),
        jnp.pad(color[:-1], ((1, 0), (0, 0), (0, 0))),
    ]
    out = color
    for wk, ck in zip(w, nb, strict=True):
        out = out + wk[..., None] * (ck - color)
    return out


def antialias_weights(buffer, dtype):
    """(4, H, W) weight of each pixel's move toward its right / left / lower / upper
    neighbour's colour in `antialias` (0 away from silhouettes); differentiable through the
    buffer's crossings. Depends on the geometry and camera only. A rasterizer's buffer
    carries them already (`Fragments.weights`, computed per searched pair): returned as they are.

    Args:
      buffer: Fragments or GBuffer (uses the id, depth and crossings).
      dtype: float dtype of the weights (the colour's).
    """
    if buffer.weights is not None:  # computed by the rasterizer's silhouette search
        return buffer.weights.astype(dtype)
    ids = buffer.triangle_id if isinstance(buffer, Fragments) else buffer.surface_id
    depth = jax.lax.stop_gradient(buffer.depth)
    cross = buffer.crossings.astype(dtype)
    if cross.shape[-1] == 4:  # no slopes: edges taken perpendicular to the pair (nvdiffrast)
        cross = jnp.concatenate([cross, jnp.zeros_like(cross)], axis=-1)
    if cross.shape[-1] == 8:  # no shares: each edge wholly to the pair that found it
        cross = jnp.concatenate([cross, jnp.ones_like(cross[..., :4])], axis=-1)

    def weights(ia, ib, da, db, ta, tb, ka, kb, sa, sb):
        # pair (a, b): the front pixel moves toward the back colour by its uncovered area
        # 1 - A(t), the back pixel toward the front colour by its covered area A(t - 1), A the
        # exact coverage by the straight edge of slope k (edge_coverage; k = 0 gives nvdiffrast's
        # 1/2 - t on the front pixel when t < 1/2, else t - 1/2 on the back one); both scaled by
        # this pair direction's share of the edge (coverage.pair_share: 1 away from 45 degrees)
        a_front = da < db
        # the backward pass of the coverage is computed once per pair, not inside each of the
        # crossing channels it flows into (forward + backward 256^2 phong: 0.87x)
        t = materialize_grad(jnp.where(a_front, ta, tb))
        k = materialize_grad(jnp.where(a_front, ka, kb))
        share = materialize_grad(jnp.where(a_front, sa, sb))
        ok = (ia != ib) & (jax.lax.stop_gradient(t) >= 0)
        wf = jnp.where(ok, share * (1.0 - edge_coverage(t, k)), 0.0)
        wb = jnp.where(ok, share * edge_coverage(t - 1.0, k), 0.0)
        return jnp.where(a_front, wf, wb), jnp.where(a_front, wb, wf)

    h_a, h_b = weights(
        ids[:, :-1], ids[:, 1:], depth[:, :-1], depth[:, 1:], cross[:, :-1, 0], cross[:, 1:, 1],
        cross[:, :-1, 4], cross[:, 1:, 5], cross[:, :-1, 8], cross[:, 1:, 9],
    )  # fmt: skip
    v_a, v_b = weights(
        ids[:-1], ids[1:], depth[:-1], depth[1:], cross[:-1, :, 2], cross[1:, :, 3],
        cross[:-1, :, 6], cross[1:, :, 7], cross[:-1, :, 10], cross[1:, :, 11],
    )  # fmt: skip
    return materialize(
        jnp.stack(
            [
                jnp.pad(h_a, ((0, 0), (0, 1))),
                jnp.pad(h_b, ((0, 0), (1, 0))),
                jnp.pad(v_a, ((0, 1), (0, 0))),
                jnp.pad(v_b, ((1, 0), (0, 0))),
            ]
        )
    )


def _interpolate_all(attributes: dict, frags, faces) -> dict:
    """`interpolate` of every attribute, each computed once into a buffer first
    (`materialize_value`): the per-pixel gathers would otherwise recompute the attributes'
    producers (e.g. the surface's normalised normals, the collision push-out) per pixel corner.
    Derivatives pass through unchanged."""
    return {
        k: interpolate(materialize_value(jnp.asarray(v)), frags, faces)
        for k, v in attributes.items()
    }


def rasterize_gbuffer(
    positions,
    faces,
    camera: Camera,
    attributes: dict,
    *,
    neighbors=None,
    cull_backfaces: bool = False,
    triangle_mask=None,
    tile_size: int = 2,
    max_tiles: int | None = None,
    silhouette_budget: int | None = None,
    batch_axes: tuple = (),
) -> GBuffer:
    """Rasterize a mesh and interpolate named per-vertex attributes into a GBuffer.

    Args:
      attributes: dict name -> (n, C) per-vertex values (positions, normals, uv, colours...).
      Other arguments as in `rasterize`.
    Returns:
      GBuffer with the interpolated attributes; surface_id is the triangle id.
    """
    frags = rasterize(
        positions,
        faces,
        camera,
        neighbors=neighbors,
        cull_backfaces=cull_backfaces,
        triangle_mask=triangle_mask,
        tile_size=tile_size,
        max_tiles=max_tiles,
        silhouette_budget=silhouette_budget,
        batch_axes=batch_axes,
    )
    attrs = _interpolate_all(attributes, frags, faces)
    return GBuffer(
        attributes=attrs,
        depth=frags.depth,
        mask=frags.triangle_id >= 0,
        surface_id=frags.triangle_id,
        crossings=frags.crossings,
        front_facing=frags.front_facing,
        weights=frags.weights,
    )


def composite(*buffers: GBuffer) -> GBuffer:
    """Depth-composite several GBuffers (meshes, spheres): the nearest surface wins per pixel.

    Attribute dicts are merged by name; a buffer lacking a name contributes zeros. Surface ids are
    made unique: id * len(buffers) + buffer index.
    """
    if len(buffers) == 1:
        return buffers[0]
    n = len(buffers)
    depth = jnp.stack([b.depth for b in buffers])
    which = jnp.argmin(jax.lax.stop_gradient(depth), axis=0)  # (H, W)
    sel = [which == i for i in range(n)]

    def pick(xs):
        out = xs[0]
        for i in range(1, n):
            s = sel[i].reshape(sel[i].shape + (1,) * (xs[i].ndim - 2))
            out = jnp.where(s, xs[i], out)
        return out

    names = {}
    for b in buffers:
        for k, v in b.attributes.items():
            names.setdefault(k, v)
    attrs = {}
    for k, proto in names.items():
        attrs[k] = pick([b.attributes.get(k, jnp.zeros_like(proto)) for b in buffers])
    ids = [jnp.where(b.surface_id >= 0, b.surface_id * n + i, -1) for i, b in enumerate(buffers)]
    return GBuffer(
        attributes=attrs,
        depth=pick([b.depth for b in buffers]),
        mask=pick([b.mask for b in buffers]),
        surface_id=pick(ids).astype(jnp.int32),
        crossings=pick([b.crossings for b in buffers]),
        front_facing=pick([b.front_facing for b in buffers]),
    )


def render_mesh(
    positions,
    faces,
    camera: Camera,
    colors,
    *,
    background=None,
    antialiased: bool = True,
    neighbors=None,
    cull_backfaces: bool = False,
    tile_size: int = 2,
    max_tiles: int | None = None,
    silhouette_budget: int | None = None,
    light_dir=None,
    normals="smooth",
):
    """Interpolated per-vertex colour, alpha = coverage, silhouette-antialiased; unlit unless
    `light_dir` is given.

    Args:
      positions: (n, 3) in m; colors: (n, C) (e.g. RGB); both differentiable.
      background: optional (C,) colour under uncovered pixels (default 0: premultiplied output).
      light_dir: optional (3,) direction toward a directional light: the colour is then scaled
        by the Lambert factor max(N . L, 0) with N the interpolated, renormalised vertex normal.
      normals: with `light_dir`: "smooth" (default) for area-weighted averages of the face
        normals (`mesh.vertex_normals`, Delannoy's smooth shading, differentiable in the
        positions), or an (n, 3) array of vertex normals (e.g. read_obj's).
    Returns:
      (H, W, C + 1) image; last channel is coverage in [0, 1].

    >>> import jax.numpy as jnp
    >>> from diffcloth.render.camera import make_camera
    >>> cam = make_camera((0, 0, 3), (0, 0, 0), (0, 1, 0), width=8, height=8)
    >>> tri = jnp.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    >>> render_mesh(tri, jnp.array([[0, 1, 2]]), cam, jnp.ones((3, 3))).shape
    (8, 8, 4)
    """
    frags = rasterize(
        positions,
        faces,
        camera,
        neighbors=neighbors,
        cull_backfaces=cull_backfaces,
        tile_size=tile_size,
        max_tiles=max_tiles,
        silhouette_budget=silhouette_budget,
    )
    col = interpolate(colors, frags, faces)
    mask = (frags.triangle_id >= 0)[..., None]
    if light_dir is not None:
        if isinstance(normals, str):
            if normals != "smooth":
                raise ValueError(f'normals must be "smooth" or an (n, 3) array, got {normals!r}')
            normals = vertex_normals(positions, faces)
        n = safe_normalize(interpolate(jnp.asarray(normals, col.dtype), frags, faces))
        light = jnp.reshape(safe_normalize(jnp.asarray(light_dir, col.dtype)), (1, 1, 3))
        col = col * jnp.maximum(jnp.sum(n * light, axis=-1, keepdims=True), 0.0)
    if background is not None:
        col = jnp.where(mask, col, jnp.asarray(background, col.dtype))
    rgba = jnp.concatenate([col, mask.astype(col.dtype)], axis=-1)
    return antialias(rgba, frags) if antialiased else rgba
