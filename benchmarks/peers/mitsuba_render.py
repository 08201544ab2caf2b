"""diffcloth vs Mitsuba 3 (CPU, LLVM variant): the same mesh, camera and diffuse light at 256 x 256.

    python benchmarks/peers/mitsuba_render.py            # spp 1 and 16 for Mitsuba
    python benchmarks/peers/mitsuba_render.py --quick    # fewer repeats
    python benchmarks/peers/mitsuba_render.py --out benchmarks/results/mitsuba_render.jsonl

Scene: the default 13 x 10 net (configs/drape.toml) draped for 1 s over its sphere by diffcloth's
physics, tessellated at level 13 (`diffcloth.surface.tessellate`: 130 x 91 = 11,830 vertices,
23,400 triangles, analytic vertex normals). Only the cloth is rendered (no sphere, no floor),
over black. Perspective camera, fov_y 45 deg, one white directional light, no ambient, Lambert
(diffcloth "phong" with zero specular and zero ambient; Mitsuba two-sided `diffuse` with the
directional emitter's irradiance pi * intensity, so both give albedo * intensity * max(N.L, 0)).
Mitsuba: `direct` integrator (one emitter sample, box filter) forward, `direct_projective`
(silhouette/visibility gradients by projective sampling, sppi = 0) for the gradient. Mitsuba
traces shadow rays; diffcloth's rasterizer has no shadows, so self-shadowed pixels differ.

Gradient: d/d(vertex positions, 11,830 x 3) of mean((I - I_target)^2), I_target rendered (by each
renderer itself, outside the timing) from the mesh moved 2 cm along +x; vertex normals are held.

One JSON line per case:
  bench "peers_render_diffcloth": fwd_ms, grad_ms (forward + backward), shading, width, height;
    prepare_ms (`render.prepare_frame`: rasterization of the static geometry and camera, once),
    fwd_traced_ms (the same forward with the camera and the appearance passed as traced
    arguments, as a fit that moves them compiles it: `fwd_ms`'s program is specialized on the
    fixed camera, whose rays are computed while tracing, and on the fixed zero specular colour,
    which leaves the highlight out; traced_max_abs_diff: its image against fwd_ms's),
    fwd_prepared_ms (`render.render_prepared`: shading, antialiasing and background of the
    prepared frame, i.e. the forward of an appearance-only change; the rasterization is NOT in
    this figure) and prepared_max_abs_diff (its image against the full forward's).
  bench "peers_render_mitsuba": spp, fwd_ms, grad_ms, ratio_fwd / ratio_grad (diffcloth / Mitsuba,
    below 1: diffcloth faster), ratio_fwd_prepared (fwd_prepared_ms / Mitsuba's forward with
    unchanged positions: both reuse geometry work, diffcloth all of its rasterization, Mitsuba
    its BVH but not its ray casts), mean_abs_diff (RGB, diffcloth vs this Mitsuba image),
    mean_abs_diff_ref (vs a 64 spp Mitsuba image), coverage_abs_diff (alpha), mean_abs_diff_interior
    (pixels fully covered in both, 3 px from silhouettes), grad_cosine (cosine between the two
    gradient fields) and grad_translate_cosine (between their sums: the gradient of a translation).
  bench "peers_render_interleaved" (`--rounds`, default 20): the forwards timed turn about, per
    round 10 diffcloth forwards, 10 Mitsuba 1 spp forwards, 3 diffcloth gradients and 10
    diffcloth forwards with the camera and appearance traced, each block after 3 untimed calls
    (`interleaved`): fwd_traced_ms and ratio_fwd_traced (_p10 / _p90: against the round's
    Mitsuba), fwd_ms and fwd_ms_mitsuba (medians over all calls), grad_ms (median;
    grad_ms_p90), ratio_fwd (median over rounds of the rounds' median ratio; ratio_fwd_p10 /
    _p90) and rounds_diffcloth_faster.
    The separate medians above are taken minutes apart; on a shared VM whose speed drifts by
    10-20 % they can disagree with this row, which compares like with like.

Mitsuba's LLVM variant needs libLLVM >= 17 on x86 (older versions fail with "Cannot select:
fmaximum"); the script points DRJIT_LIBLLVM_PATH at the newest /usr/lib/*/libLLVM-*.so unless it
is set (Debian/Ubuntu: `apt-get install libllvm19`).
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import re
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
WIDTH = HEIGHT = 256
EYE, TARGET, UP = (0.0, 1.35, 1.45), (0.0, 0.5, 0.0), (0.0, 1.0, 0.0)
FOV_Y = 45.0
LIGHT_DIR = (0.3, 1.0, 0.6)  # toward the light
ALBEDO = (0.7, 0.15, 0.2)
SHIFT = np.array([0.02, 0.0, 0.0], np.float32)


def _pick_llvm():
    """Point Dr.Jit at the newest system libLLVM (>= 17) unless the user chose one."""
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
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # benchmarks/_timing.py
from _timing import meta as _meta_line  # noqa: E402
from _timing import timed  # noqa: E402

from diffcloth import physics  # noqa: E402
from diffcloth.config import build_physics, load_config  # noqa: E402
from diffcloth.render import render  # noqa: E402
from diffcloth.render.camera import make_camera  # noqa: E402
from diffcloth.render.lights import make_appearance, make_lights  # noqa: E402
from diffcloth.render.prepared import prepare_frame, render_prepared  # noqa: E402
from diffcloth.surface import tessellate  # noqa: E402


def _median(fn, repeats):
    return timed(fn, repeats=repeats).median


def draped_surface(seconds: float = 1.0):
    """The seed's scene: 13 x 10 net dropped on the sphere of configs/drape.toml, level 13."""
    ps = build_physics(load_config(ROOT / "configs" / "drape.toml"))
    frames = int(round(seconds / float(ps.sim.dt)))
    end = physics.checked_rollout(
        ps.net, ps.sim, ps.material, ps.state, num_frames=frames, colliders=ps.colliders
    )
    return tessellate(end.x[-1], 13)


