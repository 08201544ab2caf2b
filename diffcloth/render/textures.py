"""Textures: bilinear and mip-mapped sampling, seamless cube maps, procedural fabric and sky, files.

Conventions
- A 2-D texture is an array (h, w, c). Texture coordinates (u, v) in [0, 1]: u runs along columns
  (left to right), v along rows (v = 0 is row 0, the top of the image). Texel (row i, column j) has
  its centre at u = (j + 0.5) / w, v = (i + 0.5) / h.
- A cube map holds six square faces in OpenGL order +x, -x, +y, -y, +z, -z with OpenGL's
  (sc, tc, ma) face parameterisation (row 0 = t = 0). Faces are stored with a one-texel border from
  from the neighbouring faces, so bilinear filtering is seamless across edges.
- All sampling functions are differentiable w.r.t. the texel values and the coordinates
  (piecewise-linear in the coordinates) and work in float32 and float64.
"""

# ruff: noqa: F401  (re-exports: names moved to sibling modules stay importable here)
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.render.procedural import (
    MINNAERT_EPS,
    _checker_np,
    _grid,
    _weave_np,
    checker,
    minnaert_table,
    sky_cube_map,
    value_noise,
    weave_height,
)
from diffcloth.render.sampling import (
    _FACE_AXIS,
    _FACE_MA,
    _FACE_SC,
    _FACE_TC,
    FACE_NAMES,
    WRAPS,
    CubeMap,
    _bilinear,
    _face_coords,
    _wrap_index,
    _wraps,
    face_directions,
    make_cube_map,
    mip_pyramid,
    sample_2d,
    sample_cube,
    sample_latlong,
    sample_mip,
    uv_lod,
    validate_texture,
)

# ----------------------------------------------------------------------------- files, validation


def srgb_to_linear(x):
    """The sRGB transfer function inverted (for 8-bit colour images).

    Shapes: x (...) in [0, 1] -> (...) elementwise.
    """
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def load_texture(path, *, srgb: bool = False, plugin: str | None = None, dtype=None):
    """Read an image file (PNG, JPEG, EXR/HDR if imageio supports it) as an (h, w, c) float texture.

    Integer images are scaled to [0, 1] (uint8 / 255, uint16 / 65535); float images are kept.
    A grey image gets a channel axis. With srgb=True colours are converted to linear RGB.
    `plugin` is passed to imageio (e.g. "pillow" for float TIFFs); ".npy" files are read with numpy.

    Raises:
      ValueError: the file holds NaN or inf texels.
    """
    import imageio.v3 as iio

    if str(path).endswith(".npy"):
        img = np.load(path)
    else:
        img = np.asarray(iio.imread(path, plugin=plugin))
    if img.dtype.kind in "ui":
        img = img.astype(np.float64) / np.iinfo(img.dtype).max
    img = img.astype(np.float64)
    if img.ndim == 2:
        img = img[..., None]
    validate_texture(img, f"texture file {path}")
    if srgb:
        img[..., :3] = srgb_to_linear(img[..., :3])
    return jnp.asarray(img, dtype or jnp.zeros(()).dtype)


def load_cube_map(paths, *, srgb: bool = False, dtype=None) -> CubeMap:
    """Six image files in order +x, -x, +y, -y, +z, -z -> CubeMap.

    Shapes: six files -> CubeMap faces (6, s + 2, s + 2, c).
    """
    if len(paths) != 6:
        raise ValueError(
            f"load_cube_map needs 6 face files (+x, -x, +y, -y, +z, -z), got {len(paths)}"
        )
    faces = np.stack([np.asarray(load_texture(p, srgb=srgb, dtype=dtype)) for p in paths])
    return make_cube_map(faces)


# ----------------------------------------------------------------------------- texture set


