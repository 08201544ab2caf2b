"""The whole pipeline as one differentiable function:

    physics.rollout -> surface.tessellate -> surface.collide_surface -> render.render -> video

`simulate_and_render(scene, params)` returns the video of every camera; `params` is a dict of named
values that override the scene's own (material, wind, appearance), so any of them can be fitted.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax
import jax.numpy as jnp

from diffcloth import physics, render, surface
from diffcloth.physics.material import MATERIAL_FIELDS
from diffcloth.render.lights import _APPEARANCE_DEFAULTS

__all__ = ["PARAMETERS", "apply_params", "render_frames", "simulate", "simulate_and_render"]

#: name -> (scene field, field inside it). Every fittable parameter of a scene.
PARAMETERS: dict[str, tuple[str, str]] = {
    **{name: ("material", name) for name in MATERIAL_FIELDS},
    "wind": ("sim", "wind"),
    **{name: ("appearance", name) for name in _APPEARANCE_DEFAULTS},
}


def check_param_names(names) -> None:
    """Raise ValueError for any name that is not a fittable parameter."""
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        raise ValueError(
            f"unknown parameter name(s) {unknown}; allowed: {', '.join(sorted(PARAMETERS))}"
        )


def apply_params(scene, params: Mapping[str, jax.Array] | None):
    """The scene with `params` (name -> value) written into its material, sim and appearance."""
    if not params:
        return scene
    check_param_names(params)
    groups: dict[str, dict] = {}
    for name, value in params.items():
        group, field = PARAMETERS[name]
        old = getattr(getattr(scene, group), field)
        groups.setdefault(group, {})[field] = jnp.broadcast_to(
            jnp.asarray(value, old.dtype), old.shape
        )
    changes = {g: dataclasses.replace(getattr(scene, g), **f) for g, f in groups.items()}
    return dataclasses.replace(scene, **changes)


def simulate(scene, params=None) -> physics.ClothState:
    """The cloth trajectory: ClothState with leaves (num_frames, rows, cols, 3)."""
    scene = apply_params(scene, params)
    return physics.rollout(
        scene.net,
        scene.sim,
        scene.material,
        scene.state,
        num_frames=scene.num_frames,
        colliders=scene.colliders,
    )


def render_frame(scene, x: jax.Array) -> jax.Array:
    """One control net (rows, cols, 3) -> images (num_cameras, H, W, 3) of the scene."""
    surf = surface.tessellate(x, scene.level, scene.basis, flip=scene.flip)
    if scene.spheres is not None:
        surf = surface.collide_surface(surf, scene.spheres)
    images = [
        render.render(
            surf,
            camera,
            scene.lights,
            scene.shading,
            scene.appearance,
            spheres=scene.spheres,
            textures=scene.textures,
            background=scene.background,
        )[..., :3]
        for camera in scene.cameras
    ]
    return jnp.stack(images)


def render_frames(scene, xs: jax.Array) -> jax.Array:
    """Control nets (T, rows, cols, 3) -> video (num_cameras, T, H, W, 3).

    Frames are rendered one after another (`lax.map`) with the frame body checkpointed, so the
    memory of a gradient through a long video is that of a few frames plus the trajectory.
    """
    frames = jax.lax.map(jax.checkpoint(lambda x: render_frame(scene, x)), xs)
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
    traj = simulate(scene)
    return render_frames(scene, traj.x[scene.frame_stride - 1 :: scene.frame_stride])
