"""Geometric primitives shared by physics, surface and render: spheres and planes.

They are plain pytrees of arrays (differentiable centres, radii, normals, offsets). A single
`Sphere` may also hold a batch: `center` (n, 3) and `radius` (n,).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Sphere:
    """Sphere(s). center: (3,) or (n, 3) in m; radius: () or (n,) in m (>= 0)."""

    center: jax.Array
    radius: jax.Array

    def batched(self) -> Sphere:
        """The same sphere(s) with a leading batch axis: center (n, 3), radius (n,)."""
        return Sphere(jnp.reshape(self.center, (-1, 3)), jnp.reshape(self.radius, (-1,)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Plane:
    """Half-space boundary {p : normal . p = offset}; the free side is normal . p > offset.

    normal: (3,) or (n, 3), unit length; offset: () or (n,) in m.
    """

    normal: jax.Array
    offset: jax.Array

    def batched(self) -> Plane:
        return Plane(jnp.reshape(self.normal, (-1, 3)), jnp.reshape(self.offset, (-1,)))


def make_sphere(center, radius, dtype=None) -> Sphere:
    """Validated constructor. Raises ValueError for a negative or non-finite radius."""
    c = np.asarray(center, dtype=np.float64)
    r = np.asarray(radius, dtype=np.float64)
    if c.shape[-1:] != (3,):
        raise ValueError(f"sphere center must have shape (3,) or (n, 3), got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError(f"sphere center must be finite, got {c.tolist()}")
    if not np.all(np.isfinite(r)) or np.any(r < 0):
        raise ValueError(
            f"sphere radius must be finite and >= 0 (allowed range [0, inf)), got {r.tolist()}"
        )
    dtype = dtype or jnp.zeros(()).dtype
    return Sphere(jnp.asarray(c, dtype), jnp.asarray(r, dtype))


def make_plane(normal, offset=0.0, dtype=None) -> Plane:
    """Validated constructor; the normal is normalised. Raises ValueError for a zero normal."""
    n = np.asarray(normal, dtype=np.float64)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    if n.shape[-1:] != (3,) or np.any(length == 0) or not np.all(np.isfinite(n)):
        raise ValueError(f"plane normal must be a finite non-zero 3-vector, got {n.tolist()}")
    dtype = dtype or jnp.zeros(()).dtype
    return Plane(jnp.asarray(n / length, dtype), jnp.asarray(offset, dtype))
