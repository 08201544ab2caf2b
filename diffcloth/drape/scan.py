"""3D scans of a draped Cusick specimen (OBJ, m): read, sanity-check, compare with a simulation.

A draped specimen has a flat top (the disc held by the pedestal, radius pedestal_radius, normal
along up) and a skirt that hangs at most specimen_radius - pedestal_radius below it. Scans come
in the wrong units (cm, mm) or rotated; `check_scan` says so.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree

from diffcloth.drape.images import CUSICK, check_geometry

__all__ = ["align_scan_rotation", "chamfer_distance", "check_scan", "read_drape_scan"]


def _unit(up) -> np.ndarray:
    u = np.asarray(up, np.float64)
    n = float(np.linalg.norm(u)) if u.shape == (3,) else 0.0
    if not (math.isfinite(n) and n > 0):
        raise ValueError(f"up must be a finite non-zero 3-vector, got {up!r}")
    return u / n


def _points(points, name: str = "points") -> np.ndarray:
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be (n >= 3, 3) finite, got shape {p.shape}")
    return p


def read_drape_scan(
    path, geometry=CUSICK, *, up=(0.0, 1.0, 0.0), center=(0.0, 0.0, 0.0)
) -> tuple[np.ndarray, list[str]]:
    """Read a scanned drape from an OBJ (m) and check it (`check_scan`).

    Only v and f lines are parsed (`diffcloth.physics.mesh.objfile.parse_obj`); the mesh is not
    checked for manifoldness or orientation, so closed, non-manifold or face-less scans read.
    Shapes: returns points (n, 3) as in the file and warnings (list of str naming the file).
    Raises: MeshError (a ValueError) naming the file if unreadable or malformed; ValueError if it
    has fewer than 3 vertices or non-finite ones.
    """
    from diffcloth.physics.mesh.objfile import parse_obj

    path = Path(path)
    pos = parse_obj(path)[0]
    if pos.shape[0] < 3 or not np.all(np.isfinite(pos)):
        raise ValueError(f"{path}: need at least 3 finite vertices, got {pos.shape[0]}")
    return pos, check_scan(pos, geometry, up, center=center, source=str(path))


def _top_disc(p: np.ndarray, rp: float):
    """(unit normal (3,), inlier mask (n,)) of the largest flat patch: the pedestal disc."""
    n = p.shape[0]
    if n < 20:
        return None
    sub = p if n <= 20000 else p[np.random.default_rng(0).choice(n, 20000, replace=False)]
    _, nb = cKDTree(sub).query(sub, min(16, sub.shape[0]))
    q = sub[nb] - sub[nb].mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))
    normals = v[:, :, 0]
    flat = np.flatnonzero(w[:, 0] <= 1e-3 * w.sum(axis=1))
    if flat.size == 0:
        return None
    cand = flat[np.linspace(0, flat.size - 1, min(150, flat.size)).astype(np.int64)]
    cos_t, tol = math.cos(math.radians(6.0)), 0.02 * rp
    best, best_count = None, 0
    for c in cand:
        nc = normals[c]
        ok = (np.abs(normals @ nc) >= cos_t) & (np.abs((sub - sub[c]) @ nc) <= tol)
        if ok.sum() > best_count:
            best, best_count = (nc, sub[c]), int(ok.sum())
    if best_count < 0.05 * sub.shape[0]:
        return None
    nc, pc = best
    inl = np.abs((p - pc) @ nc) <= tol
    d = p[inl] - p[inl].mean(axis=0)
    normal = np.linalg.eigh(d.T @ d)[1][:, 0]
    return normal, inl


def check_scan(
    points,
    geometry=CUSICK,
    up=(0.0, 1.0, 0.0),
    *,
    center=(0.0, 0.0, 0.0),
    source: str = "",
    hang_tol: float = 0.1,
    tilt_tol_deg: float = 3.0,
    centre_tol: float = 0.03,
) -> list[str]:
    """Problems of a drape scan (m), each naming the source and the number: [] if none.

    Units: the largest side of its bounding box (in the up frame) against the specimen
    diameter: 30x-300x looks like cm (scale by 0.01), over 300x like mm (0.001); other
    sizes beyond 1.3x or under 0.3x are flagged too (then nothing else is checked).
    Rotated: the extent along up exceeds the largest possible hang (specimen_radius -
    pedestal_radius) by more than hang_tol; or the flat top (the largest planar patch of points,
    the pedestal disc) is tilted more than tilt_tol_deg from perpendicular to up, or has the
    skirt above it (upside down).
    Off-centre: the flat top's centroid lies more than centre_tol * specimen_radius
    horizontally from `center` (m).
    Shapes: points (n, 3) m; up (3,); center (3,) m; none out (a list of str).
    """
    g = check_geometry(geometry)
    p = _points(points)
    u = _unit(up)
    where = f"{source}: " if source else ""
    rs, rp = g.specimen_radius, g.pedestal_radius
    e = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]  # two horizontal axes
    frame = p @ np.concatenate([e, u[:, None]], axis=1)
    size = float(np.ptp(frame, axis=0).max())
    ratio = size / (2 * rs)
    if ratio >= 30 or not 0.3 <= ratio <= 1.3:
        unit = "mm" if ratio >= 300 else "cm" if ratio >= 30 else None
        hint = (
            f"looks like {unit}, scale by {0.001 if unit == 'mm' else 0.01}"
            if unit
            else (f"wrong units or scale? (scale by about {1 / ratio:.3g})")
        )
        return [
            f"{where}wrong units: the scan is {size:.4g} across, {ratio:.3g} times the specimen "
            f"diameter {2 * rs:.3g} m; {hint}"
        ]
    out = []
    h = p @ u
    hang = float(np.ptp(h))
    if hang > (rs - rp) * (1 + hang_tol):
        out.append(
            f"{where}rotated: the scan extends {1e3 * hang:.1f} mm along up {u.tolist()}, more "
            f"than the largest possible hang {1e3 * (rs - rp):.1f} mm (+{100 * hang_tol:.0f} %)"
        )
    top = _top_disc(p, rp)
    if top is None:
        out.append(f"{where}no flat top (pedestal disc) found; orientation not checked")
        return out
    normal, inl = top
    if normal @ u < 0:
        normal = -normal
    tilt = math.degrees(math.acos(min(1.0, float(normal @ u))))
    if tilt > tilt_tol_deg:
        axis = np.cross(u, normal)
        axis = np.round(axis / max(np.linalg.norm(axis), 1e-300), 3).tolist()
        out.append(
            f"{where}rotated: the flat top ({int(inl.sum())} points, the pedestal disc) is "
            f"tilted {tilt:.1f} deg from perpendicular to up (its normal "
            f"{np.round(normal, 3).tolist()}; about the axis {axis})"
        )
    skirt = (p[~inl] - p[inl].mean(axis=0)) @ normal
    if skirt.size and np.median(skirt) > 0:
        out.append(f"{where}rotated: upside down (the skirt hangs above the flat top, along +up)")
    off = p[inl].mean(axis=0) - np.asarray(center, np.float64)
    off_h = float(np.linalg.norm(off - (off @ u) * u))
    if off_h > centre_tol * rs:
        out.append(
            f"{where}off-centre: the flat top's centre is {1e3 * off_h:.1f} mm from the pedestal "
            f"centre {np.asarray(center, np.float64).tolist()} horizontally, more than "
            f"{1e3 * centre_tol * rs:.1f} mm"
        )
    return out


def chamfer_distance(a, b) -> float:
    """Symmetric chamfer distance: the mean of the two mean nearest-neighbour distances (a to b
    and b to a), in the units of the points. Shapes: a (n, 3), b (m, 3); returns ()."""
    a, b = _points(a, "a"), _points(b, "b")
    return 0.5 * float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def _rotation(u: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def align_scan_rotation(
    points,
    x_sim,
    up=(0.0, 1.0, 0.0),
    *,
    center=(0.0, 0.0, 0.0),
    num_angles: int = 72,
    max_points: int = 3000,
    seed: int = 0,
):
    """The rotation about the up axis through `center` that best matches a scan to a simulated
    drape by `chamfer_distance`: num_angles angles tried, the best refined (bounded Brent) within
    one step; at most max_points random points of each are used for the search.
    Shapes: points (n, 3) m; x_sim (m, 3) m; returns (angle rad in [0, 2 pi), the chamfer
    distance () m of all points after rotation, the rotated points (n, 3)); rotation is
    right-handed about up.
    """
    p, x = _points(points), _points(x_sim, "x_sim")
    u = _unit(up)
    c = np.asarray(center, np.float64)
    rng = np.random.default_rng(seed)
    ps = p if p.shape[0] <= max_points else p[rng.choice(p.shape[0], max_points, replace=False)]
    xs = x if x.shape[0] <= max_points else x[rng.choice(x.shape[0], max_points, replace=False)]
    tree = cKDTree(xs)

    def cost(angle):
        q = (ps - c) @ _rotation(u, angle).T + c
        return 0.5 * float(tree.query(q)[0].mean() + cKDTree(q).query(xs)[0].mean())

    step = 2 * math.pi / int(num_angles)
    costs = [cost(i * step) for i in range(int(num_angles))]
    a0 = int(np.argmin(costs)) * step
    res = minimize_scalar(cost, bounds=(a0 - step, a0 + step), method="bounded")
    angle = float(res.x) if res.fun < min(costs) else a0
    rotated = (p - c) @ _rotation(u, angle).T + c
    return angle % (2 * math.pi), chamfer_distance(rotated, x), rotated
