"""Mesh records and checks of the mesh cloth (pure numpy): `MeshData` (vertices, faces,
material coordinates), `MeshError`, `check_mesh` (refuses NaN, out-of-range or repeated
indices, zero-area faces, non-manifold edges or vertices, flipped neighbours, unreferenced
vertices, naming the source and the face or vertex) and `mesh_quality`."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["MeshData", "MeshError", "check_mesh", "mesh_quality"]

_AREA_RTOL = 1e-8  # a face is degenerate below this area / mean squared edge length


class MeshError(ValueError):
    """A mesh (or builder input) the cloth model cannot use; the message names the source and the
    offending face, vertex or parameter."""


@dataclasses.dataclass(frozen=True)
class MeshData:
    """A triangle mesh with material coordinates (numpy arrays, not a pytree).

    Attributes:
      vertices: (n, 3) float64 rest positions, m.
      faces: (m, 3) int32 vertex indices, counter-clockwise seen from the front (the side the
        normal (v1 - v0) x (v2 - v0) points to).
      uv: (n, 2) float64 material (flat-pattern) coordinates, m: u along the warp, v along the weft.
      source: where the mesh came from, for messages ("disc(R=0.15, h=0.01)" or a file path).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    source: str = ""


# ------------------------------------------------------------------------------------------------
# checks


def _where(source: str) -> str:
    return source or "mesh"


def _edge_table(faces: np.ndarray):
    """Directed half-edges of (m, 3) faces: (3m, 2) vertex pairs and the (3m,) face of each."""
    m = faces.shape[0]
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    face_of = np.repeat(np.arange(m), 3)
    return half, face_of


def check_mesh(vertices, faces, source: str = "") -> None:
    """Refuse a mesh the cloth model cannot use.

    Args:
      vertices: (n, 3) positions in m.
      faces: (m, 3) integer vertex indices (0-based).
      source: the mesh's origin (file path or builder), put at the start of every message.
    Raises:
      MeshError: an empty mesh, wrong shapes, non-finite coordinates (names the vertex), face
        indices out of range, faces with a repeated vertex or (near-)zero area (area below 1e-8 of
        the mean squared edge length; names the face), an edge shared by more than two faces
        (names its vertices and the faces), neighbouring faces with opposite orientation (an edge
        used twice in the same direction; names both faces), unreferenced vertices (names one and
        the count), or a vertex whose faces form more than one fan (names the vertex).

    >>> check_mesh(np.eye(3), [[0, 1, 2]], "example")
    """
    where = _where(source)
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{where}: vertices must have shape (n, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"{where}: faces must have shape (m, 3), got {f.shape}")
    if v.shape[0] == 0 or f.shape[0] == 0:
        raise MeshError(
            f"{where}: empty mesh ({v.shape[0]} vertices, {f.shape[0]} faces); "
            "a cloth needs at least one triangle"
        )
    if f.dtype.kind not in "iu":
        if f.dtype.kind != "f" or not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            raise MeshError(f"{where}: face indices must be integers, got dtype {f.dtype}")
    f = f.astype(np.int64)
    v = v.astype(np.float64)
    n = v.shape[0]
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
    if bad.size:
        i = int(bad[0])
        raise MeshError(
            f"{where}: vertex {i} has a non-finite coordinate {v[i].tolist()} "
            f"({bad.size} such vertices)"
        )
    out = np.flatnonzero(np.any((f < 0) | (f >= n), axis=1))
    if out.size:
        k = int(out[0])
        raise MeshError(
            f"{where}: face {k} {f[k].tolist()} has a vertex index outside [0, {n - 1}] "
            f"({out.size} such faces)"
        )
    rep = np.flatnonzero((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0]))
    if rep.size:
        k = int(rep[0])
        raise MeshError(f"{where}: face {k} {f[k].tolist()} repeats a vertex")
    used = np.zeros(n, bool)
    used[f.ravel()] = True
    unused = np.flatnonzero(~used)
    if unused.size:
        raise MeshError(
            f"{where}: vertex {int(unused[0])} is not used by any face "
            f"({unused.size} unreferenced vertices)"
        )
    p = v[f]
    e = p[:, [1, 2, 0]] - p  # (m, 3, 3) the three edge vectors
    area = 0.5 * np.linalg.norm(np.cross(e[:, 0], -e[:, 2]), axis=1)
    mean_sq = float(np.mean(np.sum(e * e, axis=-1)))
    thin = np.flatnonzero(area <= _AREA_RTOL * mean_sq)
    if thin.size:
        k = int(thin[0])
        raise MeshError(
            f"{where}: face {k} {f[k].tolist()} has (near-)zero area {area[k]:.3g} m^2 "
            f"(mean edge length {math.sqrt(mean_sq):.3g} m; {thin.size} such faces)"
        )

    half, face_of = _edge_table(f)
    key = np.sort(half, axis=1)
    code = key[:, 0] * n + key[:, 1]
    order = np.argsort(code, kind="stable")
    code_s = code[order]
    starts = np.flatnonzero(np.r_[True, code_s[1:] != code_s[:-1]])
    counts = np.diff(np.r_[starts, code_s.size])
    over = np.flatnonzero(counts > 2)
    if over.size:
        s = starts[over[0]]
        hs = order[s : s + counts[over[0]]]
        a, b = key[hs[0]]
        raise MeshError(
            f"{where}: edge ({a}, {b}) is shared by {counts[over[0]]} faces "
            f"{sorted(face_of[hs].tolist())}; a cloth edge may border at most two faces "
            "(non-manifold edge)"
        )
    dcode = half[:, 0] * n + half[:, 1]
    dorder = np.argsort(dcode, kind="stable")
    dup = np.flatnonzero(dcode[dorder][1:] == dcode[dorder][:-1])
    if dup.size:
        h0, h1 = dorder[dup[0]], dorder[dup[0] + 1]
        a, b = half[h0]
        raise MeshError(
            f"{where}: faces {int(face_of[h0])} and {int(face_of[h1])} both use edge ({a} -> {b}) "
            "in the same direction: neighbouring faces are oriented inconsistently"
        )
    _check_fans(f, half, face_of, code, order, starts, counts, where)


