"""Triangle-mesh cloth builders and mesh checks (pure numpy).

Every builder returns a `MeshData`: rest positions, counter-clockwise faces and material (flat
pattern) coordinates. Conventions shared by all builders:

- World y is up. Flat builders lie in the horizontal xz-plane at height `center[1]`, centred on
  `center`, and their faces are counter-clockwise seen from +y: the face normal
  (v1 - v0) x (v2 - v0) points along +y.
- Material coordinates are in m, u along the warp and v along the weft, with u x v along the face
  normal. For flat builders uv = (x - cx, -(z - cz)): the warp runs along +x, the weft along -z.
- Faces are counter-clockwise in uv too (positive signed area in the flat pattern).

`check_mesh` refuses meshes the cloth model cannot use (NaN, out-of-range or repeated indices,
zero-area faces, non-manifold edges or vertices, flipped neighbours, unreferenced vertices) with a
`MeshError` that names the source, the face or vertex, and what is wrong.

>>> m = disc(0.15, 0.011)
>>> m.vertices.shape[0] > 700, m.faces.shape[1]
(True, 3)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from diffcloth.physics.mesh.meshdata import (  # noqa: F401  (re-exported: the builders' records)
    MeshData,
    MeshError,
    _angles,
    _positive,
    _signed_area_2d,
    _unique_edges,
    _where,
    check_mesh,
    mesh_quality,
)
from diffcloth.physics.mesh.objfile import read_cloth_obj  # noqa: F401  (re-exported)

__all__ = [
    "MeshError",
    "MeshData",
    "disc",
    "rectangle",
    "grid_square",
    "read_cloth_obj",
    "check_mesh",
    "mesh_quality",
]

_ROW_SPACING = math.sqrt(3.0) / 2.0  # ring / row spacing of an equilateral lattice, in edge lengths
_MAX_VERTICES = 2_000_000  # builders refuse resolutions beyond this (memory and time)


def _orient_ccw(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Reorder each face so that it is counter-clockwise in the (u, v) plane."""
    flip = _signed_area_2d(uv, faces) < 0
    faces = faces.copy()
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces


def _stitch(a: Sequence[int], b: Sequence[int], pts: np.ndarray, *, closed: bool) -> list:
    """Triangulate the strip between two vertex chains walked in the same direction.

    At each step adds the triangle whose new diagonal is shorter. `closed` chains are rings: b is
    rotated to start at the vertex nearest a[0]. Orientation is fixed afterwards by the caller.
    """
    a = list(a)
    b = list(b)
    if closed:
        d = np.linalg.norm(pts[b] - pts[a[0]], axis=1)
        k = int(np.argmin(d))
        b = b[k:] + b[:k]
        a = a + [a[0]]
        b = b + [b[0]]
    na, nb = len(a) - 1, len(b) - 1
    ia = ib = 0
    tris = []
    while ia < na or ib < nb:
        if ia == na:
            advance_b = True
        elif ib == nb:
            advance_b = False
        else:
            db = np.sum((pts[b[ib + 1]] - pts[a[ia]]) ** 2)
            da = np.sum((pts[a[ia + 1]] - pts[b[ib]]) ** 2)
            advance_b = db <= da
        if advance_b:
            tris.append((a[ia], b[ib], b[ib + 1]))
            ib += 1
        else:
            tris.append((a[ia], b[ib], a[ia + 1]))
            ia += 1
    return tris


def _smooth(uv, faces, *, lock_u, lock_v, circle_id, circles, sweeps: int, weight: float = 0.5):
    """Laplacian smoothing in the flat pattern that keeps the best mesh by minimum angle.

    lock_u / lock_v: (n,) bool, coordinate held (both: vertex fixed). circle_id: (n,) int index into
    circles ((k, 3) cx, cv, r) for vertices that slide on a circle, -1 otherwise. A sweep that would
    invert a face is not taken.
    """
    edges = _unique_edges(faces)
    n = uv.shape[0]
    deg = np.bincount(edges.ravel(), minlength=n).astype(np.float64)
    on_circle = circle_id >= 0
    cc = circles[circle_id[on_circle], :2] if on_circle.any() else np.zeros((0, 2))
    cr = circles[circle_id[on_circle], 2] if on_circle.any() else np.zeros(0)
    best = uv
    best_q = _angles(uv[faces]).min()
    cur = uv
    for _ in range(sweeps):
        acc = np.zeros_like(cur)
        np.add.at(acc, edges[:, 0], cur[edges[:, 1]])
        np.add.at(acc, edges[:, 1], cur[edges[:, 0]])
        avg = acc / deg[:, None]
        new = cur + weight * (avg - cur)
        new[lock_u, 0] = cur[lock_u, 0]
        new[lock_v, 1] = cur[lock_v, 1]
        if on_circle.any():
            d = new[on_circle] - cc
            new[on_circle] = cc + d * (cr / np.linalg.norm(d, axis=1))[:, None]
        if np.any(_signed_area_2d(new, faces) <= 0):
            break
        cur = new
        q = _angles(cur[faces]).min()
        if q > best_q:
            best, best_q = cur, q
    return best