# --------------------------------------------------------------------------------- diffcloth


def diffcloth_case(surface, repeats):
    camera = make_camera(EYE, TARGET, UP, width=WIDTH, height=HEIGHT, fov_y=FOV_Y)
    lights = make_lights(ambient=(0.0, 0.0, 0.0), directional=[(LIGHT_DIR, (1.0, 1.0, 1.0), 1.0)])
    app = make_appearance(diffuse=ALBEDO, specular=(0.0, 0.0, 0.0), ambient=(0.0, 0.0, 0.0))

    def frame(pos, cam, a):
        s = dataclasses.replace(surface, positions=pos)
        return render(s, cam, lights, "phong", a, background=(0.0, 0.0, 0.0))

    def image(pos):  # camera and appearance fixed: the program is specialized on them
        return frame(pos, camera, app)

    fwd = jax.jit(image)
    pos = surface.positions
    target = jax.block_until_ready(fwd(pos + jnp.asarray(SHIFT)))[..., :3]

    def loss(p):
        return jnp.mean((image(p)[..., :3] - target) ** 2)

    grad = jax.jit(jax.grad(loss))
    img = np.asarray(jax.block_until_ready(fwd(pos)))
    t_f = _median(lambda: jax.block_until_ready(fwd(pos)), repeats)
    # static geometry and camera (what Mitsuba's timed forward reuses: its BVH): rasterize once
    # with prepare_frame (its time is reported), then each forward only shades, antialiases and
    # composites (render_prepared; the same image)
    prepare = jax.jit(lambda p: prepare_frame(dataclasses.replace(surface, positions=p), camera))
    prep = jax.block_until_ready(prepare(pos))
    t_prep = _median(lambda: jax.block_until_ready(prepare(pos)), repeats)
    fwd_p = jax.jit(
        lambda pr: render_prepared(pr, lights, "phong", app, background=(0.0, 0.0, 0.0))
    )
    img_p = np.asarray(jax.block_until_ready(fwd_p(prep)))
    t_fp = _median(lambda: jax.block_until_ready(fwd_p(prep)), repeats)
    # the same forward with the camera and the appearance traced (as when a fit moves them):
    # no rays computed while tracing, the Blinn-Phong highlight kept (multiplied by zero)
    general = jax.jit(frame)
    img_g = np.asarray(jax.block_until_ready(general(pos, camera, app)))
    t_fg = _median(lambda: jax.block_until_ready(general(pos, camera, app)), repeats)
    g = np.asarray(jax.block_until_ready(grad(pos)))
    t_g = _median(lambda: jax.block_until_ready(grad(pos)), max(1, repeats // 2))
    row = dict(
        bench="peers_render_diffcloth",
        width=WIDTH,
        height=HEIGHT,
        vertices=int(pos.shape[0]),
        triangles=int(surface.faces.shape[0]),
        shading="phong (Lambert: zero specular, zero ambient)",
        fwd_ms=round(t_f * 1e3, 2),
        grad_ms=round(t_g * 1e3, 2),
        prepare_ms=round(t_prep * 1e3, 2),
        fwd_prepared_ms=round(t_fp * 1e3, 2),
        fwd_traced_ms=round(t_fg * 1e3, 2),
        traced_max_abs_diff=float(np.max(np.abs(img_g - img))),
        prepared_max_abs_diff=float(np.max(np.abs(img_p - img))),
    )
    calls = dict(
        fwd=lambda: jax.block_until_ready(fwd(pos)),
        grad=lambda: jax.block_until_ready(grad(pos)),
        traced=lambda: jax.block_until_ready(general(pos, camera, app)),
    )
    return row, img, g, calls


# --------------------------------------------------------------------------------- Mitsuba


class MitsubaScene:
    def __init__(self, surface):
        mi.set_variant("llvm_ad_rgb")
        mi.set_log_level(mi.LogLevel.Error)
        self.v = np.asarray(surface.positions, np.float32)
        n = np.asarray(surface.normals, np.float32)
        f = np.asarray(surface.faces, np.uint32)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(
            {
                "type": "twosided",
                "material": {"type": "diffuse", "reflectance": {"type": "rgb", "value": ALBEDO}},
            }
        )
        mesh = mi.Mesh("cloth", len(self.v), len(f), props=props, has_vertex_normals=True)
        mp = mi.traverse(mesh)
        mp["vertex_positions"] = mi.Float(self.v.ravel())
        mp["faces"] = mi.UInt32(f.ravel())
        mp["vertex_normals"] = mi.Float(n.ravel())
        mp.update()
        d = -np.asarray(LIGHT_DIR, np.float64)
        d = d / np.linalg.norm(d)
        self.scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
                "sensor": {
                    "type": "perspective",
                    "fov": FOV_Y,
                    "fov_axis": "y",
                    "near_clip": 0.1,
                    "far_clip": 100.0,
                    "to_world": mi.ScalarTransform4f().look_at(origin=EYE, target=TARGET, up=UP),
                    "film": {
                        "type": "hdrfilm",
                        "width": WIDTH,
                        "height": HEIGHT,
                        "rfilter": {"type": "box"},
                        "pixel_format": "rgba",
                    },
                    "sampler": {"type": "independent", "sample_count": 1},
                },
                "light": {
                    "type": "directional",
                    "direction": d.tolist(),
                    "irradiance": {"type": "rgb", "value": float(np.pi)},
                },
                "cloth": mesh,
            }
        )
        # sppi = 0: no indirectly observed discontinuities here (Mitsuba finds none and says so)
        self.projective = mi.load_dict({"type": "direct_projective", "sppi": 0})
        self.params = mi.traverse(self.scene)
        self.key = "cloth.vertex_positions"
        self._seed = 0

    def set_positions(self, v):
        self.params[self.key] = mi.Float(np.asarray(v, np.float32).ravel())
        self.params.update()

    def forward(self, spp):
        self._seed += 1
        return np.asarray(mi.render(self.scene, spp=spp, seed=self._seed))

    def forward_moved(self, spp):
        """New vertex positions (alternately shifted by 0.1 mm), then render: the per-frame cost
        when the cloth moves, as in a rollout or a fit (Mitsuba rebuilds its acceleration
        structure; diffcloth's forward always takes the positions as input)."""
        self._moved = not getattr(self, "_moved", False)
        self.set_positions(self.v + (1e-4 if self._moved else 0.0))
        return self.forward(spp)

    def grad(self, target, spp):
        """(n, 3) gradient of mean((rgb - target)^2) w.r.t. vertex positions."""
        self._seed += 1
        pos = mi.Float(self.v.ravel())
        dr.enable_grad(pos)
        self.params[self.key] = pos
        self.params.update()
        img = mi.render(
            self.scene, self.params, spp=spp, seed=self._seed, integrator=self.projective
        )
        rgb = img[:, :, :3] if img.shape[-1] > 3 else img
        loss = dr.mean(dr.square(rgb - target), axis=None)
        dr.backward(loss)
        g = np.asarray(dr.grad(pos)).reshape(-1, 3)
        self.params[self.key] = mi.Float(self.v.ravel())
        self.params.update()
        return g


