"""Static geometry and camera, many appearances: rasterize once, shade many times.

`render` rasterizes the surface on every call (setup, visibility, resolve, silhouette search:
most of a frame's time). When only the appearance, lights or textures change (an appearance fit
of a fixed captured cloth, a material or light sweep, an interactive material editor), that work
depends on nothing that changes: `prepare_frame` does it once and `render_prepared` only shades,
antialiases (with the antialiasing weights also computed once) and composites over the
background. The image equals `render`'s for the same inputs (cloth only: no spheres, planes,
boxes, shadows or ambient occlusion, which `render` handles).

    prep = prepare_frame(surface, camera)                      # geometry + camera only
    img = render_prepared(prep, lights, "phong", appearance)   # differentiable in lights,
                                                               # appearance, textures

No gradient reaches the geometry through a prepared frame (use `render` for that).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from diffcloth._math import materialize
from diffcloth.render.camera import Camera
from diffcloth.render.lights import Appearance, Lights
from diffcloth.render.raster import GBuffer, antialias, antialias_weights
from diffcloth.render.shade import MODES, ShadingBuffer, shade
from diffcloth.render.textures import Textures

__all__ = ["PreparedFrame", "prepare_frame", "render_prepared"]


class PreparedFrame(NamedTuple):
    """What a frame's shading needs from the geometry and camera. All (H, W, ...).

    shading: ShadingBuffer (position, normal, tangent, bitangent, uv, mask; face_normal when
      prepared for mode "flat").
    raster: GBuffer of the rasterizer (ids, depth, crossings, front_facing).
    eye: (H, W, 3) unit vectors toward the viewer.
    weights: (4, H, W) silhouette antialiasing weights (`raster.antialias_weights`).
    """

    shading: ShadingBuffer
    raster: GBuffer
    eye: jax.Array
    weights: jax.Array


def prepare_frame(
    surface,
    camera: Camera,
    *,
    shading: str = "phong",
    two_sided: bool = True,
    cull_backfaces: bool = False,
    max_tiles: int | None = None,
) -> PreparedFrame:
    """Rasterize a Surface once for `render_prepared` (arguments as in `render`).

    Args:
      surface: a `diffcloth.surface.Surface` (or any object with its attributes).
      camera: a `Camera`.
      shading: static; the mode the frame will be shaded with ("flat" also stores face normals).
        Every mode of `shade.MODES` except "gouraud" (its per-vertex lighting depends on the
        lights: use `render`).
    Returns:
      PreparedFrame of (H, W, ...) arrays (surface positions (n, 3) m); pass it to
      `render_prepared` (inside or outside jit).
    """
    from diffcloth.render.frame import surface_gbuffer

    if shading not in MODES:
        raise ValueError(f"shading must be one of {MODES}, got {shading!r}")
    if shading == "gouraud":
        raise ValueError(
            "prepare_frame: shading 'gouraud' lights the vertices (depends on the lights); "
            "use render() for it"
        )
    gb, buf, eye = surface_gbuffer(
        surface,
        camera,
        None,
        None,
        shading=shading,
        two_sided=two_sided,
        cull_backfaces=cull_backfaces,
        max_tiles=max_tiles,
    )
    dtype = gb.position.dtype
    return PreparedFrame(gb, buf, eye, antialias_weights(buf, dtype))


def render_prepared(
    prepared: PreparedFrame,
    lights: Lights,
    shading: str,
    appearance: Appearance,
    *,
    textures: Textures | None = None,
    background=(0.0, 0.0, 0.0),
    refraction: str = "shortened",
    antialiased: bool = True,
):
    """Shade a prepared frame: `render`'s image of the prepared surface and camera.

    Args:
      prepared: from `prepare_frame`.
      lights, appearance, textures: differentiable as in `render`; lights must not cast shadows.
      shading: static mode (as prepared; "flat" needs a frame prepared for "flat").
      background, refraction, antialiased: as in `render`.
    Returns:
      (H, W, 4) linear RGB and alpha = coverage, composited over `background` unless None.
    """
    if shading not in MODES or shading == "gouraud":
        raise ValueError(
            f"render_prepared: shading must be one of {MODES} except 'gouraud', got {shading!r}"
        )
    if shading == "flat" and prepared.shading.face_normal is None:
        raise ValueError("render_prepared: shading 'flat' needs prepare_frame(..., shading='flat')")
    if lights.casts_shadows:
        raise ValueError(
            "render_prepared: lights with shadows need the shadow maps of render(); "
            "build them without shadows or use render()"
        )
    img = shade(
        prepared.shading,
        prepared.eye,
        lights,
        appearance,
        mode=shading,
        textures=textures,
        spheres=None,
        refraction=refraction,
    )
    if antialiased:
        img = antialias(materialize(img), prepared.raster, prepared.weights.astype(img.dtype))
    if background is not None:
        bg = jnp.reshape(jnp.asarray(background, img.dtype), (1, 1, 3))
        img = jnp.concatenate([img[..., :3] + (1.0 - img[..., 3:]) * bg, img[..., 3:]], axis=-1)
    return img
