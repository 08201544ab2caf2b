"""The ray-cast layers of a frame (spheres and ground planes), lit with one batched lookup.

`frame.render` composites the cloth with these layers by depth. Both layers' receivers (a hit
point and normal per pixel) are known from the camera and the shapes alone, so their light
visibility and ambient occlusion are looked up together: one `layer_shadow_visibility` and one
`layer_sky_visibility` over the stacked (2, H, W) receivers instead of one per layer (each
lookup is a few hundred small XLA operations, forward and backward: at 64^2 their count, not
their size, sets the cost of a shadowed frame).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth.render.camera import Camera, pixel_rays, project
from diffcloth.render.lights import Appearance, Lights
from diffcloth.render.shade import blinn_phong
from diffcloth.render.shadows import ShadowMaps, layer_shadow_visibility
from diffcloth.render.sky import SkyMaps, layer_sky_visibility
from diffcloth.render.sphere_layer import sphere_geometry, sphere_shade
from diffcloth.shapes import Plane, Sphere


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


def layer_lighting(shadows: ShadowMaps | None, sky: SkyMaps | None, points, normals):
    """Light visibility and ambient visibility of L ray-cast layers, one lookup of each.

    Shapes: points (L, H, W, 3) m, normals (L, H, W, 3) -> a list of L pairs
    (vis (H, W, nl) or None, sky_vis (H, W) or None).
    """
    vis = layer_shadow_visibility(shadows, points, normals)
    sky_vis = layer_sky_visibility(sky, points, normals)
    return [
        (None if vis is None else vis[i], None if sky_vis is None else sky_vis[i])
        for i in range(points.shape[0])
    ]


def ray_cast_layers(
    camera: Camera,
    lights: Lights,
    appearance: Appearance,
    *,
    spheres: Sphere | None = None,
    planes: Plane | None = None,
    plane_color=(0.6, 0.6, 0.6),
    shadows: ShadowMaps | None = None,
    sky: SkyMaps | None = None,
):
    """The sphere layer and the plane layer of a frame (each None when absent): premultiplied
    RGBA (H, W, 4) and view depth (H, W) each, their lighting looked up together.

    Shapes: spheres (k,), planes (npl,) -> ((H, W, 4), (H, W)) or None, twice.
    """
    geoms = []
    if spheres is not None:
        geoms.append(("sphere", sphere_geometry(camera, spheres)))
    if planes is not None:
        geoms.append(("plane", plane_geometry(camera, planes)))
    if not geoms:
        return None, None
    points = jnp.stack([g[2] for _, g in geoms])
    normals = jnp.stack([g[3] for _, g in geoms])
    lit = layer_lighting(shadows, sky, points, normals)
    out = {"sphere": None, "plane": None}
    for (kind, g), (vis, sky_vis) in zip(geoms, lit, strict=True):
        if kind == "sphere":
            out[kind] = sphere_shade(camera, g, lights, appearance, vis, sky_vis)
        else:
            out[kind] = plane_shade(camera, g, lights, appearance, plane_color, vis, sky_vis)
    return out["sphere"], out["plane"]
