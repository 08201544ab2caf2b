"""Rasterizer benchmark: the seed's 130 x 91 = 11,830-vertex cloth surface (23,220 triangles).

Visibility + interpolation of an RGB colour + silhouette antialiasing, forward and forward +
backward (gradient of an image loss w.r.t. vertex positions and colours), at 256 and 512.
Prints one JSON line per case: bench, size, triangles, forward_ms, grad_ms (medians),
forward_min_ms, grad_min_ms (minimums: the machine is shared), silhouette_pairs (pairs searched)
and silhouette_budget (the first compacted list size; above it a list 4x as long, above that the
full-image search runs).

    python benchmarks/render.py [--sizes 256 512] [--repeats 7]
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from _timing import emit, meta, timed

from diffcloth.render.camera import make_camera
from diffcloth.render.raster import (
    default_silhouette_budget,
    edge_neighbors,
    render_mesh,
    silhouette_pairs,
)


def seed_cloth(rows: int = 91, cols: int = 130):
    """A draped, wavy 1.3 m x 0.91 m cloth grid: positions (rows*cols, 3), faces, colours."""
    u, v = np.meshgrid(np.linspace(0, 1, cols), np.linspace(0, 1, rows))
    x = (u - 0.5) * 1.3
    z = (v - 0.5) * 0.91
    y = 0.08 * np.sin(6 * u) * np.cos(5 * v) - 0.25 * (x**2 + z**2)
    pos = np.stack([x, y, z], -1).reshape(-1, 3)
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    colors = np.stack([u, v, 0.5 + 0 * u], -1).reshape(-1, 3)
    return pos.astype(np.float32), faces.astype(np.int32), colors.astype(np.float32)


def _times_ms(fn, *args, repeats: int):
    t = timed(fn, *args, repeats=repeats)
    return 1e3 * t.median, 1e3 * t.min


def main(sizes=(256, 512), repeats: int = 7):
    emit(meta("render"))
    pos, faces, colors = seed_cloth()
    pos, faces, colors = jnp.asarray(pos), jnp.asarray(faces), jnp.asarray(colors)
    nbr = edge_neighbors(np.asarray(faces))
    for size in sizes:
        cam = make_camera(
            (0.0, 1.1, 1.5), (0.0, -0.1, 0.0), (0.0, 1.0, 0.0), width=size, height=size
        )

        @jax.jit
        def forward(p, c, cam=cam):
            return render_mesh(p, faces, cam, c, neighbors=nbr)

        target = forward(pos + 0.01, colors * 0.9)

        @jax.jit
        def grad(p, c, cam=cam, target=target):
            loss = lambda p, c: jnp.mean(
                (render_mesh(p, faces, cam, c, neighbors=nbr) - target) ** 2
            )
            return jax.grad(loss, argnums=(0, 1))(p, c)

        f_ms, f_min = _times_ms(forward, pos, colors, repeats=repeats)
        g_ms, g_min = _times_ms(grad, pos, colors, repeats=repeats)
        pairs = int(jax.jit(lambda p, cam=cam: silhouette_pairs(p, faces, cam, neighbors=nbr))(pos))
        cover = float(forward(pos, colors)[..., 3].mean())
        print(
            json.dumps(
                {
                    "bench": "render_mesh_cloth",
                    "size": size,
                    "triangles": int(faces.shape[0]),
                    "forward_ms": round(f_ms, 2),
                    "grad_ms": round(g_ms, 2),
                    "forward_min_ms": round(f_min, 2),
                    "grad_min_ms": round(g_min, 2),
                    "silhouette_pairs": pairs,
                    "silhouette_budget": default_silhouette_budget(size, size),
                    "coverage": round(cover, 3),
                    "backend": jax.default_backend(),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    main(tuple(a.sizes), a.repeats)
