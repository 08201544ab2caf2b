"""The mesh cloth: a triangle mesh with its rest geometry in material (warp / weft) coordinates.

Everything that depends only on the rest mesh is computed once, in numpy, when the cloth is built:
edges, hinges (the two faces of each interior edge), per-face rest frames, lumped vertex areas and
the per-face curvature operator of the bending model (`energy.bending_energy`). The topology is
static; positions, pins and the rest geometry are arrays (differentiable where they are floats).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ClothMesh", "active_part", "make_cloth", "pin_mask", "PIN_RULES"]

#: named pin rules of `make_cloth(..., pinned=...)`
PIN_RULES = ("none", "all", "boundary", "top_edge", "left_edge", "corner")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ClothMesh:
    """A triangle-mesh cloth. Arrays are leaves; index arrays are int32 leaves (never static).

    Attributes:
      rest: (n, 3) rest positions in m (also the default initial state).
      uv: (n, 2) material coordinates in m: u along the warp, v along the weft.
      faces: (m, 3) int32, counter-clockwise seen from the front (normal side).
      edges: (e, 2) int32 unique undirected edges (i < j).
      hinges: (h, 4) int32 [a, b, c, d]: interior edge a-b, face (a, b, c) and face (b, a, d).
      face_hinge: (m, 3) int32: hinge index of the face's edge k (opposite vertex k), -1 on the
        boundary.
      rest_angle: (h,) rest dihedral angle of each hinge, rad (0 for a flat rest mesh).
      dm_inv: (m, 2, 2) inverse of the rest edge matrix [u1 - u0, u2 - u0] in material coords.
      face_area: (m,) rest area in m^2 (from the material coordinates).
      curvature_op: (m, 3, 3) maps the face's three hinge angles (rad, 0 on the boundary) to its
        curvature (k_uu, k_vv, k_uv) in 1/m in the warp / weft frame.
      vertex_area: (n,) lumped area in m^2 (a third of each incident face); mass = density * area.
      pinned: (n,) bool, True where a vertex is held at its position in the state.
      stencil: (m, 6) int32 [f0, f1, f2, o0, o1, o2]: the face and, across its edge k, the
        neighbour's third vertex o_k (f_k itself on the boundary): every vertex the face's
        bending energy depends on.
      face_rest_angle: (m, 3) rest dihedral angle across edge k (0 on the boundary), rad.
      hinge_faces: (h, 2) int32, the two faces of each hinge, in face order (the bending
        model's curvature-jump term couples their curvature tensors).
      neighbors: (n, K) int32, the vertices sharing a face stencil or a hinge's pair of face
        stencils with each vertex (itself first; padded with itself): the columns of the sparse
        Hessian's block rows.
      stencil_slots: (m, 6, 6) int32, the flat (n K) slot of each stencil block (a, b).
      hinge_slots: (h, 12, 12) int32, the flat (n K) slot of each block (a, b) of a hinge's
        two stencils side by side ([stencil of face 0, stencil of face 1]).
    """

    rest: jax.Array
    uv: jax.Array
    faces: jax.Array
    edges: jax.Array
    hinges: jax.Array
    face_hinge: jax.Array
    rest_angle: jax.Array
    dm_inv: jax.Array
    face_area: jax.Array
    curvature_op: jax.Array
    vertex_area: jax.Array
    pinned: jax.Array
    stencil: jax.Array
    face_rest_angle: jax.Array
    hinge_faces: jax.Array
    neighbors: jax.Array
    stencil_slots: jax.Array
    hinge_slots: jax.Array

    @property
    def num_vertices(self) -> int:
        return self.rest.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]


def _edges_and_hinges(faces: np.ndarray):
    """Unique edges, hinges and the face -> hinge table of an oriented manifold mesh (numpy)."""
    m = faces.shape[0]
    # directed half-edges: edge k of face f is opposite vertex k: (f[k+1], f[k+2])
    a = np.stack([faces[:, 1], faces[:, 2], faces[:, 0]], axis=1).reshape(-1)
    b = np.stack([faces[:, 2], faces[:, 0], faces[:, 1]], axis=1).reshape(-1)
    opp = faces.reshape(-1)
    face_of = np.repeat(np.arange(m), 3)
    slot = np.tile(np.arange(3), m)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo.astype(np.int64) * (int(faces.max()) + 1) + hi
    order = np.argsort(key, kind="stable")
    ks = key[order]
    uniq, first, counts = np.unique(ks, return_index=True, return_counts=True)
    edges = np.stack([lo[order][first], hi[order][first]], axis=1).astype(np.int32)
    face_hinge = -np.ones((m, 3), np.int32)
    pairs = first[counts == 2]
    h0, h1 = order[pairs], order[pairs + 1]
    # orient each hinge so that face (a, b, c) holds the half-edge a -> b
    hinges = np.stack([a[h0], b[h0], opp[h0], opp[h1]], axis=1).astype(np.int32)
    idx = np.arange(len(pairs), dtype=np.int32)
    face_hinge[face_of[h0], slot[h0]] = idx
    face_hinge[face_of[h1], slot[h1]] = idx
    return edges, hinges, face_hinge


def _dihedral_np(x: np.ndarray, hinges: np.ndarray) -> np.ndarray:
    a, b, c, d = (x[hinges[:, k]] for k in range(4))
    na = np.cross(b - a, c - a)
    nb = np.cross(a - b, d - b)
    e = b - a
    e = e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-300)
    return np.arctan2(np.sum(e * np.cross(na, nb), axis=1), np.sum(na * nb, axis=1))


def _curvature_operator(uv: np.ndarray, faces: np.ndarray, face_hinge: np.ndarray, hinges):
    """(m, 3, 3): face hinge angles -> (k_uu, k_vv, k_uv).

    A surface of constant curvature S (2 x 2, material frame) over the flat rest pattern is, to
    first order, the height field q(u) = u^T S u / 2 along the normal. Its piecewise-linear
    interpolant has on face f the gradient G_f(S) = sum_i q(u_i) grad(lambda_i), and the dihedral
    angle across the face's edge k is theta_k = -t_k . (G_f - G_g), where t_k is the in-plane
    unit normal of the edge pointing into f and g the face across it. So each interior edge
    gives one linear equation in (k_uu, k_vv, k_uv), exact for any triangulation; a boundary edge
    gives the row of a zero normal curvature across it, t^T S t = 0 (a free edge's natural
    condition when bending has no Poisson coupling). The three rows are inverted per face.
    """
    m = faces.shape[0]

    def grad_lambda(tri):  # (k, 3, 2) -> (k, 3, 2) gradients of the barycentric coordinates
        dm = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=2)
        gi = np.linalg.inv(dm)  # rows: grad lambda_1, grad lambda_2
        return np.stack([-gi[:, 0] - gi[:, 1], gi[:, 0], gi[:, 1]], axis=1)

    def basis_grad(tri, origin):  # (k, 3, 2): G for S = E_uu, E_vv, E_uv (k_uv counts twice)
        rel = tri - origin[:, None, :]
        gl = grad_lambda(tri)
        q = np.stack(
            [0.5 * rel[..., 0] ** 2, 0.5 * rel[..., 1] ** 2, rel[..., 0] * rel[..., 1]], -1
        )
        return np.einsum("kic,kid->kcd", q, gl)

    rows = np.zeros((m, 3, 3))
    for k in range(3):
        p, q = uv[faces[:, (k + 1) % 3]], uv[faces[:, (k + 2) % 3]]
        e = q - p
        e = e / np.linalg.norm(e, axis=1, keepdims=True)
        t = np.stack([-e[:, 1], e[:, 0]], axis=1)  # N x e: into the counter-clockwise face
        hk = face_hinge[:, k]
        inner = hk >= 0
        # boundary rows: t^T S t = 0 (sign irrelevant for a zero right-hand side)
        rows[:, k] = np.stack([t[:, 0] ** 2, t[:, 1] ** 2, 2 * t[:, 0] * t[:, 1]], axis=1)
        if inner.any():
            hh = hinges[hk[inner]]
            f_third = faces[inner, k]
            other = np.where(hh[:, 2] == f_third, hh[:, 3], hh[:, 2])
            tri_f = uv[faces[inner]]
            tri_g = np.stack([uv[hh[:, 0]], uv[hh[:, 1]], uv[other]], axis=1)
            origin = 0.5 * (p[inner] + q[inner])
            diff = basis_grad(tri_f, origin) - basis_grad(tri_g, origin)  # (k, 3 basis, 2)
            rows[inner, k] = -np.einsum("kd,kcd->kc", t[inner], diff)
    return np.linalg.pinv(rows, rcond=1e-8)


def _stencil(faces: np.ndarray, face_hinge: np.ndarray, hinges: np.ndarray) -> np.ndarray:
    """(m, 6): the face's vertices, then the vertex across each edge (the face's own on the
    boundary)."""
    st = np.concatenate([faces, faces], axis=1).astype(np.int64)
    for k in range(3):
        hk = face_hinge[:, k]
        inner = hk >= 0
        hh = hinges[hk[inner]]
        third = faces[inner, k]
        st[inner, 3 + k] = np.where(hh[:, 2] == third, hh[:, 3], hh[:, 2])
    return st


def _hinge_faces(face_hinge: np.ndarray, num_hinges: int) -> np.ndarray:
    """(h, 2): the two faces of each hinge, in face order."""
    out = -np.ones((num_hinges, 2), np.int64)
    f, k = np.nonzero(face_hinge >= 0)
    h = face_hinge[f, k]
    order = np.lexsort((f, h))  # per hinge, its two faces in face order
    h, f = h[order], f[order]
    out[h[0::2], 0], out[h[1::2], 1] = f[0::2], f[1::2]
    return out


def _pair_keys(groups: np.ndarray, n: int) -> np.ndarray:
    """groups (g, s) vertex indices -> (g, s, s) int64 keys row * n + col of all pairs."""
    return groups[:, :, None].astype(np.int64) * n + groups[:, None, :]


def _sparsity(stencil: np.ndarray, hinge_stencil: np.ndarray, n: int):
    """Block-row sparsity of the Hessian: (n, K) neighbours (self first, padded with self), the
    (m, 6, 6) flat slot of each face-stencil pair and the (h, 12, 12) flat slot of each pair of a
    hinge's two stencils."""
    face_keys = _pair_keys(stencil, n)
    hinge_keys = _pair_keys(hinge_stencil, n)
    pairs = np.unique(np.concatenate([face_keys.ravel(), hinge_keys.ravel(),
                                      np.arange(n, dtype=np.int64) * (n + 1)]))  # fmt: skip
    r, c = pairs // n, pairs % n
    counts = np.bincount(r, minlength=n)
    k = int(counts.max())
    nbr = np.repeat(np.arange(n)[:, None], k, axis=1)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # self first: order each row's columns with the diagonal leading
    order = np.argsort(r * (n + 1) + np.where(c == r, 0, c + 1), kind="stable")
    r, c = r[order], c[order]
    pos = np.arange(len(r)) - start[r]
    nbr[r, pos] = c
    flat = r * k + pos
    sorted_keys = r * n + c  # the pairs in slot order; look keys up by sorting them
    lookup = np.argsort(sorted_keys, kind="stable")
    slot_of = lambda keys: flat[lookup[np.searchsorted(sorted_keys[lookup], keys)]]
    return nbr, slot_of(face_keys), slot_of(hinge_keys)


