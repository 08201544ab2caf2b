"""The rendering floor against converged path-traced frames: diffcloth's render of the TRUE
trajectory against Mitsuba frames with many samples a pixel.

    python -m benchmarks.cross_engine.floor                        # drape soft + stiff, 2,048 spp
    python -m benchmarks.cross_engine.floor --cases drape:soft --spp 4096 --shadows none

The generated targets (`generate.py`, 32 samples a pixel) carry Monte Carlo noise of about 0.06
RMSE, so a floor measured on them cannot resolve 0.01. Here every frame the fit renders (every
`--stride`-th of the case, both cameras) is path-traced again at `--spp` samples (cached in
data/<scene>_<regime>_ref<spp>_s<stride>.npz, ignored by git; about 4 s a frame at 2,048 spp,
128^2, llvm variant, 2 cores) and compared with diffcloth's render of the true parameters'
trajectory (Provot model, float64 physics: the Warp trajectory to round-off):

- `iou_mean` / `iou_min`: cloth silhouette IoU (masks > 1/2) against the targets' coverage masks;
- `rmse_cloth_ref`: colour RMSE over pixels that are cloth in both, against the reference frames;
- `rmse_32_vs_ref`: the 32-sample targets against the reference (their own noise);
- `ref_noise`: the reference's own noise, estimated from that figure (noise falls as
  1/sqrt(spp)), and `rmse_cloth_ref_denoised`: rmse_cloth_ref with it removed in quadrature.

One JSON line per case into `--out` (default benchmarks/results/cross_engine_floor.jsonl).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.cross_engine import scenes as S
from benchmarks.cross_engine.generate import DATA, load, renderer
from benchmarks.cross_engine.protocol import _SIM_VIDEO, FREE, GUESS, build_scene, downsample, iou

ROOT = Path(__file__).resolve().parents[2]


def rendered_frames(num_frames: int, stride: int) -> np.ndarray:
    """0-based simulated frame indices the fit renders: stride - 1, 2 stride - 1, ..."""
    return np.arange(stride - 1, num_frames, stride)


def reference_frames(scene, regime, nets, frames, spp, size, stride, data_dir=DATA, log=print):
    """(cams, len(frames), size, size, 3) Mitsuba frames at `spp` of nets[frames + 1], cached."""
    path = Path(data_dir) / f"{scene}_{regime}_ref{spp}_s{stride}.npz"
    if path.exists():
        z = np.load(path)
        if z["images"].shape[2] == size and np.array_equal(z["frames"], frames):
            return z["images"], 0.0
    t = time.perf_counter()
    r = renderer(scene, spp, size)
    images = np.stack([r.render(nets[k + 1]) for k in frames], axis=1)
    wall = time.perf_counter() - t
    np.savez_compressed(path, images=images.astype(np.float32), frames=frames, spp=spp)
    log(json.dumps(dict(bench="cross_engine_reference", scene=scene, regime=regime, spp=spp,
                        frames=len(frames), render_s=round(wall, 1))))  # fmt: skip
    return images, wall


def measure(scene, regime, args):
    data = downsample(load(scene, regime, Path(args.data)), args.size)
    F = data["images"].shape[1]
    frames = rendered_frames(F, args.stride)
    ref, ref_s = reference_frames(scene, regime, data["nets"], frames, args.spp, args.size,
                                  args.stride, args.data)  # fmt: skip
    truth = S.warp_params(scene, regime)
    names = (*FREE, "d_struct", "d_shear", "d_flex")
    params = {n: jnp.asarray(truth[n], jnp.float64) for n in names}
    shadows = None if args.shadows == "none" else args.shadows
    sc = build_scene(scene, F, GUESS, size=args.size, stride=args.stride, level=args.level,
                     dtype=jnp.float64, shadows=shadows, ao=args.ao)  # fmt: skip
    t = time.perf_counter()
    traj, video, masks = (np.asarray(a) for a in _SIM_VIDEO(sc, params))
    wall = time.perf_counter() - t
    tv, tm = data["images"][:, frames], data["masks"][:, frames]
    pv, pm = video[:, : len(frames)], masks[:, : len(frames)]
    both = (tm > 0.5) & (pm > 0.5)
    ious = [iou(pm[c, f], tm[c, f]) for c in range(pm.shape[0]) for f in range(pm.shape[1])]

    def rmse(a, b):
        return float(np.sqrt(np.mean((a - b)[both] ** 2)))

    r_ref, r_32, noise32 = rmse(pv, ref), rmse(pv, tv), rmse(tv, ref)
    # var(32 - ref) = s32^2 + sref^2 with sref^2 = s32^2 * 32 / spp
    q = data["meta"]["spp"] / args.spp
    ref_noise = noise32 * np.sqrt(q / (1.0 + q))
    return dict(
        bench="cross_engine_floor",
        scene=scene,
        regime=regime,
        size=args.size,
        stride=args.stride,
        level=args.level,
        shadows=args.shadows,
        ambient_occlusion=args.ao if shadows else 0,
        ref_spp=args.spp,
        target_spp=data["meta"]["spp"],
        frames=int(len(frames)),
        cameras=int(pm.shape[0]),
        cp_max_cm=round(100 * float(np.abs(traj - data["nets"][1:]).max()), 4),
        iou_mean=round(float(np.mean(ious)), 4),
        iou_min=round(float(np.min(ious)), 4),
        rmse_cloth_ref=round(r_ref, 5),
        rmse_cloth_ref_denoised=round(float(np.sqrt(max(r_ref**2 - ref_noise**2, 0.0))), 5),
        rmse_cloth_32=round(r_32, 5),
        rmse_32_vs_ref=round(noise32, 5),
        ref_noise=round(float(ref_noise), 5),
        reference_render_s=round(ref_s, 1),
        diffcloth_s=round(wall, 1),
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=["drape:soft", "drape:stiff"])
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--spp", type=int, default=2048, help="reference samples a pixel")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--stride", type=int, default=3, help="every k-th frame, as the fit renders")
    ap.add_argument("--level", type=int, default=4, help="diffcloth tessellation level")
    ap.add_argument("--shadows", default="fit", choices=("fit", "full", "none"))
    ap.add_argument("--ao", type=int, default=8, help="sky directions with shadows")
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/cross_engine_floor.jsonl"))
    a = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                capture_output=True, text=True).stdout.strip()  # fmt: skip
    except OSError:
        commit = "unknown"
    for case in a.cases:
        scene, regime = case.split(":")
        if not (Path(a.data) / f"{scene}_{regime}.npz").exists():
            from benchmarks.cross_engine.generate import generate

            generate(scene, regime, S.FIT_FRAMES + S.PREDICT_FRAMES, 32, S.SIZE, Path(a.data))
        row = measure(scene, regime, a)
        row.update(commit=commit, machine=platform.machine(), date=time.strftime("%Y-%m-%d %H:%M"))
        print(json.dumps(row), flush=True)
        with open(a.out, "a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
