"""Cross-engine protocol: fit diffcloth to footage it did not make, predict, compare.

    python -m benchmarks.cross_engine.generate          # targets (Warp + Mitsuba), once
    python -m benchmarks.cross_engine.protocol          # every case -> results.jsonl, RESULTS.md
    python -m benchmarks.cross_engine.protocol --cases drape:soft --fit-frames 30

Per case (scene x stiffness regime), through diffcloth's public API only:
1. A scene is built from a config dict (`dc.build_scene`: net, sim, sphere, floor plane, the two
   cameras, light, albedos, background = the environment's grey) with the Provot mass-spring model
   (`diffcloth.physics.massspring`) and a generic guess, never the truth: k_struct = 100,
   k_shear = 25, k_flex = 5 N/m, air damping 0.002 N s/m; dashpots, density and friction at the
   model's defaults (the truth uses other dashpots). Simulated in float64 (`--float32` to
   compare): in float32 the round-off alone moves the draped cloth enough to make the loss jump.
2. Fit on the first `fit_frames` frames (two thirds) with `diffcloth.fit.engines.staged`
   (Levenberg-Marquardt stages, coarse to fine in the parameters and in time): air damping alone
   on the free fall (the first 35 % of the fitting frames, simulated alone); then a scan of the
   stiffness scale over 1/16 .. 16 x the guess (shear and flexion tied to k_struct at the guess's
   ratios), then LM over (k_struct, air damping) on the first half and on all fitting frames;
   `--untie` adds a last stage over all four. The loss is `dc.fit.footage`: a soft-IoU
   silhouette term + a Huber colour term over the target's cloth pixels (dilated mask: diffcloth
   draws no floor, so colour elsewhere is not comparable).
3. Predict every frame with the fitted values and compare with the Warp nets (control points:
   both engines use the same grid) and the Mitsuba frames (cloth silhouette IoU of masks > 1/2,
   RMSE over pixels that are cloth in both), for the fitting and the predicted frames; the same
   with the TRUE parameters (the floor: what the model cannot match at all).
4. A loss profile over k_struct (the others at the fitted values).

One JSON line per case and stage (bench "cross_engine_*"), and a table in RESULTS.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.cross_engine import scenes as S
from benchmarks.cross_engine.generate import DATA, load

HERE = Path(__file__).resolve().parent
GUESS = {"k_struct": 100.0, "k_shear": 25.0, "k_flex": 5.0, "air_damping": 0.002}
FREE = ("k_struct", "k_shear", "k_flex", "air_damping")


def log(row):
    print(json.dumps(row), flush=True)
    return row


def has_massspring() -> bool:
    try:
        import diffcloth.physics.massspring  # noqa: F401
    except ImportError:
        return False
    return True


def build_scene(
    scene_name: str,
    num_frames: int,
    guess: dict,
    size: int = S.SIZE,
    stride=1,
    level=4,
    dtype=jnp.float32,
    shadows=None,
    ao=8,
):
    """The diffcloth scene of a case with the given stiffnesses (Provot model). shadows: None
    (the light casts none, no floor drawn, unoccluded ambient) or a `shadow_quality` ("fit",
    "full"): the light casts shadows, the floor is drawn, and the ambient light is occluded
    over `ao` sky directions, as in the Mitsuba frames."""
    import diffcloth as dc
    from diffcloth import config as cfg

    spec = S.SCENES[scene_name]
    w = spec["warp"]
    pinned = w["pins"] or "none"
    conf = {
        "net": {
            "rows": S.ROWS,
            "cols": S.COLS,
            "width": S.CLOTH_SIZE[0],
            "height": S.CLOTH_SIZE[1],
            "center": [0.0, w["height"], 0.0],
            "plane": "xz",
            "pinned": pinned,
        },
        "sim": {
            "dt": 1.0 / S.FPS,
            "num_frames": num_frames,
            "num_substeps": S.SUBSTEPS,
            "integrator": "symplectic",
            "gravity": [0.0, -9.81, 0.0],
            "collision_margin": S.BASE["contact_thickness"],
        },
        "planes": [{"normal": [0.0, 1.0, 0.0], "offset": 0.0}],
        "render": {
            "width": size,
            "height": size,
            "level": level,
            "basis": "bspline",
            "shading": "phong",
            "background": [S.AMBIENT] * 3,
            "frame_stride": stride,
            # cloth resting on the sphere is drawn 2 mm outside it (as the Mitsuba harness does):
            # with 0, the flat triangles between pushed vertices dip under the drawn sphere
            "push_out_offset": 0.002,
        },
        "cameras": [
            {"eye": list(c["eye"]), "target": list(c["target"]), "fov_y": S.FOV_Y}
            for c in spec["cameras"]
        ],
        "lights": {
            "ambient": [S.AMBIENT] * 3,
            "directional": [{"direction": list(S.LIGHT_DIR), "intensity": S.LIGHT_INTENSITY}],
        },
        "appearance": {
            "diffuse": list(S.CLOTH_ALBEDO),
            "specular": [0.0, 0.0, 0.0],
            "ambient": [1.0, 1.0, 1.0],
            "sphere_color": list(S.SPHERE_ALBEDO),
        },
    }
    if shadows:
        conf["render"].update(draw_planes=True, plane_color=list(S.FLOOR_ALBEDO),
                              ambient_occlusion=ao, shadow_quality=shadows)  # fmt: skip
        conf["lights"]["directional"][0]["shadows"] = True
    if spec["sphere"] is not None:
        conf["spheres"] = [{"center": list(spec["sphere"][0]), "radius": spec["sphere"][1]}]
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the continuum stability check does not apply
        sc = dc.build_scene(cfg.parse_config(conf), dtype=dtype)
    from diffcloth.physics.massspring import make_mass_spring

    ms = make_mass_spring(dtype, lumping="uniform", **guess)
    sim = sc.sim
    if "friction_rule" in {f.name for f in dataclasses.fields(sim)}:
        sim = dataclasses.replace(sim, friction_rule="coulomb")
    return dataclasses.replace(sc, material=ms, sim=sim)


# ----------------------------------------------------------------------------- metrics


def iou(a, b):
    a, b = a > 0.5, b > 0.5
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0


def _sim_video(sc, p):
    from diffcloth import pipeline

    x = pipeline.simulate(sc, p).x
    return (x, *pipeline.simulate_and_render(sc, p, with_mask=True))


_SIM_VIDEO = jax.jit(_sim_video)  # one compiled program per scene structure


def compare(scene, params, data, frames: slice, run=None):
    """Trajectory, silhouette and colour figures of diffcloth with `params` against the targets
    on the simulated frames `frames` (0-based: frame k + 1 of the footage). Images are compared
    on the rendered frames (every `scene.frame_stride`-th) inside `frames`. `run`: the
    (trajectory, video, masks) of these params when already computed."""
    k = scene.frame_stride
    traj, video, masks = run or (np.asarray(a) for a in _SIM_VIDEO(scene, params))
    ref = data["nets"][1:]  # Warp frames 1 .. F
    d = np.linalg.norm(traj[frames] - ref[frames], axis=-1)
    sim_idx = np.arange(k - 1, traj.shape[0], k)  # simulated frame index of each rendered frame
    keep = (sim_idx >= frames.start) & (sim_idx < frames.stop)
    tv, tm = data["images"][:, sim_idx[keep]], data["masks"][:, sim_idx[keep]]
    pv, pm = video[:, keep], masks[:, keep]
    both = (tm > 0.5) & (pm > 0.5)
    ious = [iou(pm[c, f], tm[c, f]) for c in range(pm.shape[0]) for f in range(pm.shape[1])]
    return dict(
        cp_mean_cm=round(100 * float(d.mean()), 3),
        cp_max_cm=round(100 * float(d.max()), 3),
        iou_mean=round(float(np.mean(ious)), 4),
        iou_min=round(float(np.min(ious)), 4),
        rmse_cloth=round(float(np.sqrt(np.mean((pv - tv)[both] ** 2))), 4),
    ), (video, masks)


# ----------------------------------------------------------------------------- fit


def dilate(m, r):
    out = m.copy()
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out = np.maximum(out, np.roll(np.roll(m, dy, -2), dx, -1))
    return out


def footage_setup(scene, data, n_fit):
    from diffcloth.fit import footage

    spec = footage.FootageLoss(color="huber", color_scale=0.05, mask="iou", mask_weight=1.0)
    k = scene.frame_stride
    idx = np.arange(k - 1, n_fit, k)
    tv = np.clip(data["images"][:, idx], 0.0, 1.0)
    tm = data["masks"][:, idx]
    prep = footage.prepare_targets(scene, tv, tm, spec)
    # colour only where the target shows cloth (3 px margin): diffcloth draws no floor
    w = jnp.asarray(dilate((tm > 0.5).astype(np.float32), 3)[..., None], prep.video.dtype)
    return spec, prep, w


def residual_fn_factory(spec):
    from diffcloth import pipeline
    from diffcloth.fit import footage

    def residuals(params, scene, prep, wpix, frame_w):
        video, masks = pipeline.simulate_and_render(scene, params, with_mask=True)
        # colour residuals only on the target's cloth pixels (wpix is 0/1)
        video = wpix * video + (1.0 - wpix) * prep.video
        return footage.footage_residuals(video, masks, prep, spec, frame_w)

    return residuals


#: the generic guess's stiffness ratios, kept by the tie (one free stiffness scale)
TIES = {
    "k_shear": f"{GUESS['k_shear'] / GUESS['k_struct']:g} * k_struct",
    "k_flex": f"{GUESS['k_flex'] / GUESS['k_struct']:g} * k_struct",
}
SCAN = tuple(2.0 ** np.arange(-4, 5))  # k_struct x 1/16 .. 16 around the guess


def window(T: int, frac: float, dtype) -> jax.Array:
    """(T,) frame weights: 1 on the first max(1, round(frac * T)) rendered frames."""
    return jnp.asarray((np.arange(T) < max(1, round(frac * T))).astype(dtype))


def run_fit(case, data, n_fit, args, log_fn):
    """The staged fit (`diffcloth.fit.staged`) on the first n_fit frames:
    1. air damping alone, on a scene that simulates only the first 35 % of the fitting frames
       (the free fall, and the first contact);
    2. a scan of the stiffness scale (k_struct x 1/16 .. 16, shear and flexion tied to it at the
       guess's ratios) on the first half, then LM over (k_struct, air damping) on the first half
       and on all fitting frames;
    3. with `--untie`, LM over all four on all fitting frames.
    Returns (fitted, wall_s, method, evaluations)."""
    from diffcloth.fit.constraints import Positive
    from diffcloth.fit.engines import ParamStage
    from diffcloth.fit.engines import staged as fit_staged
    from diffcloth.fit.settings import FitSettings

    dtype = np.float64 if args.x64 else np.float32
    kw = dict(size=args.size, stride=args.stride, level=args.level, dtype=dtype,
              shadows=args.shadows, ao=args.ao)  # fmt: skip
    n_early = max(args.stride, int(round(0.35 * n_fit)) // args.stride * args.stride)
    early = build_scene(case[0], n_early, GUESS, **kw)
    scene = build_scene(case[0], n_fit, GUESS, **kw)
    spec, prep_e, w_e = footage_setup(early, data, n_early)
    _, prep, wpix = footage_setup(scene, data, n_fit)
    res = residual_fn_factory(spec)
    T = prep.video.shape[1]
    stages = [
        ParamStage(("air_damping",), loss_args=(early, prep_e, w_e),
                   stage_args=[(jnp.ones(prep_e.video.shape[1], dtype),)], steps=10,
                   name="free fall"),
        ParamStage(("k_struct", "air_damping"), scan={"k_struct": SCAN},
                   stage_args=[(window(T, 0.5, dtype),), (window(T, 1.0, dtype),)],
                   name="stiffness scale"),
    ]  # fmt: skip
    if args.untie:
        stages.append(ParamStage(FREE, stage_args=[(window(T, 1.0, dtype),)], name="untied"))
    free = FREE if args.untie else ("k_struct", "air_damping")
    t0 = time.perf_counter()
    out = fit_staged(
        res,
        {n: np.asarray(GUESS[n], dtype) for n in free},
        {n: Positive() for n in free},
        stages=stages,
        loss_args=(scene, prep, wpix),
        ties=None if args.untie else TIES,
        settings=FitSettings(
            method="lm",
            steps=args.steps,
            lm_stage_steps=max(2, args.steps // 2),
            lm_xtol=1e-3,  # 0.1 % in the log-parameters: far below what the footage resolves
            lm_ftol=1e-5,
            lm_polish=0,  # undamped Gauss-Newton steps do not settle on a footage loss
            # from a generic guess the first Gauss-Newton steps overshoot: start damped
            # (lambda0 = max diag J^T J) rather than Marquardt's 1e-3 for a close start
            lm_tau=1.0,
            progress=False,
        ),
        log=lambda row: log_fn({k: v for k, v in row.items() if k != "free"}),
    )  # fmt: skip
    wall = time.perf_counter() - t0
    fitted = {n: float(np.asarray(out.params[n])) for n in FREE}
    method = "staged lm" + (" + untied" if args.untie else " (tied)")
    log_fn(dict(method=method, wall_s=round(wall, 1), loss=out.loss, fitted=fitted,
                evaluations=out.evaluations, status=out.status))  # fmt: skip
    return fitted, wall, method, out.evaluations


def profile_loss(video, masks, data, n_fit, stride):
    """The fit's loss terms (soft-IoU silhouette, Huber colour on the target's cloth pixels)
    over the fitting frames, in numpy from a rendered video: for the loss profile."""
    idx = np.arange(stride - 1, n_fit, stride)
    k = len(idx)
    tv, tm = np.clip(data["images"][:, idx], 0, 1), data["masks"][:, idx]
    pv, pm = video[:, :k], masks[:, :k]
    inter = (pm * tm).sum(axis=(-2, -1))
    union = (pm + tm - pm * tm).sum(axis=(-2, -1))
    iou_term = float(np.mean(1 - inter / np.maximum(union, 1e-12)))
    w = dilate((tm > 0.5).astype(np.float64), 3)[..., None]
    d = np.abs(pv - tv) * w
    s = 0.05
    rho = np.where(d <= s, d * d, 2 * s * d - s * s)
    return iou_term + float(rho.mean())


# ----------------------------------------------------------------------------- main


def downsample(data, size):
    """Box-average the 128^2 footage to size^2 (what a size^2 camera with a box filter sees)."""
    f = data["images"].shape[2] // size
    if f <= 1:
        return data
    c, F, H, W, _ = data["images"].shape
    img = data["images"].reshape(c, F, H // f, f, W // f, f, 3).mean(axis=(3, 5))
    msk = data["masks"].reshape(c, F, H // f, f, W // f, f).mean(axis=(3, 5))
    return {**data, "images": img, "masks": msk}


def run_case(scene_name, regime, args, results):
    data = downsample(load(scene_name, regime, Path(args.data)), args.size)
    F = data["images"].shape[1]
    n_fit = args.fit_frames or (2 * F) // 3
    truth_all = S.warp_params(scene_name, regime)
    truth = {n: truth_all[n] for n in FREE}
    true_dyn = {n: truth_all[n] for n in ("d_struct", "d_shear", "d_flex", "air_damping")}
    head = dict(scene=scene_name, regime=regime, frames=F, fit_frames=n_fit,
                size=int(data["images"].shape[2]))  # fmt: skip
    dtype = np.float64 if args.x64 else np.float32
    kw = dict(size=head["size"], stride=args.stride, level=args.level, dtype=dtype,
              shadows=args.shadows, ao=args.ao)  # fmt: skip
    if args.shadows:
        head.update(shadows=args.shadows, ambient_occlusion=args.ao, level=args.level)
    full_scene = build_scene(scene_name, F, GUESS, **kw)
    head["stride"] = args.stride
    x0 = np.asarray(full_scene.state.x)
    head["start_layout_max_m"] = float(np.abs(x0 - data["nets"][0]).max())

    def stage_log(row):
        return log(dict(bench="cross_engine_fit", **head, **row))

    if args.steps > 0:
        fitted, wall, method, _ = run_fit((scene_name, regime), data, n_fit, args, stage_log)
    else:  # floor and loss profile only: the guess stands in for the fit
        fitted, wall, method = {n: float(GUESS[n]) for n in FREE}, 0.0, "none (guess)"
    fit_rows, pred_rows = slice(0, n_fit), slice(n_fit, F)
    out = dict(bench="cross_engine", **head, method=method, fit_wall_s=round(wall, 1),
               truth=truth, guess=GUESS, fitted=fitted)  # fmt: skip
    out["param_err_pct"] = {n: round(100 * (fitted[n] / truth[n] - 1), 2) for n in FREE}
    fp = {n: jnp.asarray(v, dtype) for n, v in fitted.items()}
    tp = {n: jnp.asarray(v, dtype) for n, v in {**truth, **true_dyn}.items()}
    t = time.perf_counter()
    run_fp = tuple(np.asarray(a) for a in _SIM_VIDEO(full_scene, fp))
    run_tp = tuple(np.asarray(a) for a in _SIM_VIDEO(full_scene, tp))
    out["fit"], _ = compare(full_scene, fp, data, fit_rows, run_fp)
    out["predict"], _ = compare(full_scene, fp, data, pred_rows, run_fp)
    out["floor_fit"], _ = compare(full_scene, tp, data, fit_rows, run_tp)
    out["floor_predict"], _ = compare(full_scene, tp, data, pred_rows, run_tp)
    log(dict(bench="cross_engine_compare", **head, wall_s=round(time.perf_counter() - t, 1)))
    if args.profile:
        prof = []
        base = tp if args.profile_at == "truth" else fp
        out["profile_at"] = args.profile_at
        for k in truth["k_struct"] * np.exp(np.linspace(np.log(0.25), np.log(4.0), 7)):
            p = {**base, "k_struct": jnp.asarray(k, dtype)}
            if not args.untie:  # along the tie: shear and flexion follow at the guess's ratios
                for n in ("k_shear", "k_flex"):
                    p[n] = jnp.asarray(k * GUESS[n] / GUESS["k_struct"], dtype)
            _, (video, masks) = compare(full_scene, p, data, fit_rows)
            prof.append((round(float(k), 2), profile_loss(video, masks, data, n_fit, args.stride)))
            log(dict(bench="cross_engine_profile", **head, k_struct=prof[-1][0], loss=prof[-1][1]))
        out["profile_k_struct"] = prof
    results.append(log(out))


NOTES = [
    "## Notes",
    "",
    '- `method` "none (guess)" rows come from `--steps 0`: no fit ran, the fitted columns are '
    "the generic guess, and only the floor (true parameters) and the loss profile are "
    "measured. A fit run (`--steps N`) fills them.",
    "- The floor's control-point error is diffcloth's Provot model against the Warp reference "
    "with identical parameters (float64 unless `--float32`); its IoU and RMSE are the rendering "
    "floor: diffcloth's rasterizer (level-3 tessellation, no floor drawn in the fit, unoccluded "
    "ambient) against Mitsuba's path-traced frames box-averaged to the fit size.",
    "- With the tie (the default), k_shear and k_flex follow k_struct at the guess's ratios "
    "(1/4 and 1/20), which are also the truth's: the fit has one free stiffness scale and the "
    "air damping. `--untie` adds a last stage over all four.",
    "- Colour is compared only on the target's cloth pixels (3 px margin): diffcloth's scene "
    "has no floor plane in the fit, so elsewhere the colours are not comparable.",
    "- Regenerate the targets first: the data folder is not committed "
    "(`python -m benchmarks.cross_engine.generate`, about 2 minutes per case here).",
    "",
]


def write_markdown(results, path):
    lines = [
        "# Cross-engine benchmark: diffcloth fitted to Warp physics + Mitsuba images",
        "",
        f"Generated by `python -m benchmarks.cross_engine.protocol` on "
        f"{time.strftime('%Y-%m-%d')} ({platform.machine()}, 2 cores shared with other jobs). "
        "Targets: `python -m benchmarks.cross_engine.generate` (Warp Provot mass-spring, "
        "dt = 1/2400 s; Mitsuba 3 `direct` integrator with shadows, 32 spp, 128^2, 2 cameras). "
        "Fit from the generic guess k_struct = 100, k_shear = 25, k_flex = 5 N/m, air damping "
        "0.002 N s/m (dashpots at the model defaults, not fitted) on the first two thirds of the "
        "frames; the last third is predicted; staged Levenberg-Marquardt (`diffcloth.fit.staged`: "
        "air damping alone on the free fall, then a scan and LM of the stiffness scale). Reduced "
        "to fit the time here (2 cores): the footage is box-averaged to "
        f"{results[0]['size'] if results else '?'}^2 and every "
        f"{results[0].get('stride', 1) if results else '?'}-th frame is rendered and compared "
        "(control points: every frame). `floor` = the same figures with "
        "the TRUE parameters (what diffcloth cannot match even then). Control-point (cp) errors "
        "against the Warp nets; IoU of cloth masks (> 1/2); RMSE over pixels that are cloth in "
        "both, linear RGB.",
        "",
        "| case | method | fit s | k_struct err | k_shear err | k_flex err | air err | "
        "pred cp mean / max (cm) "
        "| pred IoU mean / min | pred RMSE | floor pred cp mean / max | floor pred IoU | "
        "floor pred RMSE | fit-window cp mean | fit IoU |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        e = r["param_err_pct"]
        p, fp, f = r["predict"], r["floor_predict"], r["fit"]
        lines.append(
            f"| {r['scene']} {r['regime']} | {r['method']} | {r['fit_wall_s']} | "
            f"{e['k_struct']:+.1f} % | {e['k_shear']:+.1f} % | {e['k_flex']:+.1f} % | "
            f"{e['air_damping']:+.1f} % | "
            f"{p['cp_mean_cm']:.2f} / {p['cp_max_cm']:.2f} | {p['iou_mean']:.3f} / "
            f"{p['iou_min']:.3f} | {p['rmse_cloth']:.3f} | {fp['cp_mean_cm']:.2f} / "
            f"{fp['cp_max_cm']:.2f} | {fp['iou_mean']:.3f} | {fp['rmse_cloth']:.3f} | "
            f"{f['cp_mean_cm']:.2f} | {f['iou_mean']:.3f} |"
        )
    lines += ["", "Aims: k_struct within 5 %, predicted IoU >= 0.95, mean cp error <= 2 cm, "
              "each fit < 5 min.", ""]  # fmt: skip
    lines += NOTES
    prof = [r for r in results if "profile_k_struct" in r]
    if prof:
        lines += ["## Loss profile over k_struct (the fit's loss over the fitting frames)", ""]
        for r in prof:
            for key, at in (("profile_k_struct", r.get("profile_at", "fitted")),
                            ("profile_k_struct_truth", "truth")):  # fmt: skip
                if key not in r:
                    continue
                pts = ", ".join(f"{k:g}: {v:.4g}" for k, v in r[key])
                best = min(r[key], key=lambda kv: kv[1])[0]
                lines.append(
                    f"- {r['scene']} {r['regime']}, others at the {at} values (truth "
                    f"{r['truth']['k_struct']:g}, grid minimum at {best:g}): {pts}"
                )
        lines.append("")
    Path(path).write_text("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", help="scene:regime (default: all)")
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--fit-frames", type=int, default=0, help="default: two thirds")
    ap.add_argument("--steps", type=int, default=12, help="LM steps per stage; 0: no fit")
    ap.add_argument("--untie", action="store_true", help="a last stage fits all four untied")
    ap.add_argument(
        "--float32",
        dest="x64",
        action="store_false",
        help="simulate in float32 (default float64: float32 round-off makes the "
        "drape's contact trajectory, and so the loss, jump at the 1e-6 scale)",
    )
    ap.add_argument("--stride", type=int, default=3, help="render every k-th frame")
    ap.add_argument("--size", type=int, default=64, help="fit and compare at size^2 (box)")
    ap.add_argument("--level", type=int, default=3, help="diffcloth tessellation level")
    ap.add_argument(
        "--shadows",
        choices=("fit", "full"),
        default=None,
        help="the light casts shadows at this shadow_quality, the floor is drawn and the "
        "ambient light occluded over --ao sky directions (default: none of these)",
    )
    ap.add_argument("--ao", type=int, default=8, help="sky directions with --shadows")
    ap.add_argument("--no-profile", dest="profile", action="store_false")
    ap.add_argument(
        "--profile-at",
        choices=("fitted", "truth"),
        default="fitted",
        help="the other parameters of the k_struct loss profile",
    )
    ap.add_argument("--out", default=str(HERE / "results.jsonl"))
    ap.add_argument("--md", default=str(HERE / "RESULTS.md"))
    a = ap.parse_args(argv)
    if a.x64:
        jax.config.update("jax_enable_x64", True)
    if not has_massspring():
        sys.exit("the protocol needs diffcloth's Provot model (diffcloth.physics.massspring)")
    cases = [tuple(c.split(":")) for c in a.cases] if a.cases else S.CASES
    results = []
    for scene_name, regime in cases:
        run_case(scene_name, regime, a, results)
        with open(a.out, "w") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in results)
        write_markdown(results, a.md)


if __name__ == "__main__":
    main(sys.argv[1:])
