"""The mesh cloth as a render-ready surface: smooth vertex normals, texture coordinates from the
material (warp / weft) coordinates, tangents along the warp, and an optional Loop subdivision for
display. (The one place where physics meets the renderer's record: `render.mesh.MeshSurface`.)

The subdivision is a fixed linear map of the simulated positions (the topology is static), built
once in numpy (`display_mesh`) and applied with one gather and a segment sum, so the surface stays
differentiable in x and cheap inside a compiled program. It only changes what is drawn: the
physics, contacts and fits see the simulated vertices.

    >>> from diffcloth.physics.mesh import disc, make_cloth, cloth_surface
    >>> cloth = make_cloth(disc(0.1, 0.03))
    >>> surf = cloth_surface(cloth, cloth.rest)
    >>> surf.positions.shape == cloth.rest.shape, float(surf.uv.min()) >= 0.0
    (True, True)
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from diffcloth._math import safe_normalize
from diffcloth.physics.mesh.topology import ClothMesh
from diffcloth.render.mesh import MeshSurface, vertex_normals

__all__ = [
    "DisplayMesh",
    "MAX_SUBDIVIDE",
    "cloth_surface",
    "display_mesh",
    "material_uv_bounds",
    "texture_uv",
]

#: most Loop subdivision levels `display_mesh` accepts (each level has 4x the faces)
MAX_SUBDIVIDE = 3


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DisplayMesh:
    """The drawn mesh of a cloth: a linear map from the simulated vertices, its faces and uv.

    Attributes:
      rows, cols: (k,) int32; weights: (k,) float: drawn vertex rows[j] gets weights[j] times
        simulated vertex cols[j] (a sparse (n_drawn, n) matrix in COO form).
      faces: (m_drawn, 3) int32, counter-clockwise like the cloth's.
      num_vertices: static, n_drawn.
      level: static, the subdivision level.
    """

    rows: jax.Array
    cols: jax.Array
    weights: jax.Array
    faces: jax.Array
    num_vertices: int = dataclasses.field(metadata={"static": True})
    level: int = dataclasses.field(default=0, metadata={"static": True})


def material_uv_bounds(uv):
    """(lo (2,), hi (2,)) m: the bounding box of material coordinates (n, 2)."""
    uv = jnp.asarray(uv)
    return jnp.min(uv, axis=0), jnp.max(uv, axis=0)


def texture_uv(uv, *, bounds=None):
    """Material coordinates (n, 2) m -> texture coordinates (n, 2) in [0, 1] over the piece
    (`bounds`: the (lo, hi) box mapped to [0, 1]^2; default the box of `uv` itself).

    u runs along the warp from the piece's smallest to its largest warp coordinate; v along
    -weft, so that on the flat builders (weft = -z) v grows with z, as the grid net's rows do
    (`surface.grid_uv`): the square grid as a mesh gets the grid's texture layout. Each axis is
    normalised on its own (a textured rectangle shows the whole texture, as the grid does).
    """
    uv = jnp.asarray(uv)
    lo, hi = material_uv_bounds(uv) if bounds is None else bounds
    lo, hi = jnp.asarray(lo, uv.dtype), jnp.asarray(hi, uv.dtype)
    span = jnp.where(hi > lo, hi - lo, 1.0)
    u = (uv[:, 0] - lo[0]) / span[0]
    v = (hi[1] - uv[:, 1]) / span[1]
    return jnp.stack([u, v], axis=-1)


def _edge_table(faces: np.ndarray, n: int):
    """Unique edges (e, 2), each face edge's index (m, 3) (edge k opposite vertex k), and the
    number of faces of each edge (e,)."""
    a = faces[:, [1, 2, 0]].reshape(-1)
    b = faces[:, [2, 0, 1]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo.astype(np.int64) * n + hi
    uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    edges = np.stack([uniq // n, uniq % n], axis=1)
    return edges, inverse.reshape(-1, 3), counts


def _loop_level(faces: np.ndarray, n: int):
    """One Loop subdivision step (Loop 1987, with the boundary rules of Hoppe et al. 1994):
    (S (n + e, n) sparse, new faces (4 m, 3)); vertex n + k is the point of edge k."""
    edges, face_edge, counts = _edge_table(faces, n)
    e = len(edges)
    boundary_edge = counts == 1
    # neighbours: all edge endpoints; boundary neighbours: endpoints of boundary edges
    i, j = edges[:, 0], edges[:, 1]
    adj = sp.coo_matrix((np.ones(2 * e), (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    bi, bj = i[boundary_edge], j[boundary_edge]
    badj = sp.coo_matrix(
        (np.ones(2 * len(bi)), (np.r_[bi, bj], np.r_[bj, bi])), shape=(n, n)
    ).tocsr()
    valence = np.asarray(adj.sum(axis=1)).ravel()
    on_boundary = np.asarray(badj.sum(axis=1)).ravel() > 0
    # old (even) vertices
    k = np.maximum(valence, 1)
    beta = np.where(k > 3, 3.0 / (8.0 * k), 3.0 / 16.0)
    inner = (
        sp.diags(np.where(on_boundary, 0.0, 1.0 - k * beta))
        + sp.diags(np.where(on_boundary, 0.0, beta)) @ adj
    )
    edge_rule = (
        sp.diags(np.where(on_boundary, 0.75, 0.0))
        + sp.diags(np.where(on_boundary, 0.125, 0.0)) @ badj
    )
    even = (inner + edge_rule).tocoo()
    # new (odd) vertices: 3/8 endpoints + 1/8 opposite vertices, midpoints on the boundary
    rows, cols, vals = [], [], []
    w_end = np.where(boundary_edge, 0.5, 0.375)
    for end in (i, j):
        rows.append(np.arange(e)), cols.append(end), vals.append(w_end)
    for kk in range(3):
        fe = face_edge[:, kk]
        inner_f = ~boundary_edge[fe]
        rows.append(fe[inner_f]), cols.append(faces[inner_f, kk])
        vals.append(np.full(int(inner_f.sum()), 0.125))
    odd = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(e, n))  # fmt: skip
    s = sp.vstack([even, odd]).tocsr()
    # faces: the corner triangles and the middle one; edge k of a face is opposite vertex k
    m01, m12, m20 = (n + face_edge[:, 2], n + face_edge[:, 0], n + face_edge[:, 1])
    f0, f1, f2 = faces[:, 0], faces[:, 1], faces[:, 2]
    new_faces = np.concatenate([
        np.stack([f0, m01, m20], 1),
        np.stack([m01, f1, m12], 1),
        np.stack([m20, m12, f2], 1),
        np.stack([m01, m12, m20], 1),
    ])  # fmt: skip
    return s, new_faces


def display_mesh(cloth: ClothMesh, subdivide: int = 0) -> DisplayMesh:
    """The drawn mesh of `cloth` after `subdivide` Loop subdivision steps (numpy, eager: the
    cloth's faces and uv must be concrete, so build it outside jit and keep it, e.g. in the
    Scene).

    Args:
      cloth: the mesh cloth.
      subdivide: subdivision levels in [0, MAX_SUBDIVIDE]; each multiplies the faces by 4.
    Returns:
      DisplayMesh. Level 0 is the identity map. Loop's rules smooth the drawn shape (the drawn
      surface does not pass through the simulated vertices); the flat pattern's uv is
      subdivided at edge midpoints (it stays the flat pattern).
    Raises:
      ValueError: subdivide out of range.
    """
    if isinstance(subdivide, bool) or not isinstance(subdivide, int | np.integer):
        raise ValueError(f"subdivide must be an integer in [0, {MAX_SUBDIVIDE}], got {subdivide!r}")
    if not 0 <= subdivide <= MAX_SUBDIVIDE:
        raise ValueError(f"subdivide = {subdivide} is out of range; allowed [0, {MAX_SUBDIVIDE}]")
    faces = np.asarray(cloth.faces, np.int64)
    n = int(cloth.rest.shape[0])
    s = sp.identity(n, format="csr")
    f = faces
    for _ in range(int(subdivide)):
        step, f = _loop_level(f, s.shape[0])
        s = (step @ s).tocsr()
    coo = s.tocoo()
    dtype = cloth.rest.dtype
    return DisplayMesh(
        rows=jnp.asarray(coo.row, jnp.int32),
        cols=jnp.asarray(coo.col, jnp.int32),
        weights=jnp.asarray(coo.data, dtype),
        faces=jnp.asarray(f, jnp.int32),
        num_vertices=int(s.shape[0]),
        level=int(subdivide),
    )


def _apply(display: DisplayMesh, a):
    """(n, c) per simulated vertex -> (n_drawn, c) per drawn vertex."""
    return jax.ops.segment_sum(
        display.weights[:, None].astype(a.dtype) * a[display.cols],
        display.rows,
        num_segments=display.num_vertices,
    )


def _warp_tangents(x, faces, material_uv):
    """(n, 3) unit tangents along the warp: the area-weighted mean over the faces around each
    vertex of d x / d u (the first column of the deformation gradient), made orthogonal to the
    normal by the caller."""
    p = x[faces]
    q = material_uv[faces]
    ds = jnp.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=-1)  # (m, 3, 2)
    dm = jnp.stack([q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]], axis=-1)  # (m, 2, 2)
    det = dm[:, 0, 0] * dm[:, 1, 1] - dm[:, 0, 1] * dm[:, 1, 0]
    # first column of adj(dm) (det * dm^-1 [:, 0]): weights each face by twice its area
    col = jnp.stack([dm[:, 1, 1], -dm[:, 1, 0]], axis=-1) * jnp.sign(det)[:, None]
    t = jnp.einsum("mij,mj->mi", ds, col)
    n = x.shape[0]
    return jax.ops.segment_sum(jnp.repeat(t, 3, axis=0), faces.reshape(-1), num_segments=n)


def cloth_surface(
    cloth: ClothMesh, x, *, subdivide: int = 0, display: DisplayMesh | None = None
) -> MeshSurface:
    """The cloth at positions x as a surface `render.render` draws (any shading mode, textures).

    Args:
      cloth: the mesh cloth (faces and material coordinates).
      x: (n, 3) vertex positions in m; differentiable.
      subdivide: Loop subdivision levels for display (0: the simulated mesh itself). Needs a
        concrete cloth (it builds `display_mesh`); under jit pass `display` instead.
      display: a prebuilt `display_mesh(cloth, level)` (wins over `subdivide`).
    Returns:
      MeshSurface: positions (n_drawn, 3) m, smooth area-weighted vertex normals (the side the
      counter-clockwise faces face), tangents along the warp (unit, orthogonal to the normal),
      bitangents = normal x tangent, uv in [0, 1] (`texture_uv` over the cloth's material
      coordinates; the drawn vertices get the same linear map of them as their positions, so a
      flat sheet keeps its texture layout at every level), faces (m_drawn, 3) int32.
    """
    x = jnp.asarray(x)
    if display is None and subdivide:
        display = display_mesh(cloth, subdivide)
    material_uv = cloth.uv.astype(x.dtype)
    uv = texture_uv(material_uv)
    if display is None or display.level == 0:
        faces, pos = cloth.faces.astype(jnp.int32), x
    else:
        faces, pos = display.faces, _apply(display, x)
        material_uv = _apply(display, material_uv)
        uv = texture_uv(material_uv, bounds=material_uv_bounds(cloth.uv))
    normals = vertex_normals(pos, faces)
    t = _warp_tangents(pos, faces, material_uv)
    t = t - jnp.sum(t * normals, axis=-1, keepdims=True) * normals
    # a vertex whose warp tangent vanishes (degenerate faces) falls back to any orthogonal axis
    axis = jnp.where(
        (jnp.abs(normals[:, 0]) < 0.9)[:, None],
        jnp.asarray([1.0, 0.0, 0.0], x.dtype)[None, :],
        jnp.asarray([0.0, 0.0, 1.0], x.dtype)[None, :],
    )
    fallback = axis - jnp.sum(axis * normals, -1, keepdims=True) * normals
    small = jnp.sum(t * t, axis=-1, keepdims=True) <= 1e-24
    tangents = safe_normalize(jnp.where(small, fallback, t))
    bitangents = jnp.cross(normals, tangents)
    return MeshSurface(pos, normals, tangents, bitangents, uv, faces)
