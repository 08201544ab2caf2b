"""Rigid-body forces (gravity, drag, thrusters), semi-implicit Euler integration, and the
step and rollout over frames.

See `diffcloth.physics.rigid` for the model and its smoothing.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence

import jax
import jax.numpy as jnp

from diffcloth.physics.rigid.bodies import RigidBody, RigidSettings, Thrusters
from diffcloth.physics.rigid.impulse import collide_pair, collide_plane
from diffcloth.physics.rigid.quat import (
    _inv_inertia_world,
    _quat_exp_step,
    inertia_tensor,
    quat_to_matrix,
)
from diffcloth.shapes import Plane

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
    """One sequential pass over all body pairs (i < j), then every body against every plane.

    Shapes: RigidBody leaves (3,) / (4,); planes' normals (p, 3), offsets (p,) -> the same body shapes.
    """
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
    """The bodies at one frame of a `rigid_rollout` trajectory.

    Shapes: trajectory leaves (T, ...) -> one frame's leaves (...).
    """
    return tuple(jax.tree_util.tree_map(lambda a: a[frame], b) for b in trajectory)
