"""Fused grid kernels of the force terms on zero-padded planar arrays (springs, bending, cell drag),
differentiated by JAX itself."""

from __future__ import annotations

import jax.numpy as jnp

from diffcloth._math import dtype_eps
from diffcloth.physics.planar import _cross, _dot, _stiffness

# ---------------------------------------------------------------------------------------------
# Fused grid kernels on zero-padded arrays. x and v are padded once by two nodes on every side;
# every spring, cell and bend term is then an elementwise expression of shifted slices of padded
# arrays (XLA emits vectorised loops without bounds checks; pads inside a fused loop are slow).
# Springs are evaluated once each, as one scalar s per spring (force on its first node s * (x_second
# - x_first)); the four spring sets and two drag scalars per cell are computed in one loop over a
# (R + 2, C + 2) frame (frame (p, q) is node (p - 1, q - 1)), then gathered onto the nodes.
# A zero-length spring gets s = 0 (no force, finite gradient).


def _frame(a, rows, cols, top=1, left=1, value=0.0):
    """Pad a (r, c) array into the (rows + 2, cols + 2) frame with its [0, 0] at (top, left)."""
    r, c = a.shape[-2:]
    pad = [(0, 0)] * (a.ndim - 2) + [(top, rows + 2 - top - r), (left, cols + 2 - left - c)]
    return jnp.pad(a, pad, constant_values=value)


def _fs(a, di, dj, rows, cols):
    """Frame-sized view of a 2-padded (..., R + 4, C + 4) array, shifted by (di, dj) in [-1, 1]."""
    return a[..., 1 + di : 3 + di + rows, 1 + dj : 3 + dj + cols]


def _ns(a, di, dj, rows, cols, pad=2):
    """Node-sized (..., R, C) view of a padded array (pad on each side) shifted by (di, dj)."""
    return a[..., pad + di : pad + di + rows, pad + dj : pad + dj + cols]


def _spring_coef(d, dv, rest, k, ck):
    """Per-spring scalar s with force on the first node s * d (d = x_second - x_first)."""
    dd = _dot(d, d)
    ok = dd > dtype_eps(d)
    safe = jnp.where(ok, dd, 1.0)
    num = k * (safe - rest * jnp.sqrt(safe)) + ck * _dot(dv, d)
    # ending in a division (an "expensive" op) makes XLA materialise s once instead of re-deriving
    # it inside the gather loop for each of the two ends and three components
    return jnp.where(ok, num, 0.0) / safe


# (first node offset, second node offset) of each spring set, in frame coordinates
_SETS = (((0, 0), (0, 1)), ((0, 0), (1, 0)), ((0, 0), (1, 1)), ((0, 1), (1, 0)))
# per node: (set, frame offset of the spring, node offset of the other end)
_ENDS = (
    (0, (0, 0), (0, 1)),
    (1, (0, 0), (1, 0)),
    (2, (0, 0), (1, 1)),
    (3, (0, -1), (1, -1)),
    (0, (0, -1), (0, -1)),
    (1, (-1, 0), (-1, 0)),
    (2, (-1, -1), (-1, -1)),
    (3, (-1, 0), (-1, 1)),
)
_CELLS = ((0, 0), (-1, 0), (0, -1), (-1, -1))


def _frame_constants(net, material):
    """Stiffness and rest-length frames (4, R + 2, C + 2), bend frames, cell mask."""
    R, C = net.rows, net.cols
    kh, kv, kd = _stiffness(net, material)
    k = jnp.stack([_frame(kh, R, C), _frame(kv, R, C), _frame(kd, R, C), _frame(kd, R, C)])
    rests = (net.rest_h, net.rest_v, net.rest_d1, net.rest_d2)
    rest = jnp.stack([_frame(r, R, C, value=1.0) for r in rests])
    kbh = _frame(material.bend * net.weight_bh, R, C, top=1, left=2)
    kbv = _frame(material.bend * net.weight_bv, R, C, top=2, left=1)
    cells = _frame(jnp.ones((R - 1, C - 1), net.rest.dtype), R, C)
    return k, rest, kbh, kbv, cells


def _padded(a):
    return jnp.pad(a, ((0, 0), (2, 2), (2, 2)))


