"""Shadow and ambient-occlusion quality presets: how big the maps are and how they are filtered.

`[render] shadow_quality` (config) / `render(..., shadow_quality=...)`:

* "full" (default): the light's shadow map at `shadow_map_size` texels with percentage-closer
  soft shadows (a blocker search, then 4 x 4 bilinear taps whose radius follows the light's
  softness); the sky maps of ambient occlusion at `shadow_map_size // 2` texels with 3 x 3 taps,
  spheres occluding each sky direction.
* "fit": what a fit can afford (docs/shading.md, "Shadows and occlusion at fit speed"). The
  light's map is sized to half the image (the larger camera side rounded up to 8, halved, at
  least 32 and at most `shadow_map_size` texels) and looked up with one bilinear tap (a penumbra
  of about two pixels: near the sharp shadow of a path tracer's directional light, box-filtered
  by the pixels; on the ray-cast spheres and planes once per 2 x 2 pixels, upsampled
  bilinearly: `shadows.layer_shadow_visibility`; on the cloth at its vertices, interpolated
  by the rasterizer: `ShadowMaps.per_vertex`), the occluder
  rasterized into it decimated to triangles about two texels wide (`decimated_grid`), the sphere
  discs' angles from polynomial arctangents (`_math.fast_atan2`). Ambient occlusion uses no maps
  at all: closed forms (`render.sky_discs`: the cloth as discs at the vertices of a grid of at
  most 16 a side and at most one a FIT_DISC_PIXELS pixels of the image's side (12 at 64^2),
  spheres by their exact form factor, planes hiding half the directions), any
  `ambient_occlusion` > 0 turning it on; on the cloth at its vertices (both sides), interpolated
  by the rasterizer (a lower resolution that never bleeds across a silhouette; on a grid surface
  at 16 x 16 of its vertices, interpolated along the grid), on the ray-cast spheres and planes
  on 16 x 16 pixels (every 4th at least), upsampled bilinearly (`sky.layer_sky_visibility`).
  The image stays continuous in every parameter.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

#: allowed values of `shadow_quality`
SHADOW_QUALITIES = ("full", "fit")
#: smallest sky-map size of the "fit" preset, texels
FIT_SKY_MIN = 32
#: pixel stride of the "fit" preset's occlusion on the ray-cast spheres and planes: at least
#: FIT_LAYER_STRIDE, and at most FIT_LAYER_GRID evaluations a side
FIT_LAYER_STRIDE = 4
FIT_LAYER_GRID = 16
#: the "fit" preset's light-map lookups on the ray-cast spheres and planes: once per 2 x 2 pixels
FIT_SHADOW_STRIDE = 2
#: image pixels a side per occluding disc of the "fit" preset's ambient occlusion (at most
#: `sky_discs.DISC_GRID`, at least 8 discs a side): their cost is receivers x discs, and at 64^2
#: 12 discs a side changed the benchmark frame by 6e-5 RMS against 16 (benchmarks/shading.py
#: scene)
FIT_DISC_PIXELS = 5


@dataclasses.dataclass(frozen=True)
class ShadowSettings:
    """Static map sizes (texels) and filter taps per axis of the light and sky maps."""

    map_size: int
    taps: int
    sky_size: int
    sky_taps: int
    analytic_spheres: bool
    fast: bool = False
    sky_per_vertex: bool = False
    sky_layer_stride: int = 1
    decimate: bool = False
    sky_analytic: bool = False
    layer_stride: int = 1
    light_per_vertex: bool = False
    disc_grid: int = 16


def shadow_settings(quality: str, shadow_map_size: int, image_size: int) -> ShadowSettings:
    """The map sizes and filters of a quality preset (module docstring).

    Args:
      quality: one of SHADOW_QUALITIES.
      shadow_map_size: the configured light-map size (texels): "full" uses it, "fit" at most it.
      image_size: the largest camera side in pixels (what "fit" sizes its maps to).

    Shapes: none (Python ints and a string in, a ShadowSettings out).
    """
    from diffcloth.render.sky import SKY_TAPS
    from diffcloth.render.sky_discs import DISC_GRID

    if quality == "full":
        return ShadowSettings(
            int(shadow_map_size), 4, max(int(shadow_map_size) // 2, 8), SKY_TAPS, False
        )
    if quality == "fit":
        side = max(16, -(-int(image_size) // 8) * 8)
        size = min(int(shadow_map_size), max(32, side // 2))
        sky = max(FIT_SKY_MIN, side // 4)
        stride = max(FIT_LAYER_STRIDE, side // FIT_LAYER_GRID)
        discs = min(DISC_GRID, max(8, side // FIT_DISC_PIXELS))
        return ShadowSettings(
            size, 1, sky, 1, True, True, True, stride, True, True, FIT_SHADOW_STRIDE,
            light_per_vertex=True, disc_grid=discs,
        )  # fmt: skip
    raise ValueError(f"shadow_quality must be one of {SHADOW_QUALITIES}, got {quality!r}")


def frame_maps(
    surface,
    lights,
    ambient_occlusion: int,
    *,
    quality: str = "full",
    shadow_map_size: int = 256,
    image_size: int = 256,
    spheres=None,
    occluders=None,
    planes=None,
):
    """The light and sky maps of one frame at a quality preset, shared by its cameras.

    Args:
      surface: the cloth Surface (occluder; plus `occluders` triangles (positions, faces)).
      lights: Lights (maps only for those with shadows).
      ambient_occlusion: static number K of sky directions (0: no sky maps).
      quality, shadow_map_size, image_size: see `shadow_settings`.
      spheres, planes: analytic occluders (planes block the sky only).
    Returns:
      (ShadowMaps or None, SkyMaps or None), as `frame.frame_shadow_maps` and
      `sky.frame_sky_maps`.

    Shapes: surface positions (n, 3) m -> maps (lights, S, S, 2), sky maps (K, S', S', 2).
    """
    from diffcloth.render.frame import frame_shadow_maps
    from diffcloth.render.sky import frame_sky_maps

    st = shadow_settings(quality, shadow_map_size, image_size)
    coarse = decimated_grid if st.decimate else lambda s, _: s
    maps = frame_shadow_maps(
        coarse(surface, st.map_size),
        lights,
        spheres=spheres,
        occluders=occluders,
        size=st.map_size,
        taps=st.taps,
        fast=st.fast,
        layer_stride=st.layer_stride,
        per_vertex=st.light_per_vertex,
    )
    sky = frame_sky_maps(
        coarse(surface, 2 * st.disc_grid if st.sky_analytic else st.sky_size),
        ambient_occlusion,
        spheres=spheres,
        occluders=occluders,
        planes=planes,
        size=st.sky_size,
        taps=st.sky_taps,
        analytic_spheres=st.analytic_spheres,
        per_vertex=st.sky_per_vertex,
        layer_stride=st.sky_layer_stride,
        analytic=st.sky_analytic,
    )
    return maps, sky


class GridMesh(NamedTuple):
    """A grid surface's occluder mesh: (n, 3) positions, (m, 3) faces, static grid shape."""

    positions: object
    faces: object
    grid_shape: tuple
    flipped: bool


