"""diffcloth vs Mitsuba 3 path tracing on the same draped cloth frames (shadows on in both).

    python benchmarks/peers/mitsuba_agreement.py                  # 128^2 and 256^2, 5 frames
    python benchmarks/peers/mitsuba_agreement.py --out benchmarks/results/mitsuba_agreement.jsonl

Frames: the cross-engine benchmark's drape (benchmarks/cross_engine/scenes.py, stiff regime): a
13 x 13 Provot cloth dropped on a sphere above a floor, simulated by the independent Warp
reference (benchmarks/peers/warp_massspring.py). Each chosen frame's control net is drawn by

- Mitsuba 3 (`benchmarks/cross_engine/mitsuba_scene.py`): the harness's own numpy B-spline
  surface of the net (8 samples per patch), two-sided Lambertian cloth, Lambertian sphere and
  floor, a directional light (irradiance pi * I) and a constant environment of radiance `ambient`,
  `direct` integrator (shadow rays), box filter, `--spp` samples;
- diffcloth: `surface.tessellate` (level 8) + `collide_surface`, `render.render` in "phong" mode
  with zero specular (Lambert), ambient light = the environment's radiance, the floor drawn as a
  plane, the sphere drawn, shadows on for the directional light (when this diffcloth has them),
  and the ambient light occluded by the scene (`ambient_occlusion`, --ambient-occlusion sky
  directions, default 32): the model of Mitsuba's constant environment blocked by the geometry.

Same cameras (two), same light, same albedos. Figures per resolution, over frames and cameras:
  iou         cloth-mask IoU, the mask of each image by a cloth-colour test (chromaticity within
              0.1 of the cloth albedo's, `diffcloth.fit.cloth_mask_by_color`);
  rmse_cloth  RMSE over pixels that are cloth in both masks, linear RGB.
Known differences: diffcloth's occluded ambient is estimated from K fixed directions with soft
shadow maps (Mitsuba integrates the environment by Monte Carlo), its shadows are a shadow map with
soft (percentage-closer) edges where Mitsuba's directional light casts hard ones, its floor is an
infinite plane (Mitsuba's a 10 m square), and the reference carries Monte Carlo noise.
"""

from __future__ import annotations

import argparse
import inspect
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.cross_engine import scenes as S  # noqa: E402
from benchmarks.cross_engine.mitsuba_scene import ClothRenderer, mi  # noqa: E402

FRAMES = (6, 12, 20, 30, 45, 60)
#: diffcloth's sky directions for ambient occlusion (Mitsuba's environment is occluded too)
AO_DIRECTIONS = 32


def warp_frames(regime: str, frames):
    from benchmarks.peers.warp_massspring import simulate

    spec = S.SCENES["drape"]
    nets = simulate(
        S.ROWS, S.COLS, S.CLOTH_SIZE, S.warp_params("drape", regime), sphere=spec["sphere"],
        dt=S.DT, substeps=S.SUBSTEPS, frames=max(frames), dtype=np.float64,
    )  # fmt: skip
    return [nets[f] for f in frames]


def diffcloth_renderer(size: int, shadows: bool, level: int = 8, ambient_occlusion: int = 0):
    from diffcloth import render, surface
    from diffcloth.shapes import Plane, Sphere

    spec = S.SCENES["drape"]
    (c, r) = spec["sphere"]
    dt = jnp.float32
    cams = [
        render.make_camera(cam["eye"], cam["target"], (0.0, 1.0, 0.0), width=size, height=size,
                           fov_y=S.FOV_Y)
        for cam in spec["cameras"]
    ]  # fmt: skip
    kw = {}
    has_shadows = "shadows" in inspect.signature(render.make_lights).parameters
    if has_shadows and shadows:
        kw["shadows"] = True
    lights = render.make_lights(
        ambient=(S.AMBIENT,) * 3,
        directional=[(S.LIGHT_DIR, (1.0, 1.0, 1.0), S.LIGHT_INTENSITY)],
        dtype=dt,
        **kw,
    )
    app = render.make_appearance(
        diffuse=S.CLOTH_ALBEDO, specular=(0.0, 0.0, 0.0), ambient=(1.0, 1.0, 1.0),
        sphere_color=S.SPHERE_ALBEDO, dtype=dt,
    )  # fmt: skip
    sphere = Sphere(jnp.asarray(c, dt), jnp.asarray(r, dt))
    push = Sphere(jnp.asarray(c, dt), jnp.asarray(r + 0.002, dt))  # as the Mitsuba harness
    rkw = {}
    params = inspect.signature(render.render).parameters
    if "planes" in params:
        rkw["planes"] = Plane(jnp.asarray([[0.0, 1.0, 0.0]], dt), jnp.asarray([0.0], dt))
        rkw["plane_color"] = S.FLOOR_ALBEDO
    if "shadow_map_size" in params:
        rkw["shadow_map_size"] = 512
    ao = ambient_occlusion if "ambient_occlusion" in params else 0
    if ao:
        rkw["ambient_occlusion"] = ao

    def frame(net):
        surf = surface.tessellate(net, level, "bspline", flip=True)
        surf = surface.collide_surface(surf, push)
        return jnp.stack([
            render.render(surf, cam, lights, "phong", app, spheres=sphere,
                          background=(S.AMBIENT,) * 3, **rkw)[..., :3]
            for cam in cams
        ])  # fmt: skip

    return jax.jit(frame), bool(has_shadows and shadows), "planes" in params, ao


