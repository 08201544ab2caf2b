"""The whole pipeline as one differentiable function:

    physics.rollout (or coupled_rollout with rigid bodies) -> surface.tessellate
        -> surface.collide_surface -> render.render -> video

`simulate_and_render(scene, params)` returns the video of every camera; `params` is a dict of named
values that override the scene's own (material, wind, appearance, rigid bodies), so any of them
can be fitted.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax
import jax.numpy as jnp

from diffcloth import physics, render, surface
from diffcloth.physics.material import MATERIAL_FIELDS
from diffcloth.render.lights import _APPEARANCE_DEFAULTS
from diffcloth.shapes import Sphere

__all__ = [
    "PARAMETERS",
    "apply_params",
    "diagnose",
    "param_value",
    "render_frames",
    "simulate",
    "simulate_all",
    "simulate_and_render",
]

#: body parameter name -> RigidBody field; values are per body, (num_bodies,) or (num_bodies, 3).
BODY_PARAMETERS = {
    "body_mass": "mass",
    "body_restitution": "restitution",
    "body_friction": "friction",
    "body_velocity": "velocity",
    "body_position": "position",
}

#: name -> (scene field, field inside it). Every fittable parameter of a scene.
PARAMETERS: dict[str, tuple[str, str]] = {
    **{name: ("material", name) for name in MATERIAL_FIELDS},
    "wind": ("sim", "wind"),
    **{name: ("appearance", name) for name in _APPEARANCE_DEFAULTS},
    **{name: ("bodies", field) for name, field in BODY_PARAMETERS.items()},
}


def check_param_names(names) -> None:
    """Raise ValueError for any name that is not a fittable parameter."""
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        raise ValueError(
            f"unknown parameter name(s) {unknown}; allowed: {', '.join(sorted(PARAMETERS))}"
        )


def _check_bodies(scene, name: str) -> None:
    if not scene.bodies:
        raise ValueError(f"{name}: the scene has no rigid bodies (add [[bodies]] to the config)")


def param_value(scene, name: str) -> jax.Array:
    """The scene's current value of a named parameter (body parameters: stacked over bodies)."""
    check_param_names([name])
    group, field = PARAMETERS[name]
    if group == "bodies":
        _check_bodies(scene, name)
        return jnp.stack([getattr(b, field) for b in scene.bodies])
    return getattr(getattr(scene, group), field)


def apply_params(scene, params: Mapping[str, jax.Array] | None):
    """The scene with `params` (name -> value) written into its material, sim, appearance and
    rigid bodies. Body parameters take one value per body ((num_bodies,) or (num_bodies, 3)) or
    one value for all of them."""
    if not params:
        return scene
    check_param_names(params)
    groups: dict[str, dict] = {}
    for name, value in params.items():
        group, field = PARAMETERS[name]
        old = param_value(scene, name)
        groups.setdefault(group, {})[field] = jnp.broadcast_to(
            jnp.asarray(value, old.dtype), old.shape
        )
    body_fields = groups.pop("bodies", None)
    changes = {g: dataclasses.replace(getattr(scene, g), **f) for g, f in groups.items()}
    if body_fields:
        changes["bodies"] = tuple(
            dataclasses.replace(b, **{f: v[i] for f, v in body_fields.items()})
            for i, b in enumerate(scene.bodies)
        )
    return dataclasses.replace(scene, **changes)


def split_colliders(colliders):
    """Static Colliders -> (planes or None, spheres or None), as `physics.coupled_rollout` takes
    them: the planes act on bodies and cloth, the spheres on the cloth only."""
    if colliders is None:
        return None, None
    planes = colliders.planes if colliders.planes.offset.shape[0] else None
    spheres = colliders.spheres if colliders.num_spheres else None
    return planes, spheres


def simulate_all(scene, params=None) -> tuple[physics.ClothState, tuple]:
    """Cloth and rigid-body trajectories: (ClothState with leaves (num_frames, rows, cols, 3),
    tuple of RigidBody with a leading num_frames axis; empty without bodies)."""
    scene = apply_params(scene, params)
    if not scene.bodies:
        return simulate(scene), ()
    planes, spheres = split_colliders(scene.colliders)
    return physics.coupled_rollout(
        scene.net,
        scene.sim,
        scene.material,
        scene.state,
        scene.bodies,
        num_frames=scene.num_frames,
        planes=planes,
        colliders=spheres,
        two_way=scene.two_way,
    )


def simulate(scene, params=None) -> physics.ClothState:
    """The cloth trajectory: ClothState with leaves (num_frames, rows, cols, 3)."""
    scene = apply_params(scene, params)
    if scene.bodies:
        return simulate_all(scene)[0]
    return physics.rollout(
        scene.net,
        scene.sim,
        scene.material,
        scene.state,
        num_frames=scene.num_frames,
        colliders=scene.colliders,
    )


def render_frame(scene, x: jax.Array, spheres=None, boxes=None) -> jax.Array:
    """One control net (rows, cols, 3) -> images (num_cameras, H, W, 3) of the scene.

    spheres: this frame's spheres (default: the scene's static spheres); boxes: this frame's
    `render.boxes.BoxPoses` (box bodies, drawn with the cloth) or None."""
    spheres = scene.spheres if spheres is None else spheres
    surf = surface.tessellate(x, scene.level, scene.basis, flip=scene.flip)
    if spheres is not None:
        surf = surface.collide_surface(surf, spheres)
    images = [
        render.render(
            surf,
            camera,
            scene.lights,
            scene.shading,
            scene.appearance,
            spheres=spheres,
            textures=scene.textures,
            background=scene.background,
            boxes=boxes,
        )[..., :3]
        for camera in scene.cameras
    ]
    return jnp.stack(images)