def _interior(a, b, pad=3):
    """Pixels fully covered in both alpha maps and at least `pad` px from any partly covered one."""
    full = (a > 0.999) & (b > 0.999)
    m = full.copy()
    for dy in range(-pad, pad + 1):
        for dx in range(-pad, pad + 1):
            m &= np.roll(np.roll(full, dy, 0), dx, 1)
    return m


def _cos(a, b):
    a, b = np.ravel(a), np.ravel(b)
    return float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-30))


def mitsuba_cases(surface, dc_row, dc_img, dc_grad, repeats, spps, save_dir=None):
    ms = MitsubaScene(surface)
    ms.set_positions(ms.v + SHIFT)
    targets = {}
    ms.set_positions(ms.v)
    ref = ms.forward(64)
    if save_dir is not None:
        np.savez_compressed(
            Path(save_dir) / "render_images.npz", diffcloth=dc_img, mitsuba_64spp=ref
        )
    rows = []
    for spp in spps:
        ms.set_positions(ms.v + SHIFT)
        targets[spp] = mi.TensorXf(ms.forward(max(spp, 16))[..., :3])
        ms.set_positions(ms.v)
        img = ms.forward(spp)
        t_f = _median(lambda spp=spp: ms.forward(spp), repeats)
        t_fm = _median(lambda spp=spp: ms.forward_moved(spp), repeats)
        ms.set_positions(ms.v)
        g = ms.grad(targets[spp], spp)
        t_g = _median(lambda spp=spp: ms.grad(targets[spp], spp), max(1, repeats // 2))
        inner = _interior(dc_img[..., 3], ref[..., 3])
        rows.append(
            dict(
                bench="peers_render_mitsuba",
                variant=mi.variant(),
                spp=spp,
                width=WIDTH,
                height=HEIGHT,
                fwd_ms=round(t_f * 1e3, 2),
                grad_ms=round(t_g * 1e3, 2),
                fwd_moved_ms=round(t_fm * 1e3, 2),
                ratio_fwd=round(dc_row["fwd_ms"] / (t_f * 1e3), 3),
                ratio_fwd_prepared=round(dc_row["fwd_prepared_ms"] / (t_f * 1e3), 3),
                ratio_fwd_moved=round(dc_row["fwd_ms"] / (t_fm * 1e3), 3),
                ratio_grad=round(dc_row["grad_ms"] / (t_g * 1e3), 3),
                mean_abs_diff=float(np.mean(np.abs(dc_img[..., :3] - img[..., :3]))),
                mean_abs_diff_ref=float(np.mean(np.abs(dc_img[..., :3] - ref[..., :3]))),
                coverage_abs_diff=float(np.mean(np.abs(dc_img[..., 3] - ref[..., 3]))),
                mean_abs_diff_interior=float(
                    np.mean(np.abs(dc_img[..., :3] - ref[..., :3])[inner])
                ),
                interior_pixels=int(inner.sum()),
                mean_value_diffcloth=float(np.mean(dc_img[..., :3])),
                mean_value_mitsuba=float(np.mean(ref[..., :3])),
                grad_cosine=_cos(dc_grad, g),
                grad_translate_cosine=_cos(dc_grad.sum(0), g.sum(0)),
            )
        )
    return rows


def interleaved(dc_calls, ms: MitsubaScene, rounds: int, per_round: int = 10, warmup: int = 3):
    """Forward timings taken turn about, in blocks: each round times `per_round` diffcloth
    forwards, then `per_round` Mitsuba 1 spp forwards (unchanged positions), then 3 diffcloth
    gradients, then `per_round` diffcloth forwards with the camera and appearance traced
    (`fwd_traced_ms`), each block after `warmup` untimed calls. Both renderers thus see the same machine
    conditions over the run (on a shared VM the speed drifts by 10-20 % within minutes, the size
    of the margin between them), each measured warm: on this VM the first calls after the other
    renderer ran, or after 0.1-0.5 s idle, are 1.3-2x slower, for diffcloth more than for
    Mitsuba (a cold-start effect outside both programs, seen with XLA on one thread too).
    The ratio's median and spread over rounds are reported, with the share of rounds in which
    diffcloth's forward was the faster."""
    ms.set_positions(ms.v)
    dc_f, mi_f, dc_g, dc_t, ratios, ratios_t = [], [], [], [], [], []

    def clock(fn, n):
        for _ in range(warmup):
            fn()
        out = []
        for _ in range(n):
            t = time.perf_counter()
            fn()
            out.append((time.perf_counter() - t) * 1e3)
        return out

    for _ in range(rounds):
        a = clock(dc_calls["fwd"], per_round)
        b = clock(lambda: ms.forward(1), per_round)
        dc_g += clock(dc_calls["grad"], 3)
        c = clock(dc_calls["traced"], per_round)
        dc_f += a
        mi_f += b
        dc_t += c
        ratios.append(float(np.median(a) / np.median(b)))
        ratios_t.append(float(np.median(c) / np.median(b)))
    q = lambda v, p: round(float(np.percentile(v, p)), 3)
    return dict(
        bench="peers_render_interleaved",
        rounds=rounds,
        per_round=per_round,
        warmup=warmup,
        spp=1,
        fwd_ms=round(float(np.median(dc_f)), 2),
        fwd_ms_mitsuba=round(float(np.median(mi_f)), 2),
        grad_ms=round(float(np.median(dc_g)), 2),
        grad_ms_p90=round(float(np.percentile(dc_g, 90)), 2),
        ratio_fwd=q(ratios, 50),
        ratio_fwd_p10=q(ratios, 10),
        ratio_fwd_p90=q(ratios, 90),
        rounds_diffcloth_faster=float(np.mean(np.asarray(ratios) < 1.0)),
        fwd_traced_ms=round(float(np.median(dc_t)), 2),
        ratio_fwd_traced=q(ratios_t, 50),
        ratio_fwd_traced_p10=q(ratios_t, 10),
        ratio_fwd_traced_p90=q(ratios_t, 90),
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--repeats", type=int, default=15, help="timed calls per case (median)")
    parser.add_argument("--out", help="also write the JSON lines to this file")
    parser.add_argument("--spp", type=int, nargs="+", default=[1, 16], help="Mitsuba spp cases")
    parser.add_argument("--save-images", help="folder for render_images.npz (both images)")
    parser.add_argument(
        "--rounds", type=int, default=20, help="interleaved rounds (0: none; --quick: 5)"
    )
    args = parser.parse_args(argv)
    repeats = 3 if args.quick else args.repeats
    meta = _meta_line(
        "mitsuba_render", mitsuba=mi.__version__, drjit=dr.__version__, libllvm=LLVM_PATH
    )
    lines = [meta]
    print(json.dumps(meta), flush=True)
    surface = draped_surface()
    dc_row, dc_img, dc_grad, dc_calls = diffcloth_case(surface, repeats)
    lines.append(dc_row)
    print(json.dumps(dc_row), flush=True)
    for row in mitsuba_cases(
        surface, dc_row, dc_img, dc_grad, repeats, args.spp, save_dir=args.save_images
    ):
        lines.append(row)
        print(json.dumps(row), flush=True)
    rounds = min(args.rounds, 5) if args.quick else args.rounds
    if rounds > 0:
        row = interleaved(dc_calls, MitsubaScene(surface), rounds)
        lines.append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        with open(args.out, "w") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in lines)


if __name__ == "__main__":
    main()
