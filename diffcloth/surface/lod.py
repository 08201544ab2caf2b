"""Level of detail: choose a tessellation level from the surface's projected size in pixels.

Pure Python / numpy, so the result is a static int usable as `tessellate(..., level)`. Each level
compiles its own program: quantise (the default rounds up to a power of two) to keep the number of
compiled variants small.
"""

from __future__ import annotations

import math

__all__ = ["auto_level", "focal_length_pixels", "projected_size_pixels", "select_level"]


def focal_length_pixels(fov_y_degrees: float, height_pixels: int) -> float:
    """Focal length in pixels of a perspective camera: height / (2 tan(fov_y / 2)).

    Shapes: none (Python scalars).
    """
    if not 0 < fov_y_degrees < 180:
        raise ValueError(f"fov_y_degrees must be in (0, 180), got {fov_y_degrees!r}")
    if height_pixels <= 0:
        raise ValueError(f"height_pixels must be > 0, got {height_pixels!r}")
    return height_pixels / (2.0 * math.tan(math.radians(fov_y_degrees) / 2.0))


def projected_size_pixels(bounding_radius: float, distance: float, focal_pixels: float) -> float:
    """Approximate on-screen diameter (pixels) of a bounding sphere seen at `distance` (m).

    Uses the exact angular size 2 asin(r / d) of the sphere; inf when the camera is inside it.

    Shapes: none (Python scalars).
    """
    if not bounding_radius >= 0:
        raise ValueError(f"bounding_radius must be >= 0 (m), got {bounding_radius!r}")
    if not distance >= 0:
        raise ValueError(f"distance must be >= 0 (m), got {distance!r}")
    if not focal_pixels > 0:
        raise ValueError(f"focal_pixels must be > 0, got {focal_pixels!r}")
    if distance <= bounding_radius:
        return math.inf
    half_angle = math.asin(bounding_radius / distance)
    return 2.0 * focal_pixels * math.tan(half_angle)


def select_level(
    bounding_radius: float,
    distance: float,
    focal_pixels: float,
    *,
    num_patches: int,
    pixels_per_segment: float = 4.0,
    min_level: int = 2,
    max_level: int = 32,
    power_of_two: bool = True,
) -> int:
    """Tessellation level so that one mesh segment spans about `pixels_per_segment` pixels.

    Args:
      bounding_radius: radius (m) of a sphere bounding the surface.
      distance: camera-to-centre distance (m).
      focal_pixels: focal length in pixels (see `focal_length_pixels`).
      num_patches: patches along the surface's longer direction (cols - 3 for a B-spline net).
      pixels_per_segment: target on-screen edge length in pixels (> 0).
      min_level, max_level: clamp range (min_level >= 2).
      power_of_two: round the level up to a power of two (then clamp) to limit recompiles.
    Returns:
      int level in [min_level, max_level]; max_level when the camera is inside the bound.

    Example:
      >>> select_level(0.5, 3.0, focal_length_pixels(45.0, 512), num_patches=10)
      8
    """
    if num_patches < 1:
        raise ValueError(f"num_patches must be >= 1, got {num_patches!r}")
    if not pixels_per_segment > 0:
        raise ValueError(f"pixels_per_segment must be > 0, got {pixels_per_segment!r}")
    if min_level < 2 or max_level < min_level:
        raise ValueError(
            f"need 2 <= min_level <= max_level, got min_level={min_level}, max_level={max_level}"
        )
    size = projected_size_pixels(bounding_radius, distance, focal_pixels)
    if math.isinf(size):
        return int(max_level)
    level = math.ceil(size / pixels_per_segment / num_patches)
    if power_of_two and level > 1:
        level = 1 << (level - 1).bit_length()
    return int(min(max(level, min_level), max_level))


def auto_level(
    points,
    cameras,
    *,
    net_shape,
    basis: str = "bspline",
    pixels_per_segment: float = 4.0,
    min_level: int = 2,
    max_level: int = 16,
) -> int:
    """Tessellation level for `[render] lod = "auto"`: the largest `select_level` over the
    cameras for the bounding sphere of `points` (e.g. the initial control net, (..., 3) in m).

    Perspective cameras use their eye distance and focal length in pixels (projection[1, 1] H / 2);
    parallel projections use the projected diameter 2 r projection[1, 1] H / 2 directly.
    """
    import numpy as np

    from diffcloth.surface import basis as _basis

    p = np.asarray(points, float).reshape(-1, 3)
    center = 0.5 * (p.min(0) + p.max(0))
    radius = float(np.max(np.linalg.norm(p - center, axis=-1)))
    patches = max(
        _basis.num_patches(int(net_shape[0]), basis), _basis.num_patches(int(net_shape[1]), basis)
    )
    best = min_level
    for cam in cameras:
        focal = float(np.asarray(cam.projection)[1, 1]) * cam.height / 2.0
        if cam.is_perspective:
            view = np.asarray(cam.view)
            eye = -view[:3, :3].T @ view[:3, 3]
            level = select_level(
                radius,
                float(np.linalg.norm(eye - center)),
                focal,
                num_patches=patches,
                pixels_per_segment=pixels_per_segment,
                min_level=min_level,
                max_level=max_level,
            )
        else:
            size = 2.0 * radius * focal
            level = math.ceil(size / pixels_per_segment / patches)
            level = 1 << max(level - 1, 0).bit_length() if level > 1 else level
            level = min(max(level, min_level), max_level)
        best = max(best, int(level))
    return best
