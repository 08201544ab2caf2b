"""Stage-by-stage checks of the pipeline (`diagnose`) and the reason a mesh cloth gives no
shape (`mesh_failure`). Re-exported by `diffcloth.pipeline`."""

from __future__ import annotations

import jax
import numpy as np

from diffcloth import physics
from diffcloth.parameters import apply_params
from diffcloth.pipeline import (
    _kind,
    cloth_render_surface,
    mesh_simulate,
    render_frames,
    rendered_boxes,
    rendered_states,
    rendered_times,
    simulate_all,
)

__all__ = ["diagnose", "mesh_failure"]


def mesh_failure(scene, params=None) -> str | None:
    """Eager: why a mesh cloth scene's physics gives no shape (e.g. "the equilibrium solve did
    not converge after 200 Newton iterations ..."), or None."""
    from diffcloth.physics.mesh.run import status_message

    traj, status = jax.jit(mesh_simulate)(scene, params)
    msg = status_message(scene.sim, status)
    if msg is None and not np.all(np.asarray(physics.frames_ok(scene.net, traj, scene.sim,
                                                              scene.state))):  # fmt: skip
        msg = "the mesh cloth blew up (non-finite or exploded state)"
    return msg


def diagnose(scene, params=None) -> str | None:
    """Run the pipeline stage by stage and name the first stage whose output is not finite.

    Each stage (physics, surface, render) is jitted on its own and checked eagerly, frame by
    frame, so a NaN in a fit can be traced to where it starts (the fit loop itself only sees a
    non-finite loss). Returns None when every stage is finite, else a message such as
    "physics: non-finite cloth state from frame 7 of 15 (...)".
    """
    from diffcloth.physics.rollout import ADVICE

    for name, value in (params or {}).items():
        if not np.all(np.isfinite(np.asarray(value))):
            return f"parameters: {name} = {np.asarray(value).tolist()} is not finite"
    try:
        scene = apply_params(scene, params)
    except ValueError as err:
        return f"parameters: {err}"
    if _kind(scene) == "mesh":
        why = mesh_failure(scene)
        if why is not None:
            return f"physics: {why}"
    traj, bodies = jax.jit(simulate_all)(scene)
    ok = np.asarray(physics.frames_ok(scene.net, traj, scene.sim, scene.state))
    for b in bodies:
        ok &= np.isfinite(np.asarray(b.position)).all(axis=1)
    if not ok.all():
        first = int(np.argmin(ok))
        return (
            f"physics: non-finite or blown-up cloth or body state from frame {first} of "
            f"{scene.num_frames} "
            f"({ADVICE})"
        )
    xs, spheres = rendered_states(scene, traj, bodies)
    surf = jax.jit(jax.vmap(lambda x: cloth_render_surface(scene, x)))(xs)
    for field in ("positions", "normals"):
        good = np.isfinite(np.asarray(getattr(surf, field))).reshape(xs.shape[0], -1).all(axis=1)
        if not good.all():
            return (
                f"surface: non-finite {field} in rendered frame {int(np.argmin(good))} "
                "(degenerate control net?)"
            )
    boxes = rendered_boxes(scene, bodies)
    video = np.asarray(
        jax.jit(lambda sc, x, sp, bx, t: render_frames(sc, x, sp, boxes=bx, times=t))(
            scene, xs, spheres, boxes, rendered_times(scene) if scene.deform else None
        )
    )
    good = np.isfinite(video).reshape(video.shape[0], video.shape[1], -1).all(axis=2)
    if not good.all():
        cam, frame = np.unravel_index(int(np.argmin(good)), good.shape)
        return f"render: non-finite pixels in camera {cam}, rendered frame {frame}"
    return None