def compare(dc_imgs, mi_imgs):
    from diffcloth.fit import cloth_mask_by_color

    md = cloth_mask_by_color(dc_imgs, S.CLOTH_ALBEDO) > 0.5
    mm = cloth_mask_by_color(mi_imgs, S.CLOTH_ALBEDO) > 0.5
    union = np.logical_or(md, mm).sum(axis=(-2, -1))
    inter = np.logical_and(md, mm).sum(axis=(-2, -1))
    both = md & mm
    diff = (dc_imgs - mi_imgs)[both]
    return inter / np.maximum(union, 1), float(np.sqrt(np.mean(diff**2))), md, mm


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--frames", type=int, nargs="+", default=list(FRAMES))
    ap.add_argument("--regime", default="stiff", choices=sorted(S.REGIMES))
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--no-shadows", dest="shadows", action="store_false")
    ap.add_argument(
        "--ambient-occlusion", type=int, default=AO_DIRECTIONS,
        help="diffcloth's sky directions for the occluded ambient light (0: unoccluded ambient)",
    )  # fmt: skip
    ap.add_argument("--quick", action="store_true", help="128^2 only, 2 frames, 64 spp")
    ap.add_argument("--out", help="also write the JSON lines to this file")
    ap.add_argument("--save-images", help="npz with both renderers' images")
    a = ap.parse_args(argv)
    if a.quick:
        a.sizes, a.frames, a.spp = [128], [20, 45], 64
    lines = []

    def emit(row):
        print(json.dumps(row), flush=True)
        lines.append(row)

    nets = warp_frames(a.regime, a.frames)
    emit(dict(bench="meta", script="mitsuba_agreement", machine=platform.machine(),
              jax=jax.__version__, mitsuba=mi.__version__, frames=a.frames, regime=a.regime,
              spp=a.spp))  # fmt: skip
    saved = {}
    for size in a.sizes:
        t0 = time.perf_counter()
        spec = S.SCENES["drape"]
        mr = ClothRenderer(
            (S.ROWS, S.COLS), spec["cameras"], fov_y=S.FOV_Y, size=(size, size), spp=a.spp,
            samples=8, sphere=spec["sphere"],
            albedos={"cloth": S.CLOTH_ALBEDO, "sphere": S.SPHERE_ALBEDO, "floor": S.FLOOR_ALBEDO},
            light_dir=S.LIGHT_DIR, light_intensity=S.LIGHT_INTENSITY, ambient=S.AMBIENT,
        )  # fmt: skip
        mi_imgs = np.stack([mr.render(x) for x in nets], axis=1)  # (cams, F, H, W, 3)
        t1 = time.perf_counter()
        frame, shadowed, planes, ao = diffcloth_renderer(
            size, a.shadows, ambient_occlusion=a.ambient_occlusion
        )
        dc_imgs = np.stack([np.asarray(frame(jnp.asarray(x, jnp.float32))) for x in nets], 1)
        t2 = time.perf_counter()
        ious, rmse, md, mm = compare(dc_imgs, mi_imgs)
        per_frame = [
            compare(dc_imgs[:, i : i + 1], mi_imgs[:, i : i + 1]) for i in range(len(nets))
        ]
        emit(dict(
            bench="peers_mitsuba_agreement", size=size, frames=len(nets), cameras=mi_imgs.shape[0],
            diffcloth_shadows=shadowed, diffcloth_floor=planes, diffcloth_ao=ao,
            iou_mean=round(float(ious.mean()), 4), iou_min=round(float(ious.min()), 4),
            rmse_cloth=round(rmse, 4),
            rmse_per_frame=[round(p[1], 4) for p in per_frame],
            iou_per_frame=[round(float(p[0].mean()), 4) for p in per_frame],
            cloth_pixels=int((md & mm).sum()), mitsuba_s=round(t1 - t0, 1),
            diffcloth_s=round(t2 - t1, 1),
        ))  # fmt: skip
        saved[f"mitsuba_{size}"] = mi_imgs
        saved[f"diffcloth_{size}"] = dc_imgs
    if a.save_images:
        np.savez_compressed(a.save_images, **saved)
    if a.out:
        with open(a.out, "w") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in lines)


if __name__ == "__main__":
    main(sys.argv[1:])