def pin_mask(rule, vertices: np.ndarray, boundary: np.ndarray | None = None) -> np.ndarray:
    """A pin specification -> (n,) bool.

    rule: None / "none", "all", "boundary", "top_edge" (the highest vertices, y within 1e-9 of
    the max), "left_edge" (smallest x), "corner" (the vertex with the largest y - x), a (n,) bool
    mask, or a sequence of vertex indices.
    """
    n = vertices.shape[0]
    if rule is None or (isinstance(rule, str) and rule == "none"):
        return np.zeros(n, bool)
    if isinstance(rule, str):
        if rule == "all":
            return np.ones(n, bool)
        if rule == "boundary":
            if boundary is None:
                raise ValueError("pinned = 'boundary' needs the mesh's boundary")
            return boundary.copy()
        if rule in ("top_edge", "left_edge"):
            col = vertices[:, 1] if rule == "top_edge" else -vertices[:, 0]
            span = max(float(np.ptp(vertices)), 1e-12)
            return col >= col.max() - 1e-9 * span
        if rule == "corner":
            mask = np.zeros(n, bool)
            mask[np.argmax(vertices[:, 1] - vertices[:, 0] - vertices[:, 2])] = True
            return mask
        raise ValueError(f"pinned: unknown rule {rule!r}; allowed: {', '.join(PIN_RULES)}")
    arr = np.asarray(rule)
    if arr.dtype == bool:
        if arr.shape != (n,):
            raise ValueError(f"pinned: a mask must have shape ({n},), got {arr.shape}")
        return arr.copy()
    idx = arr.astype(np.int64).reshape(-1)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(
            f"pinned: vertex indices must lie in [0, {n - 1}], got {idx.min()}..{idx.max()}"
        )
    mask = np.zeros(n, bool)
    mask[idx] = True
    return mask


