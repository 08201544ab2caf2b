"""Ray-cast analytic spheres as an image layer (premultiplied RGBA and view depth per pixel),
depth-composited with the cloth by `frame.render`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth._math import materialize, safe_sqrt
from diffcloth.render.camera import Camera, pixel_rays, project
from diffcloth.render.lights import Appearance, Lights
from diffcloth.render.rays import _dot3, ray_sphere
from diffcloth.render.sampling import _normalize3
from diffcloth.render.shade import blinn_phong
from diffcloth.render.shadows import ShadowMaps, layer_shadow_visibility
from diffcloth.render.sky import SkyMaps, layer_sky_visibility
from diffcloth.shapes import Sphere


def _spacing(a):
    """(H, W) distance of a per-pixel point or direction (H, W, 3) to its right / lower
    neighbour's, the larger of the two (edge-padded)."""
    dx, dy = jnp.diff(a, axis=1), jnp.diff(a, axis=0)
    sx, sy = jnp.sqrt(_dot3(dx, dx)), jnp.sqrt(_dot3(dy, dy))
    return jnp.maximum(
        jnp.pad(sx, ((0, 0), (0, 1)), mode="edge"), jnp.pad(sy, ((0, 1), (0, 0)), mode="edge")
    )


def sphere_geometry(camera: Camera, spheres: Sphere):
    """Ray-cast spheres' nearest hit per pixel: coverage alpha (H, W) with antialiased rims,
    view depth (H, W) (1e10 where none), point (H, W, 3) m and unit normal (H, W, 3).

    Coverage of a pixel is clip((r - d) / footprint + 1/2, 0, 1) with d the distance from the
    sphere centre to the pixel's ray and footprint the pixel's width at that depth, so the rim is
    a one-pixel ramp and the image is differentiable w.r.t. centre and radius at the silhouette.

    The rays, their spacing and each sphere's hit data are materialized: XLA's CPU fusion would
    otherwise recompute them in every consumer (per channel, per shading term); 0.55x the time
    of the layer jitted alone at 256^2 with one sphere (benchmarks/interactive.py scene), about
    neutral inside the whole `render` program.
    """
    origins, dirs = map(materialize, pixel_rays(camera))
    sph = spheres.batched()
    dtype = origins.dtype
    big = jnp.asarray(1e10, dtype)
    spacing_o, spacing_d = materialize(_spacing(origins)), materialize(_spacing(dirs))

    def one(center, radius):
        c = jnp.reshape(center, (1, 1, 3))
        t, hit, _ = ray_sphere(origins, dirs, c, radius)
        t_close = -_dot3(origins - c, dirs)
        closest = origins + t_close[..., None] * dirs
        dist = safe_sqrt(_dot3(closest - c, closest - c))  # 0, finite gradient, for a ray via c
        footprint = jnp.maximum(spacing_o + jnp.maximum(t_close, 0.0) * spacing_d, 1e-12)
        alpha = jnp.clip((radius - dist) / footprint + 0.5, 0.0, 1.0)
        alpha = jnp.where(t_close > 0, alpha, 0.0)
        rim_point = c + radius * _normalize3(closest - c)
        point = jnp.where(
            hit[..., None], origins + jnp.where(hit, t, 0.0)[..., None] * dirs, rim_point
        )
        point = materialize(point)  # read by the depth and per channel by the normal
        _, depth = project(point, camera)
        return alpha, jnp.where(alpha > 0, depth, big), point, _normalize3(point - c)

    if sph.center.shape[0] == 1:  # one sphere: no nearest-of selection
        alpha, depth, point, normal = map(materialize, one(sph.center[0], sph.radius[0]))
    else:
        alpha, depth, point, normal = jax.vmap(one)(sph.center, sph.radius)  # (ns, H, W, ...)
        nearest = jnp.argmin(depth, axis=0)[None]
        alpha = jnp.take_along_axis(alpha, nearest, axis=0)[0]
        depth = jnp.take_along_axis(depth, nearest, axis=0)[0]
        point = jnp.take_along_axis(point, nearest[..., None], axis=0)[0]
        normal = jnp.take_along_axis(normal, nearest[..., None], axis=0)[0]
    return alpha, depth, point, normal


def sphere_shade(camera: Camera, geometry, lights: Lights, appearance: Appearance, vis, sky_vis):
    """Shade `sphere_geometry`'s layer: premultiplied RGBA (H, W, 4) and view depth (H, W).

    Shapes: vis (H, W, nl) light visibility or None, sky_vis (H, W) ambient visibility or None.
    """
    alpha, depth, point, normal = geometry
    dirs = pixel_rays(camera)[1]
    diffuse, specular = blinn_phong(normal, -dirs, point, lights, appearance, vis)
    amb = jnp.reshape(appearance.ambient * lights.ambient, (1, 1, 3))
    if sky_vis is not None:  # ambient occlusion
        amb = amb * sky_vis[..., None]
    albedo = jnp.reshape(appearance.sphere_color, (1, 1, 3))
    color = albedo * (amb + diffuse) + jnp.reshape(appearance.specular, (1, 1, 3)) * specular
    rgba = jnp.concatenate([color * alpha[..., None], alpha[..., None]], axis=-1)
    return rgba, depth


def _sphere_layer(
    camera: Camera,
    spheres: Sphere,
    lights: Lights,
    appearance: Appearance,
    shadows: ShadowMaps | None = None,
    sky: SkyMaps | None = None,
):
    """Ray-cast spheres alone: premultiplied RGBA (H, W, 4), view depth (H, W)."""
    geometry = sphere_geometry(camera, spheres)
    _, _, point, normal = geometry
    vis = layer_shadow_visibility(shadows, point, normal)
    sky_vis = layer_sky_visibility(sky, point, normal)
    return sphere_shade(camera, geometry, lights, appearance, vis, sky_vis)
