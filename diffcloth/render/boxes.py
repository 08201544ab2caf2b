"""Box rigid bodies as triangle meshes: drawn with the cloth by the rasterizer (occluding it and
occluded by it), shaded like the spheres (albedo `appearance.sphere_color`), and reusable as
occluders (e.g. shadow maps).

Each box has 24 vertices (4 per face, so every face keeps its own flat normal) and 12 triangles,
counter-clockwise seen from outside. Positions are differentiable in the box's pose (position,
orientation quaternion) and half extents.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["BoxPoses", "box_mesh", "box_poses", "box_triangles"]


@functools.lru_cache(maxsize=1)
def _unit_box_np():
    """(24, 3) corners in {-1, 1}^3, (24, 3) outward face normals, (12, 3) faces."""
    corners, normals, faces = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u = np.zeros(3)
            u[(axis + 1) % 3] = 1.0
            v = np.cross(n, u)  # (u, v, n) right-handed: u x v = n, counter-clockwise from outside
            base = len(corners)
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                corners.append(n + a * u + b * v)
                normals.append(n)
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    out = (np.asarray(corners), np.asarray(normals), np.asarray(faces, np.int32))
    for a in out:
        a.setflags(write=False)
    return out


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BoxPoses:
    """Boxes to draw: position (b, 3) m, orientation (b, 4) unit quaternions (w, x, y, z), body
    to world, half_extents (b, 3) m. Arrays may carry a leading frame axis (T, b, ...)."""

    position: jax.Array
    orientation: jax.Array
    half_extents: jax.Array


def box_poses(bodies) -> BoxPoses | None:
    """The box bodies of a sequence of `physics.RigidBody` (any leading axes, e.g. a trajectory
    with a frame axis: position (T, 3) per body) stacked along a body axis; None if no box."""
    boxes = [b for b in bodies if b.shape == "box"]
    if not boxes:
        return None
    ax = boxes[0].position.ndim - 1  # the body axis goes after any leading (frame) axes
    return BoxPoses(
        position=jnp.stack([b.position for b in boxes], axis=ax),
        orientation=jnp.stack([b.orientation for b in boxes], axis=ax),
        half_extents=jnp.stack([b.half_extents for b in boxes], axis=ax),
    )


def _rotations(q):
    from diffcloth.physics.rigid import quat_to_matrix

    return jax.vmap(quat_to_matrix)(q)


def box_mesh(poses: BoxPoses):
    """World-space triangle mesh of the boxes of one frame.

    Returns:
      (verts (24 b, 3), normals (24 b, 3) outward unit face normals, faces (12 b, 3) int32),
      counter-clockwise seen from outside. verts and normals are differentiable in the pose.
    """
    corners, normals, faces = _unit_box_np()
    dtype = poses.position.dtype
    b = poses.position.shape[0]
    rot = _rotations(poses.orientation.astype(dtype))  # (b, 3, 3) body -> world
    local = jnp.asarray(corners, dtype)[None] * poses.half_extents[:, None, :]  # (b, 24, 3)
    verts = jnp.einsum("bij,bkj->bki", rot, local) + poses.position[:, None, :]
    nrm = jnp.einsum("bij,kj->bki", rot, jnp.asarray(normals, dtype))
    offs = (np.arange(b, dtype=np.int32) * 24)[:, None, None]
    f = jnp.asarray((faces[None] + offs).reshape(-1, 3))
    return verts.reshape(-1, 3), nrm.reshape(-1, 3), f


def box_triangles(bodies):
    """(verts (24 b, 3), faces (12 b, 3)) of the box bodies among `bodies` (a sequence of
    `physics.RigidBody` of one frame), e.g. as shadow occluders; empty arrays without boxes."""
    poses = box_poses(bodies)
    if poses is None:
        dtype = bodies[0].position.dtype if bodies else jnp.zeros(()).dtype
        return jnp.zeros((0, 3), dtype), jnp.zeros((0, 3), jnp.int32)
    verts, _, faces = box_mesh(poses)
    return verts, faces


@functools.lru_cache(maxsize=16)
def box_neighbors_np(num_boxes: int) -> np.ndarray:
    """(12 b, 3) edge-neighbour table of `box_mesh` (local indices): each face's two triangles
    share their diagonal; the cube's edges are boundaries (faces have their own vertices), so
    the rasterizer treats them as silhouettes and antialiases them."""
    from diffcloth.render.raster import edge_neighbors

    faces = _unit_box_np()[2]
    with jax.ensure_compile_time_eval():  # concrete even when first called under a trace
        nb = np.asarray(edge_neighbors(faces))
    tiles = [np.where(nb >= 0, nb + 12 * i, -1) for i in range(num_boxes)]
    out = np.concatenate(tiles) if tiles else np.zeros((0, 3), np.int32)
    out.setflags(write=False)
    return out