def _frame_coefficients(net, material, xp, vp, consts):
    """(4, R + 2, C + 2): the spring scalars of the four spring sets."""
    R, C = net.rows, net.cols
    k, rest, _, _, cells = consts
    c = material.damping
    out = []
    for i, (a, b) in enumerate(_SETS):
        d = _fs(xp, *b, R, C) - _fs(xp, *a, R, C)
        dv = _fs(vp, *b, R, C) - _fs(vp, *a, R, C)
        out.append(_spring_coef(d, dv, rest[i], k[i], c * k[i]))
    return jnp.stack(out)


def _cell_vectors(xp, vp, wind, R, C):
    """Cell vector area (3, frame) and relative velocity (3, frame) from 2-padded x, v."""
    f = lambda a, di, dj: _fs(a, di, dj, R, C)
    an = 0.5 * _cross(f(xp, 1, 1) - f(xp, 0, 0), f(xp, 0, 1) - f(xp, 1, 0))
    u = 0.25 * (f(vp, 0, 0) + f(vp, 0, 1) + f(vp, 1, 0) + f(vp, 1, 1)) - wind[:, None, None]
    return an, u


def _frame_forces(net, material, xp, vp, coef, consts, springs=True, bend=True):
    """Node forces (3, R, C) from 2-padded x, v: springs (from coef) and bending."""
    R, C = net.rows, net.cols
    _, _, kbh, kbv, _ = consts
    x = _ns(xp, 0, 0, R, C)
    f = jnp.zeros_like(x)
    if springs:
        for k, so, no in _ENDS:
            f = f + _ns(coef[k], *so, R, C, pad=1)[None] * (_ns(xp, *no, R, C) - x)
    if not bend:
        return f
    # bending: g = kb (w_a - 2 w_b + w_c) at each centre, w = x + damping v; f = 2 g_b - g_a - g_c
    w = lambda di, dj: _ns(xp, di, dj, R, C) + material.damping * _ns(vp, di, dj, R, C)
    gh = lambda e: _ns(kbh, 0, e, R, C, pad=1)[None] * (w(0, e - 1) - 2.0 * w(0, e) + w(0, e + 1))
    gv = lambda e: _ns(kbv, e, 0, R, C, pad=1)[None] * (w(e - 1, 0) - 2.0 * w(e, 0) + w(e + 1, 0))
    f = f + 2.0 * gh(0) - gh(-1) - gh(1) + 2.0 * gv(0) - gv(-1) - gv(1)
    return f


def _cell_drag_forces(net, material, xp, vp, consts, wind):
    """Per-node drag (3, R, C): per cell f = -A (dt u + (dn - dt) (u.n) n), a quarter per corner.

    With vector area a (|a| = A, n = a / A): f = -(dt |a|^2 u + (dn - dt) (u.a) a) / |a|. The cell
    forces end in a division, so XLA materialises them once (not once per corner).
    """
    R, C = net.rows, net.cols
    cells = consts[4]
    an, u = _cell_vectors(xp, vp, wind, R, C)
    aa = _dot(an, an)
    ok = aa > dtype_eps(an)
    safe = jnp.where(ok, aa, 1.0)
    c1 = (-0.25 * material.drag_tangent) * aa * cells
    c2 = (-0.25 * (material.drag_normal - material.drag_tangent)) * _dot(u, an) * cells
    num = c1[None] * u + c2[None] * an
    fc = jnp.where(ok[None], num, 0.0) / jnp.sqrt(safe)[None]
    return sum(_ns(fc, di, dj, R, C, pad=1) for di, dj in _CELLS)


def _forces_planar(net, material, x, v, *, springs=True, bend=True, wind=None):
    """Plain (JAX-autodiff) stencil forces (3, R, C); also supports forward mode."""
    consts = _frame_constants(net, material)
    xp, vp = _padded(x), _padded(v)
    coef = _frame_coefficients(net, material, xp, vp, consts) if springs else None
    f = _frame_forces(net, material, xp, vp, coef, consts, springs=springs, bend=bend)
    if wind is not None:
        f = f + _cell_drag_forces(net, material, xp, vp, consts, wind)
    return f
