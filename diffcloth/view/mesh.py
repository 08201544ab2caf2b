"""The viewer's side of a triangle-mesh cloth (`scene.cloth_kind(scene) == "mesh"`): its sliders,
the jitted run behind them (`pipeline.mesh_simulate` -> the drawn surface of every frame), one
frame rendered, and the static colliders as plain triangle meshes (the pedestal's capped
cylinder, boxes, [[meshes]] soups) for the 3D view. `model.ViewModel` dispatches here; nothing
here imports viser.

A mesh run is either a dynamic rollout (frames of `[sim] dt`) or the static equilibrium (one
frame: the rest shape). A slider move re-runs it from the scene's start state, the way `diffcloth
simulate` does, so the shape on screen is the pipeline's for those values (a warm start from the
shape on screen saves no Newton steps on a drape: the solve still crosses the buckling phase).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth import surface
from diffcloth.pipeline import apply_params, mesh_simulate, render_frame, rendered_boxes
from diffcloth.shapes import Sphere
from diffcloth.view.frames import Frames, _sphere_radii

#: a mesh cloth's sliders in equilibrium mode: name -> (label, unit, scale) (as `frames.SLIDERS`)
MESH_SLIDERS: dict[str, tuple[str, str, str]] = {
    "bend_warp": ("bend warp", "N m", "log"),
    "bend_weft": ("bend weft", "N m", "log"),
    "bend_bias": ("bend bias", "N m", "log"),
    "density": ("density", "kg/m^2", "log"),
    "stretch_warp": ("stretch warp", "N/m", "log"),
    "stretch_weft": ("stretch weft", "N/m", "log"),
    "shear": ("shear", "N/m", "log"),
}
#: the fields only a dynamic mesh run feels (plus the wind sliders)
MESH_DYNAMIC_SLIDERS: dict[str, tuple[str, str, str]] = {
    "damping": ("damping", "s", "log"),
    "drag": ("drag", "N s/m^3", "lin"),
}
#: above this many simulated vertices a mesh cloth's sliders are shown disabled: one equilibrium
#: re-solve then takes minutes on a CPU (about 5-11 s at 630 vertices on the 2-core machine)
MESH_SLIDER_MAX_VERTICES = 3000


def mesh_sliders(scene) -> dict[str, tuple[str, str, str]]:
    """The sliders of a mesh scene: the fabric fields its run depends on."""
    if scene.sim.mode == "equilibrium":
        return dict(MESH_SLIDERS)
    return {**MESH_SLIDERS, **MESH_DYNAMIC_SLIDERS}


def slider_note(scene) -> str | None:
    """Why a mesh scene's sliders are disabled, or None when they re-simulate."""
    n = int(scene.net.rest.shape[0])
    if n > MESH_SLIDER_MAX_VERTICES:
        what = "equilibrium re-solve" if scene.sim.mode == "equilibrium" else "re-simulation"
        return (
            f"Sliders disabled: the cloth has {n:,} vertices (more than "
            f"{MESH_SLIDER_MAX_VERTICES:,}), and one {what} per slider move would take minutes. "
            "View a coarser copy ([cloth] edge_length) to explore the fabric values."
        )
    return None


def mesh_faces(scene) -> np.ndarray:
    """(m, 3) int faces of the drawn mesh cloth ([cloth] subdivide's display mesh, or the cloth's)."""
    display = getattr(scene, "display", None)
    if display is not None and display.level > 0:
        return np.asarray(display.faces, np.int64)
    return np.asarray(scene.net.faces, np.int64)


def _simulate_mesh_frames(scene, params):
    """Params -> (Frames (T frames of the drawn surface; no bodies), converged (T,), iterations
    (T,), residual (T,)); T = num_frames (dynamic) or 1 (equilibrium). Jitted as `_SIMULATE_MESH`."""
    scene = apply_params(scene, params)
    traj, status = mesh_simulate(scene)
    spheres = scene.spheres.batched() if scene.spheres is not None else None

    def one(x):
        from diffcloth.pipeline import cloth_render_surface

        s = cloth_render_surface(scene, x)
        if spheres is not None:
            s = surface.collide_surface(s, spheres)
        return s.positions

    cloth = jax.vmap(one)(traj.x)
    T, dtype = traj.x.shape[0], traj.x.dtype
    ok = jnp.all(status.converged) & jnp.all(jnp.isfinite(cloth))
    frames = Frames(
        cloth=cloth,
        x=traj.x,
        v=traj.v,
        body_position=jnp.zeros((T, 0, 3), dtype),
        body_orientation=jnp.zeros((T, 0, 4), dtype),
        body_velocity=jnp.zeros((T, 0, 3), dtype),
        body_angular_velocity=jnp.zeros((T, 0, 3), dtype),
        ok=ok,
    )
    return frames, status.converged, status.iterations, status.residual


