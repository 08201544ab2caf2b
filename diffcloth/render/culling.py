"""Frustum culling by bounding sphere and backface culling by winding (SEEDS.md section 7).

Results are boolean masks (shapes never change under jit); the rasterizer uses them to drop
triangles. Cloth is two-sided by default, so backface culling is opt-in there.
"""

from __future__ import annotations

import jax.numpy as jnp

from diffcloth._math import safe_normalize
from diffcloth.render.camera import Camera, eye_position, view_direction


def frustum_planes(camera: Camera):
    """The six frustum planes in world space with outward unit normals.

    Returns:
      (6, 4) rows (nx, ny, nz, d): a point p is outside plane i when n . p + d > 0.
      Order: left, right, bottom, top, near, far (Gribb-Hartmann extraction from projection @ view).
    """
    m = camera.projection @ camera.view
    rows = [m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]]
    inward = jnp.stack(rows)  # inward . [p, 1] >= 0 inside
    norm = jnp.linalg.norm(inward[:, :3], axis=-1, keepdims=True)
    return -inward / norm


def sphere_in_frustum(center, radius, planes):
    """Bounding-sphere frustum test (the seed's loop over six planes).

    Args:
      center: (..., 3) sphere centres in m; radius: (...) radii in m; planes: (6, 4) from
        `frustum_planes`.
    Returns:
      (...) bool: False when the sphere lies entirely outside some plane (distance > radius).
    """
    center = jnp.asarray(center)
    offset = planes[:, 3].reshape((1,) * (center.ndim - 1) + (6,))
    dist = jnp.einsum("pk,...k->...p", planes[:, :3], center) + offset
    return jnp.all(dist <= jnp.asarray(radius)[..., None], axis=-1)


def bounding_sphere(positions):
    """(center (3,), radius ()) of a point set: centre of the bounding box, max distance to it."""
    center = 0.5 * (positions.min(axis=0) + positions.max(axis=0))
    radius = jnp.sqrt(jnp.max(jnp.sum((positions - center[None]) ** 2, axis=-1)))
    return center, radius


def triangle_normals(positions, faces, normalize: bool = True):
    """(m, 3) face normals from the winding (v1 - v0) x (v2 - v0); unit unless normalize=False."""
    p = positions[faces]
    n = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return safe_normalize(n) if normalize else n


def facing_camera(positions, faces, camera: Camera):
    """(m,) bool: True where a triangle's winding normal faces the camera (counter-clockwise seen).

    The seed's test VPN . N < 0 with VPN taken as the viewing direction: for a perspective camera
    the direction from the eye to the triangle, for parallel projections the camera's -z axis.
    Degenerate (zero-area) triangles count as not facing.
    """
    n = triangle_normals(positions, faces, normalize=False)
    if camera.is_perspective:
        d = positions[faces[:, 0]] - eye_position(camera)[None]
    else:
        d = jnp.broadcast_to(view_direction(camera), n.shape)
    return jnp.sum(d * n, axis=-1) < 0


def backface_mask(positions, faces, camera: Camera):
    """(m,) bool: True for triangles to draw under backface culling (same as `facing_camera`)."""
    return facing_camera(positions, faces, camera)
