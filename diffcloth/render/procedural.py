"""Procedural textures: weave height, checker, value noise, the sky cube map and the Minnaert
lookup table (`textures` re-exports every name)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.render.sampling import CubeMap, face_directions, make_cube_map, sample_2d

# ----------------------------------------------------------------------------- procedural


def _grid(size):
    c = (np.arange(size) + 0.5) / size
    v, u = np.meshgrid(c, c, indexing="ij")
    return u, v


def weave_height(size: int = 64, threads: int = 8, *, dtype=None):
    """Plain-weave fabric height map in [0, 1]: warp and weft threads alternating over / under.

    Returns:
      (size, size, 1); tiles seamlessly (use wrap="repeat").
    """
    return jnp.asarray(_weave_np(size, threads), dtype or jnp.zeros(()).dtype)


def _weave_np(size, threads):
    u, v = _grid(size)
    a = np.abs(np.sin(np.pi * threads * u))  # warp threads: ridges across u
    b = np.abs(np.sin(np.pi * threads * v))  # weft threads: ridges across v
    over = np.sin(np.pi * threads * u) * np.sin(np.pi * threads * v) > 0
    h = np.where(over, a * (0.55 + 0.45 * b), b * (0.55 + 0.45 * a))
    h = (h - h.min()) / max(h.max() - h.min(), 1e-12)
    return h[..., None]


def checker(
    size: int = 64,
    squares: int = 8,
    color0=(0.9, 0.9, 0.85),
    color1=(0.5, 0.1, 0.15),
    *,
    dtype=None,
):
    """RGBA checkerboard with `squares` squares per side, alpha 1. Returns (size, size, 4)."""
    rgba = _checker_np(size, squares, color0, color1)
    return jnp.asarray(rgba, dtype or jnp.zeros(()).dtype)


def _checker_np(size, squares, color0, color1):
    u, v = _grid(size)
    odd = (np.floor(u * squares) + np.floor(v * squares)) % 2 == 1
    rgb = np.where(odd[..., None], np.asarray(color1, float), np.asarray(color0, float))
    return np.concatenate([rgb, np.ones((size, size, 1))], axis=-1)


def value_noise(key, size: int = 64, *, cells: int = 4, octaves: int = 4, dtype=None):
    """Tileable fractal value noise in [0, 1]: bilinearly upsampled random grids, halving amplitude.

    Args:
      key: a jax.random key (first argument by convention).
    Returns:
      (size, size, 1).
    """
    dtype = dtype or jnp.zeros(()).dtype
    u, v = _grid(size)
    uv = jnp.asarray(np.stack([u, v], -1), dtype)
    total = jnp.zeros((size, size, 1), dtype)
    norm = 0.0
    for o in range(octaves):
        key, sub = jax.random.split(key)
        n = cells * 2**o
        grid = jax.random.uniform(sub, (n, n, 1), dtype)
        amp = 0.5**o
        total = total + amp * sample_2d(grid, uv, wrap="repeat")
        norm += amp
    return total / norm


def sky_cube_map(
    size: int = 32,
    *,
    zenith=(0.25, 0.45, 0.85),
    horizon=(0.85, 0.9, 0.95),
    ground=(0.3, 0.25, 0.2),
    sun_direction=(0.3, 1.0, 0.6),
    sun_color=(1.0, 0.95, 0.8),
    sun_sharpness: float = 200.0,
    dtype=None,
) -> CubeMap:
    """Procedural sky: zenith-to-horizon gradient, darker ground, a sun glow. No files needed.

    Shapes: colours (3,), sun_direction (3,) -> CubeMap faces (6, size + 2, size + 2, 3).
    """
    d = face_directions(size)
    y = d[..., 1:2]
    sky = np.asarray(horizon) + (np.asarray(zenith) - np.asarray(horizon)) * np.sqrt(
        np.clip(y, 0, 1)
    )
    gnd = np.asarray(ground) + (np.asarray(horizon) - np.asarray(ground)) * np.exp(
        8 * np.minimum(y, 0)
    )
    rgb = np.where(y >= 0, sky, gnd)
    sun = np.asarray(sun_direction, float)
    sun = sun / np.linalg.norm(sun)
    glow = np.clip(d @ sun, 0, 1)[..., None] ** sun_sharpness
    rgb = rgb + glow * np.asarray(sun_color)
    return make_cube_map(np.asarray(rgb, dtype or jnp.zeros(()).dtype))


def minnaert_table(k, size: int = 32):
    """The seed's generated Minnaert table F(x = N.L, y = N.E) = max(x, e)^(k-1) max(y, e)^(k-1).

    Texel centres sample x along u and y along v over [0, 1] (sample with wrap="clamp"). Built from
    the array `k`, so a table made inside a traced function is differentiable w.r.t. k.

    Returns:
      (size, size, 1).
    """
    k = jnp.asarray(k)
    c = jnp.asarray((np.arange(size) + 0.5) / size, k.dtype if k.dtype.kind == "f" else None)
    fx = jnp.power(jnp.maximum(c, MINNAERT_EPS), k - 1)
    return (fx[:, None] * fx[None, :])[..., None]


MINNAERT_EPS = 1e-3  # cosines are clamped to this before pow(cos, k - 1) (ROBUSTNESS row 22)
