"""Measurements on drape silhouettes and outline radii r(theta) (numpy, scipy).

theta_i = 2 pi i / k, from the image's +x (column) axis towards -y (up as displayed); see
`diffcloth.drape.images`. Fold orientation and count vary between repeat drapes of one fabric, so
the comparisons here are rotation (and optionally mirror) invariant: `outline_spectrum`,
`align_rotation` / `iou_best_rotation`, and node counts (`node_count`, reused from
`diffcloth.physics.mesh.measure`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from diffcloth.drape.images import (
    CUSICK,
    Silhouette,
    _periodic_interp,
    check_geometry,
)
from diffcloth.physics.mesh.measure import node_count

__all__ = [
    "align_rotation",
    "chamfer_polar",
    "check_silhouette",
    "drape_coefficient_image",
    "drape_features",
    "iou_best_rotation",
    "node_count",
    "outline_centroid",
    "outline_radius_image",
    "outline_spectrum",
    "polar_iou",
    "rotate_outline",
    "shadow_area",
]

_STEP = 0.25  # pixels between samples along a ray


def _outline_px(coverage, center, num_angles: int):
    """r (num_angles,) in pixels of the farthest 0.5 crossing of the cloth region's coverage
    (`_cloth_mask`) along each ray, and
    cut (num_angles,) bool: the crossing lies at the image border (the shadow may go on)."""
    cov = np.asarray(coverage, np.float64)
    cov = np.where(_cloth_mask(cov, center), cov, 0.0)  # only the cloth around the centre
    h, w = cov.shape
    n = int(num_angles)
    if n < 8:
        raise ValueError(f"num_angles must be >= 8, got {num_angles}")
    cx, cy = float(center[0]), float(center[1])
    reach = max(math.hypot(x - cx, y - cy) for x in (-1, w) for y in (-1, h)) + 1
    rho = np.arange(0.0, reach, _STEP)
    theta = 2 * np.pi * np.arange(n) / n
    xs = cx + np.cos(theta)[:, None] * rho[None, :]
    ys = cy - np.sin(theta)[:, None] * rho[None, :]
    c = ndimage.map_coordinates(cov, [ys.ravel(), xs.ravel()], order=1, mode="grid-constant")
    c = c.reshape(n, rho.size)
    above = c >= 0.5
    j = rho.size - 1 - np.argmax(above[:, ::-1], axis=1)  # the last sample >= 0.5
    found = above[np.arange(n), j]
    j1 = np.minimum(j + 1, rho.size - 1)
    c0, c1 = c[np.arange(n), j], c[np.arange(n), j1]
    t = np.where(c0 > c1, (c0 - 0.5) / np.maximum(c0 - c1, 1e-12), 0.0)
    r = np.where(found, (j + np.clip(t, 0.0, 1.0)) * _STEP, 0.0)
    ex, ey = cx + r * np.cos(theta), cy - r * np.sin(theta)
    edge = 0.25  # pixels: a crossing this close to the border is where the image ends
    cut = found & (
        (ex < edge - 0.5) | (ex > w - 0.5 - edge) | (ey < edge - 0.5) | (ey > h - 0.5 - edge)
    )
    return r, cut


def outline_radius_image(sil: Silhouette, num_angles: int = 360) -> np.ndarray:
    """r(theta) of the silhouette's outer boundary around sil.center, m: along each ray the
    farthest crossing of coverage 0.5 (bilinear samples every 1/4 pixel, linear interpolation
    between them; 0 where the ray meets no cloth). theta_i = 2 pi i / num_angles from +column
    towards -row (counter-clockwise as displayed).
    Shapes: sil.coverage (H, W); returns (num_angles,) m."""
    return _outline_px(sil.coverage, sil.center, num_angles)[0] * sil.pixel


def _cloth_mask(cov: np.ndarray, center) -> np.ndarray:
    """(H, W) bool: the 8-connected component of coverage >= 0.5 holding the centre (else the
    largest), grown by 3 pixels to keep its soft edge."""
    lab, n = ndimage.label(cov >= 0.5, structure=np.ones((3, 3)))
    if n == 0:
        return np.zeros(cov.shape, bool)
    i, j = int(round(center[1])), int(round(center[0]))
    inside = 0 <= i < cov.shape[0] and 0 <= j < cov.shape[1]
    if inside and lab[i, j] > 0:
        keep = lab == lab[i, j]
    else:
        keep = lab == 1 + int(np.argmax(np.bincount(lab.ravel())[1:]))
    return ndimage.binary_dilation(keep, structure=np.ones((3, 3)), iterations=3)


def shadow_area(sil: Silhouette) -> float:
    """The shadow's area, m^2: sum of coverage * pixel^2 over the cloth region (the connected
    region of coverage >= 0.5 holding the centre, grown by 3 pixels to keep its soft edge), so
    dark specks elsewhere do not count. Shapes: sil.coverage (H, W); returns () m^2."""
    cov = np.asarray(sil.coverage, np.float64)
    return float(cov[_cloth_mask(cov, sil.center)].sum() * sil.pixel**2)


def drape_coefficient_image(sil: Silhouette, geometry=CUSICK) -> float:
    """DC = (A - A_ped) / (A_spec - A_ped), A = `shadow_area`, A_x = pi r_x^2 (BS 5058).
    Shapes: sil.coverage (H, W); returns () dimensionless."""
    g = check_geometry(geometry)
    a_ped = math.pi * g.pedestal_radius**2
    return (shadow_area(sil) - a_ped) / (math.pi * g.specimen_radius**2 - a_ped)


def outline_spectrum(r_theta, max_harmonic: int = 16) -> np.ndarray:
    """Rotation-invariant shape spectrum: for k = 1..max_harmonic the cosine amplitude of
    harmonic k of r(theta) over the mean radius (r = a + b cos(k theta + p) gives b / a at k).
    Shapes: r_theta (n,) with n > 2 max_harmonic; returns (max_harmonic,)."""
    r = np.asarray(r_theta, np.float64).reshape(-1)
    k = int(max_harmonic)
    if r.size <= 2 * k or not np.all(np.isfinite(r)) or r.mean() <= 0:
        raise ValueError(f"r_theta needs > {2 * k} finite samples with a positive mean")
    c = np.fft.rfft(r) / r.size
    return 2 * np.abs(c[1 : k + 1]) / c[0].real


def outline_centroid(r_theta) -> np.ndarray:
    """The centroid of the star-shaped region rho <= r(theta), relative to the rays' origin, in
    the units of r: (x, y) with x along theta = 0 (+column) and y along theta = 90 deg (-row).
    Shapes: r_theta (n,); returns (2,)."""
    r = np.asarray(r_theta, np.float64).reshape(-1)
    theta = 2 * np.pi * np.arange(r.size) / r.size
    a = np.sum(r**2)
    if a <= 0:
        return np.zeros(2)
    return (2.0 / 3.0) * np.array([np.sum(r**3 * np.cos(theta)), np.sum(r**3 * np.sin(theta))]) / a


def rotate_outline(r_theta, angle: float, mirrored: bool = False) -> np.ndarray:
    """r(theta) of the outline mirrored (theta -> -theta) if asked, then rotated by `angle` (rad,
    counter-clockwise): out(theta) = r(theta - angle) (r(angle - theta) if mirrored).
    Shapes: r_theta (n,); returns (n,)."""
    r = np.asarray(r_theta, np.float64).reshape(-1)
    theta = 2 * np.pi * np.arange(r.size) / r.size
    return _periodic_interp(r, (angle - theta) if mirrored else (theta - angle))


def polar_iou(r_a, r_b) -> float:
    """IoU of two star-shaped regions around one centre from their radii: sum min(ra, rb)^2 over
    sum max(ra, rb)^2 (the dtheta / 2 cancels). Shapes: r_a, r_b (n,); returns ()."""
    a, b = np.asarray(r_a, np.float64), np.asarray(r_b, np.float64)
    return float(np.sum(np.minimum(a, b) ** 2) / max(np.sum(np.maximum(a, b) ** 2), 1e-300))


def align_rotation(r_a, r_b, *, allow_mirror: bool = True):
    """The rotation (and mirror) of outline b that best matches outline a, by polar IoU.

    All circular shifts are tried (and, if allow_mirror, those of b mirrored), then the best is
    refined below a sample by a parabola through its neighbours. rotate_outline(r_b, angle,
    mirrored) is the aligned b. r_b is resampled to len(r_a) if the lengths differ.
    Shapes: r_a (n,), r_b (m,) radii at theta_i = 2 pi i / len; returns (angle rad in [0, 2 pi),
    mirrored bool, iou float).
    """
    a = np.asarray(r_a, np.float64).reshape(-1)
    b = np.asarray(r_b, np.float64).reshape(-1)
    n = a.size
    if b.size != n:
        b = _periodic_interp(b, 2 * np.pi * np.arange(n) / n)
    idx = (np.arange(n)[None, :] - np.arange(n)[:, None]) % n  # row s: b rotated by s samples
    best = (-1.0, 0.0, False)
    for mirrored in (False, True) if allow_mirror else (False,):
        bb = np.roll(b[::-1], 1) if mirrored else b
        shifted = bb[idx]
        iou = np.sum(np.minimum(a, shifted) ** 2, 1) / np.sum(np.maximum(a, shifted) ** 2, 1)
        s = int(np.argmax(iou))
        y0, y1, y2 = iou[s - 1], iou[s], iou[(s + 1) % n]
        den = y0 - 2 * y1 + y2
        delta = float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5)) if den < 0 else 0.0
        angle = (s + delta) * 2 * np.pi / n
        fine = polar_iou(a, rotate_outline(b, angle, mirrored))
        if fine < y1:
            angle, fine = s * 2 * np.pi / n, float(y1)
        if fine > best[0]:
            best = (fine, angle % (2 * np.pi), mirrored)
    return best[1], best[2], best[0]


def iou_best_rotation(a, r_b, *, allow_mirror: bool = True) -> float:
    """The polar IoU of outline b with a after `align_rotation`; a is a Silhouette (its outline
    is measured at len(r_b) angles) or radii. Shapes: a (n,) m or Silhouette; r_b (n,) m;
    returns ()."""
    r_b = np.asarray(r_b, np.float64).reshape(-1)
    r_a = outline_radius_image(a, r_b.size) if isinstance(a, Silhouette) else a
    return align_rotation(r_a, r_b, allow_mirror=allow_mirror)[2]


def chamfer_polar(r_a, r_b) -> float:
    """Symmetric chamfer distance of two polar outlines around one centre: the mean over both of
    the distance from each outline point to the nearest point of the other, in the units of r.
    Shapes: r_a (n,), r_b (m,); returns ()."""
    pts = []
    for r in (r_a, r_b):
        r = np.asarray(r, np.float64).reshape(-1)
        t = 2 * np.pi * np.arange(r.size) / r.size
        pts.append(np.stack([r * np.cos(t), r * np.sin(t)], axis=1))
    d_ab = cKDTree(pts[1]).query(pts[0])[0]
    d_ba = cKDTree(pts[0]).query(pts[1])[0]
    return 0.5 * float(d_ab.mean() + d_ba.mean())


def drape_features(sil: Silhouette, geometry=CUSICK, *, num_angles: int = 360) -> dict:
    """The lab's numbers for one drape image.

    Returns a dict: dc (drape coefficient), area (m^2), node_count, r_theta ((num_angles,) m),
    theta ((num_angles,) rad), spectrum ((16,) see `outline_spectrum`), mean_radius, min_radius,
    max_radius (m), centre_offset_px ((2,) shadow centroid - sil.center, x=column, y=row),
    off_centre_mm, source. Shapes: sil.coverage (H, W).
    """
    g = check_geometry(geometry)
    r = outline_radius_image(sil, num_angles)
    off = outline_centroid(r)
    return {
        "dc": drape_coefficient_image(sil, g),
        "area": shadow_area(sil),
        "node_count": node_count(r) if r.size >= 96 else 0,
        "r_theta": r,
        "theta": 2 * np.pi * np.arange(r.size) / r.size,
        "spectrum": outline_spectrum(r) if r.mean() > 0 else np.zeros(16),
        "mean_radius": float(r.mean()),
        "min_radius": float(r.min()),
        "max_radius": float(r.max()),
        "centre_offset_px": np.array([off[0], -off[1]]) / sil.pixel,
        "off_centre_mm": 1e3 * float(np.hypot(*off)),
        "source": sil.source,
    }


def check_silhouette(
    sil: Silhouette,
    geometry=CUSICK,
    *,
    radius_tol: float = 0.03,
    pedestal_tol: float = 0.05,
    centre_tol: float = 0.05,
    dc_range=(0.0, 1.02),
    cut_tol: float = 0.01,
    search: float = 0.35,
    num_angles: int = 720,
) -> list[str]:
    """Problems of a drape silhouette, each naming the file and the number: [] if none.

    Physics: the shadow covers the pedestal disc (radius pedestal_radius) and lies within the
    specimen circle (a draped cloth cannot project beyond its flat radius), both around the
    pedestal centre. With pedestal_radius * (1 - pedestal_tol) and specimen_radius *
    (1 + radius_tol):
    - off-centre: the given centre fails, but a centre within search * specimen_radius fits
      (the nearest is reported); or the centroid of the outline's region lies more than
      centre_tol * specimen_radius (7.5 mm for the 30 cm specimen) from the given centre;
    - mis-scaled: no centre fits: the largest disc inside the shadow is smaller than the
      pedestal (scale too small) or the smallest enclosing circle larger than the specimen
      (scale too large); or the drape coefficient lies outside dc_range; or the shadow is cut
      off by the image border on more than cut_tol of the rays.
    Shapes: sil.coverage (H, W); none out (a list of str).
    """
    g = check_geometry(geometry)
    where, px, c = sil.source, float(sil.pixel), np.asarray(sil.center, np.float64)
    rs, rp = g.specimen_radius, g.pedestal_radius
    cov = np.asarray(sil.coverage, np.float64)
    r, cut = _outline_px(cov, c, num_angles)
    theta = 2 * np.pi * np.arange(r.size) / r.size
    pts = np.stack([c[0] + r * np.cos(theta), c[1] - r * np.sin(theta)], axis=1)
    rin, rout = rp * (1 - pedestal_tol) / px, rs * (1 + radius_tol) / px
    edt = ndimage.distance_transform_edt(np.pad(cov >= 0.5, 1))[1:-1, 1:-1]

    def inner(q):  # px: radius of the largest disc around q inside the shadow
        return ndimage.map_coordinates(edt, [q[:, 1], q[:, 0]], order=1, mode="nearest")

    def outer(q):  # px: distance from q to the farthest outline point
        return np.sqrt(np.max(np.sum((pts[None] - q[:, None]) ** 2, axis=-1), axis=1))

    mm = lambda v: f"{1e3 * v * px:.1f} mm"
    off = outline_centroid(r)  # px, (x, up)
    off_px = float(np.hypot(*off))
    centroid = (
        f"the shadow's centre is {mm(off_px)} ({off_px:.1f} px; {off[0]:+.1f} columns, "
        f"{-off[1]:+.1f} rows) from the given centre {np.round(c, 1).tolist()}"
    )
    out, off_found = [], False
    d_in, d_out = float(inner(c[None])[0]), float(outer(c[None])[0])
    if d_in < rin or d_out > rout:
        reach = search * rs / px
        o = np.arange(-reach, reach + 1e-9, max(1.0, reach / 40))
        q = c + np.stack(np.meshgrid(o, o), axis=-1).reshape(-1, 2)
        q = q[np.hypot(*(q - c).T) <= reach]
        q_out = outer(q)
        ok = (inner(q) >= rin) & (q_out <= rout)
        at = f"around the given centre {np.round(c, 1).tolist()} the largest disc inside the "
        at += f"shadow has radius {mm(d_in)} (pedestal {1e3 * rp:.0f} mm) and the shadow reaches "
        at += f"{mm(d_out)} (specimen {1e3 * rs:.0f} mm)"
        if ok.any():
            k = int(np.argmin(np.hypot(*(q[ok] - c).T)))
            d = float(np.hypot(*(q[ok][k] - c)))
            off_found = True
            out.append(
                f"{where}: off-centre: {at}; the nearest centre that fits is {mm(d)} ({d:.1f} px) "
                f"away, at {np.round(q[ok][k], 1).tolist()}; {centroid}"
            )
        elif edt.max() < rin:
            out.append(
                f"{where}: mis-scaled: the largest disc inside the shadow has radius "
                f"{mm(edt.max())}, less than the pedestal radius {1e3 * rp:.1f} mm (-"
                f"{100 * pedestal_tol:.0f} %); the scale ({1e3 * px:.4g} mm/pixel) is too small "
                f"by a factor of at least {rp / (edt.max() * px + 1e-300):.2f}"
            )
        elif q_out.min() > rout:
            out.append(
                f"{where}: mis-scaled: the shadow needs a circle of radius {mm(q_out.min())}, more "
                f"than the specimen radius {1e3 * rs:.1f} mm (+{100 * radius_tol:.0f} %); the scale "
                f"({1e3 * px:.4g} mm/pixel) is too large by a factor of at least "
                f"{q_out.min() * px / rs:.2f}"
            )
        else:
            out.append(f"{where}: mis-scaled or off-centre: {at}, and no centre nearby fits both")
    dc = drape_coefficient_image(sil, g)
    if not dc_range[0] <= dc <= dc_range[1]:
        out.append(
            f"{where}: mis-scaled: drape coefficient {dc:.3f} outside [{dc_range[0]}, "
            f"{dc_range[1]}] at {1e3 * px:.4g} mm/pixel"
        )
    if cut.mean() > cut_tol:
        out.append(
            f"{where}: mis-scaled or mis-framed: the shadow is cut off by the image border on "
            f"{int(cut.sum())} of {cut.size} rays"
        )
    if not off_found and off_px * px > centre_tol * rs:
        out.append(f"{where}: off-centre: {centroid}, more than {1e3 * centre_tol * rs:.1f} mm")
    return out
