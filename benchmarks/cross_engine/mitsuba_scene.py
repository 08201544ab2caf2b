"""Mitsuba 3 path-traced images of a cloth control net (no diffcloth code).

The cloth is the harness's own B-spline surface (`bspline.py`) of the net, as a two-sided
Lambertian mesh with smooth vertex normals; an optional Lambertian sphere; a Lambertian floor (the
plane y = 0, 10 m square); one directional light (irradiance pi * intensity, so a Lambertian
albedo a under it reflects a * intensity * cos, the same numbers as diffcloth's Lambert term) plus a
constant environment of radiance `ambient` (diffcloth's ambient light; here it is occluded, so it
also darkens creases and the sphere under the cloth). Integrator `direct` (emitter and BSDF
sampling, shadow rays: hard shadows of the directional light, soft ambient occlusion), box pixel
filter, linear RGB, perspective cameras with a vertical field of view.

Mitsuba's LLVM variant needs libLLVM >= 17 (Debian: libllvm19); we point DRJIT_LIBLLVM_PATH at the
newest one unless it is set, and fall back to scalar_rgb.
"""

from __future__ import annotations

import glob
import os
import re

import numpy as np

from benchmarks.cross_engine import bspline


def _pick_llvm():
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    best = None
    for path in glob.glob("/usr/lib/*/libLLVM-*.so*") + glob.glob(
        "/usr/lib/llvm-*/lib/libLLVM*.so*"
    ):
        m = re.search(r"(?:libLLVM-|llvm-)(\d+)", path)
        if m and int(m.group(1)) >= 17 and (best is None or int(m.group(1)) > best[0]):
            best = (int(m.group(1)), path)
    if best:
        os.environ["DRJIT_LIBLLVM_PATH"] = best[1]
        return best[1]
    return None


LLVM_PATH = _pick_llvm()
import mitsuba as mi  # noqa: E402


def set_variant():
    for v in ("llvm_ad_rgb", "scalar_rgb"):
        try:
            mi.set_variant(v)
            return v
        except Exception:  # noqa: BLE001 - variant not available on this machine
            continue
    raise RuntimeError("no usable Mitsuba variant (llvm_ad_rgb or scalar_rgb)")


class ClothRenderer:
    """Render control nets of one scene from several cameras.

    Args:
      net_shape: (rows, cols) of the control nets to come.
      cameras: list of {"eye", "target"} (up = +y), fov_y degrees.
      size: (width, height) px.  spp: samples per pixel.  samples: B-spline samples per patch.
      sphere: None or ((cx, cy, cz), r).  floor: draw the floor plane y = 0.
      albedos: dict cloth / sphere / floor -> (3,).
    """

    def __init__(
        self,
        net_shape,
        cameras,
        *,
        fov_y,
        size=(128, 128),
        spp=64,
        samples=6,
        sphere=None,
        floor=True,
        albedos=None,
        light_dir=(0.4, 1.0, 0.3),
        light_intensity=1.0,
        ambient=0.15,
    ):
        self.variant = set_variant()
        mi.set_log_level(mi.LogLevel.Error)
        self.samples, self.sphere, self.spp = samples, sphere, spp
        rows, cols = net_shape
        dummy = np.zeros((rows, cols, 3))
        dummy[..., 0], dummy[..., 2] = np.meshgrid(np.arange(cols), np.arange(rows))
        v, n, f = bspline.surface(dummy, samples)
        self.num_vertices = len(v)
        alb = {"cloth": (0.7, 0.15, 0.2), "sphere": (0.25, 0.45, 0.75), "floor": (0.5, 0.5, 0.5)}
        alb.update(albedos or {})

        def diffuse(rgb, two_sided=False):
            b = {"type": "diffuse", "reflectance": {"type": "rgb", "value": tuple(rgb)}}
            return {"type": "twosided", "material": b} if two_sided else b

        props = mi.Properties()
        props["bsdf"] = mi.load_dict(diffuse(alb["cloth"], True))
        mesh = mi.Mesh("cloth", len(v), len(f), props=props, has_vertex_normals=True)
        mp = mi.traverse(mesh)
        mp["vertex_positions"] = mi.Float(np.asarray(v, np.float32).ravel())
        mp["faces"] = mi.UInt32(np.asarray(f, np.uint32).ravel())
        mp["vertex_normals"] = mi.Float(np.asarray(n, np.float32).ravel())
        mp.update()
        d = -np.asarray(light_dir, np.float64)
        d /= np.linalg.norm(d)
        desc = {
            "type": "scene",
            "integrator": {"type": "direct"},
            "sun": {
                "type": "directional",
                "direction": d.tolist(),
                "irradiance": {"type": "rgb", "value": float(np.pi * light_intensity)},
            },
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": float(ambient)}},
            "cloth": mesh,
        }
        for i, cam in enumerate(cameras):
            desc[f"cam{i}"] = {
                "type": "perspective",
                "fov": float(fov_y),
                "fov_axis": "y",
                "near_clip": 0.05,
                "far_clip": 100.0,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=list(cam["eye"]), target=list(cam["target"]), up=[0.0, 1.0, 0.0]
                ),
                "film": {
                    "type": "hdrfilm",
                    "width": int(size[0]),
                    "height": int(size[1]),
                    "rfilter": {"type": "box"},
                    "pixel_format": "rgb",
                },
                "sampler": {"type": "independent", "sample_count": int(spp)},
            }
        if sphere is not None:
            desc["ball"] = {
                "type": "sphere",
                "center": list(map(float, sphere[0])),
                "radius": float(sphere[1]),
                "bsdf": diffuse(alb["sphere"]),
            }
        if floor:
            desc["floor"] = {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(5.0),
                "bsdf": diffuse(alb["floor"]),
            }
        self.scene = mi.load_dict(desc)
        self.sensors = self.scene.sensors()
        self.params = mi.traverse(self.scene)
        self._seed = 0
        self._aov = mi.load_dict({"type": "aov", "aovs": "a:albedo"})

    def set_net(self, net):
        v, n, _ = bspline.surface(net, self.samples, sphere=self.sphere)
        self.params["cloth.vertex_positions"] = mi.Float(np.asarray(v, np.float32).ravel())
        self.params["cloth.vertex_normals"] = mi.Float(np.asarray(n, np.float32).ravel())
        self.params.update()

    def render(self, net, spp=None, albedo_aov=False):
        """(num_cameras, H, W, 3) float32 linear RGB of one control net (rows, cols, 3).

        albedo_aov: render the box-filtered surface albedo instead of the shaded image (with
        albedos cloth (1, 0, 0) and everything else without red, its red channel is the visible
        cloth coverage of each pixel)."""
        self.set_net(net)
        out = []
        for sensor in self.sensors:
            self._seed += 1
            img = mi.render(
                self.scene,
                sensor=sensor,
                spp=spp or self.spp,
                seed=self._seed,
                integrator=self._aov if albedo_aov else None,
            )
            out.append(np.asarray(img)[..., :3])
        return np.stack(out).astype(np.float32)
