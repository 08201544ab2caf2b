"""Cloth and rigid bodies stepped together: bodies are moving colliders for the control net.

Each frame is split into `sim.num_substeps` exchanges. In each one (substep length h):

1. the rigid bodies are integrated for h (gravity, drag, thrusters) and collide with each other
   and with the static planes (`rigid.py`);
2. the cloth takes one substep (`physics.step_with_contacts` with dt = h, one substep). Spheres
   are moving sphere colliders that travel from their start-of-substep position at their new
   velocity, so they end exactly where the rigid step put them; the planes collide with the cloth
   too. Box bodies are handled here (the cloth stage has no box collider): control points inside a
   box are moved to the nearest face (plus `sim.collision_margin`), their approaching normal
   velocity relative to the box surface is removed and Coulomb friction (material.friction) reduces
   the tangential part, as the cloth stage does for spheres;
3. with `two_way=True` the impulse the cloth received from each body is applied, opposite, to that
   body (momentum of cloth + bodies is conserved by the contact). For spheres it acts through the
   centre (the cloth stage reports summed impulses, so friction torque on a ball is neglected);
   for boxes the per-point impulses also give the torque.

No control point ends a substep inside a body (only the body's velocity changes in step 3, not its
position). Everything is differentiable like the two stages it joins.

Only the control points collide: a sphere whose radius is below half the diagonal of a net cell
can pass between four control points without touching any (the cloth then barely reacts and the
body's mass has almost no effect). Use a net fine enough for the bodies it must stop.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp

from diffcloth._math import safe_div, safe_norm
from diffcloth.physics import rigid
from diffcloth.physics.collide import Colliders, as_colliders
from diffcloth.physics.forces import node_mass
from diffcloth.physics.integrate import step_with_contacts
from diffcloth.physics.material import Material
from diffcloth.physics.net import Net
from diffcloth.physics.rigid import RigidBody, RigidSettings, Thrusters
from diffcloth.physics.state import ClothState, SimSettings
from diffcloth.shapes import Plane, Sphere


def rigid_settings(sim: SimSettings) -> RigidSettings:
    """The rigid-body settings that match the cloth's (same dt, gravity and substeps)."""
    return RigidSettings(dt=sim.dt, gravity=sim.gravity, num_substeps=sim.num_substeps)


def _box_push(x, v, mass, free, box: RigidBody, friction, margin):
    """Push control points out of a box; returns (x, v, impulse on the cloth (3,), torque-impulse
    about the box centre (3,)), impulses in N s."""
    rot = rigid.quat_to_matrix(box.orientation)
    centre = box.position[None, None, :]
    local = jnp.einsum("rcj,jk->rck", x - centre, rot)
    he = (box.half_extents + margin)[None, None, :]
    gaps = he - jnp.abs(local)
    inside = jnp.all(gaps > 0, axis=-1, keepdims=True) & free
    onehot = jax.nn.one_hot(jnp.argmin(gaps, axis=-1), 3, dtype=x.dtype)
    sign = jnp.where(local >= 0, 1.0, -1.0).astype(x.dtype)
    face_local = jnp.where(onehot > 0, sign * he, local)
    nrm = jnp.einsum("rck,jk->rcj", onehot * sign, rot)
    x_new = jnp.where(inside, centre + jnp.einsum("rck,jk->rcj", face_local, rot), x)
    arm = x_new - centre
    surf_v = box.velocity[None, None, :] + jnp.cross(
        jnp.broadcast_to(box.angular_velocity, arm.shape), arm
    )
    u = v - surf_v
    un = jnp.sum(u * nrm, -1, keepdims=True)
    approach = inside & (un < 0)
    dvn = jnp.where(approach, -un, 0.0)
    ut = u - un * nrm
    ut_len = safe_norm(ut, keepdims=True)
    scale = jnp.maximum(1.0 - safe_div(friction * dvn, ut_len), 0.0)
    v_new = jnp.where(approach, surf_v + ut * scale, v)
    imp = mass[..., None] * (v_new - v)
    return x_new, v_new, jnp.sum(imp, axis=(0, 1)), jnp.sum(jnp.cross(arm, imp), axis=(0, 1))


