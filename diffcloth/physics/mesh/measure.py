"""Measurements of a draped mesh cloth the way a textile lab takes them (pure numpy).

drape_shadow: the top-view silhouette (the orthographic shadow along -up) of all triangles, as a
  pixel mask and as an area. Each pixel row is cut exactly (the union of the triangles' x
  intervals on the row's centre line), so the area is exact across a row and sampled only down
  the rows (the midpoint rule); the error is estimated by sampling again on the row edges.
drape_coefficient: the Cusick drape coefficient DC = (A_shadow - A_pedestal) / (A_specimen -
  A_pedestal) (BS 5058, ISO 9073-9), with its pixel-size error.
outline_radius, node_count: r(theta) of the shadow's outer boundary and its number of folds.
cantilever_rigidity: ASTM D1388 option A: bending length c = overhang / 2, G = rho g c^3.

>>> import numpy as np
>>> x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, -1]])
>>> round(drape_shadow(x, [[0, 1, 2]], resolution=0.01).area, 6)
0.5
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = [
    "DrapeCoefficient",
    "Shadow",
    "cantilever_rigidity",
    "drape_coefficient",
    "drape_shadow",
    "node_count",
    "outline_radius",
    "projection_axes",
]

DEFAULT_PIXEL = 5e-4  # m: the default pixel size of `drape_shadow`


class Shadow(NamedTuple):
    """A top-view silhouette.

    Attributes:
      mask: (rows, cols) bool, True where the pixel centre lies in the shadow; row i, column j is
        the pixel centred at origin + (j * pixel, i * pixel) in the (e1, e2) plane coordinates.
      origin: (2,) plane coordinates of the centre of pixel (0, 0), m.
      pixel: pixel size, m.
      axes: (2, 3) the plane axes e1, e2 in world coordinates ((e1, e2, up) right-handed; for
        up = +y: e1 = +x, e2 = -z, the flat builders' (u, v)).
      area: the shadow's area in m^2 (exact along rows, midpoint rule down the rows).
      area_error: an estimate of the area's error in m^2: the difference to the area sampled
        on the row edges instead of the row centres (a bound for shapes whose row lengths are
        smooth between vertices; in practice the error is far smaller).
    """

    mask: np.ndarray
    origin: np.ndarray
    pixel: float
    axes: np.ndarray
    area: float
    area_error: float


class DrapeCoefficient(NamedTuple):
    """value: the drape coefficient (dimensionless); error: its pixel-size error estimate;
    shadow_area: m^2."""

    value: float
    error: float
    shadow_area: float


def projection_axes(up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(2, 3) orthonormal e1, e2 with (e1, e2, up) right-handed: the world axis least aligned
    with up, made orthogonal to it, then e2 = up x e1. For up = +y: e1 = +x, e2 = -z."""
    u = np.asarray(up, np.float64)
    norm = np.linalg.norm(u)
    if u.shape != (3,) or not np.isfinite(norm) or norm == 0:
        raise ValueError(f"up must be a finite non-zero 3-vector, got {up!r}")
    u = u / norm
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = a - (a @ u) * u
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1)])


def _project(x, faces, up):
    x = np.asarray(x, np.float64)
    f = np.asarray(faces, np.int64)
    if x.ndim != 2 or x.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"x must be (n, 3) and faces (m, 3); got {x.shape} and {f.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("x has non-finite positions")
    axes = projection_axes(up)
    return x @ axes.T, f, axes


