"""Shadow and ambient-occlusion quality presets: how big the maps are and how they are filtered.

`[render] shadow_quality` (config) / `render(..., shadow_quality=...)`:

* "full" (default): the light's shadow map at `shadow_map_size` texels with percentage-closer
  soft shadows (a blocker search, then 4 x 4 bilinear taps whose radius follows the light's
  softness); the sky maps of ambient occlusion at `shadow_map_size // 2` texels with 3 x 3 taps,
  spheres occluding each sky direction.
* "fit": what a fit can afford (docs/performance.md, "Shadows and occlusion at fit speed"). The
  light's map is sized to the image (the larger camera side, rounded up to 8 texels, at most
  `shadow_map_size`) and looked up with one bilinear tap (a penumbra of about one texel: the
  sharp shadow of a path tracer's directional light, box-filtered by the pixels); the sky maps
  have a quarter of that (at least 32 texels: ambient occlusion is low-frequency) and one tap
  each; spheres occlude the sky analytically (their exact form factor, `sky.sphere_form_factor`)
  and shadow the light with polynomial arctangents (`_math.fast_atan2`); the cloth's occlusion
  is evaluated at its vertices and interpolated (a lower resolution that never bleeds across a
  silhouette: the interpolation stays inside each triangle), and the spheres' and planes' at every
  4th pixel, upsampled bilinearly (`sky.layer_sky_visibility`).
  The image stays continuous in every parameter: bilinear taps and antialiased map coverage.
"""

from __future__ import annotations

import dataclasses

#: allowed values of `shadow_quality`
SHADOW_QUALITIES = ("full", "fit")
#: smallest sky-map size of the "fit" preset, texels
FIT_SKY_MIN = 32
#: pixel stride of the "fit" preset's occlusion on the ray-cast spheres and planes
FIT_LAYER_STRIDE = 4


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


def shadow_settings(quality: str, shadow_map_size: int, image_size: int) -> ShadowSettings:
    """The map sizes and filters of a quality preset (module docstring).

    Args:
      quality: one of SHADOW_QUALITIES.
      shadow_map_size: the configured light-map size (texels): "full" uses it, "fit" at most it.
      image_size: the largest camera side in pixels (what "fit" sizes its maps to).

    Shapes: none (Python ints and a string in, a ShadowSettings out).
    """
    from diffcloth.render.sky import SKY_TAPS

    if quality == "full":
        return ShadowSettings(
            int(shadow_map_size), 4, max(int(shadow_map_size) // 2, 8), SKY_TAPS, False
        )
    if quality == "fit":
        side = max(16, -(-int(image_size) // 8) * 8)
        size = min(int(shadow_map_size), side)
        sky = max(FIT_SKY_MIN, side // 4)
        return ShadowSettings(size, 1, sky, 1, True, True, True, FIT_LAYER_STRIDE)
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
    maps = frame_shadow_maps(
        surface,
        lights,
        spheres=spheres,
        occluders=occluders,
        size=st.map_size,
        taps=st.taps,
        fast=st.fast,
    )
    sky = frame_sky_maps(
        surface,
        ambient_occlusion,
        spheres=spheres,
        occluders=occluders,
        planes=planes,
        size=st.sky_size,
        taps=st.sky_taps,
        analytic_spheres=st.analytic_spheres,
        per_vertex=st.sky_per_vertex,
        layer_stride=st.sky_layer_stride,
    )
    return maps, sky