def _check_fans(f, half, face_of, code, order, starts, counts, where) -> None:
    """Refuse a vertex whose faces form more than one edge-connected fan."""
    n = int(f.max()) + 1
    m = f.shape[0]
    inner = np.flatnonzero(counts == 2)
    h0 = order[starts[inner]]
    h1 = order[starts[inner] + 1]
    f0, f1 = face_of[h0], face_of[h1]
    # The shared edge (a, b) joins the incidences (a, f0)-(a, f1) and (b, f0)-(b, f1); an
    # incidence (vertex, face) has id 3 * face + the vertex's slot in the face.
    inc_id = lambda face, vert: 3 * face + np.argmax(f[face] == vert[:, None], axis=1)
    a, b = half[h0, 0], half[h0, 1]
    p = np.concatenate([inc_id(f0, a), inc_id(f0, b)])
    q = np.concatenate([inc_id(f1, a), inc_id(f1, b)])
    label = np.arange(3 * m)
    while True:
        low = np.minimum(label[p], label[q])
        new = label.copy()
        np.minimum.at(new, p, low)
        np.minimum.at(new, q, low)
        new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    vert = f.ravel()
    # Fans per vertex = distinct labels among that vertex's incidences.
    pair = np.unique(vert * (3 * m) + label)
    fans = np.bincount(pair // (3 * m), minlength=n)
    multi = np.flatnonzero(fans > 1)
    if multi.size:
        i = int(multi[0])
        faces_i = sorted(np.flatnonzero(np.any(f == i, axis=1)).tolist())
        raise MeshError(
            f"{where}: vertex {i} joins {int(fans[i])} separate fans of faces {faces_i[:12]} "
            "(non-manifold vertex: its faces touch only at the vertex)"
        )


# ------------------------------------------------------------------------------------------------
# quality and shared helpers


def mesh_quality(mesh: MeshData) -> dict[str, float]:
    """Shape figures of a mesh: counts, angles in degrees, edge lengths in m.

    Returns:
      dict with num_vertices, num_faces, min_angle, max_angle, mean_min_angle (mean over faces of
      each face's smallest angle), min_edge, max_edge, mean_edge, area (m^2).
    Shapes: none (a MeshData -> a dict of scalars).
    """
    p = mesh.vertices[mesh.faces]
    ang = _angles(p)
    edges = _unique_edges(mesh.faces)
    length = np.linalg.norm(mesh.vertices[edges[:, 1]] - mesh.vertices[edges[:, 0]], axis=1)
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    return {
        "num_vertices": int(mesh.vertices.shape[0]),
        "num_faces": int(mesh.faces.shape[0]),
        "min_angle": float(ang.min()),
        "max_angle": float(ang.max()),
        "mean_min_angle": float(ang.min(axis=1).mean()),
        "min_edge": float(length.min()),
        "max_edge": float(length.max()),
        "mean_edge": float(length.mean()),
        "area": float(area.sum()),
    }


def _angles(p: np.ndarray) -> np.ndarray:
    """(m, 3) interior angles in degrees of triangles p: (m, 3, d), d = 2 or 3."""
    out = []
    for i in range(3):
        a = p[:, (i + 1) % 3] - p[:, i]
        b = p[:, (i + 2) % 3] - p[:, i]
        cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        out.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.stack(out, axis=1)


def _signed_area_2d(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = uv[faces]
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


def _unique_edges(faces: np.ndarray) -> np.ndarray:
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    return np.unique(np.sort(half, axis=1), axis=0)


def _positive(name: str, value, source: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise MeshError(f"{source}: {name} must be a number, got {value!r}") from None
    if not math.isfinite(x) or x <= 0:
        raise MeshError(f"{source}: {name} must be finite and > 0 (allowed (0, inf)), got {x}")
    return x
