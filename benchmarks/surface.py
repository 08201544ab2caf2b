"""Tessellation timings: the seed's 13 x 10 net at several levels, forward and gradient.

Prints one JSON line per case. Forward = positions + normals + tangents + bitangents; gradient =
reverse-mode gradient of a loss on positions and normals w.r.t. the control points. Each is jitted,
compiled by a warm-up call, then timed as the median of several runs with block_until_ready.

    python benchmarks/surface.py [--levels 4 8 13 26] [--repeats 50] [--dtype float32]
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from _timing import emit, meta, timed

from diffcloth.shapes import Sphere
from diffcloth.surface import collide_surface, tessellate


def seed_net(dtype):
    x, z = np.meshgrid(np.linspace(-1.0, 1.0, 13), np.linspace(-0.7, 0.7, 10))
    y = 0.1 * np.sin(3 * x) * np.cos(2 * z)
    return jnp.asarray(np.stack([x, y, z], -1), dtype)  # (10 rows, 13 cols, 3)


def _timed(fn, *args, repeats):
    t = timed(fn, *args, repeats=repeats)
    return t.median, t.min


def main():
    emit(meta("surface"))
    ap = argparse.ArgumentParser()
    ap.add_argument("--levels", type=int, nargs="+", default=[4, 8, 13, 26])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    args = ap.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.dtype(args.dtype)
    net = seed_net(dtype)
    sphere = Sphere(jnp.asarray([0.0, -0.6, 0.0], dtype), jnp.asarray(0.65, dtype))
    for level in args.levels:

        def frames(net, level=level):
            s = tessellate(net, level)
            return s.positions, s.normals, s.tangents, s.bitangents

        def loss(net, level=level):
            s = tessellate(net, level)
            return jnp.sum(s.positions[:, 1] ** 2) + jnp.sum(s.normals[:, 1])

        def collided(net, level=level):
            s = collide_surface(tessellate(net, level), sphere)
            return s.positions, s.normals, s.tangents, s.bitangents

        n_vertices = int(np.prod(tessellate(net, level).grid_shape))
        cases = [
            ("forward", jax.jit(frames)),
            ("gradient", jax.jit(jax.grad(loss))),
            ("forward+collide", jax.jit(collided)),
        ]
        for name, fn in cases:
            med, best = _timed(fn, net, repeats=args.repeats)
            print(
                json.dumps(
                    {
                        "bench": "surface.tessellate",
                        "case": name,
                        "net": [10, 13],
                        "level": level,
                        "vertices": n_vertices,
                        "dtype": args.dtype,
                        "median_ms": round(med * 1e3, 4),
                        "min_ms": round(best * 1e3, 4),
                        "repeats": args.repeats,
                        "device": jax.devices()[0].platform,
                    }
                ),
                flush=True,
            )


if __name__ == "__main__":
    main()
