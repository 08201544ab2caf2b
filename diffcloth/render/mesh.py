"""Plain triangle meshes for the renderer: smooth vertex normals by area-weighted averaging of
face normals (Delannoy slide 18), and a Surface-like record so `render.render` can light any
mesh (an OBJ file, a box body) with every shading mode.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from diffcloth._math import safe_normalize

__all__ = ["MeshSurface", "face_normals", "mesh_surface", "vertex_normals"]


def face_normals(verts, faces, *, normalize: bool = True):
    """(m, 3) face normals (v1 - v0) x (v2 - v0) (counter-clockwise = front); their length is
    twice the triangle's area unless `normalize`."""
    p = verts[faces]
    n = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return safe_normalize(n) if normalize else n


def vertex_normals(verts, faces):
    """Smooth vertex normals: the area-weighted mean of the normals of the faces around each vertex.

    Args:
      verts: (n, 3) positions in m; differentiable.
      faces: (m, 3) int vertex indices, counter-clockwise seen from the front.
    Returns:
      (n, 3) unit normals (a vertex in no face, or whose faces cancel, gets +y). The cross product
      of two edges is the face normal scaled by twice the area, so summing them per vertex
      (`segment_sum`) weights each face by its area.
    """
    verts = jnp.asarray(verts)
    faces = jnp.asarray(faces).astype(jnp.int32)
    fn = face_normals(verts, faces, normalize=False)  # (m, 3), |fn| = 2 area
    n = verts.shape[0]
    acc = jax.ops.segment_sum(jnp.repeat(fn, 3, axis=0), faces.reshape(-1), num_segments=n)
    return safe_normalize(acc)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MeshSurface:
    """What `render.render` reads from a surface, for an arbitrary triangle mesh.

    positions, normals, tangents, bitangents: (n, 3); uv: (n, 2); faces: (m, 3) int32.
    """

    positions: jax.Array
    normals: jax.Array
    tangents: jax.Array
    bitangents: jax.Array
    uv: jax.Array
    faces: jax.Array


def mesh_surface(verts, faces, *, normals=None, uv=None) -> MeshSurface:
    """A renderable surface from a triangle mesh.

    Args:
      verts: (n, 3) positions in m; faces: (m, 3) int (counter-clockwise = front).
      normals: optional (n, 3) vertex normals; default `vertex_normals` (smooth shading; for a
        faceted look render with shading="flat", which uses the face normals).
      uv: optional (n, 2) texture coordinates (default zeros).
    Returns:
      MeshSurface; tangents are any unit vectors orthogonal to the normals, bitangent = N x T.
    """
    verts = jnp.asarray(verts)
    faces = jnp.asarray(faces).astype(jnp.int32)
    if normals is None:
        normals = vertex_normals(verts, faces)
    normals = safe_normalize(jnp.asarray(normals, verts.dtype))
    axis = jnp.where(
        (jnp.abs(normals[:, 0]) < 0.9)[:, None],
        jnp.asarray([1.0, 0.0, 0.0], verts.dtype)[None, :],
        jnp.asarray([0.0, 0.0, 1.0], verts.dtype)[None, :],
    )
    tangents = safe_normalize(axis - jnp.sum(axis * normals, -1, keepdims=True) * normals)
    bitangents = jnp.cross(normals, tangents)
    if uv is None:
        uv = jnp.zeros((verts.shape[0], 2), verts.dtype)
    return MeshSurface(verts, normals, tangents, bitangents, jnp.asarray(uv, verts.dtype), faces)
