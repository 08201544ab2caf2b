"""Rigid-body impulse response (restitution, Coulomb friction, continuous-time position
correction) for body pairs and body-plane contacts.

See `diffcloth.physics.rigid` for the model and its smoothing.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from diffcloth._math import safe_div, safe_norm, safe_normalize
from diffcloth.physics.rigid.bodies import Contact, RigidBody
from diffcloth.physics.rigid.contact import (
    _patch_box_box,
    _patch_box_plane,
    contact,
    contact_sphere_plane,
)
from diffcloth.physics.rigid.quat import _inv_inertia_world, quat_to_matrix

# ----------------------------------------------------------------------------------------------
# Impulse response


class _Dyn(NamedTuple):
    x: jax.Array
    v: jax.Array
    w: jax.Array
    inv_mass: jax.Array
    inv_inertia: jax.Array  # (3, 3) world


def _dyn(body: RigidBody) -> _Dyn:
    rot = None if body.shape == "sphere" else quat_to_matrix(body.orientation)
    return _Dyn(
        body.position,
        body.velocity,
        body.angular_velocity,
        1.0 / body.mass,
        _inv_inertia_world(body, rot),
    )


def _static_dyn(dtype) -> _Dyn:
    z = jnp.zeros(3, dtype)
    return _Dyn(z, z, z, jnp.zeros((), dtype), jnp.zeros((3, 3), dtype))


def _resolve(a: _Dyn, b: _Dyn, c: Contact, restitution, friction, *, b_static: bool):
    """Apply the contact impulse (slide 29 + Coulomb friction) and the continuous-time position
    correction to a (and b). Returns the updated pair."""
    ra = c.point - a.x
    rb = c.point - b.x
    n = c.normal
    v_rel = (a.v + jnp.cross(a.w, ra)) - (b.v + jnp.cross(b.w, rb))
    vn = v_rel @ n

    def k_along(d):
        ang = jnp.cross(a.inv_inertia @ jnp.cross(ra, d), ra)
        if not b_static:
            ang = ang + jnp.cross(b.inv_inertia @ jnp.cross(rb, d), rb)
        return a.inv_mass + b.inv_mass + d @ ang

    touching = c.depth > 0
    active = touching & (vn < 0)
    jn = jnp.where(active, -(1 + restitution) * vn / k_along(n), 0.0)
    vt = v_rel - vn * n
    t = safe_normalize(vt)
    jt = jnp.minimum(friction * jn, safe_div(safe_norm(vt), k_along(t)))
    jt = jnp.where(active, jt, 0.0)
    impulse = jn * n - jt * t

    # Continuous-time correction: undo the penetration and add the distance the pair would have
    # separated since the (sub-substep) moment of contact, e * depth.
    corr = jnp.where(touching, c.depth * (1 + restitution * active.astype(c.depth.dtype)), 0.0)
    share = a.inv_mass / (a.inv_mass + b.inv_mass)
    a = a._replace(
        x=a.x + n * (corr * share),
        v=a.v + a.inv_mass * impulse,
        w=a.w + a.inv_inertia @ jnp.cross(ra, impulse),
    )
    if not b_static:
        b = b._replace(
            x=b.x - n * (corr * (1 - share)),
            v=b.v - b.inv_mass * impulse,
            w=b.w - b.inv_inertia @ jnp.cross(rb, impulse),
        )
    return a, b


def _resolve_patch(
    a: _Dyn, b: _Dyn, points, normals, depths, main: Contact, restitution, friction, *, b_static
):
    """Several simultaneous contact points (a box's corners): solve for the normal impulses
    lambda_i >= 0 that give every approaching corner the post-contact normal velocity
    -e v_n,i at once (two active-set rounds of a Tikhonov-regularised least-squares solve of the
    k x k Delassus system). A face landing flat gets equal corner impulses (no spurious spin); a
    single corner reduces to the slide-29 formula. Friction is one Coulomb impulse at the
    impulse-weighted centre of the patch; the position correction is as in `_resolve`."""
    dtype = points.dtype
    ra = points - a.x[None, :]
    rb = points - b.x[None, :]
    v_rel = (a.v[None, :] + jnp.cross(a.w[None, :], ra)) - (
        b.v[None, :] + jnp.cross(b.w[None, :], rb)
    )
    vn = jnp.sum(v_rel * normals, axis=-1)
    ang_a = jnp.cross(ra, normals)
    delassus = (a.inv_mass + b.inv_mass) * (normals @ normals.T) + ang_a @ a.inv_inertia @ ang_a.T
    if not b_static:
        ang_b = jnp.cross(rb, normals)
        delassus = delassus + ang_b @ b.inv_inertia @ ang_b.T
    k = points.shape[0]
    eye = jnp.eye(k, dtype=dtype)
    rel = 1e-5 if dtype == jnp.float32 else 1e-11
    active = (depths > 0) & (vn < 0)
    lam = jnp.zeros(k, dtype)
    for _ in range(2):
        m = active.astype(dtype)
        mat = delassus * (m[:, None] * m[None, :]) + eye * (1 - m)[:, None]
        rhs = m * (-(1 + restitution) * vn)
        scale = jnp.trace(mat) / k
        lam = jnp.linalg.solve(mat.T @ mat + rel * scale**2 * eye, mat.T @ rhs) * m
        active = active & (lam > 0)
    lam = jnp.where(active, lam, 0.0)
    impulses = lam[:, None] * normals
    total = jnp.sum(lam)
    any_active = total > 0
    a = a._replace(
        v=a.v + a.inv_mass * jnp.sum(impulses, axis=0),
        w=a.w + a.inv_inertia @ jnp.sum(jnp.cross(ra, impulses), axis=0),
    )
    if not b_static:
        b = b._replace(
            v=b.v - b.inv_mass * jnp.sum(impulses, axis=0),
            w=b.w - b.inv_inertia @ jnp.sum(jnp.cross(rb, impulses), axis=0),
        )
    # Friction at the impulse-weighted centre, bounded by mu * (total normal impulse).
    centre = jnp.where(any_active, safe_div(lam @ points, total, fallback=0.0), main.point)
    patch = Contact(main.depth, main.normal, centre)
    a, b = _friction(a, b, patch, friction * total, any_active, b_static=b_static)
    return _correct(a, b, main, restitution, jnp.any(active), b_static=b_static)


def _friction(a: _Dyn, b: _Dyn, c: Contact, limit, active, *, b_static):
    """Coulomb friction impulse at c.point: min(limit, |v_t| / k_t) against the sliding velocity."""
    ra, rb, n = c.point - a.x, c.point - b.x, c.normal
    v_rel = (a.v + jnp.cross(a.w, ra)) - (b.v + jnp.cross(b.w, rb))
    vt = v_rel - (v_rel @ n) * n
    t = safe_normalize(vt)
    k_t = a.inv_mass + b.inv_mass + t @ jnp.cross(a.inv_inertia @ jnp.cross(ra, t), ra)
    if not b_static:
        k_t = k_t + t @ jnp.cross(b.inv_inertia @ jnp.cross(rb, t), rb)
    jt = jnp.where(active, jnp.minimum(limit, safe_div(safe_norm(vt), k_t)), 0.0)
    impulse = -jt * t
    a = a._replace(v=a.v + a.inv_mass * impulse, w=a.w + a.inv_inertia @ jnp.cross(ra, impulse))
    if not b_static:
        b = b._replace(v=b.v - b.inv_mass * impulse, w=b.w - b.inv_inertia @ jnp.cross(rb, impulse))
    return a, b


def _correct(a: _Dyn, b: _Dyn, c: Contact, restitution, active, *, b_static):
    """Continuous-time position correction: push the pair apart along n by (1 + e) * depth when
    approaching (depth when only touching), split by inverse mass."""
    corr = jnp.where(c.depth > 0, c.depth * (1 + restitution * active.astype(c.depth.dtype)), 0.0)
    share = a.inv_mass / (a.inv_mass + b.inv_mass)
    a = a._replace(x=a.x + c.normal * (corr * share))
    if not b_static:
        b = b._replace(x=b.x - c.normal * (corr * (1 - share)))
    return a, b


def _put(body: RigidBody, d: _Dyn) -> RigidBody:
    return dataclasses.replace(body, position=d.x, velocity=d.v, angular_velocity=d.w)


def collide_pair(a: RigidBody, b: RigidBody) -> tuple[RigidBody, RigidBody]:
    """Detect and resolve one contact between two bodies (no-op when apart or separating).

    Shapes: RigidBody leaves: position, velocity (3,), orientation (4,) -> the same shapes.
    """
    e = (a.restitution + b.restitution) / 2
    mu = (a.friction + b.friction) / 2
    if a.shape == b.shape == "box":
        patch = _patch_box_box(a, b)
        da, db = _resolve_patch(_dyn(a), _dyn(b), *patch, e, mu, b_static=False)
    else:
        da, db = _resolve(_dyn(a), _dyn(b), contact(a, b), e, mu, b_static=False)
    return _put(a, da), _put(b, db)


def collide_plane(a: RigidBody, normal: jax.Array, offset: jax.Array) -> RigidBody:
    """Detect and resolve a contact between a body and a static plane.

    Shapes: normal (3,), offset () m; RigidBody leaves (3,) / (4,) -> the same shapes.
    """
    ground = _static_dyn(a.position.dtype)
    if a.shape == "box":
        patch = _patch_box_plane(a, normal, offset)
        da, _ = _resolve_patch(_dyn(a), ground, *patch, a.restitution, a.friction, b_static=True)
    else:
        c = contact_sphere_plane(a, normal, offset)
        da, _ = _resolve(_dyn(a), ground, c, a.restitution, a.friction, b_static=True)
    return _put(a, da)
