"""Shading benchmark: every mode at 256 x 256 on the seed surface (13 x 10 net, 11,830 vertices).

For each mode, one JSON line with the median wall time (ms) of
  shade_fwd   shading a pre-rasterized G-buffer (the shading cost alone),
  shade_grad  value and gradient of an image loss w.r.t. lights and appearance (shading only),
  render_fwd  the full render (rasterize + shade + antialias + spheres + background),
  render_grad value and gradient of the full render w.r.t. lights and appearance.
Timings after one warm-up (compile) call, block_until_ready, median of --repeats runs. float32.

Shadow cases (--shadow-modes, default phong and minnaert; "none" skips them): the full render of
the same scene plus a ground plane, with both lights casting shadows ("shadows": true) and
without ("shadows": false), forward and value-and-gradient w.r.t. lights and appearance, plus
the shadow-map build alone ("mode": "shadow_maps") at --shadow-map-size texels. With
--ambient-occlusion K (default 32; 0 skips), each shadow mode also runs with shadows and K sky
directions of occluded ambient light ("ambient_occlusion": K; maps of shadow-map-size // 2).

Fit-speed ratio (--ratio-sizes, default 64,128,256; "none" skips): the case a fit pays for, the
seed net tessellated at --ratio-level (default 4, as the fit configs) from the control net, one
directional light, two spheres, the ground plane, phong; forward and value-and-gradient w.r.t.
the control net (geometry: rasterizer and shadow-map gradients), the lights and the appearance.
Per size: "shadows": false, then shadows on the light with --ratio-ao sky directions (default 8)
at shadow_quality "fit" ("shadow_ratio" lines: fwd_ratio and grad_ratio = shadowed / unshadowed,
same process; *_min_ratio: of the minimum times), and with --ratio-full also at "full" (256^2
maps, 32 directions: slow). All cases of a size are timed in one alternating loop (each round
calls every one once, the order reversed every other round: "timing": "alternating"), so a
change of the shared machine's load reaches the shadowed and the unshadowed call alike.

Lines are appended to --out (default benchmarks/results/shading.jsonl; "-": stdout only), after
a "meta" line.

    python benchmarks/shading.py [--size 256] [--repeats 5] [--modes phong,second_pass]
    python benchmarks/shading.py --modes none --shadow-modes none        # the fit-speed ratio only
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np
from _timing import emit, meta, timed, timed_alternating

from diffcloth.render import lights as Lm
from diffcloth.render import textures as T
from diffcloth.render.camera import make_camera
from diffcloth.render.frame import render, surface_gbuffer
from diffcloth.render.shade import MODES, shade
from diffcloth.shapes import make_sphere
from diffcloth.surface import tessellate


def seed_surface():
    """The seed's 13 x 10 control net, gently draped (sine folds), tessellated at level 13."""
    x, z = np.meshgrid(np.linspace(-0.6, 0.6, 13), np.linspace(-0.45, 0.45, 10))
    y = 0.25 * np.exp(-(x**2 + z**2) / 0.08) + 0.03 * np.sin(9 * x) * np.cos(5 * z)
    return tessellate(jnp.asarray(np.stack([x, y, z], -1), jnp.float32), 13)


def _timed_ms(fn, *args, repeats):
    return round(timed(fn, *args, repeats=repeats).median * 1e3, 2)


RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "shading.jsonl")
_OUT = []  # the open results file, if any


