"""Tutorial 1: simulate a grid-net cloth and render it, stage by stage.

A horizontal 10 x 13 control net, held at two corners of one edge, swings down under gravity
for 24 frames (symplectic Euler, 40 substeps a frame); every sixth frame is tessellated into a smooth B-spline
surface and rendered with Phong shading at 128 x 128. Writes `simulate_and_render.png` (four frames
side by side) and `simulate_and_render.gif` into the figures folder (`DIFFCLOTH_FIGURES`, default
`docs/tutorials/figures/`).
"""

import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import diffcloth as dc

FIGURES = Path(os.environ.get("DIFFCLOTH_FIGURES", Path(__file__).parent / "figures"))
t0 = time.perf_counter()

# 1. physics: a horizontal net (plane "xz"), pinned at the two corners of row 0
net = dc.physics.grid_net(10, 13, (1.2, 0.9), center=(0.0, 1.2, 0.0), pinned="top_corners")
sim = dc.physics.make_sim(1.0 / 30.0, num_substeps=40)
material = dc.physics.make_material()  # the defaults: stretch 200 N/m, bend 1e-4 N m, ...
traj = jax.jit(dc.physics.rollout, static_argnames="num_frames")(
    net, sim, material, dc.physics.rest_state(net), num_frames=24
)
print("trajectory x:", traj.x.shape)  # (frames, rows, cols, 3)

# 2. surface + 3. render, one frame at a time (the same function vmapped over frames)
camera = dc.render.make_camera((0.8, 1.6, 1.4), (0.0, 0.85, -0.2), (0, 1, 0), width=128, height=128)
lights = dc.render.make_lights()
appearance = dc.render.make_appearance()


def frame(x):
    surface = dc.surface.tessellate(x, level=6)
    return dc.render.render(surface, camera, lights, "phong", appearance)


frames = jax.jit(jax.vmap(frame))(traj.x[5::6])  # frames 6, 12, 18, 24
images = np.asarray(frames[..., :3])
print("images:", images.shape)

FIGURES.mkdir(parents=True, exist_ok=True)
dc.io.save_png(FIGURES / "simulate_and_render.png", np.concatenate(list(images), axis=1),
               colorspace="srgb")  # fmt: skip
dc.io.save_video(FIGURES / "simulate_and_render.gif", images, fps=4, colorspace="srgb")

# checks: the free edge fell, the pins held, the cloth is in the picture, nothing is NaN
drop = float(net.rest[-1, 0, 1] - traj.x[-1, -1, 0, 1])
pin_move = float(jnp.abs(traj.x[-1, 0, 0] - net.rest[0, 0]).max())
covered = float((images.sum(-1) > 0).mean())
print(f"bottom corner fell {drop:.3f} m, pinned corner moved {pin_move:.1e} m, "
      f"cloth covers {covered:.0%} of the last image")  # fmt: skip
assert np.all(np.isfinite(images))
assert drop > 0.05 and pin_move < 1e-6 and 0.05 < covered < 0.9
print(f"done in {time.perf_counter() - t0:.1f} s")