#: one compiled program per mesh scene structure (vertex count, mode, frames), shared by viewers
_SIMULATE_MESH = jax.jit(_simulate_mesh_frames)


def _render_mesh_one(scene, params, x, centers):
    """One camera's diffcloth render (H, W, 3) of mesh vertices x (n, 3), as the pipeline renders
    a mesh scene (its box colliders drawn); centers (s, 3) the static spheres or (0, 3)."""
    scene = apply_params(scene, params)
    spheres = Sphere(centers, _sphere_radii(scene)) if centers.shape[0] else None
    boxes = rendered_boxes(scene)
    if boxes is not None:  # leaves (T_video, b, ...): the boxes are static, take one frame
        boxes = jax.tree_util.tree_map(lambda a: a[0], boxes)
    return render_frame(scene, x, spheres, boxes=boxes)[0]


_RENDER_MESH = jax.jit(_render_mesh_one)


# ---- colliders as triangle meshes ------------------------------------------------------------
def cylinder_mesh(top, radius: float, height: float, segments: int = 48):
    """A vertical capped cylinder from its top cap's centre down `height` m (the drape tester's
    pedestal, `MeshColliders.cylinder_*`): (vertices (2 segments + 2, 3), faces (4 segments, 3)),
    faces counter-clockwise seen from outside."""
    top = np.asarray(top, np.float64)
    a = 2.0 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(a), np.zeros(segments), radius * np.sin(a)], axis=1)
    down = np.array([0.0, height, 0.0])
    v = np.concatenate([top + ring, top - down + ring, [top, top - down]])
    i = np.arange(segments)
    j = (i + 1) % segments
    ct, cb = 2 * segments, 2 * segments + 1
    faces = np.concatenate([
        np.stack([i, j, i + segments], 1),  # side
        np.stack([j, j + segments, i + segments], 1),
        np.stack([np.full(segments, ct), j, i], 1),  # top cap, facing +y
        np.stack([np.full(segments, cb), i + segments, j + segments], 1),  # bottom cap, -y
    ])  # fmt: skip
    return v, faces.astype(np.int64)


def _wxyz(rotation) -> np.ndarray:
    """A rotation matrix (3, 3) -> a unit quaternion (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(rotation, np.float64)).as_quat()
    return np.array([w, x, y, z])


def collider_boxes(colliders) -> list[dict]:
    """center (3,), half_extents (3,), wxyz (4,) of each box of `MeshColliders`."""
    if colliders is None:
        return []
    c = colliders
    return [
        {
            "center": np.asarray(c.box_center[k], np.float64),
            "half_extents": np.asarray(c.box_half[k], np.float64),
            "wxyz": _wxyz(c.box_rotation[k]),
        }
        for k in range(c.box_center.shape[0])
    ]


def collider_meshes(colliders) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(kind, vertices, faces) of every capped cylinder and of the triangle soup ([[meshes]]) of
    `MeshColliders`: what the 3D view draws besides planes, spheres and boxes."""
    if colliders is None:
        return []
    c = colliders
    out = []
    for k in range(c.cylinder_top.shape[0]):
        v, f = cylinder_mesh(c.cylinder_top[k], float(c.cylinder_radius[k]),
                             float(c.cylinder_height[k]))  # fmt: skip
        out.append(("cylinder", v, f))
    tri = np.asarray(c.triangles, np.float64)
    if tri.shape[0]:
        out.append(("mesh", tri.reshape(-1, 3), np.arange(3 * tri.shape[0]).reshape(-1, 3)))
    return out


def collider_planes(colliders) -> list[tuple[np.ndarray, float]]:
    """(normal (3,), offset) of each plane of `MeshColliders`."""
    if colliders is None or colliders.plane_offset.shape[0] == 0:
        return []
    return [
        (np.asarray(n, np.float64), float(o))
        for n, o in zip(colliders.plane_normal, colliders.plane_offset, strict=True)
    ]
