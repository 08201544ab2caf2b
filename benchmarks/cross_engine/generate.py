"""Generate the cross-engine targets: Warp physics (Provot mass-spring), Mitsuba 3 images.

    python -m benchmarks.cross_engine.generate      # every case -> benchmarks/cross_engine/data
    python -m benchmarks.cross_engine.generate --cases drape:soft --spp 32

For each (scene, regime) of `scenes.CASES`, one file data/<scene>_<regime>.npz holding
  nets    (F + 1, rows, cols, 3) float64  the Warp control nets, entry 0 the initial state
  images  (cams, F, H, W, 3) float32     Mitsuba frames 1 .. F (the end of each 1/30 s frame)
  masks   (cams, F, H, W) float32        visible cloth coverage (Mitsuba albedo AOV, box filter)
plus the scene's parameters as JSON. No diffcloth code runs here. The data folder is ignored by
git: regenerate it (about a minute per case at 128^2, 32 spp, on 2 loaded cores).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.cross_engine import scenes as S

DATA = Path(__file__).resolve().parent / "data"


def simulate(scene: str, regime: str, frames: int) -> np.ndarray:
    from benchmarks.peers.warp_massspring import simulate as warp_simulate

    spec = S.SCENES[scene]
    return warp_simulate(
        S.ROWS,
        S.COLS,
        S.CLOTH_SIZE,
        S.warp_params(scene, regime),
        sphere=spec["sphere"],
        dt=S.DT,
        substeps=S.SUBSTEPS,
        frames=frames,
        dtype=np.float64,
    )


def renderer(scene: str, spp: int, size: int, albedos=None):
    from benchmarks.cross_engine.mitsuba_scene import ClothRenderer

    spec = S.SCENES[scene]
    return ClothRenderer(
        (S.ROWS, S.COLS),
        spec["cameras"],
        fov_y=S.FOV_Y,
        size=(size, size),
        spp=spp,
        sphere=spec["sphere"],
        albedos=albedos
        or {"cloth": S.CLOTH_ALBEDO, "sphere": S.SPHERE_ALBEDO, "floor": S.FLOOR_ALBEDO},
        light_dir=S.LIGHT_DIR,
        light_intensity=S.LIGHT_INTENSITY,
        ambient=S.AMBIENT,
    )


MASK_ALBEDOS = {"cloth": (1.0, 0.0, 0.0), "sphere": (0.0, 1.0, 0.0), "floor": (0.0, 0.0, 1.0)}


def cloth_masks(scene, nets, spp, size):
    """(cams, F, H, W) visible cloth coverage: Mitsuba's box-filtered albedo AOV with the cloth
    albedo (1, 0, 0) and no red anywhere else (its red channel)."""
    r = renderer(scene, spp, size, albedos=MASK_ALBEDOS)
    return np.stack([r.render(x, albedo_aov=True)[..., 0] for x in nets], axis=1)


def generate(scene, regime, frames, spp, size, out_dir=DATA, log=print):
    t0 = time.perf_counter()
    nets = simulate(scene, regime, frames)
    t1 = time.perf_counter()
    r = renderer(scene, spp, size)
    images = np.stack([r.render(x) for x in nets[1:]], axis=1)
    t2 = time.perf_counter()
    masks = cloth_masks(scene, nets[1:], spp, size)
    t3 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = dict(
        scene=scene,
        regime=regime,
        frames=frames,
        spp=spp,
        size=size,
        params=S.warp_params(scene, regime),
        sphere=S.SCENES[scene]["sphere"],
        cameras=S.SCENES[scene]["cameras"],
        dt=S.DT,
        substeps=S.SUBSTEPS,
        variant=r.variant,
    )
    np.savez_compressed(
        out_dir / f"{scene}_{regime}.npz", nets=nets, images=images, masks=masks,
        meta=json.dumps(meta),
    )  # fmt: skip
    row = dict(
        bench="cross_engine_generate",
        scene=scene,
        regime=regime,
        frames=frames,
        physics_s=round(t1 - t0, 2),
        render_s=round(t2 - t1, 2),
        mask_s=round(t3 - t2, 2),
        lowest_y=float(nets[..., 1].min()),
        finite=bool(np.isfinite(nets).all()),
        mean_mask=float(masks.mean()),
    )
    log(json.dumps(row))
    return row


def load(scene, regime, data=DATA):
    z = np.load(data / f"{scene}_{regime}.npz")
    return dict(
        nets=z["nets"], images=z["images"], masks=z["masks"], meta=json.loads(str(z["meta"]))
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", help="scene:regime, default all")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--size", type=int, default=S.SIZE)
    ap.add_argument("--frames", type=int, default=S.FIT_FRAMES + S.PREDICT_FRAMES)
    a = ap.parse_args(argv)
    cases = [tuple(c.split(":")) for c in a.cases] if a.cases else S.CASES
    for scene, regime in cases:
        generate(scene, regime, a.frames, a.spp, a.size)


if __name__ == "__main__":
    main(sys.argv[1:])
