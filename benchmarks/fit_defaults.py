"""Fit defaults against the footage recipe (issue 33): old defaults, new defaults, the recipe.

    python benchmarks/fit_defaults.py                       # four cases, all three methods
    python benchmarks/fit_defaults.py --cases soft --runs auto --frames 24

The target is synthetic footage of the cross-engine drape (`configs/cross_engine_drape.toml`: a
13 x 13 Provot mass-spring cloth dropped onto a sphere, two cameras, float64 truth), rendered at
twice the fit's resolution and box-averaged to it, plus Gaussian pixel noise (so it is not the
model's own rendering); the "*_footage" cases also draw what the fit's scene leaves out, as
path-traced footage has it (the floor, the light's shadows, ambient occlusion). Two regimes,
the stiffness started off the truth as in the cross-engine protocol: "soft" (truth k_struct
40 N/m, start 100: 2.5x too stiff) and "stiff" (truth 400, start 100: 4x too soft); air
damping starts at 0.002 (truth 0.01, 5x off) in both. Shear and flexion are tied to k_struct
at the truth's ratios in every run; the fit's free values are k_struct and air_damping. The
scene is built in float32, as `dc.build_scene` does by default.

Runs, each in a fresh process (cold: import, compilation and fit):
- "old": what `dc.fit.fit` did by default before the front door (LM, the scene's float32, the
  coarse-to-fine schedule, no scan): `method="lm"`.
- "auto": today's default, `method="auto"` (float64 under contact, the far-start scan).
- "recipe": docs/fit.md's recipe spelled out (`method="staged"`, x64, air damping alone on the
  first 35 % of the frames, a scan of k_struct over 1/16..16x on the first half, then both).

One JSON line per run (benchmarks/results/fit_defaults.jsonl): relative errors, the silhouette
IoU of the fitted against the true cloth over every frame and camera (masks > 1/2), wall time,
status, what "auto" decided, and the hints.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "cross_engine_drape.toml"
CASES = {
    "soft": {"k_struct": 40.0, "air_damping": 0.01},
    "stiff": {"k_struct": 400.0, "air_damping": 0.01},
}
CASES["soft_footage"], CASES["stiff_footage"] = CASES["soft"], CASES["stiff"]
START = {"k_struct": 100.0, "air_damping": 0.002}
TIES = {"k_shear": "0.25 * k_struct", "k_flex": "0.05 * k_struct"}
DASHPOTS = {"d_struct": 0.02, "d_shear": 0.01, "d_flex": 0.002}  # the truth's, not fitted
RUNS = ("old", "auto", "recipe")


def scene_data(frames: int, size: int, footage: bool = False) -> dict:
    """The scene; `footage`: rendered with what the fit's scene leaves out, as a path tracer's
    footage has it: the floor drawn, the light's shadows, ambient occlusion."""
    data = tomllib.loads(CONFIG.read_text())
    data.pop("fit", None)
    data.pop("truth", None)
    data["sim"]["num_frames"] = frames
    data["render"].update(width=size, height=size)
    data["material"].update(DASHPOTS)
    if footage:
        data["render"].update(draw_planes=True, ambient_occlusion=8)
        data["lights"]["directional"][0]["shadows"] = True
    return data


