"""The viewer's sliders and the jitted functions behind it: a scene's frames (tessellated cloth, sphere
and box bodies) simulated from given values, and one frame rendered (`model` re-exports the names)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth import physics, surface
from diffcloth.pipeline import apply_params, frame_spheres, split_colliders
from diffcloth.shapes import Sphere

#: slider name -> (label, unit, scale). "log": the slider moves log10 of the value.
SLIDERS: dict[str, tuple[str, str, str]] = {
    "stretch": ("stretch", "N/m", "log"),
    "shear": ("shear", "N/m", "log"),
    "bend": ("bend", "N m", "log"),
    "damping": ("damping", "s", "log"),
    "density": ("density", "kg/m^2", "log"),
    "drag_normal": ("drag (normal)", "N s/m^3", "lin"),
    "drag_tangent": ("drag (tangent)", "N s/m^3", "lin"),
}
WIND_LIMIT = 5.0  # m/s, default range of each wind component slider


def slider_range(name: str, value: float, scale: str | None = None) -> tuple[float, float]:
    """(lo, hi) of a slider around the scene's value: two decades either side for "log" sliders
    (in log10 units), [0, max(4 value, 2)] for linear ones, +-5 m/s (or more) for wind.
    scale: "log" or "lin" (default: the grid's `SLIDERS` entry of `name`)."""
    if name.startswith("wind"):
        lim = max(WIND_LIMIT, 2 * abs(value))
        return -lim, lim
    if (scale or SLIDERS[name][2]) == "log":
        c = math.log10(value) if value > 0 else -4.0
        return c - 2.0, c + 2.0
    return 0.0, max(4.0 * value, 2.0)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Frames:
    """One simulated sequence, ready to draw (numpy after `to_numpy`).

    cloth: (T, n, 3) tessellated, collided surface vertices in m; x, v: (T, rows, cols, 3) control
    net states; body_position: (T, nb, 3); body_orientation: (T, nb, 4) quaternions w, x, y, z;
    body_velocity: (T, nb, 3); ok: () bool, finite and not blown up.
    """

    cloth: Any
    x: Any
    v: Any
    body_position: Any
    body_orientation: Any
    body_velocity: Any
    body_angular_velocity: Any
    ok: Any


def _stack_bodies(btraj, field, T, width, dtype):
    if not btraj:
        return jnp.zeros((T, 0, width), dtype)
    return jnp.stack([getattr(b, field) for b in btraj], axis=1)


def _thrusters(bodies, directions, strengths):
    """One thruster per body at its centre; directions (nb, 3) body frame, strengths (nb,) N."""
    zeros = jnp.zeros((1, 3), directions.dtype)
    return tuple(
        physics.rigid.Thrusters(zeros, directions[i : i + 1], strengths[i : i + 1])
        for i in range(len(bodies))
    )


def _simulate_frames(scene, params, state, bodies, controls, directions, strengths, level):
    """Params + a start state -> Frames of scene.num_frames frames (jitted by `_compiled`).

    controls: (nb, T, 1) thruster levels per body and frame; directions (nb, 3) and strengths
    (nb,) the thrusters (body frame, N). Without bodies these are empty and ignored.
    """
    scene = apply_params(scene, params)
    T = scene.num_frames
    if scene.bodies:
        planes, spheres = split_colliders(scene.colliders)
        traj, btraj = physics.coupled_rollout(
            scene.net,
            scene.sim,
            scene.material,
            state,
            bodies,
            num_frames=T,
            planes=planes,
            colliders=spheres,
            thrusters=_thrusters(bodies, directions, strengths),
            controls=tuple(controls[i] for i in range(len(bodies))),
            two_way=scene.two_way,
        )
    else:
        traj = physics.rollout(
            scene.net, scene.sim, scene.material, state, num_frames=T, colliders=scene.colliders
        )
        btraj = ()
    sph = frame_spheres(scene, btraj)  # None without sphere bodies: then the static spheres
    if sph is None and scene.spheres is not None:
        static = scene.spheres.batched()
        sph = Sphere(jnp.broadcast_to(static.center, (T,) + static.center.shape), static.radius)

    def one(x, centers):
        s = surface.tessellate(x, level, scene.basis, flip=scene.flip)
        if sph is not None:
            s = surface.collide_surface(s, Sphere(centers, sph.radius))
        return s.positions

    centers = sph.center if sph is not None else jnp.zeros((T, 0, 3), traj.x.dtype)
    cloth = jax.vmap(one)(traj.x, centers)
    dtype = traj.x.dtype
    ok = physics.trajectory_ok(scene.net, traj) & jnp.all(jnp.isfinite(cloth))
    return Frames(
        cloth=cloth,
        x=traj.x,
        v=traj.v,
        body_position=_stack_bodies(btraj, "position", T, 3, dtype),
        body_orientation=_stack_bodies(btraj, "orientation", T, 4, dtype),
        body_velocity=_stack_bodies(btraj, "velocity", T, 3, dtype),
        body_angular_velocity=_stack_bodies(btraj, "angular_velocity", T, 3, dtype),
        ok=ok,
    )


#: the jitted simulate function, shared by every viewer in the process: jax.jit's own cache then
#: keeps one compiled program per scene structure (net size, frames, bodies, level).
_SIMULATE = jax.jit(_simulate_frames, static_argnames=("level",))


def _render_one(scene, params, x, centers):
    """One camera's diffcloth render (H, W, 3) of control net x; centers (n, 3) this frame's
    spheres (static + sphere bodies) or (0, 3)."""
    from diffcloth.pipeline import render_frame

    scene = apply_params(scene, params)
    spheres = None
    if centers.shape[0]:
        radius = _sphere_radii(scene)
        spheres = Sphere(centers, radius)
    return render_frame(scene, x, spheres)[0]


_RENDER = jax.jit(_render_one)


def _sphere_radii(scene):
    radii = []
    if scene.spheres is not None:
        radii.append(scene.spheres.batched().radius)
    balls = [b for b in scene.bodies if b.shape == "sphere"]
    if balls:
        radii.append(jnp.stack([jnp.reshape(b.radius, ()) for b in balls]))
    return jnp.concatenate(radii) if radii else jnp.zeros((0,))


def _to_numpy(frames: Frames) -> Frames:
    return Frames(
        **{f.name: np.asarray(getattr(frames, f.name)) for f in dataclasses.fields(Frames)}
    )
