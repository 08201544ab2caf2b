"""diffcloth's Provot model against the independent Warp reference: trajectory agreement.

    python benchmarks/peers/massspring_agreement.py [--out FILE]

Runs configs/drape_provot.toml (16 x 16 net dropped centred onto a sphere over a ground plane,
1/2400 s substeps, 90 frames) and a hanging net (two corner pins, no contact) in diffcloth and in
benchmarks/peers/warp_massspring.py with identical parameters, in float64 and float32. One JSON
line per case: max and mean distance (mm) between the engines' control points over all frames
(initial state included), and each float32 run against the float64 Warp run. diffcloth_s and
warp_s are wall times of one run including compilation (not a speed comparison).
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.peers.warp_massspring import simulate  # noqa: E402
from diffcloth import physics  # noqa: E402
from diffcloth.scene import load_scene  # noqa: E402


def _diffcloth(scene, frames):
    traj = jax.jit(
        lambda s: physics.rollout(
            s.net, s.sim, s.material, s.state, num_frames=frames, colliders=s.colliders
        )
    )(scene)
    return np.concatenate([np.asarray(scene.state.x)[None], np.asarray(traj.x)])


def _dist(a, b):
    d = np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1)
    return round(float(d.max()) * 1e3, 9), round(float(d.mean()) * 1e3, 9)


def cases(frames):
    """(name, scene overrides, warp kwargs) for the two scenes."""
    base = load_scene(ROOT / "configs" / "drape_provot.toml", dtype=np.float64)
    m = base.material
    params = {k: float(getattr(m, k)) for k in physics.MASS_SPRING_FIELDS}
    params.update(contact_thickness=0.005, friction_rule="coulomb", mass_lumping="uniform")
    drape = dict(params, height=1.0, planes=[((0.0, 1.0, 0.0), 0.0)])
    hang = dict(params, height=1.0, pins="top_corners")
    return [
        ("drape_provot", drape, ((0.0, 0.5, 0.0), 0.3), None),
        ("hang_two_corners", hang, None, "top_corners"),
    ]


def run_case(name, wparams, sphere, pins, frames, dtype):
    scene = load_scene(ROOT / "configs" / "drape_provot.toml", dtype=dtype)
    if sphere is None:
        import dataclasses

        net = physics.grid_net(16, 16, (1.0, 1.0), center=(0.0, 1.0, 0.0), pinned=pins, dtype=dtype)
        scene = dataclasses.replace(
            scene, net=net, state=physics.rest_state(net), colliders=None, spheres=None
        )
    t = time.perf_counter()
    a = _diffcloth(scene, frames)
    t_dc = time.perf_counter() - t
    t = time.perf_counter()
    b = simulate(16, 16, (1.0, 1.0), wparams, sphere=sphere, dt=1 / 2400, substeps=40,
                 frames=frames, dtype=np.dtype(dtype))  # fmt: skip
    t_wp = time.perf_counter() - t
    return a, b, t_dc, t_wp


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--out", help="also write the JSON lines to this file")
    args = parser.parse_args(argv)
    lines = []
    for name, wparams, sphere, pins in cases(args.frames):
        ref = None
        for dtype in (np.float64, np.float32):
            a, b, t_dc, t_wp = run_case(name, wparams, sphere, pins, args.frames, dtype)
            ref = b if dtype == np.float64 else ref
            dmax, dmean = _dist(a, b)
            row = dict(
                bench="peers_massspring_agreement",
                case=name,
                net="16x16",
                frames=args.frames,
                substep_s=1 / 2400,
                dtype=np.dtype(dtype).name,
                max_mm=dmax,
                mean_mm=dmean,
                diffcloth_s=round(t_dc, 2),
                warp_s=round(t_wp, 2),
            )
            if dtype == np.float32:
                row["diffcloth_vs_warp64_max_mm"], row["diffcloth_vs_warp64_mean_mm"] = _dist(
                    a, ref
                )
                row["warp_vs_warp64_max_mm"], row["warp_vs_warp64_mean_mm"] = _dist(b, ref)
            lines.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        with open(args.out, "w") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in lines)


if __name__ == "__main__":
    main()
