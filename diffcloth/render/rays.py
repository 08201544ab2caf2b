"""Ray-sphere intersection, shared by the analytic sphere renderer and the sphere-reflection shader."""

from __future__ import annotations

import jax.numpy as jnp

from diffcloth._math import safe_sqrt


def _dot3(a, b):
    """Dot product over a last axis of 3 (...) written out."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def ray_sphere(origins, directions, center, radius):
    """Nearest forward intersection of rays with one sphere.

    Args:
      origins: (..., 3) ray origins in m.
      directions: (..., 3) unit ray directions.
      center: (3,) sphere centre in m.
      radius: () sphere radius in m.
    Returns:
      (t, hit, discriminant): t (...) distance along the ray to the nearest hit in front of the origin
      (a large finite value where there is none), hit (...) bool, discriminant (...) = radius^2 minus the
      squared distance from the centre to the ray's line (> 0 means the line crosses the sphere;
      it goes to 0 at the sphere's silhouette, which shaders use to fade near the rim).
      Finite values and gradients everywhere.
    """
    oc = origins - center
    # dot products written out: a reduce over a minor axis of 3 is a slow generic loop on CPU
    b = _dot3(oc, directions)
    c = _dot3(oc, oc) - radius * radius
    disc = b * b - c
    root = safe_sqrt(disc)
    t_near = -b - root
    t_far = -b + root
    t = jnp.where(t_near > 0, t_near, t_far)
    hit = (disc > 0) & (t > 0)
    far = jnp.asarray(1e10, t.dtype)
    return jnp.where(hit, t, far), hit, disc