def one_run(case: str, run: str, args) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import diffcloth as dc
    import diffcloth.config  # noqa: F401
    from diffcloth import pipeline

    t_all = time.perf_counter()
    truth = CASES[case]
    full = {**truth, "k_shear": 0.25 * truth["k_struct"], "k_flex": 0.05 * truth["k_struct"]}
    # footage: the truth in float64 at 2x the size, box-averaged, plus noise
    with jax.enable_x64(True):
        big = dc.build_scene(
            dc.config.parse_config(scene_data(args.frames, 2 * args.size, "footage" in case)),
            dtype=jnp.float64,
        )
        video = np.asarray(jax.jit(dc.simulate_and_render)(big, full))
    c, t, h, w, _ = video.shape
    video = video.reshape(c, t, h // 2, 2, w // 2, 2, 3).mean(axis=(3, 5))
    rng = np.random.default_rng(0)
    video = (video + args.noise * rng.standard_normal(video.shape)).astype(np.float32)
    scene = dc.build_scene(dc.config.parse_config(scene_data(args.frames, args.size)))
    kw = dict(free=["k_struct", "air_damping"], init=START, ties=TIES, progress=False)
    if run == "old":
        kw.update(method="lm")
    elif run == "recipe":
        kw.update(method="staged", x64=True, steps=12, lm_stage_steps=6,
                  stages=[{"frames": 0.35, "free": ["air_damping"]},
                          {"frames": 0.5, "scan": {"k_struct": [2.0**k for k in range(-4, 5)]}}])  # fmt: skip
    t0 = time.perf_counter()
    result = dc.fit.fit(scene, video, **kw)
    fit_s = time.perf_counter() - t0
    fitted = {k: float(np.asarray(result.params[k])) for k in truth}
    err = {k: round(100 * (fitted[k] / truth[k] - 1), 2) for k in truth}
    # silhouettes of the fitted and the true cloth, every frame and camera, at the fit's size
    with jax.enable_x64(True):
        sc64 = dc.build_scene(dc.config.parse_config(scene_data(args.frames, args.size)),
                              dtype=jnp.float64)  # fmt: skip
        sim = jax.jit(lambda p: pipeline.simulate_and_render(sc64, p, with_mask=True)[1])
        fitted_all = {k: float(np.asarray(v)) for k, v in result.params.items()}
        m_fit, m_true = np.asarray(sim(fitted_all)) > 0.5, np.asarray(sim(full)) > 0.5
    inter = (m_fit & m_true).sum(axis=(-2, -1))
    union = np.maximum((m_fit | m_true).sum(axis=(-2, -1)), 1)
    iou = inter / union
    auto = dict(result.auto or {})
    scans = [
        {
            "name": s["name"],
            "best": s["best"],
            "moved": s["moved"],
            "best_loss": min(v for _, v in s["profile"]),
        }
        for s in auto.pop("scans", [])
    ]
    return dict(
        bench="fit_defaults", case=case, run=run, method=result.method,
        x64=bool(auto.get("x64")), far=auto.get("far"), scans=scans,
        scan_loss=[auto.get("initial_loss"), auto.get("loss")],
        truth=truth, start=START, fitted=fitted, err_pct=err,
        iou_mean=round(float(iou.mean()), 4), iou_min=round(float(iou.min()), 4),
        status=result.status, loss=float(result.loss), evaluations=result.evaluations,
        fit_s=round(fit_s, 1), wall_s=round(time.perf_counter() - t_all, 1),
        hints=list(result.hints),
        stages=[s["name"] for s in (result.stages or [])],
    )  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--append", action="store_true", help="add to --out instead of replacing")
    ap.add_argument("--runs", nargs="*", default=list(RUNS), choices=list(RUNS))
    ap.add_argument("--frames", type=int, default=30, help="simulated frames (30 fps)")
    ap.add_argument("--size", type=int, default=64, help="fit image size (targets at 2x)")
    ap.add_argument("--noise", type=float, default=0.01, help="pixel noise std")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "fit_defaults.jsonl"))
    ap.add_argument("--one", help=argparse.SUPPRESS)  # case:run, in this process
    a = ap.parse_args(argv)
    if a.one:
        case, run = a.one.split(":")
        print(json.dumps(one_run(case, run, a)), flush=True)
        return
    meta = dict(bench="fit_defaults", meta=True, date=time.strftime("%Y-%m-%d %H:%M"),
                machine=platform.machine(), frames=a.frames, size=a.size, noise=a.noise,
                commit=subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                      capture_output=True, text=True).stdout.strip())  # fmt: skip
    old = Path(a.out).read_text().splitlines(keepends=True) if a.append else []
    rows = [meta]
    print(json.dumps(meta), flush=True)
    for case in a.cases:
        for run in a.runs:
            cmd = [sys.executable, __file__, "--one", f"{case}:{run}", "--frames", str(a.frames),
                   "--size", str(a.size), "--noise", str(a.noise)]  # fmt: skip
            out = subprocess.run(cmd, capture_output=True, text=True)
            line = out.stdout.strip().splitlines()[-1:] if out.returncode == 0 else []
            row = json.loads(line[0]) if line else dict(
                bench="fit_defaults", case=case, run=run, error=out.stderr[-2000:])  # fmt: skip
            rows.append(row)
            print(json.dumps(row), flush=True)
            Path(a.out).write_text("".join(old) + "".join(json.dumps(r) + "\n" for r in rows))
    print(
        "\n| case | run | method | x64 | k_struct err | air err | IoU mean / min | fit s | status |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows[1:]:
        if "error" in r:
            print(f"| {r['case']} | {r['run']} | error | | | | | | |")
            continue
        e = r["err_pct"]
        print(f"| {r['case']} | {r['run']} | {r['method']} | {r['x64']} | {e['k_struct']:+.1f} % "
              f"| {e['air_damping']:+.1f} % | {r['iou_mean']:.3f} / {r['iou_min']:.3f} | "
              f"{r['fit_s']} | {r['status']} |")  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