def _print(row):
    emit(row, _OUT[0] if _OUT else None)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--no-render", action="store_true", help="time shading only")
    parser.add_argument("--no-grad", action="store_true")
    parser.add_argument("--shadow-modes", default="phong,minnaert")
    parser.add_argument("--shadow-map-size", type=int, default=256)
    parser.add_argument("--ambient-occlusion", type=int, default=32)
    parser.add_argument("--ratio-sizes", default="64,128,256")
    parser.add_argument("--ratio-level", type=int, default=4)
    parser.add_argument("--ratio-ao", type=int, default=8)
    parser.add_argument("--ratio-full", action="store_true")
    parser.add_argument("--out", default=RESULTS)
    args = parser.parse_args()
    if args.out != "-":
        _OUT.append(open(args.out, "a"))  # noqa: SIM115
    _print(meta("shading", run="shadow_ratio"))
    surf = seed_surface()
    size = args.size
    cam = make_camera(
        (0.9, 0.9, 1.6), (0.0, 0.0, 0.0), (0, 1, 0), width=size, height=size, fov_y=40.0
    )
    lights = Lm.make_lights(point=[((-1.0, 1.2, 1.0), (0.4, 0.5, 0.7), 0.8)], dtype=jnp.float32)
    app = Lm.make_appearance(dtype=jnp.float32)
    tex = T.default_textures(dtype=jnp.float32)
    spheres = make_sphere([(0.0, -0.3, 0.0), (0.55, 0.0, 0.35)], [0.3, 0.18], dtype=jnp.float32)
    weights = jnp.asarray(np.random.default_rng(0).uniform(size=(size, size, 4)), jnp.float32)
    device = jax.devices()[0].device_kind
    for mode in [m for m in args.modes.split(",") if m and m != "none"]:
        gb, _, eye = jax.jit(surface_gbuffer, static_argnames=("shading",))(
            surf, cam, lights, app, shading=mode
        )

        def shade_fn(gb, eye, lights, app, mode=mode):
            return shade(gb, eye, lights, app, mode=mode, textures=tex, spheres=spheres)

        def shade_loss(params, gb, eye, mode=mode):
            return jnp.sum(weights * shade_fn(gb, eye, *params, mode=mode))

        def render_fn(lights, app, mode=mode):
            return render(surf, cam, lights, mode, app, spheres=spheres, textures=tex)

        def render_loss(params, mode=mode):
            return jnp.sum(weights * render_fn(*params, mode=mode))

        row = {
            "bench": "shading",
            "mode": mode,
            "size": size,
            "vertices": int(surf.positions.shape[0]),
        }
        row["shade_fwd_ms"] = _timed_ms(
            jax.jit(shade_fn), gb, eye, lights, app, repeats=args.repeats
        )
        if not args.no_grad:
            g = jax.jit(jax.value_and_grad(shade_loss))
            row["shade_grad_ms"] = _timed_ms(g, (lights, app), gb, eye, repeats=args.repeats)
        if not args.no_render:
            row["render_fwd_ms"] = _timed_ms(jax.jit(render_fn), lights, app, repeats=args.repeats)
            if not args.no_grad:
                g = jax.jit(jax.value_and_grad(render_loss))
                row["render_grad_ms"] = _timed_ms(g, (lights, app), repeats=args.repeats)
        row["device"] = device
        _print(row)
    shadow_cases(args, surf, cam, app, tex, spheres, weights, device)
    ratio_cases(args, spheres, device)


def shadow_cases(args, surf, cam, app, tex, spheres, weights, device):
    """Render cost with and without shadows (module docstring)."""
    from diffcloth.render.frame import frame_shadow_maps
    from diffcloth.shapes import make_plane

    modes = [m for m in args.shadow_modes.split(",") if m and m != "none"]
    if not modes:
        return
    ground = make_plane((0.0, 1.0, 0.0), -0.3, dtype=jnp.float32)
    size, map_size = args.size, args.shadow_map_size

    def lights_with(shadows):
        return Lm.make_lights(
            directional=[((0.3, 1.0, 0.6), (1.0, 1.0, 1.0), 1.0)],
            point=[((-1.0, 1.2, 1.0), (0.4, 0.5, 0.7), 0.8)],
            shadows=shadows,
            dtype=jnp.float32,
        )

    lights = lights_with(True)
    build = jax.jit(lambda lt: frame_shadow_maps(surf, lt, spheres=spheres, size=map_size))
    row = {"bench": "shading", "mode": "shadow_maps", "size": size, "shadow_map_size": map_size}
    row["fwd_ms"] = _timed_ms(build, lights, repeats=args.repeats)
    row["device"] = device
    _print(row)
    for mode in modes:
        cases = [(False, 0), (True, 0)]
        if args.ambient_occlusion:
            cases.append((True, args.ambient_occlusion))
        for shadows, ao in cases:
            lights = lights_with(shadows)

            def render_fn(lights, app, mode=mode, ao=ao):
                return render(
                    surf,
                    cam,
                    lights,
                    mode,
                    app,
                    spheres=spheres,
                    textures=tex,
                    planes=ground,
                    shadow_map_size=map_size,
                    ambient_occlusion=ao,
                )

            def render_loss(params, mode=mode, ao=ao):
                return jnp.sum(weights * render_fn(*params, mode=mode, ao=ao))

            row = {
                "bench": "shading",
                "mode": mode,
                "size": size,
                "planes": 1,
                "shadows": shadows,
                "shadow_map_size": map_size,
                "ambient_occlusion": ao,
            }
            row["render_fwd_ms"] = _timed_ms(jax.jit(render_fn), lights, app, repeats=args.repeats)
            if not args.no_grad:
                g = jax.jit(jax.value_and_grad(render_loss))
                row["render_grad_ms"] = _timed_ms(g, (lights, app), repeats=args.repeats)
            row["device"] = device
            _print(row)


