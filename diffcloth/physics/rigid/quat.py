"""Quaternion and mass-property math of rigid bodies: rotation, inertia, momentum, energy.

See `diffcloth.physics.rigid` for the model and its smoothing.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp

from diffcloth._math import safe_norm, safe_normalize
from diffcloth.physics.rigid.bodies import RigidBody

# ----------------------------------------------------------------------------------------------
# Quaternions and mass properties


def quat_multiply(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product a * b of (w, x, y, z) quaternions, (..., 4)."""
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    w = aw * bw - jnp.sum(av * bv, axis=-1, keepdims=True)
    v = aw * bv + bw * av + jnp.cross(av, bv)
    return jnp.concatenate([w, v], axis=-1)


def quat_to_matrix(q: jax.Array) -> jax.Array:
    """Rotation matrix (3, 3) of a unit quaternion (w, x, y, z) (body to world)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def quat_from_axis_angle(axis, angle) -> jax.Array:
    """Unit quaternion (w, x, y, z) for a rotation by `angle` rad about `axis` (3,)."""
    axis = safe_normalize(jnp.asarray(axis))
    angle = jnp.asarray(angle, axis.dtype)
    return jnp.concatenate([jnp.cos(angle / 2)[None], jnp.sin(angle / 2) * axis])


def _quat_exp_step(q: jax.Array, w: jax.Array, h) -> jax.Array:
    """Rotate q by angular velocity w (world) for time h: exp(h w / 2) * q, renormalised."""
    speed = safe_norm(w)
    half = speed * h / 2
    # sin(|w| h / 2) / |w| = (h / 2) sinc(|w| h / (2 pi)); jnp.sinc has a finite derivative at 0.
    dq = jnp.concatenate([jnp.cos(half)[None], (h / 2) * jnp.sinc(half / jnp.pi) * w])
    q = quat_multiply(dq, q)
    return q / safe_norm(q)


def inertia_tensor(body: RigidBody) -> jax.Array:
    """Body-frame inertia tensor (3, 3) in kg m^2 from shape and mass.

    Solid sphere: 2/5 m r^2 I. Solid box with half extents (a, b, c): m/3 diag(b^2 + c^2,
    a^2 + c^2, a^2 + b^2).
    """
    if body.shape == "sphere":
        d = jnp.full((3,), 0.4, body.mass.dtype) * body.mass * body.radius**2
    else:
        s = body.half_extents**2
        d = body.mass / 3 * jnp.stack([s[1] + s[2], s[0] + s[2], s[0] + s[1]])
    return jnp.diag(d)


def _inv_inertia_world(body: RigidBody, rot: jax.Array | None) -> jax.Array:
    if body.shape == "sphere":  # isotropic: no rotation needed
        inv = 1.0 / (0.4 * body.mass * body.radius**2)
        return jnp.eye(3, dtype=body.position.dtype) * inv
    inv_d = 1.0 / jnp.diagonal(inertia_tensor(body))
    return (rot * inv_d[None, :]) @ rot.T


def world_inertia(body: RigidBody) -> jax.Array:
    """World-frame inertia tensor R I R^T (3, 3)."""
    rot = quat_to_matrix(body.orientation)
    return rot @ inertia_tensor(body) @ rot.T


def angular_momentum(body: RigidBody) -> jax.Array:
    """World angular momentum about the centre of mass, (3,) kg m^2/s."""
    return world_inertia(body) @ body.angular_velocity


def linear_momentum(body: RigidBody) -> jax.Array:
    """m v, (3,) kg m/s."""
    return body.mass * body.velocity


def kinetic_energy(body: RigidBody) -> jax.Array:
    """Translational plus rotational kinetic energy, () J."""
    w = body.angular_velocity
    return 0.5 * body.mass * jnp.sum(body.velocity**2) + 0.5 * w @ (world_inertia(body) @ w)


def box_vertices(body: RigidBody) -> jax.Array:
    """The 8 world-space corners (8, 3) of a box body."""
    signs = jnp.asarray(list(itertools.product((-1.0, 1.0), repeat=3)), body.position.dtype)
    rot = quat_to_matrix(body.orientation)
    return body.position[None, :] + (signs * body.half_extents[None, :]) @ rot.T
