"""Cloth meshes from Wavefront OBJ files (pure numpy): `read_cloth_obj` parses v / vt / f
(polygons fan-triangulated), checks the mesh and derives the material coordinates."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from diffcloth.physics.mesh.meshdata import (
    _AREA_RTOL,
    MeshData,
    MeshError,
    _positive,
    _signed_area_2d,
    _unique_edges,
    check_mesh,
)

__all__ = ["parse_obj", "read_cloth_obj"]

_PLANAR_RTOL = (
    1e-5  # an OBJ mesh is flat if every vertex lies this close (x bbox diagonal) to its plane
)


def parse_obj(path: Path):
    """v, vt and triangulated f of an OBJ: positions (n, 3), texcoords (k, 2) or None,
    faces (m, 3), face texcoord indices (m, 3) or None (when any face lacks them)."""
    where = str(path)
    v, vt, fv, ft = [], [], [], []
    all_ft = True
    try:
        text = path.read_text()
    except OSError as e:
        raise MeshError(f"{where}: cannot read the file ({e.strerror or e})") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        tag, rest = parts[0], parts[1:]
        try:
            if tag == "v":
                if len(rest) < 3:
                    raise ValueError("a vertex needs 3 coordinates")
                v.append([float(x) for x in rest[:3]])
            elif tag == "vt":
                if len(rest) < 2:
                    raise ValueError("a texture coordinate needs 2 values")
                vt.append([float(x) for x in rest[:2]])
            elif tag == "f":
                if len(rest) < 3:
                    raise ValueError(f"a face needs at least 3 vertices, got {len(rest)}")
                ids = [(c.split("/") + ["", ""])[:2] for c in rest]
                pv = [int(i[0]) for i in ids]
                pv = [i - 1 if i > 0 else len(v) + i for i in pv]
                has_t = all(i[1] for i in ids)
                pt = [int(i[1]) for i in ids] if has_t else []
                pt = [i - 1 if i > 0 else len(vt) + i for i in pt]
                all_ft &= has_t
                for k in range(1, len(pv) - 1):  # fan triangulation
                    fv.append([pv[0], pv[k], pv[k + 1]])
                    ft.append([pt[0], pt[k], pt[k + 1]] if has_t else [-1, -1, -1])
        except ValueError as e:
            raise MeshError(f"{where}: line {lineno} {line.strip()!r}: {e}") from None
    pos = np.asarray(v, np.float64).reshape(-1, 3)
    faces = np.asarray(fv, np.int64).reshape(-1, 3)
    tex = np.asarray(vt, np.float64).reshape(-1, 2) if vt else None
    ftex = np.asarray(ft, np.int64).reshape(-1, 3) if (vt and all_ft and fv) else None
    return pos, tex, faces, ftex


def _uv_from_vt(pos, faces, tex, ftex, where) -> np.ndarray | None:
    """Per-vertex uv from vt if every vertex has exactly one texture coordinate, else None."""
    if tex is None or ftex is None:
        return None
    if ftex.min() < 0 or ftex.max() >= tex.shape[0]:
        k = int(np.flatnonzero(np.any((ftex < 0) | (ftex >= tex.shape[0]), axis=1))[0])
        raise MeshError(
            f"{where}: face {k} has a texture index outside [1, {tex.shape[0]}] (1-based)"
        )
    n = pos.shape[0]
    first = np.full(n, -1)
    fvr, ftr = faces.ravel(), ftex.ravel()
    first[fvr[::-1]] = ftr[::-1]
    if np.any(~np.all(tex[first[fvr]] == tex[ftr], axis=1)):
        return None  # a vertex with two texture coordinates: a seam
    uv = tex[first]
    edges = _unique_edges(faces)
    l3 = np.linalg.norm(pos[edges[:, 1]] - pos[edges[:, 0]], axis=1).mean()
    l2 = np.linalg.norm(uv[edges[:, 1]] - uv[edges[:, 0]], axis=1).mean()
    if not l2 > 0:
        raise MeshError(f"{where}: all vt coordinates coincide; they cannot give material axes")
    uv = uv * (l3 / l2)
    area = _signed_area_2d(uv, faces)
    p = uv[faces]
    scale = np.sum((p[:, [1, 2, 0]] - p) ** 2, axis=(1, 2)) / 3
    bad = np.flatnonzero(area <= _AREA_RTOL * scale.mean())
    if bad.size:
        k = int(bad[0])
        raise MeshError(
            f"{where}: face {k} is flipped or degenerate in its vt (material) coordinates "
            f"(signed area {area[k]:.3g} m^2; {bad.size} such faces); vt must be counter-clockwise "
            "in the same order as the face's vertices"
        )
    return uv


def _plane_frame(pos, faces, warp, where):
    """Unit normal (along the summed face normals) and in-plane warp axis, or None if not flat."""
    p = pos[faces]
    nsum = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(axis=0)
    centred = pos - pos.mean(axis=0)
    _, s, vh = np.linalg.svd(centred, full_matrices=False)
    normal = vh[2]
    diag = float(np.linalg.norm(pos.max(axis=0) - pos.min(axis=0)))
    if np.max(np.abs(centred @ normal)) > _PLANAR_RTOL * diag:
        return None
    if normal @ nsum < 0:
        normal = -normal
    if warp is None:
        cand = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
        axis = cand if np.linalg.norm(cand) >= 0.5 else vh[0]
    else:
        w = np.asarray(warp, np.float64)
        if w.shape != (3,) or not np.all(np.isfinite(w)):
            raise MeshError(f"{where}: warp must be a finite 3-vector, got {warp!r}")
        axis = w - (w @ normal) * normal
        if np.linalg.norm(axis) < 1e-6 * max(np.linalg.norm(w), 1e-300):
            raise MeshError(
                f"{where}: warp {w.tolist()} is perpendicular to the mesh's plane "
                f"(normal {np.round(normal, 6).tolist()}); give a direction within the plane"
            )
    u = axis / np.linalg.norm(axis)
    return normal, u


def read_cloth_obj(path, *, warp=None, scale: float = 1.0) -> MeshData:
    """Read a cloth mesh from a Wavefront OBJ, with material coordinates.

    Reads `v`, `vt` and `f` lines (`f a`, `a/b`, `a//c`, `a/b/c`, negative indices; polygons with
    more than three vertices are fan-triangulated), scales positions by `scale` and runs
    `check_mesh`. Material coordinates (uv, m) follow this rule:

    1. `warp` is None and the file has exactly one vt per vertex (no seams): uv = vt, scaled so
       that the mean uv edge length equals the mean 3D edge length. Every face must be
       counter-clockwise in uv, as in space.
    2. Otherwise, if the mesh is flat (every vertex within 1e-5 of the bounding-box diagonal of
       one plane): uv are coordinates in that plane, relative to the vertex mean, with u along
       the projection of `warp` onto the plane (default: world x projected, or the longest
       principal axis if the plane is nearly perpendicular to x) and v = normal x u, the normal
       being the side the faces' normals point to. vt, if any, are ignored.
    3. Otherwise (a curved rest shape without usable vt) the mesh is refused: a non-flat cloth
       needs per-vertex vt material coordinates (or a flat rest shape and a `warp`).

    Args:
      path: the OBJ file.
      warp: optional (3,) warp direction in world coordinates, for flat meshes.
      scale: factor from file units to m, > 0 (e.g. 0.01 for cm).
    Returns:
      MeshData with source = str(path).
    Raises:
      MeshError: unreadable or malformed lines, any `check_mesh` failure (named by file and face
        or vertex), flipped or degenerate vt, a warp perpendicular to the plane, or a non-flat
        mesh without per-vertex vt.
    """
    path = Path(path)
    where = str(path)
    s = _positive("scale", scale, where)
    pos, tex, faces, ftex = parse_obj(path)
    pos = pos * s
    check_mesh(pos, faces, where)
    uv = _uv_from_vt(pos, faces, tex, ftex, where) if warp is None else None
    if uv is None:
        frame = _plane_frame(pos, faces, warp, where)
        if frame is None:
            if warp is not None and tex is not None:
                why = "warp only applies to flat meshes; pass warp=None to use the file's vt"
            elif tex is not None:
                why = (
                    "its vt are not one per vertex (seams) and cannot serve as material coordinates"
                )
            else:
                why = "it has no vt"
            raise MeshError(
                f"{where}: the mesh is not flat and {why}; a curved cloth needs per-vertex vt "
                "material coordinates (or give a flat rest shape and a warp direction)"
            )
        normal, u_axis = frame
        v_axis = np.cross(normal, u_axis)
        d = pos - pos.mean(axis=0)
        uv = np.stack([d @ u_axis, d @ v_axis], axis=1)
    return MeshData(
        vertices=pos, faces=faces.astype(np.int32), uv=uv.astype(np.float64), source=where
    )
