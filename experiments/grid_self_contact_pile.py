"""A grid net that lands on itself (self-contact of the grid net, issue 34): an n x n vertical
sheet (spacing 20 mm), tilted a few degrees off vertical, its lower edge 20 mm above a floor,
released: it buckles and piles onto itself. float64, symplectic Euler, dt = 1/60 s, 12 substeps,
stretch 20 N/m, shear 5 N/m, thickness 4 mm, floor margin 2 mm. Every frame is checked by the
independent numpy triangle-triangle test (tests/tri_intersections.py) on the control net's
triangles; with --off, self-contact is off (for comparison). Writes
results/grid_self_contact_pile/<name>.json (per 10 frames: pairs within the thickness, height,
intersecting frames, seconds).

    python experiments/grid_self_contact_pile.py --n 14 --frames 120 [--off]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from tri_intersections import intersecting_pairs  # noqa: E402

from diffcloth import physics  # noqa: E402
from diffcloth.physics import grid_contact as gc  # noqa: E402
from diffcloth.shapes import make_plane  # noqa: E402

SPACING, THICKNESS, CHUNK = 0.02, 4e-3, 10


def scene(n: int, tilt_deg: float):
    size = (n - 1) * SPACING
    net = physics.grid_net(n, n, (size, size), center=(0.0, 0.02 + size / 2, 0.0), plane="xy")
    x = np.array(net.rest)
    th = np.deg2rad(tilt_deg)
    y = x[..., 1] - 0.02
    x[..., 1], x[..., 2] = 0.02 + y * np.cos(th), x[..., 2] + y * np.sin(th)
    return net, jnp.asarray(x)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=14)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--tilt", type=float, default=2.0, help="degrees off vertical")
    ap.add_argument("--capacity", type=int, default=16)
    ap.add_argument("--off", action="store_true", help="self-contact off")
    args = ap.parse_args()
    net, x0 = scene(args.n, args.tilt)
    mat = physics.make_material(stretch=20.0, shear=5.0, friction=0.3)
    sc = None if args.off else gc.make_grid_self_contact(THICKNESS, net=net, capacity=args.capacity)
    sim = physics.make_sim(1 / 60, num_substeps=12, collision_margin=0.002)
    sim = dataclasses.replace(sim, self_contact=sc)
    floor = physics.make_colliders(planes=[make_plane((0, 1, 0), 0.0)])
    faces = np.asarray(gc.grid_triangles(net).faces)
    run = jax.jit(lambda s: physics.rollout(net, sim, mat, s, num_frames=CHUNK, colliders=floor))
    state = physics.ClothState(x=x0, v=jnp.zeros_like(x0))
    rows, crossing, t0 = [], [], time.perf_counter()
    for c in range(args.frames // CHUNK):
        traj = run(state)
        xs = np.asarray(traj.x)
        if not np.all(np.isfinite(xs)):
            k = int(np.argmin(np.isfinite(xs).reshape(CHUNK, -1).all(axis=1)))
            last = state if k == 0 else physics.ClothState(traj.x[k - 1], traj.v[k - 1])
            why = gc.failure_note(net, sim, last.x, last.v) or "; non-finite"
            print(f"frame {c * CHUNK + k}: not finite{why}")
            rows.append({"frame": c * CHUNK + k, "finite": False})
            break
        bad = [
            c * CHUNK + k
            for k in range(CHUNK)
            if len(intersecting_pairs(xs[k].reshape(-1, 3), faces))
        ]
        crossing += bad
        state = physics.ClothState(x=traj.x[-1], v=traj.v[-1])
        probe = sc or gc.make_grid_self_contact(THICKNESS, net=net, capacity=args.capacity)
        zero = jnp.zeros(args.n * args.n)
        pairs = jax.jit(gc.contact_pairs)(net, probe, state.x.reshape(-1, 3), zero)
        row = {"frame": (c + 1) * CHUNK, "finite": True, "intersecting_frames": bad,
               "pairs_within_thickness": int(pairs.count), "height_m": float(xs[-1, ..., 1].max()),
               "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
        rows.append(row)
        print(row, flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=ROOT).stdout.strip()  # fmt: skip
    out = ROOT / "results" / "grid_self_contact_pile"
    out.mkdir(parents=True, exist_ok=True)
    name = f"n{args.n}_{'off' if args.off else 'on'}"
    summary = {
        "args": vars(args),
        "commit": commit,
        "intersecting_frames": crossing,
        "chunks": rows,
    }
    (out / f"{name}.json").write_text(json.dumps(summary, indent=1))
    print(f"intersecting frames: {crossing if crossing else 'none'}; wrote {out / name}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