def _row_intervals(tri: np.ndarray, y0: float, dy: float, num_rows: int, shift: float):
    """Cut projected triangles (m, 3, 2) with the lines y = y0 + (i + shift) dy, i in
    [0, num_rows). Returns (row, x_left, x_right) of every triangle-line intersection."""
    ys = tri[..., 1]
    lo = np.ceil((ys.min(axis=1) - y0) / dy - shift).astype(np.int64)
    hi = np.floor((ys.max(axis=1) - y0) / dy - shift).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, num_rows - 1)
    count = np.maximum(hi - lo + 1, 0)
    tid = np.repeat(np.arange(tri.shape[0]), count)
    row = np.repeat(lo, count) + (
        np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    )
    yl = y0 + (row + shift) * dy
    t = tri[tid]  # (k, 3, 2)
    xl = np.full(tid.shape, np.inf)
    xr = np.full(tid.shape, -np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        pa, pb = t[:, a], t[:, b]
        d = pb[:, 1] - pa[:, 1]
        lo_y = np.minimum(pa[:, 1], pb[:, 1])
        hi_y = np.maximum(pa[:, 1], pb[:, 1])
        hit = (yl >= lo_y) & (yl <= hi_y)
        s = np.where(d != 0, (yl - pa[:, 1]) / np.where(d != 0, d, 1.0), 0.0)
        xs = pa[:, 0] + np.clip(s, 0.0, 1.0) * (pb[:, 0] - pa[:, 0])
        # a horizontal edge on the line covers both its ends
        xs_lo = np.where(d == 0, np.minimum(pa[:, 0], pb[:, 0]), xs)
        xs_hi = np.where(d == 0, np.maximum(pa[:, 0], pb[:, 0]), xs)
        xl = np.where(hit, np.minimum(xl, xs_lo), xl)
        xr = np.where(hit, np.maximum(xr, xs_hi), xr)
    ok = xr >= xl
    return row[ok], xl[ok], xr[ok]


def _union_length(row, xl, xr, num_rows: int, span: float) -> np.ndarray:
    """(num_rows,) total length of the union of the intervals on each row."""
    big = 4.0 * span + 1.0
    a = xl + row * big
    b = xr + row * big
    order = np.lexsort((a, row))
    a, b, r = a[order], b[order], row[order]
    reach = np.maximum.accumulate(b)
    prev = np.concatenate([[-np.inf], reach[:-1]])
    new = np.maximum(b - np.maximum(a, prev), 0.0)
    return np.bincount(r, weights=new, minlength=num_rows)


def drape_shadow(x, faces, *, up=(0.0, 1.0, 0.0), resolution: float = DEFAULT_PIXEL) -> Shadow:
    """The top-view silhouette of a cloth: the union of all its triangles projected along -up.

    Args:
      x: (n, 3) vertex positions, m.
      faces: (m, 3) vertex indices.
      up: the viewing direction's opposite (world up), any non-zero 3-vector.
      resolution: pixel size in m (> 0). The default 0.5 mm gives a Cusick specimen (0.3 m
        across) a 600 x 600 mask.
    Returns:
      Shadow (mask, origin, pixel, axes, area, area_error). Edge-on triangles add nothing beyond
      their neighbours; overlapping layers (folds) count once.
    Raises:
      ValueError: bad shapes, non-finite positions, or a non-positive resolution.

    >>> import numpy as np
    >>> sq = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.1, 0, -0.1], [0, 0, -0.1]])
    >>> s = drape_shadow(sq, [[0, 1, 2], [0, 2, 3]], resolution=0.001)
    >>> round(s.area, 8), s.mask.sum()
    (0.01, np.int64(10000))
    """
    pixel = float(resolution)
    if not (math.isfinite(pixel) and pixel > 0):
        raise ValueError(f"resolution (pixel size) must be > 0 m, got {resolution!r}")
    p, f, axes = _project(x, faces, up)
    tri = p[f]
    lo = p.min(axis=0)
    hi = p.max(axis=0)
    cols = int(np.ceil((hi[0] - lo[0]) / pixel)) + 1
    rows = int(np.ceil((hi[1] - lo[1]) / pixel)) + 1
    if rows * cols > 2e8:
        raise ValueError(f"resolution {pixel} m gives a {rows} x {cols} mask; use larger pixels")
    origin = lo + 0.5 * pixel  # the pixels tile the bounding box from its lower-left corner
    y0 = origin[1]
    span = float(hi[0] - lo[0])
    row, xl, xr = _row_intervals(tri, y0, pixel, rows, 0.0)
    length_mid = _union_length(row, xl, xr, rows, span)
    # rows on the pixel edges (half a pixel below each centre line, one more at the top)
    row_e, xl_e, xr_e = _row_intervals(tri, y0, pixel, rows + 1, -0.5)
    length_edge = _union_length(row_e, xl_e, xr_e, rows + 1, span)
    area = float(length_mid.sum() * pixel)
    area_edge = float(length_edge.sum() * pixel)
    # mask: pixel centres x0 + j pixel inside an interval of their row
    j0 = np.ceil((xl - origin[0]) / pixel - 1e-9).astype(np.int64)  # (centres on an edge count)
    j1 = np.floor((xr - origin[0]) / pixel + 1e-9).astype(np.int64) + 1
    keep = j1 > j0
    diff = np.zeros((rows, cols + 1), np.int32)
    np.add.at(diff, (row[keep], np.clip(j0[keep], 0, cols)), 1)
    np.add.at(diff, (row[keep], np.clip(j1[keep], 0, cols)), -1)
    mask = np.cumsum(diff, axis=1)[:, :cols] > 0
    return Shadow(
        mask=mask,
        origin=origin,
        pixel=pixel,
        axes=axes,
        area=area,
        area_error=abs(area_edge - area),
    )


def drape_coefficient(
    x,
    faces,
    specimen_radius: float,
    pedestal_radius: float,
    *,
    center=(0.0, 0.0, 0.0),
    up=(0.0, 1.0, 0.0),
    resolution: float = DEFAULT_PIXEL,
) -> DrapeCoefficient:
    """The Cusick drape coefficient of a draped disc.

    DC = (A_shadow - A_pedestal) / (A_specimen - A_pedestal), with A = pi r^2 for the specimen
    and the pedestal (a flat specimen of the nominal radius has DC = 1; a flat mesh disc, whose
    rim is the inscribed polygon, slightly less).

    Args:
      x: (n, 3) draped positions, m; faces: (m, 3).
      specimen_radius, pedestal_radius: m, specimen_radius > pedestal_radius > 0.
      center: (3,) the pedestal's centre, m: the shadow must cover it (checked).
      up, resolution: as in `drape_shadow`.
    Returns:
      DrapeCoefficient(value, error, shadow_area). error is the shadow's area_error over
      A_specimen - A_pedestal: below 1e-3 at the default 0.5 mm pixels for a specimen of 0.15 m
      radius (the rows are cut exactly; only the row sampling errs).
    Raises:
      ValueError: bad radii, or a shadow that does not cover the pedestal's centre.
    """
    rs, rp = float(specimen_radius), float(pedestal_radius)
    if not (math.isfinite(rs) and math.isfinite(rp) and 0 < rp < rs):
        raise ValueError(
            f"need 0 < pedestal_radius < specimen_radius, got {pedestal_radius!r}, "
            f"{specimen_radius!r}"
        )
    s = drape_shadow(x, faces, up=up, resolution=resolution)
    c = np.asarray(center, np.float64) @ s.axes.T
    ij = np.round((c - s.origin) / s.pixel).astype(np.int64)
    inside = 0 <= ij[1] < s.mask.shape[0] and 0 <= ij[0] < s.mask.shape[1]
    if not (inside and s.mask[ij[1], ij[0]]):
        raise ValueError(
            f"the cloth's shadow does not cover the pedestal centre {np.asarray(center).tolist()}"
        )
    a_ped = math.pi * rp * rp
    denom = math.pi * rs * rs - a_ped
    return DrapeCoefficient(
        value=(s.area - a_ped) / denom, error=s.area_error / denom, shadow_area=s.area
    )


def _edges(faces: np.ndarray) -> np.ndarray:
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    return np.unique(np.sort(half, axis=1), axis=0)


def outline_radius(
    x, faces, num_angles: int = 360, center=(0.0, 0.0, 0.0), *, up=(0.0, 1.0, 0.0)
) -> np.ndarray:
    """r(theta) of the shadow's outer boundary: along each ray from the centre, the distance to
    the farthest shadow point (exact: the farthest crossing of any projected mesh edge).

    Args:
      x: (n, 3) positions, m; faces: (m, 3).
      num_angles: rays at theta_k = 2 pi k / num_angles from e1 towards e2 (`projection_axes`;
        for up = +y from +x towards -z, counter-clockwise seen from above).
      center: (3,) the rays' origin, m (projected along up).
    Returns:
      (num_angles,) radii in m (0 where a ray meets no edge).
    """
    p, f, axes = _project(x, faces, up)
    c = np.asarray(center, np.float64) @ axes.T
    e = _edges(f)
    a = p[e[:, 0]] - c
    b = p[e[:, 1]] - c
    ab = b - a
    theta = 2 * np.pi * np.arange(int(num_angles)) / int(num_angles)
    out = np.zeros(theta.shape)
    cross = lambda u, v: u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    for start in range(0, theta.size, 32):
        th = theta[start : start + 32]
        d = np.stack([np.cos(th), np.sin(th)], axis=1)[:, None, :]  # (k, 1, 2)
        den = cross(d, ab[None])  # (k, e)
        ok = np.abs(den) > 1e-300
        den = np.where(ok, den, 1.0)
        t = cross(a[None], ab[None]) / den
        s = cross(a[None], d) / den
        hit = ok & (s >= 0) & (s <= 1) & (t >= 0)
        out[start : start + 32] = np.max(np.where(hit, t, 0.0), axis=1)
    return out


def node_count(r_theta, *, max_harmonic: int = 24, min_prominence: float = 0.2) -> int:
    """The number of nodes (folds) of a drape from its outline radius r(theta).

    r(theta) is smoothed by keeping its Fourier harmonics 1..min(max_harmonic, 1.5 k + 1), k the
    dominant one (a drape has 3 to about 12 nodes; sharper detail and noise go), then the maxima
    whose prominence reaches
    min_prominence times the smoothed range (max - min) are counted around the circle.

    Args:
      r_theta: (k,) radii at equally spaced angles over a full turn (k >= 4 max_harmonic).
      max_harmonic: the highest harmonic kept.
      min_prominence: fraction of the range a maximum must stand above the higher of its two
        bases (the lowest points between it and the nearest higher maxima on either side).
    Returns:
      The node count (0 for a round outline).

    >>> t = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    >>> node_count(0.12 + 0.01 * np.cos(7 * t))
    7
    """
    r = np.asarray(r_theta, np.float64).reshape(-1)
    if r.size < 4 * max_harmonic or not np.all(np.isfinite(r)):
        raise ValueError(f"r_theta needs at least {4 * max_harmonic} finite samples, got {r.size}")
    spec = np.fft.rfft(r - r.mean())
    spec[0] = 0.0
    spec[max_harmonic + 1 :] = 0.0
    # low-pass at about 1.5 times the dominant harmonic: keeps uneven nodes apart, drops the
    # ringing of sharp peaks or valleys and noise
    dominant = int(np.argmax(np.abs(spec[: max_harmonic + 1])))
    spec[min(max_harmonic, int(1.5 * dominant) + 1) + 1 :] = 0.0
    s = np.fft.irfft(spec, n=r.size)
    span = float(s.max() - s.min())
    if span <= 1e-9 * max(float(np.abs(r).max()), 1e-300):
        return 0
    # rotate to start at the global minimum: every maximum then has a base on both sides
    s = np.roll(s, -int(np.argmin(s)))
    s = np.concatenate([s, s[:1]])
    peaks = np.flatnonzero((s[1:-1] > s[:-2]) & (s[1:-1] >= s[2:])) + 1
    count = 0
    for i in peaks:
        left = s[:i][::-1]
        higher = np.flatnonzero(left > s[i])
        lb = left[: higher[0]].min() if higher.size else left.min()
        right = s[i + 1 :]
        higher = np.flatnonzero(right > s[i])
        rb = right[: higher[0]].min() if higher.size else right.min()
        if s[i] - max(lb, rb) >= min_prominence * span:
            count += 1
    return count


def cantilever_rigidity(overhang, density, g: float = 9.81):
    """ASTM D1388 option A: flexural rigidity G = rho g c^3 (N m) from the overhang (m) at which
    the tip line reaches 41.5 degrees, with the bending length c = overhang / 2, and the areal
    density rho (kg/m^2).

    >>> f"{cantilever_rigidity(0.05, 0.2):.4e}"
    '3.0656e-05'
    """
    c = 0.5 * np.asarray(overhang, np.float64)
    return np.asarray(density, np.float64) * g * c**3
