"""Does a texture's detail survive mip filtering at the image's resolution?

Trilinear mip filtering averages texels that fall inside one pixel, as it should: a 16-thread
weave tiled 4 x 4 across a cloth that spans 40 pixels puts ~1.6 threads in every pixel, so the
bump slopes (which alternate in sign from thread to thread) average to ~0 and bump_strength has
no effect on the image (issue 14 measured d(loss)/d(bump_strength) = -4e-22 at 64^2). That is
physically fair, but a fit of bump_strength then cannot move. `bump_detail` measures how much of
the slope signal is left; `check_bump_detail` warns before such a fit. Remedies: fewer texture
repeats (`make_textures(tiling=...)`, config `[render] texture_tiling`), or more pixels.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["BumpDetailWarning", "bump_detail", "check_bump_detail"]


class BumpDetailWarning(UserWarning):
    """The bump map is filtered away at this resolution: bump_strength has ~no gradient."""


def bump_detail(surface, camera, textures) -> float:
    """Fraction (0..1) of the bump map's slope signal left after mip filtering, over the pixels
    that see the surface: RMS of the filtered slopes / RMS of the level-0 slopes at the same uv.
    1 when every texel is resolved, ~0 when the weave is averaged away. nan without a bump map or
    covered pixels.

    Shapes: surface positions (n, 3), uv (n, 2) -> a Python float ().
    """
    if textures is None or textures.bump is None:
        return float("nan")
    f2, s2 = (float(a) for a in _slope_power(surface, camera, textures))
    return float(np.sqrt(f2 / s2)) if s2 > 0 else float("nan")


@jax.jit
def _slope_power(surface, camera, textures):
    """(mean squared filtered slope, mean squared level-0 slope) over covered pixels."""
    from diffcloth.render.frame import surface_gbuffer
    from diffcloth.render.lights import make_appearance, make_lights
    from diffcloth.render.textures import sample_2d, sample_mip, uv_lod

    dtype = surface.positions.dtype
    gb, _, _ = surface_gbuffer(
        surface, camera, make_lights(dtype=dtype), make_appearance(dtype=dtype)
    )
    tiling = textures.tiling if textures.tiling is not None else jnp.ones(2, dtype)
    uv = gb.uv * jnp.reshape(tiling, (1, 1, 2))
    lod = uv_lod(uv, gb.mask, textures.bump[0].shape)
    filtered = sample_mip(textures.bump, uv, lod, wrap="repeat")
    full = sample_2d(textures.bump[0], uv, wrap="repeat")
    m = (gb.mask > 0)[..., None]
    count = jnp.maximum(jnp.sum(m) * filtered.shape[-1], 1)
    return (
        jnp.sum(jnp.where(m, filtered**2, 0.0)) / count,
        jnp.sum(jnp.where(m, full**2, 0.0)) / count,
    )


def check_bump_detail(scene, names, *, threshold: float = 0.1) -> float | None:
    """Warn (BumpDetailWarning) when `names` includes "bump_strength" and, in every camera, less
    than `threshold` of the bump signal survives mip filtering on the scene's first rendered
    state. Returns the best camera's `bump_detail`, or None when not applicable.

    Shapes: none (a Scene in, a Python float () or None out).
    """
    if "bump_strength" not in names or scene.textures is None or scene.textures.bump is None:
        return None
    from diffcloth import surface as surf_mod

    surf = surf_mod.tessellate(scene.state.x, scene.level, scene.basis, flip=scene.flip)
    best = max(bump_detail(surf, cam, scene.textures) for cam in scene.cameras)
    if not best >= threshold:
        tiling = scene.textures.tiling
        tiling = None if tiling is None else np.asarray(tiling).tolist()
        warnings.warn(
            f"bump_strength: only {best:.2g} of the bump map's slope signal survives mip "
            f"filtering at {scene.image_shape[1]} x {scene.image_shape[0]} px (texture tiling "
            f"{tiling}): the weave is averaged away, so the image barely depends on "
            "bump_strength and its gradient is ~0. Use fewer repeats ([render] texture_tiling, "
            "e.g. [1, 1]) or a larger image.",
            BumpDetailWarning,
            stacklevel=3,
        )
    return best