def _flat_mesh(uv: np.ndarray, faces: np.ndarray, center: np.ndarray, source: str) -> MeshData:
    """Lift flat-pattern coordinates to the xz-plane: x = cx + u, y = cy, z = cz - v."""
    faces = _orient_ccw(uv, np.asarray(faces, np.int64))
    vertices = np.stack(
        [center[0] + uv[:, 0], np.full(uv.shape[0], center[1]), center[2] - uv[:, 1]], axis=1
    )
    check_mesh(vertices, faces, source)
    return MeshData(
        vertices=vertices.astype(np.float64),
        faces=faces.astype(np.int32),
        uv=np.ascontiguousarray(uv, np.float64),
        source=source,
    )


def _center(center, source: str) -> np.ndarray:
    c = np.asarray(center, np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise MeshError(f"{source}: center must be a finite 3-vector, got {np.asarray(center)}")
    return c


def _check_size(estimate: float, source: str) -> None:
    if estimate > _MAX_VERTICES:
        raise MeshError(
            f"{source}: about {estimate:.3g} vertices requested, more than {_MAX_VERTICES}; "
            "use a larger edge_length"
        )


# ------------------------------------------------------------------------------------------------
# builders


def disc(radius, edge_length, *, rings_at=(), center=(0.0, 0.0, 0.0), smooth: int = 8) -> MeshData:
    """A flat circular sheet (the drape-test specimen) in the xz-plane, evenly triangulated.

    Vertices lie on concentric rings: the centre, then rings about edge_length * sqrt(3) / 2
    apart, with the spacing adjusted so that the outer ring is exactly `radius` and every radius in
    `rings_at` is exactly a ring (e.g. a pedestal edge). Ring k carries round(2 pi r_k / h)
    evenly spaced vertices (6 on the first). Neighbouring rings are stitched by walking both in
    angle order and always adding the triangle with the shorter new diagonal. Then up to `smooth`
    sweeps of Laplacian smoothing move the interior vertices (those on a `rings_at` circle slide
    along it; the boundary stays fixed), kept only where they raise the minimum angle.
    The vertex count is about 3.63 (radius / edge_length)^2, e.g. 725 to 10,090 for radius 0.15 m
    and edge_length 0.0108 m to 0.00285 m. Over radius / edge_length from 3 to 40, with and
    without `rings_at`, the minimum angle stays above 34 degrees and every edge within
    [0.6, 1.6] edge_length. The boundary is the inscribed polygon of the circle.

    Args:
      radius: disc radius in m, > 0.
      edge_length: target edge length h in m, 0 < h <= radius / 2.
      rings_at: radii in m, strictly between 0 and radius, that must be resolved by a ring of
        vertices; neighbouring ring radii (and radius) at least h / 2 apart.
      center: (3,) centre in m; the disc lies at height center[1].
      smooth: number of smoothing sweeps (0: none).
    Returns:
      MeshData with uv = (x - cx, -(z - cz)). The centre is vertex 0, followed by the rings from
      the inside out, each counter-clockwise in uv; the last ring is the boundary.
    Raises:
      MeshError: non-positive or non-finite sizes, too coarse or too fine a resolution, or a
        `rings_at` radius outside (0, radius) or too close to another ring.

    >>> m = disc(0.15, 0.01, rings_at=(0.09,))
    >>> bool(np.allclose(np.linalg.norm(m.uv[-1]), 0.15))
    True
    """
    source = f"disc(R={radius}, h={edge_length})"
    R = _positive("radius", radius, source)
    h = _positive("edge_length", edge_length, source)
    c = _center(center, source)
    if h > R / 2:
        raise MeshError(f"{source}: edge_length must be <= radius / 2 = {R / 2}, got {h}")
    _check_size(3.63 * (R / h) ** 2, source)
    fixed = []
    for k, r in enumerate(rings_at):
        r = float(r)
        if not (math.isfinite(r) and 0 < r < R):
            raise MeshError(f"{source}: rings_at[{k}] = {r} must lie in (0, {R})")
        fixed.append(r)
    breaks = sorted(set(fixed)) + [R]
    prev = 0.0
    radii = []
    for r in breaks:
        gap = r - prev
        if gap < 0.5 * h:
            this = "the rim" if r == R else f"rings_at radius {r}"
            what = "the centre" if prev == 0 else f"the ring at {prev}"
            raise MeshError(
                f"{source}: {this} is {gap:.3g} m from {what}; rings must be at least "
                f"edge_length / 2 = {h / 2} apart (and from the centre and the rim)"
            )
        steps = max(1, round(gap / (_ROW_SPACING * h)))
        radii.extend(prev + gap * np.arange(1, steps) / steps)
        radii.append(r)  # exactly, so that the ring is found again below
        prev = r
    radii = np.asarray(radii)

    rings = []
    pts = [np.zeros((1, 2))]
    start = 1
    offset = 0.0
    for k, r in enumerate(radii):
        count = 6 if k == 0 else max(6, round(2 * math.pi * r / h))
        # Stagger each ring by half its spacing against the previous one.
        offset += math.pi / count
        theta = offset + 2 * math.pi * np.arange(count) / count
        rings.append(list(range(start, start + count)))
        start += count
        pts.append(np.stack([r * np.cos(theta), r * np.sin(theta)], axis=1))
    uv = np.concatenate(pts)
    first = rings[0]
    tris = [(0, first[i], first[(i + 1) % len(first)]) for i in range(len(first))]
    for inner, outer in zip(rings[:-1], rings[1:], strict=True):
        tris.extend(_stitch(inner, outer, uv, closed=True))
    faces = _orient_ccw(uv, np.asarray(tris, np.int64))

    if smooth > 0:
        n = uv.shape[0]
        fixed_v = np.zeros(n, bool)
        fixed_v[0] = True  # the centre stays: keeps the disc symmetric about its centre
        fixed_v[rings[-1]] = True
        circle_id = np.full(n, -1)
        circles = np.array([[0.0, 0.0, r] for r in sorted(set(fixed))]).reshape(-1, 3)
        for i, r in enumerate(circles[:, 2]):
            k = int(np.argmin(np.abs(radii - r)))
            circle_id[rings[k]] = i
        uv = _smooth(
            uv,
            faces,
            lock_u=fixed_v,
            lock_v=fixed_v,
            circle_id=circle_id,
            circles=circles,
            sweeps=int(smooth),
        )
    # Boundary and rings_at radii exactly on their circles (undo rounding of the trig).
    for r, ring in zip(radii, rings, strict=True):
        if r == R or r in fixed:
            d = uv[ring]
            uv[ring] = d * (r / np.linalg.norm(d, axis=1))[:, None]
    return _flat_mesh(uv, faces, c, source)


def rectangle(
    width, height, edge_length, *, holes=(), center=(0.0, 0.0, 0.0), smooth: int = 8
) -> MeshData:
    """A flat rectangular sheet in the xz-plane, optionally with circular holes.

    The triangulation is an offset-row (nearly equilateral) lattice: rows along x about
    edge_length * sqrt(3) / 2 apart, alternate rows shifted by half a spacing, with vertices exactly
    on the border (so the border of a shifted row has a half-length edge). Holes remove every
    triangle whose centroid lies inside the circle; the vertices of the new boundary are then moved
    radially onto the circle (triangles left with all three vertices on the circle are removed),
    and unreferenced vertices dropped. Up to `smooth` Laplacian sweeps then even out the mesh:
    border vertices slide along their side (corners fixed), hole vertices along their circle; a
    sweep is kept only if it raises the minimum angle.

    Args:
      width: size along x in m, > 0.
      height: size along z in m, > 0.
      edge_length: target edge length h in m, at most min(width, height).
      holes: sequence of (cx, cz, r) circles in m in the sheet's own coordinates (relative to
        `center`, x and z). Each needs r >= h, a gap of at least h to the border and to every
        other hole.
      center: (3,) centre in m; the sheet lies at height center[1].
      smooth: number of smoothing sweeps (0: none).
    Returns:
      MeshData with uv = (x - cx, -(z - cz)).
    Raises:
      MeshError: bad sizes, a hole that is too small, cuts (or nearly touches) the outer border,
        or overlaps another hole (names the hole index).

    >>> m = rectangle(0.4, 0.3, 0.02, holes=[(0.0, 0.0, 0.05)])
    >>> m.vertices.shape[1], m.faces.dtype.name
    (3, 'int32')
    """
    source = f"rectangle(W={width}, H={height}, h={edge_length})"
    W = _positive("width", width, source)
    H = _positive("height", height, source)
    h = _positive("edge_length", edge_length, source)
    c = _center(center, source)
    if h > min(W, H):
        raise MeshError(f"{source}: edge_length must be <= min(width, height), got {h}")
    _check_size(1.16 * W * H / h**2, source)
    hole_arr = []
    for k, hole in enumerate(holes):
        try:
            hx, hz, hr = (float(x) for x in hole)
        except (TypeError, ValueError):
            raise MeshError(f"{source}: hole {k} must be (cx, cz, r), got {hole!r}") from None
        if not all(math.isfinite(x) for x in (hx, hz, hr)) or hr < h:
            raise MeshError(
                f"{source}: hole {k} ({hx}, {hz}, r={hr}) needs a finite radius >= edge_length {h}"
            )
        gap = min(W / 2 - abs(hx), H / 2 - abs(hz)) - hr
        if gap < h:
            raise MeshError(
                f"{source}: hole {k} ({hx}, {hz}, r={hr}) cuts or nearly touches the outer border "
                f"(gap {gap:.3g} m; at least edge_length {h} needed)"
            )
        for j, (ox, oz, orad) in enumerate(hole_arr):
            gap = math.hypot(hx - ox, hz - oz) - hr - orad
            if gap < h:
                raise MeshError(
                    f"{source}: hole {k} ({hx}, {hz}, r={hr}) overlaps or nearly touches hole {j} "
                    f"(gap {gap:.3g} m; at least edge_length {h} needed)"
                )
        hole_arr.append((hx, hz, hr))

    nu = max(1, round(W / h))
    nv = max(1, round(H / (_ROW_SPACING * h)))
    du = W / nu
    rows = []
    pts = []
    count = 0
    for k in range(nv + 1):
        if k % 2 == 0:
            u = -W / 2 + du * np.arange(nu + 1)
        else:
            u = np.r_[-W / 2, -W / 2 + du * (np.arange(nu) + 0.5), W / 2]
        v = np.full(u.shape, -H / 2 + H * k / nv)
        pts.append(np.stack([u, v], axis=1))
        rows.append(list(range(count, count + u.size)))
        count += u.size
    uv = np.concatenate(pts)
    tris = []
    for a, b in zip(rows[:-1], rows[1:], strict=True):
        tris.extend(_stitch(a, b, uv, closed=False))
    faces = _orient_ccw(uv, np.asarray(tris, np.int64))

    n = uv.shape[0]
    lock_u = np.isclose(np.abs(uv[:, 0]), W / 2, rtol=0, atol=1e-12 * W)
    lock_v = np.isclose(np.abs(uv[:, 1]), H / 2, rtol=0, atol=1e-12 * H)
    circle_id = np.full(n, -1)
    # Holes are given in (x, z); the flat pattern has v = -z.
    circles = np.array([[hx, -hz, hr] for hx, hz, hr in hole_arr]).reshape(-1, 3)
    for k, (cu, cv, r) in enumerate(circles):
        cen = uv[faces].mean(axis=1)
        inside = np.sum((cen - (cu, cv)) ** 2, axis=1) < r * r
        ring = np.intersect1d(faces[inside].ravel(), faces[~inside].ravel())
        faces = faces[~inside]
        d = uv[ring] - (cu, cv)
        uv[ring] = (cu, cv) + d * (r / np.linalg.norm(d, axis=1))[:, None]
        circle_id[ring] = k
        # A triangle with all corners on the circle lies inside it: drop it.
        faces = faces[~np.all(circle_id[faces] == k, axis=1)]
    used = np.zeros(n, bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    uv, faces = uv[used], remap[faces]
    lock_u, lock_v, circle_id = lock_u[used], lock_v[used], circle_id[used]
    if smooth > 0:
        uv = _smooth(
            uv,
            faces,
            lock_u=lock_u,
            lock_v=lock_v,
            circle_id=circle_id,
            circles=circles,
            sweeps=int(smooth),
        )
    return _flat_mesh(uv, faces, c, source)


def grid_square(
    rows: int,
    cols: int,
    size=(1.2, 0.9),
    *,
    center=(0.0, 0.0, 0.0),
    plane: str = "xz",
    diagonal: str = "alternate",
) -> MeshData:
    """The grid net's layout as a triangle mesh, for comparing the grid and mesh paths.

    Vertex (i, j) (row i, column j) is index i * cols + j, at exactly the rest position that
    `diffcloth.physics.net.grid_net(rows, cols, size, center=center, plane=plane)` gives node
    (i, j): columns along +x, rows along +z ("xz", horizontal, grid_net's default) or downwards along
    -y ("xy", hanging). Each cell is split into two triangles.

    Args:
      rows, cols: node counts, >= 2 each.
      size: (width, height) in m as in grid_net (width along the columns, height along the rows),
        or one number for a square.
      center: (3,) centre in m.
      plane: "xz" or "xy", as in grid_net.
      diagonal: which cell diagonal splits the cells: "d1" ((i, j)-(i+1, j+1)), "d2"
        ((i, j+1)-(i+1, j)) or "alternate" (d1 and d2 in a checkerboard, no direction preferred).
    Returns:
      MeshData, faces counter-clockwise in uv, with uv = (x - cx, -(z - cz)) for "xz" (normal +y)
      and uv = (x - cx, y - cy) for "xy" (normal +z): u along the columns (the warp) either way.
    Raises:
      MeshError: bad counts, size, center, plane or diagonal.

    >>> grid_square(3, 4, 0.3).faces.shape
    (12, 3)
    """
    source = f"grid_square({rows}, {cols}, {size})"
    for name, val in (("rows", rows), ("cols", cols)):
        if isinstance(val, bool) or not isinstance(val, int | np.integer) or val < 2:
            raise MeshError(f"{source}: {name} must be an int >= 2, got {val!r}")
    sz = np.broadcast_to(np.asarray(size, np.float64), (2,))
    width = _positive("size[0] (width)", sz[0], source)
    height = _positive("size[1] (height)", sz[1], source)
    c = _center(center, source)
    if plane not in ("xz", "xy"):
        raise MeshError(f"{source}: plane must be 'xz' or 'xy', got {plane!r}")
    if diagonal not in ("d1", "d2", "alternate"):
        raise MeshError(f"{source}: diagonal must be 'd1', 'd2' or 'alternate', got {diagonal!r}")
    # Same arithmetic as grid_net, so positions agree to the last bit.
    u = np.linspace(-width / 2, width / 2, cols)
    w = np.linspace(-height / 2, height / 2, rows)
    uu, ww = np.meshgrid(u, w)
    zeros = np.zeros_like(uu)
    if plane == "xz":
        rest = np.stack([uu, zeros, ww], axis=-1) + c
    else:
        rest = np.stack([uu, -ww, zeros], axis=-1) + c
    uv = np.stack([uu, -ww], axis=-1).reshape(-1, 2)  # (x - cx, -(z - cz)) or (x - cx, y - cy)
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (i * cols + j).ravel()
    b, cc, d = a + 1, a + cols, a + cols + 1
    if diagonal == "d1":
        use_d1 = np.ones(a.shape, bool)
    elif diagonal == "d2":
        use_d1 = np.zeros(a.shape, bool)
    else:
        use_d1 = ((i + j) % 2 == 0).ravel()
    t1 = np.where(use_d1[:, None], np.stack([a, d, b], 1), np.stack([a, cc, b], 1))
    t2 = np.where(use_d1[:, None], np.stack([a, cc, d], 1), np.stack([b, cc, d], 1))
    faces = np.stack([t1, t2], axis=1).reshape(-1, 3)
    faces = _orient_ccw(uv, faces)
    vertices = rest.reshape(-1, 3)
    check_mesh(vertices, faces, source)
    return MeshData(vertices, faces.astype(np.int32), uv.astype(np.float64), source)


# ------------------------------------------------------------------------------------------------
# OBJ
