"""Rigid-body collision detection: sphere-sphere, sphere-plane, box-plane, box-sphere and
box-box contacts. Every contact's normal points from body b to body a.

See `diffcloth.physics.rigid` for the model and its smoothing.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from diffcloth._math import safe_div, safe_norm, safe_normalize
from diffcloth.physics.rigid.bodies import Contact, RigidBody
from diffcloth.physics.rigid.quat import box_vertices, quat_to_matrix

# ----------------------------------------------------------------------------------------------
# Collision detection. Every contact's normal points from body b to body a.


def contact_sphere_sphere(a: RigidBody, b: RigidBody) -> Contact:
    """Contact of sphere a with sphere b; coincident centres separate along +y.

    Shapes: body positions (3,) m -> Contact: depth () m, normal (3,), point (3,) m.
    """
    n = safe_normalize(a.position - b.position)
    depth = a.radius + b.radius - safe_norm(a.position - b.position)
    return Contact(depth, n, a.position - n * (a.radius - depth / 2))


def contact_sphere_plane(a: RigidBody, normal: jax.Array, offset: jax.Array) -> Contact:
    """Contact of sphere a with the plane {p : normal . p = offset} (free side above).

    Shapes: normal (3,), offset () m -> Contact: depth () m, normal (3,), point (3,) m.
    """
    depth = a.radius - (normal @ a.position - offset)
    return Contact(depth, normal, a.position - normal * (a.radius - depth / 2))


class _Patch(NamedTuple):
    """Candidate contact points of a box (k,): points (k, 3), normals (k, 3) (b -> a), depths
    (k,) (<= 0 where not in contact), and the summary `Contact`."""

    points: jax.Array
    normals: jax.Array
    depths: jax.Array
    main: Contact


def _patch_mean(points, depths, fallback):
    """Mean of the penetrating points (equal weights), or `fallback` when none penetrates."""
    inside = (depths > 0).astype(points.dtype)
    count = jnp.sum(inside)
    return jnp.where(count > 0, safe_div(inside @ points, count), fallback)


def _patch_box_plane(a: RigidBody, normal: jax.Array, offset: jax.Array) -> _Patch:
    verts = box_vertices(a)
    depths = offset - verts @ normal
    point = _patch_mean(verts, depths, verts[jnp.argmax(depths)])
    normals = jnp.broadcast_to(normal, verts.shape)
    return _Patch(verts, normals, depths, Contact(jnp.max(depths), normal, point))


def contact_box_plane(a: RigidBody, normal: jax.Array, offset: jax.Array) -> Contact:
    """Box a against a plane: its corners against the plane (the seed's vertices-against-planes
    test). Depth: the deepest corner's; point: the mean of the penetrating corners (a face landing
    flat gives its centre, a corner landing first that corner). The response treats every
    penetrating corner as a simultaneous contact (see `_resolve_patch`)."""
    return _patch_box_plane(a, normal, offset).main


def _box_axes_contact(box: RigidBody, points: jax.Array):
    """For world points (k, 3): the depth inside `box` (k,) (negative outside) and the outward
    normal of the nearest face (k, 3), world frame."""
    rot = quat_to_matrix(box.orientation)
    local = (points - box.position[None, :]) @ rot
    gaps = box.half_extents[None, :] - jnp.abs(local)
    k = jnp.argmin(gaps, axis=-1)
    onehot = jax.nn.one_hot(k, 3, dtype=points.dtype)
    sign = jnp.where(local >= 0, 1.0, -1.0).astype(points.dtype)
    normal_local = onehot * sign
    return jnp.min(gaps, axis=-1), normal_local @ rot.T


def contact_box_sphere(a: RigidBody, b: RigidBody) -> Contact:
    """Box a against sphere b: the sphere centre's closest point on the box; inside the box the
    nearest face decides. Normal from the sphere to the box.

    Shapes: body positions (3,) m -> Contact: depth () m, normal (3,), point (3,) m.
    """
    rot = quat_to_matrix(a.orientation)
    local = rot.T @ (b.position - a.position)
    clamped = jnp.clip(local, -a.half_extents, a.half_extents)
    diff = local - clamped
    dist = safe_norm(diff)
    outside = dist > 0
    # Inside: the face with the smallest gap.
    gaps = a.half_extents - jnp.abs(local)
    onehot = jax.nn.one_hot(jnp.argmin(gaps), 3, dtype=local.dtype)
    sign = jnp.where(local >= 0, 1.0, -1.0).astype(local.dtype)
    n_in = onehot * sign
    n_local = jnp.where(outside, safe_normalize(diff), n_in)
    depth = jnp.where(outside, b.radius - dist, b.radius + jnp.min(gaps))
    face = jnp.where(onehot > 0, sign * a.half_extents, local)
    point_local = jnp.where(outside, clamped, face)
    n_box_to_sphere = rot @ n_local
    return Contact(depth, -n_box_to_sphere, a.position + rot @ point_local)


def _patch_box_box(a: RigidBody, b: RigidBody) -> _Patch:
    va, vb = box_vertices(a), box_vertices(b)
    da, na = _box_axes_contact(b, va)  # corners of a inside b: normal out of b (b -> a)
    db, nb = _box_axes_contact(a, vb)  # corners of b inside a: normal out of a (a -> b)
    depths = jnp.concatenate([da, db])
    normals = jnp.concatenate([na, -nb])
    points = jnp.concatenate([va, vb])
    onehot = jax.nn.one_hot(jnp.argmax(depths), 16, dtype=va.dtype)
    normal, deepest = onehot @ normals, onehot @ points
    # Only corners pressing on the same face as the deepest one take part.
    depths = jnp.where(normals @ normal > 0.999, depths, -1.0)
    point = _patch_mean(points, depths, deepest)
    normals = jnp.broadcast_to(normal, points.shape)
    return _Patch(points, normals, depths, Contact(depths @ onehot, normal, point))


def contact_box_box(a: RigidBody, b: RigidBody) -> Contact:
    """Box a against box b: every corner of each box against the other's face planes (the seed's
    OBB test). The deepest corner gives depth and face normal; the point is the mean of the
    corners pressing on that face. Edge-edge contacts are not detected.

    Shapes: body positions (3,) m -> Contact: depth () m, normal (3,), point (3,) m.
    """
    return _patch_box_box(a, b).main


def contact(a: RigidBody, b: RigidBody) -> Contact:
    """Contact between two bodies of any shapes (dispatch on the static shapes).

    Shapes: body positions (3,) m -> Contact: depth () m, normal (3,), point (3,) m.
    """
    kinds = (a.shape, b.shape)
    if kinds == ("sphere", "sphere"):
        return contact_sphere_sphere(a, b)
    if kinds == ("box", "sphere"):
        return contact_box_sphere(a, b)
    if kinds == ("sphere", "box"):
        c = contact_box_sphere(b, a)
        return Contact(c.depth, -c.normal, c.point)
    return contact_box_box(a, b)


def contact_plane(a: RigidBody, normal: jax.Array, offset: jax.Array) -> Contact:
    """Contact between a body and a static plane.

    Shapes: normal (3,), offset () m -> Contact: depth () m, normal (3,), point (3,) m.
    """
    if a.shape == "sphere":
        return contact_sphere_plane(a, normal, offset)
    return contact_box_plane(a, normal, offset)
