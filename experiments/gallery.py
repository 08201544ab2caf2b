"""Render the default draped cloth once in every shading mode; write one labelled contact sheet.

    python experiments/gallery.py [--smoke] [--out results/gallery]

The cloth is the seed's 13 x 10 control net dropped onto a sphere with diffcloth.physics (a
procedurally draped net if the physics stage is unavailable), tessellated with
diffcloth.surface.tessellate, pushed out of the sphere per vertex, and rendered with
diffcloth.render.render.render. A second sphere beside the cloth shows up in the reflection modes.
Both lights cast soft shadows (diffcloth.render.shadows): the cloth and the spheres shadow each
other and the ground plane under them, in every mode.
Output: results/gallery/gallery.png (+ gallery.json with the timing of each mode).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.io import linear_to_srgb, save_png, to_uint8
from diffcloth.render import lights as Lm
from diffcloth.render import textures as T
from diffcloth.render.camera import make_camera
from diffcloth.render.frame import frame_shadow_maps, render
from diffcloth.render.shade import MODES
from diffcloth.shapes import make_plane, make_sphere
from diffcloth.surface import push_out_of_spheres, tessellate

SPHERE_CENTER, SPHERE_RADIUS = (0.0, 0.0, 0.0), 0.3
GROUND = -0.3  # height of the ground plane (the big sphere rests on it)


def procedural_drape(rows=10, cols=13, size=(1.2, 0.9)):
    """A net draped over the sphere by construction (cap on top, skirt falling with folds)."""
    x, z = np.meshgrid(
        np.linspace(-size[0] / 2, size[0] / 2, cols), np.linspace(-size[1] / 2, size[1] / 2, rows)
    )
    r = np.sqrt(x**2 + z**2)
    cap = SPHERE_RADIUS + 0.02
    y = np.where(r < cap, np.sqrt(np.maximum(cap**2 - r**2, 0.0)), -(r - cap) * 1.4)
    scale = np.where(
        r < cap, 1.0, cap / np.maximum(r, 1e-9) + (1 - cap / np.maximum(r, 1e-9)) * 0.45
    )
    fold = 0.05 * np.sin(5 * np.arctan2(z, x)) * np.clip(r - cap, 0, None) / 0.4
    return np.stack([x * scale + fold * x, y, z * scale + fold * z], -1)


def draped_net(smoke: bool):
    """Physics drape if available, else the procedural one. Returns ((rows, cols, 3), source)."""
    try:
        from diffcloth import physics

        net = physics.grid_net(10, 13, (1.2, 0.9), center=(0.0, 0.35, 0.0))
        sim = physics.make_sim(1.0 / 30.0, num_substeps=16)
        sphere = make_sphere(SPHERE_CENTER, SPHERE_RADIUS)
        colliders = physics.make_colliders(spheres=[sphere])
        traj = physics.rollout(
            net,
            sim,
            physics.make_material(),
            physics.rest_state(net),
            num_frames=10 if smoke else 45,
            colliders=colliders,
        )
        x = np.asarray(traj.x[-1])
        if np.all(np.isfinite(x)):
            return x, "diffcloth.physics rollout"
    except Exception as err:  # physics stage missing or its API changed: fall back
        print(json.dumps({"physics_unavailable": repr(err)[:200]}))
    return procedural_drape(), "procedural drape"


def label(img: np.ndarray, text: str) -> np.ndarray:
    """Write `text` into the top-left corner of a uint8 image (Pillow's default font)."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(img)
    draw = ImageDraw.Draw(im)
    draw.rectangle([0, 0, 7 * len(text) + 6, 14], fill=(0, 0, 0))
    draw.text((3, 1), text, fill=(255, 255, 255))
    return np.asarray(im)


def main(out: str = "results/gallery", *, smoke: bool = False) -> pathlib.Path:
    size = 64 if smoke else 256
    level = 4 if smoke else 13
    net, source = draped_net(smoke)
    surf = tessellate(jnp.asarray(net, jnp.float32), level)
    spheres = make_sphere(
        [SPHERE_CENTER, (0.55, -0.05, 0.35)], [SPHERE_RADIUS, 0.18], dtype=jnp.float32
    )
    # push rendered vertices out of slightly inflated spheres so cloth resting on a sphere wins the
    # depth test against the ray-cast sphere surface
    inflated = dataclasses.replace(spheres, radius=spheres.radius + 0.01)
    surf = dataclasses.replace(surf, positions=push_out_of_spheres(surf.positions, inflated))
    cam = make_camera(
        (0.7, 0.75, 1.2), (0.1, -0.1, 0.0), (0, 1, 0), width=size, height=size, fov_y=40.0
    )
    lights = Lm.make_lights(
        ambient=(0.12, 0.12, 0.14),
        directional=[((0.3, 1.0, 0.6), (1.0, 0.97, 0.9), 0.9)],
        point=[((-1.0, 1.2, 1.0), (0.4, 0.5, 0.7), 0.8)],
        shadows=True,
        softness=[1.5, 3.0],
        dtype=jnp.float32,
    )
    ground = make_plane((0.0, 1.0, 0.0), GROUND, dtype=jnp.float32)
    tiles, timing = [], {}
    app = Lm.make_appearance(sphere_color=(0.75, 0.72, 0.6), dtype=jnp.float32)
    tex = T.default_textures(
        size=32 if smoke else 128, threads=4 if smoke else 16, dtype=jnp.float32
    )
    fn = jax.jit(render, static_argnames=("shading",))
    map_size = 64 if smoke else 512
    # the shadow maps do not depend on the mode: built once, shared by every mode's render
    t0 = time.perf_counter()
    maps = jax.jit(frame_shadow_maps, static_argnames=("size",))(
        surf, lights, spheres=spheres, size=map_size
    )
    jax.block_until_ready(maps)
    timing["shadow_maps"] = round(time.perf_counter() - t0, 3)
    for mode in MODES:
        t0 = time.perf_counter()
        img = fn(
            surf,
            cam,
            lights,
            mode,
            app,
            spheres=spheres,
            textures=tex,
            background=(0.16, 0.17, 0.2),
            planes=ground,
            shadow_maps=maps,
        )
        img = np.asarray(jax.block_until_ready(img))
        timing[mode] = round(time.perf_counter() - t0, 3)
        print(json.dumps({"mode": mode, "seconds": timing[mode]}), flush=True)
        rgb = to_uint8(linear_to_srgb(img[..., :3]))  # sRGB-encoded, for people
        tiles.append(label(rgb, mode))
    rows = [np.concatenate(tiles[i : i + 5], axis=1) for i in range(0, len(tiles), 5)]
    sheet = np.concatenate(rows, axis=0)
    out_dir = pathlib.Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = save_png(out_dir / "gallery.png", sheet, colorspace="srgb")  # uint8: marked sRGB
    meta = {
        "modes": list(MODES),
        "cloth": source,
        "size": size,
        "level": level,
        "shadows": f"both lights, softness 1.5 / 3.0 degrees; ground plane y = {GROUND:.2f}",
        "seconds_incl_compile": timing,
    }
    (out_dir / "gallery.json").write_text(json.dumps(meta, indent=1))
    print(json.dumps({"wrote": str(path), **meta}))
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, for CI")
    parser.add_argument("--out", default="results/gallery")
    args = parser.parse_args()
    main(args.out, smoke=args.smoke)