def frame_spheres(scene, body_traj: tuple):
    """Per-frame spheres to draw: the static ones plus the sphere bodies at each frame.

    Returns None (no spheres) or a Sphere with center (T, n, 3) and radius (n,). Box bodies are
    drawn as triangles (see `frame_boxes`).
    """
    balls = [b for b in body_traj if b.shape == "sphere"]
    if not balls:
        return None
    T = balls[0].position.shape[0]
    centers = [jnp.stack([b.position for b in balls], axis=1)]
    radii = [jnp.stack([b.radius[0] if b.radius.ndim else b.radius for b in balls])]
    if scene.spheres is not None:
        static = scene.spheres.batched()
        centers.insert(0, jnp.broadcast_to(static.center, (T,) + static.center.shape))
        radii.insert(0, static.radius)
    dtype = centers[-1].dtype
    return Sphere(
        jnp.concatenate([c.astype(dtype) for c in centers], axis=1),
        jnp.concatenate([r.astype(dtype) for r in radii]),
    )


def frame_boxes(body_traj: tuple):
    """Per-frame poses of the box bodies (`render.boxes.BoxPoses` with leaves (T, b, ...)), or
    None without boxes."""
    return render.boxes.box_poses(body_traj)


def render_frames(scene, xs: jax.Array, spheres=None, boxes=None) -> jax.Array:
    """Control nets (T, rows, cols, 3) -> video (num_cameras, T, H, W, 3).

    spheres: optional per-frame spheres (center (T, n, 3), radius (n,)), e.g. `frame_spheres`.
    boxes: optional per-frame box poses (leaves (T, b, ...)), e.g. `frame_boxes`.
    Frames are rendered one after another (`lax.map`) with the frame body checkpointed, so the
    memory of a gradient through a long video is that of a few frames plus the trajectory.
    """
    radius = None if spheres is None else spheres.radius
    centers = None if spheres is None else spheres.center

    def one(a):
        x, c, b = a
        return render_frame(scene, x, None if c is None else Sphere(c, radius), b)

    frames = jax.lax.map(jax.checkpoint(one), (xs, centers, boxes))
    return jnp.moveaxis(frames, 0, 1)


def simulate_and_render(scene, params=None) -> jax.Array:
    """Parameters -> physics -> surface -> collision -> render, for every camera.

    Args:
      scene: a `diffcloth.Scene` (see `diffcloth.scene`).
      params: optional dict name -> value overriding the scene's own (see `PARAMETERS`);
        differentiable.
    Returns:
      video (num_cameras, T, H, W, 3), linear RGB, T = num_frames // frame_stride (frames frame_stride, 2 frame_stride, ...).
    """
    scene = apply_params(scene, params)
    traj, bodies = simulate_all(scene)
    k = scene.frame_stride
    spheres = frame_spheres(scene, bodies)
    if spheres is not None:
        spheres = Sphere(spheres.center[k - 1 :: k], spheres.radius)
    boxes = frame_boxes(bodies)
    if boxes is not None:
        boxes = jax.tree.map(lambda a: a[k - 1 :: k], boxes)
    return render_frames(scene, traj.x[k - 1 :: k], spheres, boxes)


def diagnose(scene, params=None) -> str | None:
    """Run the pipeline stage by stage and name the first stage whose output is not finite.

    Each stage (physics, surface, render) is jitted on its own and checked eagerly, frame by
    frame, so a NaN in a fit can be traced to where it starts (the fit loop itself only sees a
    non-finite loss). Returns None when every stage is finite, else a message such as
    "physics: non-finite cloth state from frame 7 of 15 (...)".
    """
    import numpy as np

    from diffcloth.physics.rollout import ADVICE

    scene = apply_params(scene, params)
    for name, value in (params or {}).items():
        if not np.all(np.isfinite(np.asarray(value))):
            return f"parameters: {name} = {np.asarray(value).tolist()} is not finite"
    traj, bodies = jax.jit(simulate_all)(scene)
    ok = np.isfinite(np.asarray(traj.x)).reshape(scene.num_frames, -1).all(axis=1)
    ok &= np.isfinite(np.asarray(traj.v)).reshape(scene.num_frames, -1).all(axis=1)
    for b in bodies:
        ok &= np.isfinite(np.asarray(b.position)).all(axis=1)
    if not ok.all():
        first = int(np.argmin(ok))
        return (
            f"physics: non-finite cloth or body state from frame {first} of {scene.num_frames} "
            f"({ADVICE})"
        )
    k = scene.frame_stride
    xs = traj.x[k - 1 :: k]
    surf = jax.jit(
        jax.vmap(lambda x: surface.tessellate(x, scene.level, scene.basis, flip=scene.flip))
    )(xs)
    for field in ("positions", "normals"):
        good = np.isfinite(np.asarray(getattr(surf, field))).reshape(xs.shape[0], -1).all(axis=1)
        if not good.all():
            return (
                f"surface: non-finite {field} in rendered frame {int(np.argmin(good))} "
                "(degenerate control net?)"
            )
    spheres = frame_spheres(scene, bodies)
    if spheres is not None:
        spheres = Sphere(spheres.center[k - 1 :: k], spheres.radius)
    boxes = frame_boxes(bodies)
    if boxes is not None:
        boxes = jax.tree.map(lambda a: a[k - 1 :: k], boxes)
    video = np.asarray(jax.jit(render_frames)(scene, xs, spheres, boxes))
    good = np.isfinite(video).reshape(video.shape[0], video.shape[1], -1).all(axis=2)
    if not good.all():
        cam, frame = np.unravel_index(int(np.argmin(good)), good.shape)
        return f"render: non-finite pixels in camera {cam}, rendered frame {frame}"
    return None
