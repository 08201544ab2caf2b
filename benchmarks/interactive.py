"""Interactive frame rate: one frame of the seed's default scene, end to end, per shading mode.

The default scene (`configs/drape.toml`: 13 x 10 net, 40 symplectic substeps per frame, one
sphere and a ground plane) part-way through its drape (frame 20, cloth touching the sphere), then
per frame: physics (one frame = 40 substeps with colliders), tessellation at level 13 (11,830
vertices, 23,220 triangles), surface collision with the sphere, render at 256 x 256 with the
scene's camera, lights and sphere (default textures for the modes that need them).

One JSON line per shading mode (schema: benchmarks/_timing.py):
  bench "interactive", mode, size, vertices,
  frame_ms (the whole frame as one jitted function, median), fps (1000 / frame_ms),
  physics_ms, tessellate_ms, collide_ms, render_ms (each stage jitted alone, median),
  raster_ms (`surface_gbuffer`: rasterize + interpolate the G-buffer), shade_ms (`shade` of that
  G-buffer alone); render_ms - raster_ms - shade_ms is the rest (antialias, sphere layer,
  background compositing),
  aim_fps (60 for phong, 30 for the others), meets_aim.

    python benchmarks/interactive.py [--size 256] [--repeats 15] [--modes phong,flat]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
from _timing import emit, meta, timed

from diffcloth import physics, render, surface
from diffcloth.render import textures as T
from diffcloth.render.frame import surface_gbuffer
from diffcloth.render.shade import MODES, shade
from diffcloth.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent


def setup(size: int, warm_frames: int = 20):
    scene = load_scene(ROOT / "configs" / "drape.toml", dtype=jnp.float32)
    cam = dataclasses.replace(scene.cameras[0], width=size, height=size)
    textures = (
        scene.textures if scene.textures is not None else T.default_textures(dtype=jnp.float32)
    )
    traj = jax.jit(
        lambda m: physics.rollout(
            scene.net,
            scene.sim,
            m,
            scene.state,
            num_frames=warm_frames,
            colliders=scene.colliders,
        )
    )(scene.material)
    state = physics.ClothState(traj.x[-1], traj.v[-1])
    return scene, cam, textures, state


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--level", type=int, default=13)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--out", help="also write the JSON lines to this file")
    args = parser.parse_args()
    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    emit(meta("interactive"), out)
    scene, cam, textures, state = setup(args.size)

    def phys(state):
        return physics.step(scene.net, scene.sim, scene.material, state, scene.colliders)

    def tess(x):
        return surface.tessellate(x, args.level, scene.basis, flip=scene.flip)

    def coll(surf):
        return surface.collide_surface(surf, scene.spheres)

    def draw(surf, mode):
        return render.render(
            surf,
            cam,
            scene.lights,
            mode,
            scene.appearance,
            spheres=scene.spheres,
            textures=textures,
            background=scene.background,
        )

    phys_j, tess_j, coll_j = jax.jit(phys), jax.jit(tess), jax.jit(coll)
    r = args.repeats
    t_phys = timed(phys_j, state, repeats=r)
    surf0 = tess_j(state.x)
    t_tess = timed(tess_j, state.x, repeats=r)
    surf = coll_j(surf0)
    t_coll = timed(coll_j, surf0, repeats=r)
    for mode in args.modes.split(","):

        def frame(state, mode=mode):
            new = phys(state)
            return new, draw(coll(tess(new.x)), mode)

        t_frame = timed(jax.jit(frame), state, repeats=r)
        t_draw = timed(jax.jit(draw, static_argnums=1), surf, mode, repeats=r)
        gbuf = jax.jit(
            lambda s, mode=mode: surface_gbuffer(
                s, cam, scene.lights, scene.appearance, shading=mode
            )
        )
        gb, _, eye = gbuf(surf)
        t_raster = timed(gbuf, surf, repeats=r)

        def shade_only(gb, eye, mode=mode):
            return shade(
                gb,
                eye,
                scene.lights,
                scene.appearance,
                mode=mode,
                textures=textures,
                spheres=scene.spheres,
            )

        t_shade = timed(jax.jit(shade_only), gb, eye, repeats=r)
        aim = 60 if mode == "phong" else 30
        fps = 1.0 / t_frame.median
        emit(
            dict(
                bench="interactive",
                mode=mode,
                size=args.size,
                vertices=int(surf.positions.shape[0]),
                frame_ms=t_frame.median_ms,
                frame_min_ms=t_frame.min_ms,
                fps=round(fps, 1),
                physics_ms=t_phys.median_ms,
                tessellate_ms=t_tess.median_ms,
                collide_ms=t_coll.median_ms,
                render_ms=t_draw.median_ms,
                raster_ms=t_raster.median_ms,
                shade_ms=t_shade.median_ms,
                aim_fps=aim,
                meets_aim=bool(fps >= aim),
            ),
            out,
        )
    if out is not None:
        out.close()


if __name__ == "__main__":
    main()