def _apply_reaction(body: RigidBody, impulse, angular_impulse=None) -> RigidBody:
    """Give the body the opposite of the impulse the cloth received (N s, N m s)."""
    v = body.velocity - impulse / body.mass
    w = body.angular_velocity
    if angular_impulse is not None:
        rot = rigid.quat_to_matrix(body.orientation)
        w = w - rigid._inv_inertia_world(body, rot) @ angular_impulse
    return dataclasses.replace(body, velocity=v, angular_velocity=w)


def _stack(items, empty_shape, dtype):
    return jnp.stack(items) if items else jnp.zeros(empty_shape, dtype)


def _check(bodies, planes, colliders):
    if not isinstance(bodies, Sequence) or not all(isinstance(b, RigidBody) for b in bodies):
        raise TypeError(f"bodies: expected a sequence of RigidBody, got {type(bodies)}")
    if planes is not None and not isinstance(planes, Plane):
        raise TypeError(f"planes: expected a Plane (single or batched) or None, got {type(planes)}")
    extra = as_colliders(colliders)
    if extra is not None and extra.spheres.center.ndim != 2:
        raise ValueError("colliders: static extra colliders only (no frame axis)")
    return extra


def _frame(net, sim, material, state, bodies, planes, extra, thrusters, controls, pin_target,
           two_way):  # fmt: skip
    num = sim.num_substeps
    h = sim.dt / num
    sim1 = dataclasses.replace(sim, dt=h, num_substeps=1)
    dtype = state.x.dtype
    mass = node_mass(net, material)
    free = ~net.pinned[..., None]
    x0 = state.x
    sphere_ids = [i for i, b in enumerate(bodies) if b.shape == "sphere"]
    box_ids = [i for i, b in enumerate(bodies) if b.shape == "box"]
    n_static = 0 if extra is None else extra.num_spheres
    static_c = [] if extra is None else list(extra.spheres.center)
    static_r = [] if extra is None else list(extra.spheres.radius)
    plane_n, plane_o = [], []
    for p in ([] if extra is None else [extra.planes]) + ([] if planes is None else [planes]):
        p = p.batched()
        plane_n += list(jnp.asarray(p.normal, dtype))
        plane_o += list(jnp.asarray(p.offset, dtype))

    def substep(carry, s):
        cloth, bodies = carry
        start = [b.position for b in bodies]
        bodies = rigid._substep_bodies(bodies, h, sim.gravity, planes, thrusters, controls)
        # Sphere bodies travel from their start at the new velocity: they end where the rigid
        # step put them.
        centers = [c for c in static_c] + [start[i] for i in sphere_ids]
        radii = [r for r in static_r] + [bodies[i].radius for i in sphere_ids]
        vels = [jnp.zeros(3, dtype)] * n_static + [bodies[i].velocity for i in sphere_ids]
        cols = Colliders(
            spheres=Sphere(_stack(centers, (0, 3), dtype), _stack(radii, (0,), dtype)),
            sphere_velocity=_stack(vels, (0, 3), dtype),
            planes=Plane(_stack(plane_n, (0, 3), dtype), _stack(plane_o, (0,), dtype)),
        )
        target = None
        if pin_target is not None:
            target = x0 + (pin_target - x0) * ((s + 1).astype(dtype) / num)
        cloth, contacts = step_with_contacts(net, sim1, material, cloth, cols, pin_target=target)
        bodies = list(bodies)
        x, v = cloth.x, cloth.v
        for i in box_ids:
            x, v, imp, ang = _box_push(
                x, v, mass, free, bodies[i], material.friction, sim.collision_margin
            )
            if two_way:
                bodies[i] = _apply_reaction(bodies[i], imp, ang)
        if two_way:
            for k, i in enumerate(sphere_ids):
                bodies[i] = _apply_reaction(bodies[i], contacts.sphere[n_static + k])
        return (ClothState(x=x, v=v), tuple(bodies)), None

    return jax.lax.scan(substep, (state, tuple(bodies)), jnp.arange(num))[0]


