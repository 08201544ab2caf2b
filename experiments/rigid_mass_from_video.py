"""Recover the mass and restitution of a ball from a rendered video (issue: rigid bodies).

A ball is thrown down onto the floor, bounces (restitution) and flies into a hanging cloth, which it
pushes back (two-way coupling: the heavier the ball, the deeper the cloth gives way and the less the
ball slows down). A side camera films it; mass and restitution are fitted to the video from wrong
initial guesses by gradient descent through physics.coupled_rollout, tessellation, per-vertex
collision with the ball and rendering.

    python experiments/rigid_mass_from_video.py [--smoke] [--out results/rigid_mass_from_video]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth import physics, render, report, surface
from diffcloth.fit import fit_params, pyramid_loss
from diffcloth.shapes import Sphere, make_plane

TRUTH = {"mass": 0.25, "restitution": 0.7}
INITIAL = {"mass": 0.08, "restitution": 0.4}


def build(smoke: bool):
    size = 24 if smoke else 64
    net = physics.grid_net(8, 8, (0.8, 0.8), center=(0.0, 0.1, 0.0), plane="xy", pinned="top_row")
    sim = physics.make_sim(1.0 / 60.0, num_substeps=12, collision_margin=0.005)
    material = physics.make_material(
        stretch=40.0, shear=15.0, bend=5e-4, damping=1e-4, density=0.3, friction=0.2
    )
    floor = make_plane((0.0, 1.0, 0.0), -0.45)
    camera = render.make_camera(
        (1.6, 0.2, 0.45), (0.0, -0.05, 0.3), (0.0, 1.0, 0.0), width=size, height=size, fov_y=50.0
    )
    return dict(
        net=net,
        sim=sim,
        material=material,
        floor=floor,
        camera=camera,
        lights=render.make_lights(),
        appearance=render.make_appearance(),
        num_frames=6 if smoke else 36,
    )


def make_video(setup, params):
    ball = physics.make_body(
        "sphere",
        mass=1.0,
        radius=0.08,
        position=(0.0, 0.0, 0.75),
        velocity=(0.0, -2.5, -2.6),
        friction=0.1,
    )
    ball = dataclasses.replace(ball, mass=params["mass"], restitution=params["restitution"])
    cloth, (traj,) = physics.coupled_rollout(
        setup["net"],
        setup["sim"],
        setup["material"],
        physics.rest_state(setup["net"]),
        (ball,),
        num_frames=setup["num_frames"],
        planes=setup["floor"],
        two_way=True,
    )

    def frame(x, center):
        spheres = Sphere(center[None], jnp.reshape(ball.radius, (1,)))
        surf = surface.collide_surface(surface.tessellate(x, 2), spheres)
        return render.render(
            surf, setup["camera"], setup["lights"], "phong", setup["appearance"], spheres=spheres
        )[..., :3]

    return jax.lax.map(jax.checkpoint(lambda a: frame(*a)), (cloth.x, traj.position))


def main(out_dir="results/rigid_mass_from_video", *, smoke: bool = False, steps: int = 60):
    setup = build(smoke)
    t0 = time.perf_counter()
    truth = {k: jnp.float32(v) for k, v in TRUTH.items()}
    target = jax.jit(lambda p: make_video(setup, p))(truth)

    def loss(p, tgt):  # multi-scale: a blurred ball overlaps its target from farther away
        return jnp.mean(jax.vmap(pyramid_loss)(make_video(setup, p), tgt))

    result = fit_params(
        loss,
        INITIAL,
        {"mass": "positive", "restitution": (0.0, 1.0)},
        steps=2 if smoke else steps,
        learning_rate=0.15,
        patience=None,
        loss_args=(target,),
    )
    fitted = jax.jit(lambda p: make_video(setup, p))(
        {k: jnp.float32(v) for k, v in result.params.items()}
    )
    out = Path(out_dir)
    display = lambda v: np.clip(np.asarray(v), 0, 1) ** (1 / 2.2)
    report.write_fit_report(
        out,
        result,
        truth=TRUTH,
        initial=INITIAL,
        target=display(target),
        fitted=display(fitted),
        fps=15.0,
        gain=4.0,
        title="Rigid body: mass and restitution of a ball from video",
        extra_sections={
            "Scene": (
                "Ball (radius 8 cm) thrown onto a floor (restitution) and into a hanging 8 x 8 cloth "
                "(two-way coupling), 36 frames at 60 fps, 12 substeps, one 64 x 64 side camera; "
                f"total time with compilation {time.perf_counter() - t0:.1f} s. "
                "gradsim reports an absolute relative mass error of 9e-5 for rigid bodies (its Table 1)."
            )
        },
    )
    summary = report.fit_summary(result, TRUTH, INITIAL)
    if not smoke:
        report.append_results_row(
            Path("results/README.md"),
            report.results_row("rigid_mass_from_video", summary, "rigid_mass_from_video/report.md"),
        )
    print(summary)
    return summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--out", default="results/rigid_mass_from_video")
    ap.add_argument("--steps", type=int, default=60)
    a = ap.parse_args()
    main(a.out, smoke=a.smoke, steps=a.steps)
