"""The observed side of a drape fit: every image of a config read, checked and measured.

Images that fail `check_silhouette` (mis-scaled, off-centre, cut off) are set aside with their
reasons, never fitted; an image that cannot be read at all (empty, all dark, uniform) is an
error naming the file. The features are rotation invariant (drape coefficient, node count,
outline spectrum) except the second harmonic, which is turned into the warp frame when the
image's warp direction is known.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from diffcloth.drape.config import DrapeConfig, Observation
from diffcloth.drape.images import Silhouette, read_silhouette
from diffcloth.drape.outline import check_silhouette, drape_features

__all__ = ["Measured", "ObservedSet", "measure_observations"]


@dataclasses.dataclass(frozen=True)
class Measured:
    """One accepted observation with its silhouette and features (see `drape_features`);
    c2: the second harmonic 2 c_2 / c_0 of r(theta) turned into the warp frame (complex; None
    when the warp direction is unknown). A 3D scan has sil None and its points (n, 3) m."""

    obs: Observation
    sil: Silhouette | None
    features: dict
    c2: complex | None
    points: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class ObservedSet:
    """The accepted observations and the rejected ones (observation, reasons)."""

    accepted: tuple[Measured, ...]
    rejected: tuple[tuple[Observation, tuple[str, ...]], ...]

    @property
    def dc(self) -> np.ndarray:
        return np.array([m.features["dc"] for m in self.accepted])

    @property
    def nodes(self) -> np.ndarray:
        return np.array([m.features["node_count"] for m in self.accepted], int)

    @property
    def warp_known(self) -> bool:
        """Every image's warp direction is known (scans carry none: their c2 is left out)."""
        images = [m for m in self.accepted if m.sil is not None]
        return bool(images) and all(m.c2 is not None for m in images)

    @property
    def c2(self) -> np.ndarray:
        """(N,) complex, or (N,) NaN when the warp direction is unknown."""
        nan = complex(np.nan, np.nan)
        return np.array([nan if m.c2 is None else m.c2 for m in self.accepted], complex)

    @property
    def a2(self) -> np.ndarray:
        """(N,) |2 c_2 / c_0|: the elongation of the outline, rotation invariant."""
        return np.array([m.features["spectrum"][1] for m in self.accepted])


def second_harmonic(r_theta, warp_angle_deg: float | None) -> complex | None:
    """2 c_2 / c_0 of r(theta) (theta counter-clockwise from the image's +column axis), turned
    so that the warp lies at theta = 0: r = a (1 + e cos 2 (theta - w)) gives e for a warp at w
    (the outline longer along the warp). None if warp_angle_deg is None."""
    if warp_angle_deg is None:
        return None
    c = np.fft.fft(np.asarray(r_theta, np.float64)) / len(r_theta)
    return complex(2 * c[2] / c[0].real * np.exp(2j * math.radians(warp_angle_deg)))


def measure_observations(cfg: DrapeConfig, *, log=print) -> ObservedSet:
    """Read, check and measure every observation of `cfg`. Raises SilhouetteError for an image
    that cannot be read, and ValueError when no observation passes the checks."""
    accepted, rejected = [], []
    for obs in cfg.observations:
        sil = read_silhouette(obs.path, cfg.geometry, mm_per_pixel=obs.mm_per_pixel,
                              center_px=obs.center_px)  # fmt: skip
        problems = check_silhouette(sil, cfg.geometry)
        if problems:
            rejected.append((obs, tuple(problems)))
            for p in problems:
                log(f"  set aside: {p}")
            continue
        feats = drape_features(sil, cfg.geometry)
        accepted.append(Measured(obs, sil, feats, second_harmonic(feats["r_theta"],
                                                                  obs.warp_angle)))  # fmt: skip
    for path in cfg.scans:
        m, problems = _measure_scan(cfg, path)
        if problems:
            obs = Observation(path, "scan", "-", None, None, None)
            rejected.append((obs, tuple(problems)))
            for p in problems:
                log(f"  set aside: {p}")
        else:
            accepted.append(m)
    if not accepted:
        raise ValueError(
            f"{cfg.source}: none of the {len(cfg.observations)} images passed the checks "
            "(see the messages above); fix their mm_per_pixel / center_px or replace them"
        )
    return ObservedSet(tuple(accepted), tuple(rejected))


def scan_outline(points, num_angles: int = 360) -> np.ndarray:
    """r(theta) of a scanned drape seen from above (+y), about the y axis: the largest horizontal
    radius of the points in each of num_angles sectors (theta from +x towards -z), empty sectors
    filled periodically. Shapes: points (n, 3) m -> (num_angles,) m."""
    p = np.asarray(points, np.float64)
    rho = np.hypot(p[:, 0], p[:, 2])
    theta = np.mod(np.arctan2(-p[:, 2], p[:, 0]), 2 * np.pi)
    idx = np.minimum((theta / (2 * np.pi) * num_angles).astype(int), num_angles - 1)
    r = np.zeros(num_angles)
    np.maximum.at(r, idx, rho)
    have = np.flatnonzero(r > 0)
    if have.size < num_angles:
        ang = np.arange(num_angles)
        r = np.interp(ang, have, r[have], period=num_angles)
    return r


def _measure_scan(cfg: DrapeConfig, path):
    """A scan's features as an observation (DC, node count, spectrum of its top-view outline)
    and the problems `check_scan` finds (wrong units, rotated, off-centre)."""
    from diffcloth.drape.outline import node_count, outline_spectrum
    from diffcloth.drape.scan import read_drape_scan
    from diffcloth.physics.mesh import measure
    from diffcloth.physics.mesh.objfile import parse_obj

    points, problems = read_drape_scan(path, cfg.geometry)
    if problems:
        return None, problems
    faces = parse_obj(Path(path))[2]
    # with faces: the exact outline of the projected surface; a point cloud: the farthest point
    # per sector (needs points dense along the rim)
    r = measure.outline_radius(points, faces, 360) if len(faces) else scan_outline(points)
    g = cfg.geometry
    area = 0.5 * np.sum(r**2) * (2 * np.pi / r.size)
    a_p = math.pi * g.pedestal_radius**2
    dc = (area - a_p) / (math.pi * g.specimen_radius**2 - a_p)
    feats = {"dc": float(dc), "node_count": node_count(r), "r_theta": r,
             "spectrum": outline_spectrum(r), "source": str(path)}  # fmt: skip
    obs = Observation(path, "scan", "-", None, None, None)
    return Measured(obs, None, feats, None, points), []