def ratio_cases(args, spheres, device):
    """Shadows + occlusion at fit speed against the unshadowed render (module docstring)."""
    from diffcloth.shapes import make_plane
    from diffcloth.surface import tessellate

    sizes = [int(v) for v in args.ratio_sizes.split(",") if v and v != "none"]
    x, z = np.meshgrid(np.linspace(-0.6, 0.6, 13), np.linspace(-0.45, 0.45, 10))
    y = 0.25 * np.exp(-(x**2 + z**2) / 0.08) + 0.03 * np.sin(9 * x) * np.cos(5 * z)
    net = jnp.asarray(np.stack([x, y, z], -1), jnp.float32)
    level = args.ratio_level
    ground = make_plane((0.0, 1.0, 0.0), -0.3, dtype=jnp.float32)
    app = Lm.make_appearance(dtype=jnp.float32)
    cases = [("none", 0), ("fit", args.ratio_ao)] + ([("full", 32)] if args.ratio_full else [])
    for size in sizes:
        cam = make_camera(
            (0.9, 0.9, 1.6), (0.0, 0.0, 0.0), (0, 1, 0), width=size, height=size, fov_y=40.0
        )
        weights = jnp.asarray(np.random.default_rng(0).uniform(size=(size, size, 4)), jnp.float32)
        rows, calls = {}, {}
        for quality, ao in cases:
            lights = Lm.make_lights(
                directional=[((0.3, 1.0, 0.6), (1.0, 1.0, 1.0), 1.0)],
                shadows=quality != "none",
                dtype=jnp.float32,
            )

            def render_fn(net, lights, app, quality=quality, ao=ao, cam=cam):
                return render(
                    tessellate(net, level),
                    cam,
                    lights,
                    "phong",
                    app,
                    spheres=spheres,
                    planes=ground,
                    ambient_occlusion=ao,
                    shadow_quality="full" if quality == "none" else quality,
                )

            def render_loss(params, render_fn=render_fn, weights=weights):
                return jnp.sum(weights * render_fn(*params))

            rows[quality] = {
                "bench": "shading",
                "mode": "phong",
                "case": "shadow_ratio",
                "size": size,
                "level": level,
                "vertices": int(tessellate(net, level).positions.shape[0]),
                "shadows": quality != "none",
                "shadow_quality": quality,
                "ambient_occlusion": ao,
                "timing": "alternating",
            }
            calls[("fwd", quality)] = (jax.jit(render_fn), (net, lights, app))
            calls[("grad", quality)] = (
                jax.jit(jax.value_and_grad(render_loss)),
                ((net, lights, app),),
            )
        # every case's forward and gradient timed in one alternating loop (same load for all);
        # median and minimum: on the shared machine the minimum is the steadier figure
        times = timed_alternating(calls, repeats=args.repeats)
        base = rows["none"]
        for quality, row in rows.items():
            for k in ("fwd", "grad"):
                t = times[(k, quality)]
                row[f"render_{k}_ms"], row[f"render_{k}_min_ms"] = t.median_ms, t.min_ms
            if row is not base:
                for k in ("fwd", "grad", "fwd_min", "grad_min"):
                    key = f"render_{k}_ms"
                    row[f"{k}_ratio"] = round(row[key] / base[key], 2)
            row["device"] = device
            _print(row)


if __name__ == "__main__":
    main()
