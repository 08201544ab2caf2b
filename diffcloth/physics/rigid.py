"""Rigid bodies: spheres and boxes with forces, thrusters, collisions and impulse response.

The model follows the "Virtual Environments" deck (slides 19-33, SEEDS.md section 9):

* A `RigidBody` carries position, orientation (unit quaternion, w x y z), linear and angular
  velocity (world frame), mass, restitution, friction, and drag coefficients. Its inertia tensor
  is derived from its shape and mass (`inertia_tensor`), so gradients w.r.t. mass reach the
  rotation too.
* Forces applied at points are split into a force through the centre (F = m a) and a torque
  (M = I alpha) by `force_and_torque`. Gravity, drag (`linear_drag` along the body's front axis,
  `orthogonal_drag` along its right and top axes; body axes x = right, y = top, z = front) and
  thrusters (body-fixed points and directions, switched by a control signal per frame) are
  integrated each substep with semi-implicit Euler. Rotation integrates the world angular momentum
  L (dL/dt = torque) and maps it back with w = R I^-1 R^T L, so torque-free bodies keep L exactly.
* Collision detection sphere-sphere, sphere-plane, box-plane, box-sphere and box-box
  (vertices against the other box's face planes, as in the seed) gives a `Contact`: depth,
  normal (pointing from the second body to the first) and point.
* Impulse response (slide 29): j = -(1 + e) v_rel . n / (1/m_a + 1/m_b
  + n . ((I_a^-1 (r_a x n)) x r_a + (I_b^-1 (r_b x n)) x r_b)), with Coulomb friction
  (tangential impulse min(mu j, |v_t| / k_t) against the sliding direction). For spheres hit
  along the line of centres the arms are parallel to n and it reduces to the linear response
  of slide 26.

Differentiability and the smoothing used
----------------------------------------
Contacts are detected and resolved once per substep (pairs in a fixed order, one sequential
pass). The impulse itself is a smooth function of masses, restitution, friction and velocities.
What would make the final position jump is *when* the contact is seen: a penetration is only
noticed at the end of a substep. We therefore use a continuous-time correction: a contact of depth
d with approach speed |v_n| happened d/|v_n| ago, and since then the bodies would have separated
at e |v_n|, so the pair is pushed apart by (1 + e) d along n (split by inverse mass; the centre of
mass does not move). In the absence of other forces within the substep this is exact, so the final
position is continuous (and smooth away from the contact time landing on a substep boundary) in
restitution, initial velocity and mass; e.g. a sphere thrown at a plane in zero gravity ends at
exactly the analytic position whichever substep sees the hit. The correction is linear only (it
does not rotate bodies) and ignores forces acting during the fraction of the substep. Box-box
contact checks vertices against faces only (edge-edge contacts are missed, as in the seed).
Pair restitution and friction are the mean of the two bodies' values; planes use the body's.

Pairwise collision code is unrolled in Python over the (static, small) set of bodies: meant for a
handful of bodies, not for granular media.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import safe_div, safe_norm, safe_normalize
from diffcloth.shapes import Plane

SHAPES = ("sphere", "box")


# ----------------------------------------------------------------------------------------------
# Records


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RigidBody:
    """A rigid sphere or box: state and physical parameters (all arrays differentiable).

    Attributes:
      position: (3,) centre of mass in m.
      orientation: (4,) unit quaternion (w, x, y, z), body to world.
      velocity: (3,) m/s, world frame.
      angular_velocity: (3,) rad/s, world frame.
      mass: () kg, > 0.
      radius: () m; the sphere's radius (for a box, its bounding-sphere radius; unused).
      half_extents: (3,) m; the box's half sizes along body x, y, z (for a sphere r, r, r; unused).
      restitution: () in [0, 1].
      friction: () Coulomb coefficient >= 0.
      linear_drag: () N s/m, drag along the body's front axis (body z).
      orthogonal_drag: () N s/m, drag along the right (x) and top (y) axes.
      angular_drag: () N m s, torque -angular_drag * angular_velocity.
      shape: "sphere" or "box" (static).
    """

    position: jax.Array
    orientation: jax.Array
    velocity: jax.Array
    angular_velocity: jax.Array
    mass: jax.Array
    radius: jax.Array
    half_extents: jax.Array
    restitution: jax.Array
    friction: jax.Array
    linear_drag: jax.Array
    orthogonal_drag: jax.Array
    angular_drag: jax.Array
    shape: str = dataclasses.field(default="sphere", metadata={"static": True})


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Thrusters:
    """Forces fixed to a body, switched on and off by a control signal.

    Attributes:
      points: (k, 3) application points in the body frame, m.
      directions: (k, 3) unit thrust directions in the body frame.
      strengths: (k,) N at full control; differentiable.
    """

    points: jax.Array
    directions: jax.Array
    strengths: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RigidSettings:
    """How bodies are stepped. dt: () s per frame; gravity: (3,) m/s^2; num_substeps static."""

    dt: jax.Array
    gravity: jax.Array
    num_substeps: int = dataclasses.field(default=8, metadata={"static": True})


class Contact(NamedTuple):
    """depth () m (> 0 when penetrating); normal (3,) unit, from body b to body a; point (3,) m."""

    depth: jax.Array
    normal: jax.Array
    point: jax.Array


# ----------------------------------------------------------------------------------------------
# Constructors and validation


def _vec(name, value, size, dtype):
    a = np.asarray(value, dtype=np.float64)
    if a.shape == () and size > 1:
        a = np.full(size, float(a))
    if a.shape != ((size,) if size > 1 else ()):
        raise ValueError(f"{name} must have {size} components, got {np.asarray(value).tolist()}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    return a if dtype is None else jnp.asarray(a, dtype)


def _scalar(name, value, lo, hi, dtype, *, open_lo=False):
    a = np.asarray(value, dtype=np.float64)
    bad = a.shape != () or not np.isfinite(a) or a > hi or (a <= lo if open_lo else a < lo)
    if bad:
        lb = "(" if open_lo else "["
        raise ValueError(
            f"{name} must be a number in {lb}{lo}, {hi}], got {np.asarray(value).tolist()}"
        )
    return a if dtype is None else jnp.asarray(a, dtype)


def make_body(
    shape: str = "sphere",
    *,
    mass,
    position=(0.0, 0.0, 0.0),
    velocity=(0.0, 0.0, 0.0),
    orientation=(1.0, 0.0, 0.0, 0.0),
    angular_velocity=(0.0, 0.0, 0.0),
    radius=None,
    half_extents=None,
    restitution=0.5,
    friction=0.0,
    linear_drag=0.0,
    orthogonal_drag=0.0,
    angular_drag=0.0,
    dtype=None,
) -> RigidBody:
    """Validated `RigidBody` constructor (eager; raises ValueError naming the bad argument).

    A sphere needs `radius` > 0, a box `half_extents` (3 numbers > 0). The orientation is
    normalised. Example: ``make_body("sphere", mass=1.0, radius=0.1, position=(0, 1, 0))``.
    """
    dtype = dtype or jnp.zeros(()).dtype
    if shape not in SHAPES:
        raise ValueError(f"shape must be one of {SHAPES}, got {shape!r}")
    inf = math.inf
    if shape == "sphere":
        if radius is None:
            raise ValueError("radius is required for a sphere (allowed range (0, inf))")
        r = _scalar("radius", radius, 0.0, inf, None, open_lo=True)
        he = np.full(3, float(r))
    else:
        if half_extents is None:
            raise ValueError("half_extents is required for a box (3 numbers in (0, inf))")
        he = _vec("half_extents", half_extents, 3, None)
        if np.any(he <= 0):
            raise ValueError(
                f"half_extents must be > 0 (allowed range (0, inf)), got {he.tolist()}"
            )
        r = np.linalg.norm(he)
    q = _vec("orientation", orientation, 4, None)
    if np.linalg.norm(q) == 0:
        raise ValueError(
            f"orientation must be a non-zero quaternion (w, x, y, z), got {q.tolist()}"
        )
    q = q / np.linalg.norm(q)
    return RigidBody(
        position=_vec("position", position, 3, dtype),
        orientation=jnp.asarray(q, dtype),
        velocity=_vec("velocity", velocity, 3, dtype),
        angular_velocity=_vec("angular_velocity", angular_velocity, 3, dtype),
        mass=_scalar("mass", mass, 0.0, inf, dtype, open_lo=True),
        radius=jnp.asarray(r, dtype),
        half_extents=jnp.asarray(he, dtype),
        restitution=_scalar("restitution", restitution, 0.0, 1.0, dtype),
        friction=_scalar("friction", friction, 0.0, inf, dtype),
        linear_drag=_scalar("linear_drag", linear_drag, 0.0, inf, dtype),
        orthogonal_drag=_scalar("orthogonal_drag", orthogonal_drag, 0.0, inf, dtype),
        angular_drag=_scalar("angular_drag", angular_drag, 0.0, inf, dtype),
        shape=shape,
    )


def make_thrusters(points, directions, strengths, dtype=None) -> Thrusters:
    """Validated `Thrusters`: points and directions (k, 3) in the body frame, strengths (k,) N.

    Directions are normalised; a zero direction raises ValueError.
    """
    dtype = dtype or jnp.zeros(()).dtype
    p = np.asarray(points, np.float64).reshape(-1, 3) if np.size(points) else np.zeros((0, 3))
    d = (
        np.asarray(directions, np.float64).reshape(-1, 3)
        if np.size(directions)
        else np.zeros((0, 3))
    )
    s = np.asarray(strengths, np.float64).reshape(-1)
    if not (p.shape[0] == d.shape[0] == s.shape[0]):
        raise ValueError(
            f"thruster points, directions and strengths must have the same count, got "
            f"{p.shape[0]}, {d.shape[0]}, {s.shape[0]}"
        )
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(n == 0) or not (np.all(np.isfinite(d)) and np.all(np.isfinite(p))):
        raise ValueError(f"thruster directions must be finite and non-zero, got {d.tolist()}")
    if not np.all(np.isfinite(s)):
        raise ValueError(f"thruster strengths must be finite, got {s.tolist()}")
    return Thrusters(jnp.asarray(p, dtype), jnp.asarray(d / n, dtype), jnp.asarray(s, dtype))


def make_settings(dt=1.0 / 60.0, gravity=(0.0, -9.81, 0.0), num_substeps=8, dtype=None):
    """Validated `RigidSettings`: dt > 0 s, gravity (3,) m/s^2, num_substeps >= 1."""
    dtype = dtype or jnp.zeros(()).dtype
    if not isinstance(num_substeps, int | np.integer) or num_substeps < 1:
        raise ValueError(f"num_substeps must be an integer >= 1, got {num_substeps!r}")
    return RigidSettings(
        dt=_scalar("dt", dt, 0.0, math.inf, dtype, open_lo=True),
        gravity=_vec("gravity", gravity, 3, dtype),
        num_substeps=int(num_substeps),
    )


BODY_KEYS = {
    "shape", "radius", "half_extents", "position", "velocity", "orientation", "angular_velocity",
    "mass", "restitution", "friction", "linear_drag", "orthogonal_drag", "angular_drag", "drag",
}  # fmt: skip


def bodies_from_config(entries: Sequence[Mapping], dtype=None) -> tuple[RigidBody, ...]:
    """Bodies from a list of TOML `[[bodies]]` tables (dicts).

    Keys: shape ("sphere" | "box"), radius (sphere) or half_extents (box), mass (> 0), position,
    velocity, orientation (w, x, y, z), angular_velocity, restitution ([0, 1]), friction (>= 0),
    linear_drag, orthogonal_drag, angular_drag (>= 0); `drag` sets linear and orthogonal drag at
    once. Errors name the entry index, the key, its value and the allowed range.
    """
    bodies = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            raise ValueError(f"bodies[{i}] must be a table, got {entry!r}")
        unknown = sorted(set(entry) - BODY_KEYS)
        if unknown:
            raise ValueError(
                f"bodies[{i}]: unknown key(s) {unknown}; allowed: {sorted(BODY_KEYS)}"
            )
        kw = dict(entry)
        shape = kw.pop("shape", "sphere")
        if "drag" in kw:
            drag = kw.pop("drag")
            kw.setdefault("linear_drag", drag)
            kw.setdefault("orthogonal_drag", drag)
        if "mass" not in kw:
            raise ValueError(f"bodies[{i}]: key 'mass' is required (kg, allowed range (0, inf))")
        if shape == "sphere" and "half_extents" in kw:
            raise ValueError(f"bodies[{i}]: a sphere takes 'radius', not 'half_extents'")
        if shape == "box" and "radius" in kw:
            raise ValueError(f"bodies[{i}]: a box takes 'half_extents', not 'radius'")
        try:
            bodies.append(make_body(shape, dtype=dtype, **kw))
        except ValueError as err:
            raise ValueError(f"bodies[{i}]: {err}") from None
    return tuple(bodies)


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


# ----------------------------------------------------------------------------------------------
# Forces


def force_and_torque(center: jax.Array, forces: jax.Array, points: jax.Array):
    """Split forces (k, 3) N applied at world points (k, 3) m into the total force through the
    centre (3,) and the torque about `center` (3,) N m (slide 31)."""
    arms = points - center[None, :]
    return jnp.sum(forces, axis=0), jnp.sum(jnp.cross(arms, forces), axis=0)


def drag_force(body: RigidBody) -> jax.Array:
    """Linear air drag (3,) N: -linear_drag * v_front - orthogonal_drag * (v_right + v_top)."""
    rot = quat_to_matrix(body.orientation)
    v_local = rot.T @ body.velocity
    coef = jnp.stack([body.orthogonal_drag, body.orthogonal_drag, body.linear_drag])
    return -(rot @ (coef * v_local))


def thruster_force(body: RigidBody, thrusters: Thrusters, control: jax.Array):
    """Force (3,) and torque (3,) of thrusters at control levels (k,) (0 off, 1 full)."""
    rot = quat_to_matrix(body.orientation)
    forces = (thrusters.directions * (thrusters.strengths * control)[:, None]) @ rot.T
    points = body.position[None, :] + thrusters.points @ rot.T
    return force_and_torque(body.position, forces, points)


# ----------------------------------------------------------------------------------------------
# Collision detection. Every contact's normal points from body b to body a.


def contact_sphere_sphere(a: RigidBody, b: RigidBody) -> Contact:
    """Contact of sphere a with sphere b; coincident centres separate along +y."""
    n = safe_normalize(a.position - b.position)
    depth = a.radius + b.radius - safe_norm(a.position - b.position)
    return Contact(depth, n, a.position - n * (a.radius - depth / 2))


def contact_sphere_plane(a: RigidBody, normal: jax.Array, offset: jax.Array) -> Contact:
    """Contact of sphere a with the plane {p : normal . p = offset} (free side above)."""
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
    nearest face decides. Normal from the sphere to the box."""
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
    corners pressing on that face. Edge-edge contacts are not detected."""
    return _patch_box_box(a, b).main


def contact(a: RigidBody, b: RigidBody) -> Contact:
    """Contact between two bodies of any shapes (dispatch on the static shapes)."""
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
    """Contact between a body and a static plane."""
    if a.shape == "sphere":
        return contact_sphere_plane(a, normal, offset)
    return contact_box_plane(a, normal, offset)


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
    """Detect and resolve one contact between two bodies (no-op when apart or separating)."""
    e = (a.restitution + b.restitution) / 2
    mu = (a.friction + b.friction) / 2
    if a.shape == b.shape == "box":
        patch = _patch_box_box(a, b)
        da, db = _resolve_patch(_dyn(a), _dyn(b), *patch, e, mu, b_static=False)
    else:
        da, db = _resolve(_dyn(a), _dyn(b), contact(a, b), e, mu, b_static=False)
    return _put(a, da), _put(b, db)


def collide_plane(a: RigidBody, normal: jax.Array, offset: jax.Array) -> RigidBody:
    """Detect and resolve a contact between a body and a static plane."""
    ground = _static_dyn(a.position.dtype)
    if a.shape == "box":
        patch = _patch_box_plane(a, normal, offset)
        da, _ = _resolve_patch(_dyn(a), ground, *patch, a.restitution, a.friction, b_static=True)
    else:
        c = contact_sphere_plane(a, normal, offset)
        da, _ = _resolve(_dyn(a), ground, c, a.restitution, a.friction, b_static=True)
    return _put(a, da)


# ----------------------------------------------------------------------------------------------
# Integration


def integrate_body(
    body: RigidBody,
    h,
    gravity: jax.Array,
    *,
    force: jax.Array | None = None,
    torque: jax.Array | None = None,
) -> RigidBody:
    """One semi-implicit Euler substep of length h s under gravity, drag and extra force/torque
    (world, N and N m). Angular momentum is integrated, so torque-free rotation keeps it."""
    f = body.mass * gravity + drag_force(body)
    tau = -body.angular_drag * body.angular_velocity
    if force is not None:
        f = f + force
    if torque is not None:
        tau = tau + torque
    v = body.velocity + h * f / body.mass
    if body.shape == "sphere":  # isotropic inertia: w = L / I, no gyroscopic term
        inv_i = _inv_inertia_world(body, None)
        w = body.angular_velocity + h * (inv_i @ tau)
        moved = dataclasses.replace(body, orientation=_quat_exp_step(body.orientation, w, h))
    else:
        rot = quat_to_matrix(body.orientation)
        ang_mom = rot @ (inertia_tensor(body) @ (rot.T @ body.angular_velocity)) + h * tau
        # Midpoint rule for the orientation (second order): w at the half-step orientation.
        q_half = _quat_exp_step(body.orientation, _inv_inertia_world(body, rot) @ ang_mom, h / 2)
        w_mid = _inv_inertia_world(body, quat_to_matrix(q_half)) @ ang_mom
        q = _quat_exp_step(body.orientation, w_mid, h)
        moved = dataclasses.replace(body, orientation=q)
        w = _inv_inertia_world(moved, quat_to_matrix(q)) @ ang_mom
    return dataclasses.replace(
        moved, position=body.position + h * v, velocity=v, angular_velocity=w
    )


def _plane_list(planes: Plane | None, dtype):
    if planes is None:
        return []
    p = planes.batched()
    normal = jnp.asarray(p.normal, dtype)
    offset = jnp.asarray(p.offset, dtype)
    return [(normal[k], offset[k]) for k in range(normal.shape[0])]


def collide_all(bodies: Sequence[RigidBody], planes: Plane | None = None) -> tuple[RigidBody, ...]:
    """One sequential pass over all body pairs (i < j), then every body against every plane."""
    bodies = list(bodies)
    for i, j in itertools.combinations(range(len(bodies)), 2):
        bodies[i], bodies[j] = collide_pair(bodies[i], bodies[j])
    if bodies:
        plist = _plane_list(planes, bodies[0].position.dtype)
        for i in range(len(bodies)):
            for normal, offset in plist:
                bodies[i] = collide_plane(bodies[i], normal, offset)
    return tuple(bodies)


def _check_controls(bodies, thrusters, controls, num_frames):
    if thrusters is None:
        if controls is not None:
            raise ValueError("controls were given without thrusters")
        return None, None
    if len(thrusters) != len(bodies):
        raise ValueError(
            f"thrusters must have one entry (or None) per body: {len(bodies)}, got {len(thrusters)}"
        )
    if controls is None:
        controls = tuple(None for _ in bodies)
    if len(controls) != len(bodies):
        raise ValueError(
            f"controls must have one entry (or None) per body: {len(bodies)}, got {len(controls)}"
        )
    out = []
    for i, (th, u) in enumerate(zip(thrusters, controls, strict=True)):
        if th is None:
            out.append(None)
            continue
        k = th.strengths.shape[0]
        if u is None:
            u = (
                jnp.ones((k,), th.strengths.dtype)
                if num_frames is None
                else jnp.ones((num_frames, k), th.strengths.dtype)
            )
        want = (k,) if num_frames is None else (num_frames, k)
        if tuple(jnp.shape(u)) != want:
            raise ValueError(
                f"controls[{i}] must have shape {want} (frames, thrusters), got {jnp.shape(u)}"
            )
        out.append(u)
    return tuple(thrusters), tuple(out)


def _substep_bodies(bodies, h, gravity, planes, thrusters, controls) -> tuple[RigidBody, ...]:
    """Integrate every body for h (forces, thrusters), then resolve all contacts."""
    moved = []
    for i, b in enumerate(bodies):
        force = torque = None
        if thrusters is not None and thrusters[i] is not None:
            force, torque = thruster_force(b, thrusters[i], controls[i])
        moved.append(integrate_body(b, h, gravity, force=force, torque=torque))
    return collide_all(moved, planes)


def _step(bodies, sim: RigidSettings, planes, thrusters, controls):
    h = sim.dt / sim.num_substeps

    def substep(bodies, _):
        return _substep_bodies(bodies, h, sim.gravity, planes, thrusters, controls), None

    return jax.lax.scan(substep, tuple(bodies), length=sim.num_substeps)[0]


def rigid_step(
    sim: RigidSettings,
    bodies: Sequence[RigidBody],
    *,
    planes: Plane | None = None,
    thrusters: Sequence[Thrusters | None] | None = None,
    controls: Sequence[jax.Array | None] | None = None,
) -> tuple[RigidBody, ...]:
    """Advance the bodies by one frame (`sim.num_substeps` substeps).

    Args:
      sim: dt, gravity, substeps.
      bodies: the bodies (a fixed tuple; shapes static).
      planes: static ground/wall planes (a `Plane`, single or batched), or None.
      thrusters: per body a `Thrusters` or None.
      controls: per body the control levels (k,) for this frame (default: full on), or None.
    Returns:
      The bodies after one frame.
    """
    thrusters, controls = _check_controls(bodies, thrusters, controls, None)
    return _step(tuple(bodies), sim, planes, thrusters, controls)


def rigid_rollout(
    sim: RigidSettings,
    bodies: Sequence[RigidBody],
    *,
    num_frames: int,
    planes: Plane | None = None,
    thrusters: Sequence[Thrusters | None] | None = None,
    controls: Sequence[jax.Array | None] | None = None,
) -> tuple[RigidBody, ...]:
    """Simulate `num_frames` frames with `lax.scan` (checkpointed body).

    Args:
      sim, bodies, planes, thrusters: as in `rigid_step`.
      num_frames: number of frames (static).
      controls: per body a (num_frames, k) array of thruster levels per frame, or None (full on).
    Returns:
      A tuple of `RigidBody` whose array leaves have a leading [num_frames] axis: the state after
      each frame.

    Example:
      >>> sim = make_settings(dt=1 / 60, num_substeps=4)
      >>> ball = make_body("sphere", mass=1.0, radius=0.1, position=(0, 1, 0))
      >>> traj = rigid_rollout(sim, (ball,), num_frames=10)
      >>> traj[0].position.shape
      (10, 3)
    """
    if not isinstance(num_frames, int) or num_frames < 1:
        raise ValueError(f"num_frames must be an integer >= 1, got {num_frames!r}")
    thrusters, controls = _check_controls(bodies, thrusters, controls, num_frames)

    def body(state, u):
        state = _step(state, sim, planes, thrusters, u)
        return state, state

    return jax.lax.scan(jax.checkpoint(body), tuple(bodies), xs=controls, length=num_frames)[1]


def body_at(trajectory: Sequence[RigidBody], frame: int) -> tuple[RigidBody, ...]:
    """The bodies at one frame of a `rigid_rollout` trajectory."""
    return tuple(jax.tree_util.tree_map(lambda a: a[frame], b) for b in trajectory)