def height_slopes(height):
    """Per-texel central-difference slopes (dh/du, dh/dv) of a tiling height map: (h, w, 2)."""
    xp = np if isinstance(height, np.ndarray) else jnp
    h = height[..., 0]
    du = 0.5 * (xp.roll(h, -1, axis=1) - xp.roll(h, 1, axis=1))
    dv = 0.5 * (xp.roll(h, -1, axis=0) - xp.roll(h, 1, axis=0))
    return xp.stack([du, dv], axis=-1)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Textures:
    """The textures a shading mode may read; any of them may be None.

    Attributes:
      color: mip pyramid (tuple) of (h, w, 4) RGBA colour textures (wrap repeat).
      bump: mip pyramid of (h, w, 2) height slopes in height units per texel (wrap repeat).
      env: environment CubeMap (c = 3).
      minnaert: (n, n, 1) Minnaert table F(N.L along u, N.E along v) (wrap clamp); None = build from
        appearance.minnaert_k at `minnaert_size`.
      tiling: (2,) uv multiplier applied before colour and bump lookups.
    """

    color: tuple | None = None
    bump: tuple | None = None
    env: CubeMap | None = None
    minnaert: jax.Array | None = None
    tiling: jax.Array | None = None


def make_textures(
    *,
    color=None,
    height=None,
    env=None,
    minnaert=None,
    tiling=(1.0, 1.0),
    mip: bool = True,
    dtype=None,
) -> Textures:
    """Validated constructor.

    Args:
      color: (h, w, 3 or 4) colour texture (alpha 1 is appended to RGB).
      height: (h, w, 1) or (h, w) height map in [0, 1] (stored as slopes; all-zero is flat).
      env: CubeMap or six (s, s, 3) faces.
      minnaert: (n, n) or (n, n, 1) custom F table.
      tiling: repeats of the colour / bump textures across the surface's uv range.
      mip: build mip pyramids for colour and bump (else a single level).
    Raises:
      ValueError for NaN / inf texels or bad shapes.
    """
    dtype = dtype or jnp.zeros(()).dtype
    levels = None if mip else 1
    c = b = e = m = None
    if color is not None:
        validate_texture(color, "color texture")
        c = np.asarray(color, np.float64)
        if c.ndim != 3 or c.shape[-1] not in (3, 4):
            raise ValueError(f"color texture must have shape (h, w, 3|4), got {c.shape}")
        if c.shape[-1] == 3:
            c = np.concatenate([c, np.ones((*c.shape[:2], 1))], axis=-1)
        c = tuple(jnp.asarray(level, dtype) for level in mip_pyramid(c, levels))
    if height is not None:
        validate_texture(height, "height texture")
        h = np.asarray(height, np.float64)
        if h.ndim == 2:
            h = h[..., None]
        if h.ndim != 3 or h.shape[-1] != 1:
            raise ValueError(f"height texture must have shape (h, w) or (h, w, 1), got {h.shape}")
        b = tuple(jnp.asarray(level, dtype) for level in mip_pyramid(height_slopes(h), levels))
    if env is not None:
        e = env if isinstance(env, CubeMap) else make_cube_map(np.asarray(env, dtype))
    if minnaert is not None:
        validate_texture(minnaert, "minnaert table")
        m = jnp.asarray(minnaert, dtype)
        if m.ndim == 2:
            m = m[..., None]
    t = np.asarray(tiling, np.float64)
    if t.shape != (2,) or not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise ValueError(f"tiling must be two finite numbers > 0, got {t.tolist()}")
    return Textures(color=c, bump=b, env=e, minnaert=m, tiling=jnp.asarray(t, dtype))


def default_textures(
    *, size: int = 128, threads: int = 16, tiling=(4.0, 4.0), dtype=None
) -> Textures:
    """Default cloth look, no files: tinted weave colour, weave bump, procedural sky cube map.

    Shapes: -> Textures: colour (size, size, 3), height (size, size), sky (6, 34, 34, 3).
    """
    dtype = dtype or jnp.zeros(()).dtype
    h = _weave_np(size, threads)
    color = _checker_np(size, 2, (1.0, 1.0, 1.0), (0.8, 0.85, 1.0))
    color[..., :3] *= 0.75 + 0.25 * h
    color[..., 3] = 0.4 + 0.6 * h[..., 0]
    return make_textures(
        color=color, height=h, env=sky_cube_map(32, dtype=dtype), tiling=tiling, dtype=dtype
    )