def decimated_grid(surface, map_size: int):
    """The occluder a map of `map_size` texels needs: a tessellated grid surface keeps every s-th
    vertex row and column (and the last), s the smallest stride that leaves at most
    map_size / 2 vertices a side (triangles about two texels wide: a finer mesh only adds
    rasterizer work); other meshes, and grids already that coarse, are returned unchanged.
    Differentiable (a gather of the positions).

    Shapes: surface positions (vrows * vcols, 3) m -> positions (r * c, 3), faces (m', 3).
    """
    from diffcloth.surface.tessellate import grid_faces_np

    shape = getattr(surface, "grid_shape", None)
    if shape is None:
        return surface
    vrows, vcols = int(shape[0]), int(shape[1])
    limit = max(int(map_size) // 2, 4)
    stride = max(-(-(max(vrows, vcols) - 1) // (limit - 1)), 1)
    if stride == 1:
        return surface
    rows = np.unique(np.r_[0:vrows:stride, vrows - 1])
    cols = np.unique(np.r_[0:vcols:stride, vcols - 1])
    pos = jnp.reshape(surface.positions, (vrows, vcols, 3))[rows][:, cols].reshape(-1, 3)
    flipped = bool(getattr(surface, "flipped", False))
    faces = grid_faces_np(len(rows), len(cols))
    faces = np.ascontiguousarray(faces[:, ::-1] if flipped else faces)
    return GridMesh(pos, jnp.asarray(faces), (len(rows), len(cols)), flipped)
