"""Smooth per-vertex attributes of a tessellated grid surface, evaluated on a coarse sub-grid.

A tessellated control net has far more vertices than a small image has pixels (the level-4
tessellation of a 13 x 10 net: 28k vertices for a 64^2 frame). Attributes that vary slowly over
the surface, or no faster than the map they are read from (the light's visibility from a map
of S texels, ambient occlusion), are evaluated on every s-th vertex row and column (and the
last), and interpolated linearly along the grid to the others: a separable pair of small dense
matrices. Continuous and differentiable in the vertices (a gather, then linear maps).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def coarse_axis(n: int, lines: int):
    """Every s-th of n grid lines (and the last), s the smallest stride that leaves at most
    `lines` of them, and the matrix interpolating linearly from them back onto all n.

    Shapes: none in -> idx (n',) int, w (n, n') float64 numpy.
    """
    stride = max(-(-(n - 1) // max(int(lines) - 1, 1)), 1)
    idx = np.unique(np.r_[0:n:stride, n - 1])
    eye = np.eye(len(idx))
    w = np.stack([np.interp(np.arange(n), idx, eye[k]) for k in range(len(idx))], axis=1)
    return idx, w


def coarse_grid(points, normals, grid_shape, lines: int):
    """The sub-grid receivers of `on_coarse_grid` and the map back: (points', normals', expand),
    expand(values (m', k)) -> (n, k) interpolated along the grid (the identity when there is
    no grid, grid_shape None or not matching, or the grid is already that coarse).

    Shapes: points (n, 3) m, normals (n, 3) -> (m', 3), (m', 3), a function.
    """
    if grid_shape is None or points.shape[0] != grid_shape[0] * grid_shape[1]:
        return points, normals, lambda a: a
    R, C = int(grid_shape[0]), int(grid_shape[1])
    (rows, wr), (cols, wc) = coarse_axis(R, lines), coarse_axis(C, lines)
    if len(rows) == R and len(cols) == C:
        return points, normals, lambda a: a

    def pick(x):
        return x.reshape(R, C, 3)[rows][:, cols].reshape(-1, 3)

    def expand(a):
        a = a.reshape(len(rows), len(cols), a.shape[-1])
        a = jnp.einsum("ri,ijk->rjk", jnp.asarray(wr, a.dtype), a)
        return jnp.einsum("cj,rjk->rck", jnp.asarray(wc, a.dtype), a).reshape(R * C, a.shape[-1])

    return pick(points), pick(normals), expand


def on_coarse_grid(fn, points, normals, grid_shape, lines: int):
    """fn(points, normals) -> (m, k) evaluated at most `lines` vertex rows and columns of a grid
    surface and interpolated along the grid to every vertex; fn at every vertex when there is no
    grid (grid_shape None or not matching) or the grid is already that coarse.

    Shapes: points (n, 3) m, normals (n, 3), grid_shape (vrows, vcols) with n = vrows * vcols
    -> (n, k).
    """
    p, n, expand = coarse_grid(points, normals, grid_shape, lines)
    return expand(fn(p, n))
