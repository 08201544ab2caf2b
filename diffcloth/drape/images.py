"""Top-view Cusick drape-test images (BS 5058, ISO 9073-9): read, check, synthesize, overlay.

Conventions shared by diffcloth.drape:
- Pixel (row i, column j) is centred at image coordinates (x=j, y=i) and covers [j-0.5, j+0.5] x
  [i-0.5, i+0.5]. A centre is (x, y) = (column, row); the default is the image centre
  ((W-1)/2, (H-1)/2).
- theta runs from +x (the column axis, to the right) towards -y (up in the displayed image):
  counter-clockwise as displayed. `shadow_image` draws a mesh seen from above with the plane axes
  e1 right and e2 up (`projection_axes`; for up = +y world +x right and -z up), so an image's
  r(theta) matches `diffcloth.physics.mesh.measure.outline_radius`.
- Default scale (reading and writing alike, so defaults round-trip): the image width spans
  DEFAULT_FRAME (1.0) specimen diameters, i.e. 0.3 m for the 30 cm specimen. Pass mm_per_pixel
  (or frame_mm, the width in mm) for any other framing.
- Levels: cloth dark (CLOTH_LEVEL, 35) on a light background (BACKGROUND_LEVEL, 225), 8 bits.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy import ndimage

__all__ = [
    "BACKGROUND_LEVEL",
    "CLOTH_LEVEL",
    "CUSICK",
    "DEFAULT_FRAME",
    "DrapeGeometry",
    "Silhouette",
    "SilhouetteError",
    "check_geometry",
    "check_silhouette",
    "overlay_image",
    "polar_shadow_image",
    "read_silhouette",
    "shadow_image",
    "write_silhouette",
]

DEFAULT_FRAME = 1.0  # image width in specimen diameters when no scale is given
CLOTH_LEVEL = 35.0
BACKGROUND_LEVEL = 225.0
MIN_SIZE = 32  # pixels, the smallest image side accepted
MIN_CONTRAST = 40.0  # grey levels (of 255) between the cloth and background levels
# overlay colours (RGB)
OBSERVED_COLOUR = (220, 30, 30)  # red: the observed outline
PREDICTED_COLOUR = (30, 90, 235)  # blue: the predicted outline
PEDESTAL_COLOUR = (0, 160, 60)  # green, dashed: the pedestal circle


class DrapeGeometry(NamedTuple):
    """The Cusick set-up, m: a 30 cm specimen on an 18 cm pedestal by default.
    Shapes: none (two floats)."""

    specimen_radius: float = 0.15
    pedestal_radius: float = 0.09


CUSICK = DrapeGeometry()  # the standard set-up, the default geometry everywhere


class SilhouetteError(ValueError):
    """A drape image that cannot be used (unreadable, empty, all dark, uniform, too small);
    the message names the file."""


class Silhouette(NamedTuple):
    """A top-view drape silhouette.

    Attributes:
      coverage: (H, W) float64 in [0, 1], 1 = cloth; soft edges are fractional coverage.
      pixel: pixel size, m.
      center: (2,) the pedestal centre (x=column, y=row), pixels.
      source: the file it came from.
      warnings: tuple of str, oddities that did not stop the reading.
    """

    coverage: np.ndarray
    pixel: float
    center: np.ndarray
    source: str
    warnings: tuple = ()


def check_geometry(geometry) -> DrapeGeometry:
    """A validated DrapeGeometry: finite radii with 0 < pedestal_radius < specimen_radius (m).
    Shapes: none. Raises ValueError naming the field and its allowed range."""
    try:
        rs, rp = (float(v) for v in DrapeGeometry(*geometry))
    except (TypeError, ValueError):
        raise ValueError(
            f"geometry must be (specimen_radius, pedestal_radius), got {geometry!r}"
        ) from None
    if not (math.isfinite(rs) and rs > 0):
        raise ValueError(f"specimen_radius must be finite and > 0 m, got {rs!r}")
    if not (math.isfinite(rp) and 0 < rp < rs):
        raise ValueError(f"pedestal_radius must be finite and in (0, {rs}) m, got {rp!r}")
    return DrapeGeometry(rs, rp)


def _periodic_interp(r, theta) -> np.ndarray:
    """r (k,) sampled at 2 pi i / k, linearly interpolated at theta (...) radians."""
    r = np.asarray(r, np.float64).reshape(-1)
    t = np.mod(np.asarray(theta, np.float64), 2 * np.pi) * (r.size / (2 * np.pi))
    i0 = np.floor(t).astype(np.int64) % r.size
    f = t - np.floor(t)
    return r[i0] * (1 - f) + r[(i0 + 1) % r.size] * f


# ------------------------------------------------------------------------------------------------
# reading


def _load_luminance(path, where: str):
    import imageio.v3 as iio

    warnings = []
    try:
        a = np.asarray(iio.imread(path))
    except Exception as e:  # imageio raises many kinds
        raise SilhouetteError(f"{where}: cannot read the image ({type(e).__name__}: {e})") from None
    if a.ndim == 3 and a.shape[-1] not in (1, 2, 3, 4):
        raise SilhouetteError(f"{where}: not a single 2-D image (array shape {a.shape})")
    if a.ndim not in (2, 3) or a.size == 0:
        raise SilhouetteError(f"{where}: not a single 2-D image (array shape {a.shape})")
    if a.dtype == np.uint16:
        x = a / 257.0
        warnings.append(f"{where}: 16-bit image scaled to 8 bits")
    elif a.dtype.kind == "f":
        x = a * (255.0 if np.nanmax(a) <= 1.0 else 1.0)
    else:
        x = a.astype(np.float64) * (255.0 if a.dtype == bool else 1.0)
    if x.ndim == 2:
        return x, warnings
    alpha = None
    if x.shape[-1] in (2, 4):
        alpha, x = x[..., -1] / 255.0, x[..., :-1]
    lum = x[..., 0] if x.shape[-1] == 1 else x[..., :3] @ np.array([0.299, 0.587, 0.114])
    if alpha is not None and alpha.min() < 1.0:
        lum = lum * alpha + 255.0 * (1 - alpha)
        warnings.append(f"{where}: transparent pixels composited over white")
    return lum, warnings


def _otsu(v: np.ndarray) -> float:
    """The threshold (grey level) maximizing the between-class variance."""
    hist, _ = np.histogram(v, bins=256, range=(0.0, 256.0))
    p = hist / hist.sum()
    c = np.arange(256) + 0.5
    w0 = np.cumsum(p)
    m0 = np.cumsum(p * c)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (m0[-1] * w0 - m0) ** 2 / (w0 * (1 - w0))
    between[~np.isfinite(between)] = 0.0
    return float(np.argmax(between) + 1)


def _levels(lum: np.ndarray, where: str, dark_word: str = "dark"):
    """(cloth level, background level, dead-zone margin) in grey levels of a dark-cloth image.
    No background: under 2 % of the pixels; no cloth: under 0.5 %."""
    lo, hi = np.percentile(lum, [0.5, 99.5])
    t = _otsu(lum)
    dark, light = lum[lum < t], lum[lum >= t]
    if hi - lo < MIN_CONTRAST or min(dark.size, light.size) < 1e-3 * lum.size:
        d = l = float(np.median(lum))
    else:
        d, l = float(np.median(dark)), float(np.median(light))
    levels = f"grey levels {lo:.0f}..{hi:.0f} of 255"
    if l - d < MIN_CONTRAST:
        if hi < 64 or l < 64:
            raise SilhouetteError(
                f"{where}: the image is all {dark_word} ({levels}): no background"
            )
        if lo > 150 or d > 150:
            raise SilhouetteError(f"{where}: the image is empty ({levels}): no cloth pixels")
        raise SilhouetteError(f"{where}: the image is uniform ({levels}): no cloth/background")
    if light.size < 0.02 * lum.size:
        raise SilhouetteError(
            f"{where}: the image is all {dark_word} ({100 * light.size / lum.size:.1f} % "
            "background pixels): no background"
        )
    if dark.size < 0.005 * lum.size:
        raise SilhouetteError(
            f"{where}: the image is empty ({100 * dark.size / lum.size:.2f} % cloth pixels)"
        )
    mad = lambda v, m: 1.4826 * float(np.median(np.abs(v - m)))
    margin = min(2.5 * max(mad(dark, d), mad(light, l)), 0.2 * (l - d))
    return d, l, margin


def _scale(width: int, g: DrapeGeometry, mm_per_pixel, frame_mm) -> float:
    if mm_per_pixel is not None and frame_mm is not None:
        raise ValueError("give mm_per_pixel or frame_mm, not both")
    if frame_mm is not None:
        mm_per_pixel = float(frame_mm) / width
    if mm_per_pixel is None:
        return 2 * g.specimen_radius * DEFAULT_FRAME / width
    s = float(mm_per_pixel)
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"mm_per_pixel (or frame_mm) must be finite and > 0, got {s!r}")
    return s / 1000.0


def _center(center_px, shape) -> np.ndarray:
    h, w = shape
    if center_px is None:
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    c = np.asarray(center_px, np.float64)
    if c.shape != (2,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center_px must be a finite (x=column, y=row) pair, got {center_px!r}")
    if not (-0.5 <= c[0] <= w - 0.5 and -0.5 <= c[1] <= h - 0.5):
        raise ValueError(f"center_px {c.tolist()} lies outside the {w} x {h} image")
    return c


def read_silhouette(
    path,
    geometry=CUSICK,
    *,
    mm_per_pixel=None,
    frame_mm=None,
    center_px=None,
    cloth="dark",
) -> Silhouette:
    """Read a top-view drape photo (PNG/JPEG, any bit depth; RGB -> Rec. 601 luminance).

    Levels are estimated robustly: an Otsu threshold splits cloth from background, each level is
    its class's median; the background level maps to coverage 0 and the cloth level to 1, linearly,
    with a dead zone of 2.5 noise sigmas (MAD) at both ends so noise adds no area.
    Shapes: coverage (H, W) in [0, 1]; center (2,) pixels (x=column, y=row).

    Args:
      path: the image file.
      geometry: DrapeGeometry (m).
      mm_per_pixel: the scale. If it and frame_mm are None, the image width spans DEFAULT_FRAME
        specimen diameters (the width is the specimen's diameter).
      frame_mm: alternatively, the image width in mm.
      center_px: the pedestal centre (x=column, y=row), pixels; default the image centre.
      cloth: "dark" (cloth darker than the background) or "light".
    Raises:
      SilhouetteError (naming the file): unreadable, smaller than 32 px, empty (no cloth pixels),
        all dark (no background), uniform.
    """
    where = str(path)
    g = check_geometry(geometry)
    if cloth not in ("dark", "light"):
        raise ValueError(f'cloth must be "dark" or "light", got {cloth!r}')
    lum, warnings = _load_luminance(path, where)
    h, w = lum.shape
    if min(h, w) < MIN_SIZE:
        raise SilhouetteError(f"{where}: the image is {w} x {h} pixels; need at least {MIN_SIZE}")
    if cloth == "light":
        lum = 255.0 - lum
    d, l, m = _levels(lum, where, "dark" if cloth == "dark" else "light")
    coverage = np.clip((l - m - lum) / (l - d - 2 * m), 0.0, 1.0)
    pixel = _scale(w, g, mm_per_pixel, frame_mm)
    center = _center(center_px, (h, w))
    if h != w:
        warnings.append(f"{where}: the image is not square ({w} x {h})")
    border = np.concatenate([coverage[0], coverage[-1], coverage[:, 0], coverage[:, -1]])
    if border.mean() > 0.5:
        warnings.append(
            f"{where}: {100 * border.mean():.0f} % of the image border is 'cloth'; is the cloth "
            f"{'light' if cloth == 'dark' else 'dark'}, or the image cropped?"
        )
    return Silhouette(coverage, pixel, center, where, tuple(warnings))


# ------------------------------------------------------------------------------------------------
# checks


def check_silhouette(sil: Silhouette, geometry=CUSICK, **tolerances) -> list[str]:
    """Problems of a drape silhouette (mis-scaled, off-centre), each naming the file and the
    number; [] if none. See `diffcloth.drape.outline.check_silhouette` for the tests and the
    keyword tolerances. Shapes: sil.coverage (H, W); none out (a list of str)."""
    from diffcloth.drape import outline

    return outline.check_silhouette(sil, geometry, **tolerances)


# ------------------------------------------------------------------------------------------------
# synthetic images in the real format


def _frame(size, g: DrapeGeometry, mm_per_pixel, center_px):
    size = int(size)
    if size < MIN_SIZE:
        raise ValueError(f"size must be >= {MIN_SIZE} pixels, got {size}")
    return size, _scale(size, g, mm_per_pixel, None), _center(center_px, (size, size))


def _finish(cov, blur_px, noise, seed, levels) -> np.ndarray:
    if blur_px > 0:
        cov = ndimage.gaussian_filter(cov, float(blur_px), mode="nearest")
    img = levels[1] + (levels[0] - levels[1]) * cov
    if noise > 0:
        img = img + float(noise) * np.random.default_rng(seed).standard_normal(img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def shadow_image(
    x,
    faces,
    geometry=CUSICK,
    *,
    size: int = 256,
    mm_per_pixel=None,
    center_px=None,
    center=(0.0, 0.0, 0.0),
    up=(0.0, 1.0, 0.0),
    supersample: int = 4,
    blur_px: float = 0.7,
    noise: float = 2.0,
    seed: int = 0,
    levels=(CLOTH_LEVEL, BACKGROUND_LEVEL),
) -> np.ndarray:
    """A synthetic drape photo of a mesh: its top-view shadow (`drape_shadow`, cut exactly along
    rows at supersample x the pixel), box-averaged to anti-aliased coverage, blurred (Gaussian,
    blur_px), mapped to levels (cloth, background) and given Gaussian noise (grey levels).

    Shapes: x (n, 3) m; faces (m, 3); returns (size, size) uint8. The world point `center` (m)
    lands on center_px (default the image centre); e1 points right, e2 up (module docstring).
    Default scale: the width spans DEFAULT_FRAME specimen diameters, as `read_silhouette` assumes.
    """
    from diffcloth.physics.mesh.measure import drape_shadow, projection_axes

    g = check_geometry(geometry)
    size, pixel, c_px = _frame(size, g, mm_per_pixel, center_px)
    s = int(supersample)
    sub = pixel / s
    axes = projection_axes(up)
    x = np.asarray(x, np.float64)
    c = np.asarray(center, np.float64) @ axes.T
    lo = c + pixel * np.array([-0.5 - c_px[0], c_px[1] + 0.5 - size])  # frame's lower-left
    hi = lo + size * pixel
    p = x.reshape(-1, 3) @ axes.T
    k = np.maximum(np.ceil((lo - p.min(axis=0)) / sub), 0)  # extra sub-pixels below the frame
    start = lo - k * sub
    # two unreferenced vertices pin the mask's grid to the frame's sub-pixels
    pins = np.stack([start, np.maximum(hi, p.max(axis=0))]) @ axes
    sh = drape_shadow(np.concatenate([x.reshape(-1, 3), pins]), faces, up=up, resolution=sub)
    mask = np.zeros((size * s, size * s), bool)
    kx, ky = int(k[0]), int(k[1])
    part = sh.mask[ky : ky + size * s, kx : kx + size * s]
    mask[: part.shape[0], : part.shape[1]] = part
    cov = mask[::-1].reshape(size, s, size, s).mean(axis=(1, 3))  # mask rows go up the image
    return _finish(cov, blur_px, noise, seed, levels)


def polar_shadow_image(
    r_theta,
    geometry=CUSICK,
    *,
    size: int = 256,
    mm_per_pixel=None,
    center_px=None,
    supersample: int = 4,
    blur_px: float = 0.7,
    noise: float = 2.0,
    seed: int = 0,
    levels=(CLOTH_LEVEL, BACKGROUND_LEVEL),
) -> np.ndarray:
    """A synthetic drape photo of the star-shaped region rho <= r(theta) around the centre, made
    like `shadow_image` (supersampled coverage, blur, levels, noise).

    Shapes: r_theta (k,) m at theta_i = 2 pi i / k (linear interpolation between), or a callable
    theta (...) rad -> r (...) m; returns (size, size) uint8.
    """
    g = check_geometry(geometry)
    size, pixel, c = _frame(size, g, mm_per_pixel, center_px)
    s = int(supersample)
    u = np.arange(size * s) / s - 0.5 + 0.5 / s  # sub-pixel centres, pixel units
    dx = (u - c[0])[None, :]
    dy = (u - c[1])[:, None]
    theta = np.arctan2(-dy, dx)
    rho = np.hypot(dx, dy) * pixel
    r = r_theta(theta) if callable(r_theta) else _periodic_interp(r_theta, theta)
    cov = (rho <= r).reshape(size, s, size, s).mean(axis=(1, 3))
    return _finish(cov, blur_px, noise, seed, levels)


def write_silhouette(path, image, quality: int = 90) -> Path:
    """Write an image (H, W) or (H, W, 3) uint8 as JPEG (at `quality`) or PNG, by the suffix.
    Shapes: image (H, W) or (H, W, 3)."""
    import imageio.v3 as iio

    path = Path(path)
    suffix = path.suffix.lower()
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise ValueError(
            f"{path}: image must be (H, W) or (H, W, 3) uint8, got {a.dtype} {a.shape}"
        )
    if suffix in (".jpg", ".jpeg"):
        iio.imwrite(path, a, extension=suffix, quality=int(quality))
    elif suffix == ".png":
        iio.imwrite(path, a, extension=".png")
    else:
        raise ValueError(f"{path}: the suffix must be .png, .jpg or .jpeg")
    return path


# ------------------------------------------------------------------------------------------------
# overlay


def _draw_polar(img, center, r_px, colour, dash: int = 0) -> None:
    n = max(720, int(8 * np.pi * max(float(np.max(r_px)), 1.0)))
    theta = 2 * np.pi * np.arange(n) / n
    r = _periodic_interp(r_px, theta) if np.ndim(r_px) else np.full(n, float(r_px))
    x = np.round(center[0] + r * np.cos(theta)).astype(np.int64)
    y = np.round(center[1] - r * np.sin(theta)).astype(np.int64)
    keep = (x >= 0) & (x < img.shape[1]) & (y >= 0) & (y < img.shape[0])
    if dash:  # dash lengths in samples, 4 per pixel of arc at the largest radius
        keep &= (np.arange(n) // (4 * dash)) % 2 == 0
    img[y[keep], x[keep]] = colour


def overlay_image(
    sil: Silhouette, predicted_r_theta=None, predicted_coverage=None, geometry=CUSICK
) -> np.ndarray:
    """A comparison picture: the observed silhouette in grey (background 235, cloth 145), the
    observed outline in red OBSERVED_COLOUR, the predicted outline (from predicted_r_theta, or the
    0.5 level of predicted_coverage on the same pixel grid) in blue PREDICTED_COLOUR, the pedestal
    circle dashed in green PEDESTAL_COLOUR; 1-pixel lines, no legend.

    Shapes: sil.coverage (H, W); predicted_r_theta (k,) m at theta_i = 2 pi i / k;
    predicted_coverage (H, W) in [0, 1]; returns (H, W, 3) uint8.
    """
    from diffcloth.drape.outline import _outline_px

    g = check_geometry(geometry)
    grey = np.round(235.0 - 90.0 * sil.coverage).astype(np.uint8)
    img = np.repeat(grey[..., None], 3, axis=2)
    _draw_polar(img, sil.center, g.pedestal_radius / sil.pixel, PEDESTAL_COLOUR, dash=6)
    _draw_polar(img, sil.center, _outline_px(sil.coverage, sil.center, 720)[0], OBSERVED_COLOUR)
    if predicted_coverage is not None:
        pc = np.asarray(predicted_coverage, np.float64)
        if pc.shape != sil.coverage.shape:
            raise ValueError(f"predicted_coverage is {pc.shape}, the silhouette {grey.shape}")
        _draw_polar(img, sil.center, _outline_px(pc, sil.center, 720)[0], PREDICTED_COLOUR)
    if predicted_r_theta is not None:
        r = np.asarray(predicted_r_theta, np.float64) / sil.pixel
        _draw_polar(img, sil.center, r, PREDICTED_COLOUR)
    return img
