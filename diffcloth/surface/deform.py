"""Vertex deformations (seed slides 7, 27): waves and ripples computed from time, displacing
vertices along their normals; normals are then recomputed on the deformed geometry.

Height functions take any coordinates: pass ``surface.uv`` (unitless, material space: the pattern
moves with the cloth) or ``surface.positions`` (m, world space). Recomputed frames come from
central differences of the deformed vertex grid (`grid_frames`), which is what the seed's vertex
shader does ("compute normals on the fly").
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from diffcloth._math import safe_norm, safe_normalize
from diffcloth.surface.tessellate import Surface, grid_frames

__all__ = ["waves", "ripples", "displace_along_normals", "apply_deformations"]


def _check_positive(name: str, value) -> None:
    try:
        bad = not float(value) > 0
    except TypeError:  # a traced value: cannot check eagerly
        return
    if bad:
        raise ValueError(f"{name} must be > 0, got {value!r}")


def waves(points, time, *, amplitude, wavelength, speed=0.0, direction=(1.0, 0.0), phase=0.0):
    """Travelling plane wave h = A sin(2 pi (d . x - speed t) / wavelength + phase).

    Args:
      points: (n, k) coordinates (uv or positions); differentiable.
      time: () s; differentiable.
      amplitude: () height (m); differentiable.
      wavelength: () > 0, in the units of `points`.
      speed: () units of `points` per s.
      direction: (k,) direction of travel (normalised here).
      phase: () rad.
    Returns:
      (n,) heights.
    """
    _check_positive("wavelength", wavelength)
    dtype = points.dtype
    d = safe_normalize(jnp.asarray(direction, dtype))
    x = points @ d
    arg = 2.0 * jnp.pi * (x - speed * time) / wavelength + phase
    return amplitude * jnp.sin(arg)


def ripples(points, time, *, amplitude, wavelength, speed=0.0, center=(0.5, 0.5), decay=0.0):
    """Circular ripple from `center`: h = A exp(-decay r) sin(2 pi (r - speed t) / wavelength).

    Args:
      points: (n, k) coordinates (uv or positions); differentiable.
      time: () s; differentiable.
      amplitude: () height (m); wavelength > 0 and `decay` >= 0 (1/units) in the units of points.
      speed: () outward speed, units of `points` per s.
      center: (k,) origin of the ripple.
    Returns:
      (n,) heights; finite with finite gradients also at the centre.
    """
    _check_positive("wavelength", wavelength)
    c = jnp.asarray(center, points.dtype)
    r = safe_norm(points - c[None, :], axis=-1)
    arg = 2.0 * jnp.pi * (r - speed * time) / wavelength
    return amplitude * jnp.exp(-decay * r) * jnp.sin(arg)


def displace_along_normals(surface: Surface, height) -> Surface:
    """Move every vertex by `height` along its normal and recompute the frames.

    Args:
      surface: a tessellated Surface.
      height: (n,) displacement in m along each vertex normal; differentiable.
    Returns:
      The deformed Surface; normals, tangents and bitangents recomputed from the deformed grid
      (on the same side as the original: see `Surface.flipped`).

    Example:
      >>> h = waves(s.uv, 0.5, amplitude=0.01, wavelength=0.25)  # doctest: +SKIP
      >>> s2 = displace_along_normals(s, h)  # doctest: +SKIP
    """
    height = jnp.asarray(height, surface.positions.dtype)
    if height.shape != surface.positions.shape[:1]:
        raise ValueError(
            f"height must have shape {surface.positions.shape[:1]} (one per vertex), "
            f"got {height.shape}"
        )
    pos = surface.positions + height[:, None] * surface.normals
    n, t, b = grid_frames(pos, surface.grid_shape, flip=surface.flipped)
    return dataclasses.replace(surface, positions=pos, normals=n, tangents=t, bitangents=b)


# deform kind -> (height kernel, its own keyword fields besides amplitude, wavelength, speed)
_KERNELS = {"waves": (waves, ("direction", "phase")), "ripples": (ripples, ("center", "decay"))}


def apply_deformations(surface: Surface, entries, time) -> Surface:
    """Sum of the [[deform]] entries' heights at `time` (s), on the surface's uv, displaced along
    the normals (`displace_along_normals`). entries: objects with the fields of
    `config.render.DeformConfig` (kind "waves" or "ripples"); none: the surface unchanged.

    Shapes: surface positions (n, 3), uv (n, 2); time () s -> Surface (n, 3).
    """
    if not entries:
        return surface
    uv = surface.uv
    h = jnp.zeros(uv.shape[:1], surface.positions.dtype)
    for e in entries:
        if e.kind not in _KERNELS:
            raise ValueError(f"deform kind must be 'waves' or 'ripples', got {e.kind!r}")
        kernel, own = _KERNELS[e.kind]
        keys = ("amplitude", "wavelength", "speed") + own
        h = h + kernel(uv, time, **{k: getattr(e, k) for k in keys})
    return displace_along_normals(surface, h)
