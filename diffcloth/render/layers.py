"""The ray-cast layers of a frame (spheres and ground planes), lit with one batched lookup.

`frame.render` composites the cloth with these layers by depth. Both layers' receivers (a hit
point and normal per pixel) are known from the camera and the shapes alone, so their light
visibility and ambient occlusion are looked up together: one `layer_shadow_visibility` and one
`layer_sky_visibility` over the stacked (2, H, W) receivers instead of one per layer, joined
by the cloth's per-vertex receivers where the "fit" preset looks the cloth up per vertex (each
lookup is a few hundred small XLA operations, forward and backward: at 64^2 their count, not
their size, sets the cost of a shadowed frame).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.render.camera import Camera, pixel_rays, project
from diffcloth.render.grid_coarse import coarse_grid
from diffcloth.render.lights import Appearance, Lights
from diffcloth.render.shade import blinn_phong
from diffcloth.render.shadows import ShadowMaps, layer_shadow_receivers, shadow_visibility
from diffcloth.render.sky import COARSE_GRID, SkyMaps, layer_sky_receivers, sky_visibility
from diffcloth.render.sphere_layer import sphere_geometry, sphere_shade
from diffcloth.shapes import Plane, Sphere

#: default albedo of drawn ground planes (linear RGB)
PLANE_COLOR = (0.6, 0.6, 0.6)


def safe_div_neg(side, nd):
    """Ray parameter t = side / -nd of a plane hit; 0 where the ray is parallel.

    Shapes: side (...), nd (...) -> (...) elementwise.
    """
    ok = nd < 0
    return jnp.where(ok, side / jnp.where(ok, -nd, 1.0), 0.0)


def plane_geometry(camera: Camera, planes: Plane):
    """Ray-cast planes (seen from their free side, up to the far plane), the nearest per pixel:
    hit (H, W) bool, view depth (H, W) (1e10 where none), point (H, W, 3) m (0 where none) and
    unit normal (H, W, 3).

    Shapes: planes (npl,) -> (H, W), (H, W), (H, W, 3), (H, W, 3).
    """
    origins, dirs = pixel_rays(camera)
    pl = planes.batched()
    big = jnp.asarray(1e10, origins.dtype)

    def one(normal, offset):
        n = jnp.reshape(normal, (1, 1, 3))
        side = jnp.sum(origins * n, axis=-1) - offset  # > 0: eye on the free side
        nd = jnp.sum(dirs * n, axis=-1)
        t = safe_div_neg(side, nd)
        point = origins + t[..., None] * dirs
        _, depth = project(point, camera)
        hit = (side > 0) & (nd < 0) & (depth < camera.far)
        return jnp.where(hit, depth, big), point

    depth, point = jax.vmap(one)(pl.normal, pl.offset)  # (npl, H, W, ...)
    nearest = jnp.argmin(depth, axis=0)
    depth = jnp.take_along_axis(depth, nearest[None], axis=0)[0]
    point = jnp.take_along_axis(point, nearest[None, ..., None], axis=0)[0]
    normal = pl.normal[nearest]
    hit = depth < big
    return hit, depth, jnp.where(hit[..., None], point, 0.0), normal


def plane_shade(camera, geometry, lights: Lights, appearance: Appearance, color, vis, sky_vis):
    """Opaque Lambertian RGBA (H, W, 4) (premultiplied; alpha 1 where a plane is hit) and view
    depth (H, W) of `plane_geometry`'s layer: color * (appearance.ambient * ambient light * A +
    sum_l radiance_l max(N.L_l, 0) V_l); no specular (a matte ground).

    Shapes: color (3,), vis (H, W, nl) or None, sky_vis (H, W) or None.
    """
    hit, depth, point, normal = geometry
    dirs = pixel_rays(camera)[1]
    diffuse, _ = blinn_phong(normal, -dirs, point, lights, appearance, vis)
    amb = jnp.reshape(appearance.ambient * lights.ambient, (1, 1, 3))
    if sky_vis is not None:
        amb = amb * sky_vis[..., None]
    rgb = jnp.reshape(jnp.asarray(color, point.dtype), (1, 1, 3)) * (amb + diffuse)
    alpha = hit.astype(point.dtype)[..., None]
    return jnp.concatenate([rgb * alpha, alpha], axis=-1), depth


def _batched(fn, groups):
    """fn over the concatenation of receiver groups [(points (..., 3), normals (..., 3))], split
    back into each group's leading shape: one lookup instead of one per group.

    Shapes: groups of points (..., 3) m, normals (..., 3) -> a list of fn's (..., k) or (...).
    """
    flat = [(p.reshape(-1, 3), n.reshape(-1, 3)) for p, n in groups]
    out = fn(jnp.concatenate([p for p, _ in flat]), jnp.concatenate([n for _, n in flat]))
    sizes = np.cumsum([p.shape[0] for p, _ in flat])[:-1]
    return [
        o.reshape(*p.shape[:-1], *out.shape[1:])
        for o, (p, _) in zip(jnp.split(out, sizes), groups, strict=True)
    ]


class FrameLayers(NamedTuple):
    """`ray_cast_layers`' result: each ray-cast layer's (RGBA (H, W, 4), depth (H, W)) or None;
    the cloth's per-vertex light visibility (n, nl) and occlusion (n, 2) (front, back) when
    they were looked up with the layers (`surface_gbuffer`'s vertex_light / vertex_sky)."""

    sphere: tuple | None
    plane: tuple | None
    vertex_light: jax.Array | None
    vertex_sky: jax.Array | None


def ray_cast_layers(
    camera: Camera,
    lights: Lights,
    appearance: Appearance,
    *,
    spheres: Sphere | None = None,
    planes: Plane | None = None,
    plane_color=PLANE_COLOR,
    shadows: ShadowMaps | None = None,
    sky: SkyMaps | None = None,
    cloth=None,
) -> FrameLayers:
    """The sphere layer and the plane layer of a frame (module docstring) and, with `cloth` =
    (positions (n, 3), normals (n, 3), grid_shape or None), the cloth's per-vertex light
    visibility (when `shadows.per_vertex`) and occlusion (when `sky.per_vertex`), all from one
    light lookup and one occlusion lookup.

    Shapes: spheres (k,), planes (npl,) -> FrameLayers.
    """
    geoms = []
    if spheres is not None:
        geoms.append(("sphere", sphere_geometry(camera, spheres)))
    if planes is not None:
        geoms.append(("plane", plane_geometry(camera, planes)))
    light_groups, sky_groups, light_back, sky_back = [], [], [], []
    if geoms:
        points = jnp.stack([g[2] for _, g in geoms])
        normals = jnp.stack([g[3] for _, g in geoms])
        if shadows is not None:
            p, n, up = layer_shadow_receivers(shadows, points, normals)
            light_groups.append((p, n))
            light_back.append(up)
        if sky is not None:
            p, n, up = layer_sky_receivers(sky, points, normals)
            sky_groups.append((p, n))
            sky_back.append(up)
    if cloth is not None and shadows is not None and shadows.per_vertex:
        p, n, expand = coarse_grid(*cloth, shadows.size)
        light_groups.append((p, n))
        light_back.append(expand)
    if cloth is not None and sky is not None and sky.per_vertex:
        p, n, expand = coarse_grid(*cloth, COARSE_GRID)
        sky_groups.append((jnp.stack([p, p]), jnp.stack([n, -n])))  # both sides
        sky_back.append(lambda a, expand=expand: expand(jnp.moveaxis(a, 0, -1)))
    vis = _batched(partial(shadow_visibility, shadows), light_groups) if light_groups else []
    sky_vis = _batched(partial(sky_visibility, sky), sky_groups) if sky_groups else []
    vis = [back(v) for back, v in zip(light_back, vis, strict=True)]
    sky_vis = [back(v) for back, v in zip(sky_back, sky_vis, strict=True)]
    layer_vis = vis.pop(0) if geoms and shadows is not None else None
    layer_sky = sky_vis.pop(0) if geoms and sky is not None else None
    out = {"sphere": None, "plane": None}
    for i, (kind, g) in enumerate(geoms):
        v = None if layer_vis is None else layer_vis[i]
        a = None if layer_sky is None else layer_sky[i]
        if kind == "sphere":
            out[kind] = sphere_shade(camera, g, lights, appearance, v, a)
        else:
            out[kind] = plane_shade(camera, g, lights, appearance, plane_color, v, a)
    return FrameLayers(
        out["sphere"], out["plane"], vis[0] if vis else None, sky_vis[0] if sky_vis else None
    )