def coupled_step(
    net: Net,
    sim: SimSettings,
    material: Material,
    state: ClothState,
    bodies: Sequence[RigidBody],
    *,
    planes: Plane | None = None,
    colliders=None,
    thrusters: Sequence[Thrusters | None] | None = None,
    controls: Sequence[jax.Array | None] | None = None,
    pin_target=None,
    two_way: bool = True,
) -> tuple[ClothState, tuple[RigidBody, ...]]:
    """Advance cloth and bodies together by one frame (sim.dt, sim.num_substeps exchanges).

    Args:
      net, sim, material, state: the cloth, as for `physics.step`.
      bodies: the rigid bodies (a fixed tuple; shapes static); differentiable.
      planes: static planes for bodies and cloth (a `Plane`, single or batched), or None.
      colliders: extra static cloth-only colliders (Sphere/Plane/Colliders), or None.
      thrusters, controls: per body, as in `rigid.rigid_step` (controls (k,) for this frame).
      pin_target: (rows, cols, 3) where pinned points are at the end of the frame, or None.
      two_way: if True the cloth's contact impulses act back on the bodies (equal and opposite).
    Returns:
      (cloth state, bodies) at the end of the frame.
    """
    extra = _check(bodies, planes, colliders)
    thrusters, controls = rigid._check_controls(bodies, thrusters, controls, None)
    return _frame(net, sim, material, state, tuple(bodies), planes, extra, thrusters, controls,
                  pin_target, two_way)  # fmt: skip


def coupled_rollout(
    net: Net,
    sim: SimSettings,
    material: Material,
    state: ClothState,
    bodies: Sequence[RigidBody],
    *,
    num_frames: int,
    planes: Plane | None = None,
    colliders=None,
    thrusters: Sequence[Thrusters | None] | None = None,
    controls: Sequence[jax.Array | None] | None = None,
    two_way: bool = True,
) -> tuple[ClothState, tuple[RigidBody, ...]]:
    """Simulate cloth and rigid bodies together for `num_frames` frames (lax.scan, checkpointed).

    Args:
      net, sim, material, state, bodies, planes, colliders, thrusters, two_way: as `coupled_step`.
      num_frames: number of frames (static).
      controls: per body a (num_frames, k) array of thruster levels, or None (full on).
    Returns:
      (cloth trajectory, body trajectory): a ClothState with leaves (frames, rows, cols, 3) and a
      tuple of RigidBody with a leading frames axis; the states after each frame.

    Example:
      >>> from diffcloth import physics
      >>> net = physics.grid_net(4, 4, (0.4, 0.4), plane="xy", pinned="top_corners")
      >>> ball = rigid.make_body("sphere", mass=0.2, radius=0.05, position=(0, -0.2, 0.3),
      ...                        velocity=(0, 0, -3.0))
      >>> cloth, (ball_traj,) = coupled_rollout(net, physics.make_sim(), physics.make_material(),
      ...     physics.rest_state(net), (ball,), num_frames=3)
      >>> cloth.x.shape, ball_traj.position.shape
      ((3, 4, 4, 3), (3, 3))
    """
    if not isinstance(num_frames, int) or num_frames < 1:
        raise ValueError(f"num_frames must be an integer >= 1, got {num_frames!r}")
    extra = _check(bodies, planes, colliders)
    thrusters, controls = rigid._check_controls(bodies, thrusters, controls, num_frames)

    def body(carry, u):
        cloth, bs = _frame(net, sim, material, carry[0], carry[1], planes, extra, thrusters, u,
                           None, two_way)  # fmt: skip
        return (cloth, bs), (cloth, bs)

    init = (state, tuple(bodies))
    return jax.lax.scan(jax.checkpoint(body), init, xs=controls, length=num_frames)[1]


def body_colliders(bodies: Sequence[RigidBody]) -> Colliders:
    """Sphere colliders (and their velocities) for the sphere bodies of one frame, e.g. to render
    or to tessellate-and-push-out the surface with `surface.push_out_of_spheres`.

    Shapes: bodies' positions (3,) m and radii () m -> Colliders with (k, 3) centres and velocities, (k,)
      radii.
    """
    sph = [b for b in bodies if b.shape == "sphere"]
    dtype = bodies[0].position.dtype if bodies else jnp.zeros(()).dtype
    return Colliders(
        spheres=Sphere(_stack([b.position for b in sph], (0, 3), dtype),
                       _stack([b.radius for b in sph], (0,), dtype)),
        sphere_velocity=_stack([b.velocity for b in sph], (0, 3), dtype),
        planes=Plane(jnp.zeros((0, 3), dtype), jnp.zeros((0,), dtype)),
    )  # fmt: skip