def boundary_vertices(faces: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: vertices on a boundary edge."""
    _, _, face_hinge = _edges_and_hinges(faces)
    mask = np.zeros(n, bool)
    for k in range(3):
        b = face_hinge[:, k] < 0
        mask[faces[b, (k + 1) % 3]] = True
        mask[faces[b, (k + 2) % 3]] = True
    return mask


def make_cloth(mesh, *, pinned=None, warp_angle: float = 0.0, dtype=None) -> ClothMesh:
    """A ClothMesh from a `builders.MeshData` (vertices, faces, uv) or a (vertices, faces, uv)
    tuple.

    Args:
      mesh: MeshData; vertices (n, 3) m, faces (m, 3) counter-clockwise, uv (n, 2) m.
      pinned: see `pin_mask`.
      warp_angle: degrees; rotates the warp direction in the material plane (the fabric cut at
        an angle: 45 is a bias cut).
      dtype: float dtype of the leaves (default: JAX's default float).
    Returns:
      ClothMesh with every rest quantity precomputed.
    """
    from diffcloth.physics.mesh.builders import MeshData, MeshError, check_mesh

    if not isinstance(mesh, MeshData):
        v, f, uv = mesh
        mesh = MeshData(np.asarray(v, float), np.asarray(f, np.int32), np.asarray(uv, float))
    verts = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    check_mesh(verts, faces, mesh.source)
    uv = np.asarray(mesh.uv, np.float64)
    if uv.shape != (verts.shape[0], 2) or not np.all(np.isfinite(uv)):
        raise MeshError(
            f"{mesh.source or 'mesh'}: uv must be finite with shape ({verts.shape[0]}, 2)"
        )
    if warp_angle:
        c, s = np.cos(np.radians(warp_angle)), np.sin(np.radians(warp_angle))
        uv = uv @ np.array([[c, -s], [s, c]])
    edges, hinges, face_hinge = _edges_and_hinges(faces)
    dm = np.stack([uv[faces[:, 1]] - uv[faces[:, 0]], uv[faces[:, 2]] - uv[faces[:, 0]]], axis=2)
    det = np.linalg.det(dm)
    if np.any(det <= 0):
        bad = int(np.argmax(det <= 0))
        raise MeshError(
            f"{mesh.source or 'mesh'}: face {bad} is degenerate or flipped in the material (uv) "
            f"coordinates (signed area {0.5 * det[bad]:.3g} m^2); uv must be counter-clockwise "
            "like the faces"
        )
    face_area = 0.5 * det
    vertex_area = np.zeros(verts.shape[0])
    np.add.at(vertex_area, faces.reshape(-1), np.repeat(face_area / 3.0, 3))
    mask = pin_mask(pinned, verts, boundary_vertices(faces, verts.shape[0]))
    stencil = _stencil(faces, face_hinge, hinges)
    hinge_faces = _hinge_faces(face_hinge, len(hinges))
    hinge_stencil = stencil[hinge_faces].reshape(-1, 12)
    nbr, slots, hinge_slots = _sparsity(stencil, hinge_stencil, verts.shape[0])
    rest_angle = _dihedral_np(verts, hinges) if len(hinges) else np.zeros(0)
    face_rest = np.where(face_hinge >= 0, rest_angle[np.maximum(face_hinge, 0)] if len(hinges)
                         else 0.0, 0.0)  # fmt: skip
    dtype = dtype or jnp.zeros(()).dtype
    arr = lambda a: jnp.asarray(a, dtype)
    idx = lambda a: jnp.asarray(a, jnp.int32)
    return ClothMesh(
        rest=arr(verts),
        uv=arr(uv),
        faces=idx(faces),
        edges=idx(edges),
        hinges=idx(hinges),
        face_hinge=idx(face_hinge),
        rest_angle=arr(rest_angle),
        dm_inv=arr(np.linalg.inv(dm)),
        face_area=arr(face_area),
        curvature_op=arr(_curvature_operator(uv, faces, face_hinge, hinges)),
        vertex_area=arr(vertex_area),
        pinned=jnp.asarray(mask),
        stencil=idx(stencil),
        face_rest_angle=arr(face_rest),
        hinge_faces=idx(hinge_faces),
        neighbors=idx(nbr),
        stencil_slots=idx(slots),
        hinge_slots=idx(hinge_slots),
    )


def active_part(cloth: ClothMesh, free) -> ClothMesh:
    """The faces and hinges of `cloth` whose energy terms move with the free vertices, as a
    ClothMesh over the same vertices: its energy differs from the cloth's by a constant, its
    gradient and Hessian on the free vertices are the same. (A Cusick drape pins the 36 % of
    the disc on the pedestal: its solve then evaluates two thirds of the faces.)

    Kept: every face whose stencil holds a free vertex, the faces of every hinge next to one
    (the curvature-jump term couples them), and the faces of the hinges those need for their
    curvature; a hinge outside the kept set is a boundary edge of the part (its angle enters
    only terms of pinned vertices). Needs concrete arrays (not traced).
    Shapes: free (n,) bool.
    """
    free = np.asarray(free, bool)
    stencil, hinge_faces = np.asarray(cloth.stencil), np.asarray(cloth.hinge_faces)
    face_hinge = np.asarray(cloth.face_hinge)
    moving = free[stencil].any(axis=1)  # faces with an energy term of their own that moves
    jump = moving[hinge_faces].any(axis=1) if len(hinge_faces) else np.zeros(0, bool)
    curv = moving.copy()
    curv[hinge_faces[jump].ravel()] = True  # their curvature enters a moving jump term
    keep_h = np.zeros(len(hinge_faces), bool)
    keep_h[face_hinge[curv][face_hinge[curv] >= 0]] = True
    keep_f = curv.copy()
    keep_f[hinge_faces[keep_h].ravel()] = True
    fmap = np.full(len(stencil), -1, np.int64)
    fmap[keep_f] = np.arange(int(keep_f.sum()))
    hmap = np.full(len(hinge_faces), -1, np.int64)
    hmap[keep_h] = np.arange(int(keep_h.sum()))
    fh = face_hinge[keep_f]
    fh = np.where(fh >= 0, hmap[np.maximum(fh, 0)], -1)
    per_face = ("faces", "dm_inv", "face_area", "curvature_op", "stencil", "face_rest_angle",
                "stencil_slots")  # fmt: skip
    per_hinge = ("hinges", "rest_angle", "hinge_slots")
    sub = {f: getattr(cloth, f)[np.flatnonzero(keep_f)] for f in per_face}
    sub.update({f: getattr(cloth, f)[np.flatnonzero(keep_h)] for f in per_hinge})
    sub["face_hinge"] = jnp.asarray(fh, jnp.int32)
    sub["hinge_faces"] = jnp.asarray(fmap[hinge_faces[keep_h]], jnp.int32)
    return dataclasses.replace(cloth, **sub)
