"""Ambient occlusion without sky maps: the occluder mesh as small discs, spheres and planes exact.

The "fit" shadow quality (`render.shadow_quality`) replaces the K per-direction shadow maps of
`render.sky` by closed forms, with no rasterization at all:

* Mesh (the cloth, decimated to at most 16 vertices a side, plus box triangles): each vertex
  stands for a two-sided disc of a third of its triangles' area, and occludes a receiver p with
  normal N by the disc's form factor A cos_e max(cos_r, 0) / (pi d^2 + A) (d the distance,
  cos_r = N.v and cos_e = |n_e.v| along the unit vector v from p to the disc; exact for a small
  disc, bounded by 1 when d -> 0, Bunnell's "dynamic ambient occlusion", GPU Gems 2 ch. 14,
  single pass). The mesh's occlusion is the sum, clipped to [0, 1]: exact for a single layer
  (the floor under a cloth), too dark where layers overlap as seen from the receiver.
* Spheres: their exact form factor (`sky.sphere_form_factor`), multiplied in.
* Planes: an infinite plane below a receiver hides exactly the half of the directions on its
  side, a cosine-weighted fraction (1 - N.n_plane) / 2; A is multiplied by (1 + N.n_plane) / 2.

Smooth in the receivers and occluders everywhere except where a cosine is clipped at 0
(continuous there). Cost: receivers x discs multiply-adds (no gathers).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from diffcloth._math import safe_normalize

#: vertices a side of the decimated cloth grid whose vertices are the occluding discs
DISC_GRID = 16


def mesh_discs(positions, faces):
    """Per-vertex discs of a triangle mesh: centres (the vertices), unit normals (area-weighted
    face normals, sign irrelevant: discs are two-sided) and areas (a third of the adjacent
    triangles' area each). Differentiable.

    Shapes: positions (n, 3) m, faces (m, 3) -> centres (n, 3) m, normals (n, 3), areas (n,) m^2.
    """
    p = positions[faces]
    cross = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # (m, 3), |.| = 2 area
    n = positions.shape[0]
    acc = jnp.zeros((n, 3), positions.dtype)
    nrm = acc.at[faces.reshape(-1)].add(jnp.repeat(cross, 3, axis=0))
    area2 = jnp.sqrt(jnp.sum(cross * cross, axis=-1) + 1e-30)
    area = jnp.zeros((n,), positions.dtype).at[faces.reshape(-1)].add(jnp.repeat(area2, 3)) / 6.0
    return positions, safe_normalize(nrm), area


def disc_occlusion(points, normals, discs):
    """Summed form factor of the discs seen from receivers (module docstring), not clipped.

    Shapes: points (..., 3) m, normals (..., 3) unit, discs as `mesh_discs` -> (...).
    """
    centre, dn, area = discs
    lead = (1,) * (points.ndim - 1)
    v = jnp.reshape(centre, lead + centre.shape) - points[..., None, :]  # (..., j, 3)
    d2 = jnp.sum(v * v, axis=-1)
    ok = d2 > 1e-12
    inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, d2, 1.0)), 0.0)
    cos_r = jnp.maximum(jnp.sum(v * normals[..., None, :], axis=-1) * inv, 0.0)
    cos_e = jnp.abs(jnp.sum(v * jnp.reshape(dn, lead + dn.shape), axis=-1)) * inv
    a = jnp.reshape(area, lead + area.shape)
    return jnp.sum(a * cos_e * cos_r / (math.pi * d2 + a), axis=-1)


def plane_openness(normals, plane_normal):
    """Fraction (1 + N.n_p) / 2 of the cosine-weighted hemisphere each infinite plane leaves
    open to a receiver on its free side, multiplied over the planes.

    Shapes: normals (..., 3) unit, plane_normal (p, 3) unit -> (...).
    """
    cos = jnp.einsum("...c,pc->...p", normals, plane_normal)
    return jnp.prod(0.5 * (1.0 + cos), axis=-1)
