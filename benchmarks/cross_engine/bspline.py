"""Uniform cubic B-spline surface of a control net, in numpy (independent of diffcloth.surface).

A net of n x m control points gives (n - 3) x (m - 3) bicubic patches; patch (a, b) over
s, t in [0, 1] is  sum_ij B_i(s) B_j(t) P[a + i, b + j]  with the uniform cubic B-spline
blending functions

    B_0 = (1 - s)^3 / 6,  B_1 = (3 s^3 - 6 s^2 + 4) / 6,  B_2 = (-3 s^3 + 3 s^2 + 3 s + 1) / 6,
    B_3 = s^3 / 6.

The surface does not pass through the net (it lies inside its convex hull). Normals are the
normalised cross product of the two parametric derivatives. Vertices that end up inside a sphere
(the spline cuts the curved contact region) are pushed out onto radius + offset, as a renderer of
cloth on a ball must, and take the sphere's normal (on their own side).
"""

from __future__ import annotations

import numpy as np


def _basis(samples: int):
    """(samples, 4) blending weights and their derivatives at s = 0 .. 1 - 1/samples."""
    s = np.arange(samples) / samples
    b = (
        np.stack(
            [(1 - s) ** 3, 3 * s**3 - 6 * s**2 + 4, -3 * s**3 + 3 * s**2 + 3 * s + 1, s**3], -1
        )
        / 6.0
    )
    db = np.stack([-3 * (1 - s) ** 2, 9 * s**2 - 12 * s, -9 * s**2 + 6 * s + 3, 3 * s**2], -1) / 6.0
    return b, db


def _curve_matrix(n: int, samples: int):
    """(K, n) matrices mapping n control values to K = (n - 3) samples + 1 curve samples (value,
    derivative), the last one at the end of the last patch."""
    b, db = _basis(samples)
    patches = n - 3
    k = patches * samples + 1
    m = np.zeros((k, n))
    dm = np.zeros((k, n))
    for p in range(patches):
        m[p * samples : (p + 1) * samples, p : p + 4] = b
        dm[p * samples : (p + 1) * samples, p : p + 4] = db
    # end point: s = 1 of the last patch
    m[-1, patches - 1 : patches + 3] = np.array([0.0, 1.0, 4.0, 1.0]) / 6.0
    dm[-1, patches - 1 : patches + 3] = np.array([0.0, -3.0, 0.0, 3.0]) / 6.0
    return m, dm


def surface(net, samples: int = 6, sphere=None, offset: float = 0.002):
    """Triangle mesh of the B-spline surface of `net` (rows, cols, 3).

    Returns (vertices (V, 3), normals (V, 3) unit, faces (F, 3) int32), V = K_r K_c grid samples.
    sphere: optional ((cx, cy, cz), r): vertices inside are pushed to r + offset from the centre.
    """
    p = np.asarray(net, np.float64)
    rows, cols, _ = p.shape
    mr, dmr = _curve_matrix(rows, samples)
    mc, dmc = _curve_matrix(cols, samples)
    pos = np.einsum("ir,rcx,jc->ijx", mr, p, mc)
    du = np.einsum("ir,rcx,jc->ijx", mr, p, dmc)  # along the columns
    dv = np.einsum("ir,rcx,jc->ijx", dmr, p, mc)  # along the rows
    nrm = np.cross(dv, du)  # +y for the "xz" net (rows along +z, columns along +x)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
    kr, kc = pos.shape[:2]
    pos = pos.reshape(-1, 3)
    nrm = nrm.reshape(-1, 3)
    if sphere is not None:
        c, r = np.asarray(sphere[0], np.float64), float(sphere[1])
        d = pos - c
        dist = np.linalg.norm(d, axis=-1)
        inside = dist < r + offset
        out = d[inside] / np.maximum(dist[inside, None], 1e-12)
        pos[inside] = c + out * (r + offset)
        # a pushed vertex lies on the sphere: its normal is the sphere's, on the old normal's side
        side = np.sign(np.sum(out * nrm[inside], axis=-1, keepdims=True))
        nrm[inside] = out * np.where(side == 0, 1.0, side)
    idx = np.arange(kr * kc).reshape(kr, kc)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c_, d_ = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c_, b], -1), np.stack([b, c_, d_], -1)]).astype(np.int32)
    return pos, nrm, faces
