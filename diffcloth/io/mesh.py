"""Mesh export (OBJ). Owned by the surface stage.

Writes a tessellated surface as a Wavefront OBJ with positions (``v``), texture coordinates
(``vt``), normals (``vn``) and triangles (``f a/a/a b/b/b c/c/c``, 1-based indices, vertex, uv
and normal sharing one index), which Blender and MeshLab open directly. OBJ's ``vt`` is written
as the surface's uv unchanged (u along net columns, v along net rows).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

__all__ = ["write_obj", "write_obj_sequence", "read_obj"]


def _as_np(x, name: str, shape_tail: tuple[int, ...], n: int | None = None) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        raise ValueError(
            f"{name} must have shape (n, {', '.join(map(str, shape_tail))}), got {a.shape}"
        )
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} must have {n} rows (one per vertex), got {a.shape[0]}")
    return a


def _fmt_rows(prefix: str, a: np.ndarray, fmt: str, per_row: int | None = None) -> str:
    """One line per row of `a`: prefix, then `fmt` per_row times (default: once per column)."""
    if a.size == 0:
        return ""
    line = prefix + " " + " ".join([fmt] * (per_row or a.shape[1]))
    return "\n".join(line % tuple(row) for row in a.tolist()) + "\n"


def write_obj(
    path,
    surface=None,
    *,
    positions=None,
    faces=None,
    normals=None,
    uv=None,
    precision: int = 6,
    comment: str | None = None,
) -> Path:
    """Write one mesh as OBJ.

    Args:
      path: output file (parent folders are created).
      surface: a `diffcloth.surface.Surface` (or anything with positions, faces and optionally
        normals and uv attributes). Keyword arrays override its fields.
      positions: (n, 3) in m, if no surface is given.
      faces: (m, 3) 0-based vertex indices (written 1-based).
      normals: optional (n, 3); uv: optional (n, 2).
      precision: decimals written per float.
      comment: optional first-line comment.
    Returns:
      The path written.
    Raises:
      ValueError: missing positions/faces, wrong shapes, face indices out of range,
        non-finite values.
    """
    if surface is not None:
        positions = surface.positions if positions is None else positions
        faces = surface.faces if faces is None else faces
        normals = getattr(surface, "normals", None) if normals is None else normals
        uv = getattr(surface, "uv", None) if uv is None else uv
    if positions is None or faces is None:
        raise ValueError("write_obj needs positions and faces (pass a Surface or both arrays)")
    v = _as_np(positions, "positions", (3,))
    n = v.shape[0]
    f = _as_np(faces, "faces", (3,)).astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= n):
        raise ValueError(f"faces index range [{f.min()}, {f.max()}] is outside [0, {n - 1}]")
    vn = None if normals is None else _as_np(normals, "normals", (3,), n)
    vt = None if uv is None else _as_np(uv, "uv", (2,), n)
    for name, a in (("positions", v), ("normals", vn), ("uv", vt)):
        if a is not None and not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains non-finite values")
    num = f"%.{int(precision)}f"
    parts = [f"# {comment}\n" if comment else "", "# written by diffcloth\n"]
    parts.append(_fmt_rows("v", v, num))
    if vt is not None:
        parts.append(_fmt_rows("vt", vt, num))
    if vn is not None:
        parts.append(_fmt_rows("vn", vn, num))
    idx = f + 1
    if vt is not None and vn is not None:
        rows = np.repeat(idx, 3, axis=1)
        parts.append(_fmt_rows("f", rows, "%d/%d/%d", 3))
    elif vt is not None:
        parts.append(_fmt_rows("f", np.repeat(idx, 2, axis=1), "%d/%d", 3))
    elif vn is not None:
        parts.append(_fmt_rows("f", np.repeat(idx, 2, axis=1), "%d//%d", 3))
    else:
        parts.append(_fmt_rows("f", idx, "%d"))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(parts))
    return path


def _frames(surfaces_or_positions) -> Iterable[dict]:
    """Yield per-frame dicts of arrays from a list of surfaces, a batched Surface (leading T axis)
    or a (T, n, 3) positions array."""
    obj = surfaces_or_positions
    if hasattr(obj, "positions"):  # one Surface with a leading frame axis
        pos = np.asarray(obj.positions)
        if pos.ndim != 3:
            raise ValueError(
                f"a Surface passed as a sequence needs positions (T, n, 3), got {pos.shape}; "
                "use write_obj for one frame"
            )
        fields = {k: getattr(obj, k, None) for k in ("positions", "faces", "normals", "uv")}
        for t in range(pos.shape[0]):
            yield {
                k: (None if a is None else (np.asarray(a)[t] if np.ndim(a) == 3 else np.asarray(a)))
                for k, a in fields.items()
            }
        return
    if isinstance(obj, Sequence) and obj and hasattr(obj[0], "positions"):
        for s in obj:
            yield {k: getattr(s, k, None) for k in ("positions", "faces", "normals", "uv")}
        return
    pos = np.asarray(obj)
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise ValueError(
            f"surfaces_or_positions must be a list of Surfaces, a batched Surface or a (T, n, 3) "
            f"array, got shape {pos.shape}"
        )
    for t in range(pos.shape[0]):
        yield {"positions": pos[t], "faces": None, "normals": None, "uv": None}


def write_obj_sequence(
    directory,
    surfaces_or_positions,
    *,
    faces=None,
    normals=None,
    uv=None,
    prefix: str = "frame_",
    start: int = 0,
    precision: int = 6,
) -> list[Path]:
    """Write one OBJ per frame: ``directory/{prefix}{index:04d}.obj``.

    Args:
      directory: output folder (created).
      surfaces_or_positions: a list of Surfaces, one Surface whose leaves carry a leading frame
        axis (e.g. from `jax.vmap(tessellate)`), or a (T, n, 3) positions array.
      faces: (m, 3) indices shared by every frame (needed for a bare positions array).
      normals: optional (T, n, 3) per-frame normals (for a bare positions array).
      uv: optional (n, 2) shared uv.
      prefix, start: file name prefix and first index.
    Returns:
      The list of paths written, in frame order.
    """
    directory = Path(directory)
    os.makedirs(directory, exist_ok=True)
    normals_seq = None if normals is None else np.asarray(normals)
    paths = []
    for t, fr in enumerate(_frames(surfaces_or_positions)):
        fr_faces = faces if faces is not None else fr["faces"]
        fr_uv = uv if uv is not None else fr["uv"]
        fr_normals = fr["normals"]
        if normals_seq is not None:
            fr_normals = normals_seq[t] if normals_seq.ndim == 3 else normals_seq
        if fr_faces is None:
            raise ValueError("write_obj_sequence needs faces for a bare positions array")
        path = directory / f"{prefix}{start + t:04d}.obj"
        paths.append(
            write_obj(
                path,
                positions=fr["positions"],
                faces=fr_faces,
                normals=fr_normals,
                uv=fr_uv,
                precision=precision,
                comment=f"frame {start + t}",
            )
        )
    return paths


def read_obj(path, *, smooth: bool = False) -> dict[str, np.ndarray]:
    """Read back a triangle OBJ as written by `write_obj` (for tests and round trips).

    Returns a dict with "positions" (n, 3), "faces" (m, 3) 0-based vertex indices, and, if present,
    "uv" (k, 2), "normals" (k, 3), "face_uv" and "face_normals" (m, 3) 0-based. With smooth=True
    also "vertex_normals" (n, 3): area-weighted averages of the face normals
    (`render.mesh.vertex_normals`), one per position, for smooth shading of meshes without normals
    (`render.mesh.mesh_surface(out["positions"], out["faces"], normals=out["vertex_normals"])`).
    """
    v, vt, vn, fv, ft, fn = [], [], [], [], [], []
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        tag, rest = parts[0], parts[1:]
        if tag == "v":
            v.append([float(x) for x in rest[:3]])
        elif tag == "vt":
            vt.append([float(x) for x in rest[:2]])
        elif tag == "vn":
            vn.append([float(x) for x in rest[:3]])
        elif tag == "f":
            if len(rest) != 3:
                raise ValueError(
                    f"only triangles are supported, got a face with {len(rest)} vertices"
                )
            ids = [(c.split("/") + ["", ""])[:3] for c in rest]
            fv.append([int(i[0]) - 1 for i in ids])
            if ids[0][1]:
                ft.append([int(i[1]) - 1 for i in ids])
            if ids[0][2]:
                fn.append([int(i[2]) - 1 for i in ids])
    out = {
        "positions": np.asarray(v, float).reshape(-1, 3),
        "faces": np.asarray(fv, int).reshape(-1, 3),
    }
    if vt:
        out["uv"] = np.asarray(vt, float)
    if vn:
        out["normals"] = np.asarray(vn, float)
    if ft:
        out["face_uv"] = np.asarray(ft, int)
    if fn:
        out["face_normals"] = np.asarray(fn, int)
    if smooth:
        from diffcloth.render.mesh import vertex_normals

        out["vertex_normals"] = np.asarray(vertex_normals(out["positions"], out["faces"]))
    return out
