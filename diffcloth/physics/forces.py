"""Pure force terms on the control net: (net, material, x, v) -> (rows, cols, 3) in N.

Springs are evaluated on zero-padded planar arrays as shifted slices (no gathers, no scatter-adds):
one scalar per spring (force on its first node s * (x_second - x_first)), then one loop gathers the
eight spring ends, the bending stencil and the cell drag onto each node. A gather/scatter version over
explicit spring lists (`make_gather_forces`) is kept as a reference and benchmark.

Degenerate springs (two nodes at one point): the grid kernels give them zero force (ROBUSTNESS row 1
allows it), the reference `_pair_force` falls back to +y; values and gradients stay finite.
"""

from __future__ import annotations

import contextlib
import functools

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import _eps
from diffcloth.physics.material import Material
from diffcloth.physics.net import Net, bend_triplets, spring_list

# ---------------------------------------------------------------------------------------------
# Internally vectors are stored planar, (3, rows, cols): every operation is then an elementwise loop
# over a (rows, cols) plane, which XLA vectorises far better than reductions over a trailing axis of 3.


def to_planar(a):
    """(rows, cols, 3) -> (3, rows, cols)."""
    return jnp.moveaxis(a, -1, 0)


def from_planar(a):
    """(3, rows, cols) -> (rows, cols, 3)."""
    return jnp.moveaxis(a, 0, -1)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _direction(d):
    """(rows, cols, 3)-style: length (..., 1) and unit direction (..., 3); +y fallback at zero."""
    sq = jnp.sum(d * d, axis=-1, keepdims=True)
    ok = sq > _eps(d)
    length = jnp.sqrt(jnp.where(ok, sq, 1.0))
    fallback = jnp.zeros((1,) * (d.ndim - 1) + (3,), d.dtype).at[..., 1].set(1.0)
    return jnp.where(ok, length, 0.0), jnp.where(ok, d / length, fallback)


def _direction_planar(d):
    """Length (...) and unit direction (3, ...) of planar d; +y fallback at zero length."""
    sq = _dot(d, d)
    ok = sq > _eps(d)
    length = jnp.sqrt(jnp.where(ok, sq, 1.0))
    fallback = jnp.zeros((3,) + (1,) * (d.ndim - 1), d.dtype).at[1].set(1.0)
    n = jnp.where(ok[None], d / length[None], fallback)
    return jnp.where(ok, length, 0.0), n


def _pair_force(d, dv, rest, k, c):
    """Force (3, ...) on the first node of each spring, d = x_second - x_first; k, c, rest: (...)."""
    length, n = _direction_planar(d)
    mag = k * (length - rest) + c * _dot(dv, n)
    return mag[None] * n


def _pair_dforce(d, dd, du, rest, k, c):
    """Differential of `_pair_force` for the implicit solver, made positive semi-definite.

    The transverse stiffness k (1 - rest/L) is clamped at 0 (Choi & Ko), and the change of the damping
    direction is neglected: this is the Newton matrix, not the exact derivative.
    """
    length, n = _direction_planar(d)
    nd = _dot(n, dd)
    pos = length > 0
    trans = jnp.where(pos, jnp.maximum(1.0 - rest / jnp.where(pos, length, 1.0), 0.0), 0.0)
    return (
        k[None] * (nd[None] * n + trans[None] * (dd - nd[None] * n)) + (c * _dot(n, du))[None] * n
    )


def _pad(a, top, bottom, left, right):
    return jnp.pad(a, ((0, 0), (top, bottom), (left, right)))


def _accumulate(fh, fv, fd1, fd2):
    """Node forces from per-spring forces on each spring's first node (second gets the opposite)."""
    out = _pad(fh, 0, 0, 0, 1) - _pad(fh, 0, 0, 1, 0)
    out = out + _pad(fv, 0, 1, 0, 0) - _pad(fv, 1, 0, 0, 0)
    out = out + _pad(fd1, 0, 1, 0, 1) - _pad(fd1, 1, 0, 1, 0)
    out = out + _pad(fd2, 0, 1, 1, 0) - _pad(fd2, 1, 0, 0, 1)
    return out


def _pairs(a):
    """(second - first) for the four spring sets of the planar array a (3, rows, cols)."""
    return (
        a[:, :, 1:] - a[:, :, :-1],
        a[:, 1:, :] - a[:, :-1, :],
        a[:, 1:, 1:] - a[:, :-1, :-1],
        a[:, 1:, :-1] - a[:, :-1, 1:],
    )


def _stiffness(net: Net, material: Material):
    kh = material.stretch * net.weight_h
    kv = material.stretch * net.weight_v
    kd = material.shear * net.weight_d
    return kh, kv, kd


def _second_diff(a):
    sh = a[:, :, :-2] - 2.0 * a[:, :, 1:-1] + a[:, :, 2:]
    sv = a[:, :-2] - 2.0 * a[:, 1:-1] + a[:, 2:]
    return sh, sv


def _bend_accumulate(gh, gv):
    """Node forces from per-triplet g = dE/ds: f_a = -g, f_b = 2g, f_c = -g."""
    out = -_pad(gh, 0, 0, 0, 2) + 2.0 * _pad(gh, 0, 0, 1, 1) - _pad(gh, 0, 0, 2, 0)
    out = out - _pad(gv, 0, 2, 0, 0) + 2.0 * _pad(gv, 1, 1, 0, 0) - _pad(gv, 2, 0, 0, 0)
    return out


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
    ok = dd > _eps(d)
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
    ok = aa > _eps(an)
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


# ---------------------------------------------------------------------------------------------
# The same stencil forces with a hand-written reverse-mode derivative. JAX's own transpose of the
# forward turns each of the ~30 shifted slices into a pad and sums them in one slow fusion; the
# VJP below pads the cotangent once and reads shifted slices of it, mirroring the forward: per
# spring it forms three scalars (s, and the coefficients of d and dv in the cotangent of d) and
# gathers them onto the nodes exactly as the forward gathers s. Reverse mode only (custom_vjp);
# `autodiff_forces()` switches back to the plain form where forward mode is needed (jacfwd).

_HAND_VJP = [True]


@contextlib.contextmanager
def autodiff_forces():
    """Context manager: trace the stencil forces with JAX autodiff (forward mode works).

    By default the symplectic step uses a hand-written VJP (`jax.custom_vjp`, faster reverse
    mode, no forward mode). Wrap the *tracing* of code that needs `jax.jvp` / `jax.jacfwd`
    through a symplectic rollout in `with autodiff_forces():` (`identifiability` does).
    """
    prev = _HAND_VJP[0]
    _HAND_VJP[0] = False
    try:
        yield
    finally:
        _HAND_VJP[0] = prev


def _stencil_params(net, material, wind):
    """The differentiable inputs of the stencil kernel, all frame-shaped (no scalar inside the
    kernel, so its VJP has no reductions: a scan accumulates frame cotangents elementwise).

    (k, rest, ck, kbh, kbv, kbhc, kbvc, ac, bc, wind) with ck = damping k, kbhc = damping kbh,
    ac, bc the cell drag coefficients times the cell mask, wind (3, frame). Gradients flow to
    net and material through this function (plain autodiff).
    """
    k, rest, kbh, kbv, cells = _frame_constants(net, material)
    c = material.damping
    shape = (3,) + cells.shape
    if wind is None:
        ac = bc = jnp.zeros_like(cells)
        wf = jnp.zeros(shape, cells.dtype)
    else:
        ac = (-0.25 * material.drag_tangent) * cells
        bc = (-0.25 * (material.drag_normal - material.drag_tangent)) * cells
        wf = jnp.broadcast_to(jnp.asarray(wind, cells.dtype)[:, None, None], shape)
    return (k, rest, c * k, kbh, kbv, c * kbh, c * kbv, ac, bc, wf)


def _cell_frame(xp, vp, wf, R, C):
    """`_cell_vectors` with the wind as a (3, frame) array."""
    f = lambda a, di, dj: _fs(a, di, dj, R, C)
    an = 0.5 * _cross(f(xp, 1, 1) - f(xp, 0, 0), f(xp, 0, 1) - f(xp, 1, 0))
    u = 0.25 * (f(vp, 0, 0) + f(vp, 0, 1) + f(vp, 1, 0) + f(vp, 1, 1)) - wf
    return an, u


def _bend_stencil(xp, vp, kbh, kbv, kbhc, kbvc, R, C):
    """-D^T K D x - D^T (c K) D v (3, R, C) from 2-padded x, v (vp may be None)."""

    def g(kb, kbc, e, axis):
        def sd(a):
            if axis == 1:
                return _ns(a, 0, e - 1, R, C) - 2.0 * _ns(a, 0, e, R, C) + _ns(a, 0, e + 1, R, C)
            return _ns(a, e - 1, 0, R, C) - 2.0 * _ns(a, e, 0, R, C) + _ns(a, e + 1, 0, R, C)

        at = (0, e) if axis == 1 else (e, 0)
        out = _ns(kb, *at, R, C, pad=1)[None] * sd(xp)
        if vp is not None:
            out = out + _ns(kbc, *at, R, C, pad=1)[None] * sd(vp)
        return out

    f = 0.0
    for kb, kbc, axis in ((kbh, kbhc, 1), (kbv, kbvc, 0)):
        f = f + 2.0 * g(kb, kbc, 0, axis) - g(kb, kbc, -1, axis) - g(kb, kbc, 1, axis)
    return f


def _stencil_primal(cfg, params, x, v):
    """Springs + bending (+ drag when cfg says so) (3, R, C) from the stencil parameters."""
    R, C, drag = cfg
    k, rest, ck, kbh, kbv, kbhc, kbvc, ac, bc, wf = params
    xp, vp = _padded(x), _padded(v)
    coef = []
    for i, (a, b) in enumerate(_SETS):
        d = _fs(xp, *b, R, C) - _fs(xp, *a, R, C)
        dv = _fs(vp, *b, R, C) - _fs(vp, *a, R, C)
        coef.append(_spring_coef(d, dv, rest[i], k[i], ck[i]))
    xn = _ns(xp, 0, 0, R, C)
    f = jnp.zeros_like(x)
    for s, so, no in _ENDS:
        f = f + _ns(coef[s], *so, R, C, pad=1)[None] * (_ns(xp, *no, R, C) - xn)
    f = f + _bend_stencil(xp, vp, kbh, kbv, kbhc, kbvc, R, C)
    if drag:
        an, u = _cell_frame(xp, vp, wf, R, C)
        aa = _dot(an, an)
        ok = aa > _eps(an)
        safe = jnp.where(ok, aa, 1.0)
        num = (ac * aa)[None] * u + (bc * _dot(u, an))[None] * an
        fc = jnp.where(ok[None], num, 0.0) / jnp.sqrt(safe)[None]
        f = f + sum(_ns(fc, di, dj, R, C, pad=1) for di, dj in _CELLS)
    return f


def _stencil_vjp(cfg, params, x, v, g):
    """Cotangents (params, x, v) of `_stencil_primal` for the output cotangent g (3, R, C)."""
    R, C, drag = cfg
    k, rest, ck, kbh, kbv, kbhc, kbvc, ac, bc, wf = params
    xp, vp, gp = _padded(x), _padded(v), _padded(g)
    fs = lambda a, di, dj: _fs(a, di, dj, R, C)
    ns = lambda a, di, dj: _ns(a, di, dj, R, C)
    # springs. Per spring: s (force scalar), and a, b with cotangent(d) = s G + a d + b dv
    # (G = g_first - g_second) and cotangent(dv) = b d; gathered onto the nodes like s.
    scal, cts = [], []
    for i, (p, q) in enumerate(_SETS):
        d = fs(xp, *q) - fs(xp, *p)
        dv = fs(vp, *q) - fs(vp, *p)
        dd = _dot(d, d)
        ok = dd > _eps(d)
        inv = 1.0 / jnp.where(ok, dd, 1.0)
        rl = jnp.sqrt(inv)  # 1 / L
        ki, ri, cki = k[i], rest[i], ck[i]
        dvd = _dot(dv, d) * inv
        sig = jnp.where(ok, _dot(fs(gp, *p) - fs(gp, *q), d), 0.0)
        s = jnp.where(ok, ki * (1.0 - ri * rl) + cki * dvd, 0.0)
        scal.append(jnp.stack([s, sig * (ki * ri * rl - 2.0 * cki * dvd) * inv, sig * cki * inv]))
        cts.append(jnp.stack([sig * (1.0 - ri * rl), -sig * ki * rl, sig * dvd]))
    cts = jnp.stack(cts)  # (4, 3, frame): k, rest, ck
    # materialise the per-spring scalars once (not once per end and component)
    scal = jax.lax.optimization_barrier(scal)
    xn, vn, gn = ns(xp, 0, 0), ns(vp, 0, 0), ns(gp, 0, 0)
    ct_x = jnp.zeros_like(x)
    ct_v = jnp.zeros_like(v)
    for si, so, no in _ENDS:
        s, a, b = (_ns(t, *so, R, C, pad=1)[None] for t in scal[si])
        dx = ns(xp, *no) - xn
        ct_x = ct_x + s * (ns(gp, *no) - gn) - a * dx - b * (ns(vp, *no) - vn)
        ct_v = ct_v - b * dx
    # bending: the operator is symmetric, so its transpose is itself
    ct_x = ct_x + _bend_stencil(gp, None, kbh, kbv, None, None, R, C)
    ct_v = ct_v + _bend_stencil(gp, None, kbhc, kbvc, None, None, R, C)
    dh = lambda a: fs(a, 0, -1) - 2.0 * fs(a, 0, 0) + fs(a, 0, 1)
    dv_ = lambda a: fs(a, -1, 0) - 2.0 * fs(a, 0, 0) + fs(a, 1, 0)
    gh, gv = dh(gp), dv_(gp)
    ct_bend = (-_dot(gh, dh(xp)), -_dot(gv, dv_(xp)), -_dot(gh, dh(vp)), -_dot(gv, dv_(vp)))
    ct_ac, ct_bc, ct_wf = jnp.zeros_like(ac), jnp.zeros_like(bc), jnp.zeros_like(wf)
    if drag:
        an, u = _cell_frame(xp, vp, wf, R, C)
        gc = fs(gp, 0, 0) + fs(gp, 0, 1) + fs(gp, 1, 0) + fs(gp, 1, 1)
        aa = _dot(an, an)
        ok = aa > _eps(an)
        inv_a = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, aa, 1.0)), 0.0)  # 1 / A, 0 if degenerate
        area = aa * inv_a
        gu, ga, ua = _dot(gc, u), _dot(gc, an), _dot(u, an)
        ct_ac = area * gu
        ct_bc = ua * ga * inv_a
        ct_u = (ac * area)[None] * gc + (bc * ga * inv_a)[None] * an
        ct_a = (
            (inv_a * (ac * gu - bc * ua * ga * inv_a * inv_a))[None] * an
            + (bc * ga * inv_a)[None] * u
            + (bc * ua * inv_a)[None] * gc
        )
        ct_wf = -ct_u
        p = fs(xp, 1, 1) - fs(xp, 0, 0)
        q = fs(xp, 0, 1) - fs(xp, 1, 0)
        ct_p = 0.5 * _cross(q, ct_a)
        ct_q = 0.5 * _cross(ct_a, p)
        cell = lambda a, di, dj: _ns(a, di, dj, R, C, pad=1)
        ct_v = ct_v + 0.25 * sum(cell(ct_u, di, dj) for di, dj in _CELLS)
        ct_x = ct_x - cell(ct_p, 0, 0) + cell(ct_p, -1, -1) + cell(ct_q, 0, -1) - cell(ct_q, -1, 0)
    ct_params = (cts[:, 0], cts[:, 1], cts[:, 2], *ct_bend, ct_ac, ct_bc, ct_wf)
    return ct_params, ct_x, ct_v


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _stencil(cfg, params, x, v):
    return _stencil_primal(cfg, params, x, v)


def _stencil_fwd(cfg, params, x, v):
    return _stencil_primal(cfg, params, x, v), (params, x, v)


def _stencil_bwd(cfg, res, g):
    return _stencil_vjp(cfg, *res, g)


_stencil.defvjp(_stencil_fwd, _stencil_bwd)


def total_forces_fn(net: Net, material: Material, gravity, wind):
    """A function (x, v) -> springs + bending + drag + gravity (3, R, C) on planar x, v.

    The material-dependent frames are built once, here (call it outside a substep loop), and the
    forces carry the hand-written VJP (reverse mode only; see `autodiff_forces`).
    """
    if hasattr(material, "total_forces_planar"):  # another force model (physics.massspring)
        return lambda x, v: material.total_forces_planar(net, x, v, gravity, wind)
    mass_g = node_mass(net, material)[None] * gravity[:, None, None]
    if not _HAND_VJP[0]:
        return lambda x, v: _forces_planar(net, material, x, v, wind=wind) + mass_g
    cfg = (net.rows, net.cols, wind is not None)
    params = _stencil_params(net, material, wind)
    return lambda x, v: _stencil(cfg, params, x, v) + mass_g


def _stencil_forces(net, material, x, v, wind):
    """Springs + bending + drag (3, R, C) with the hand-written VJP (see `autodiff_forces`)."""
    if not _HAND_VJP[0]:
        return _forces_planar(net, material, x, v, wind=wind)
    cfg = (net.rows, net.cols, wind is not None)
    return _stencil(cfg, _stencil_params(net, material, wind), x, v)


def _spring_forces(net, material, x, v):
    return _forces_planar(net, material, x, v, bend=False)


def _bend_forces(net, material, x, v):
    return _forces_planar(net, material, x, v, springs=False)


def _internal_forces(net, material, x, v):
    return _forces_planar(net, material, x, v)


def _total_forces(net, material, x, v, gravity, wind):
    """Springs, bending, drag and gravity (3, R, C) on planar x, v."""
    if hasattr(material, "total_forces_planar"):  # another force model (physics.massspring)
        return material.total_forces_planar(net, x, v, gravity, wind)
    f = _stencil_forces(net, material, x, v, wind)
    return f + node_mass(net, material)[None] * gravity[:, None, None]


def _internal_force_differential(net, material, x, dx, dv):
    kh, kv, kd = _stiffness(net, material)
    c = material.damping
    rests = (net.rest_h, net.rest_v, net.rest_d1, net.rest_d2)
    ks = (kh, kv, kd, kd)
    fs = [
        _pair_dforce(d, dd, du, r, k, c * k)
        for d, dd, du, r, k in zip(_pairs(x), _pairs(dx), _pairs(dv), rests, ks, strict=True)
    ]
    sh, sv = _second_diff(dx)
    uh, uv = _second_diff(dv)
    gh = (material.bend * net.weight_bh)[None] * (sh + c * uh)
    gv = (material.bend * net.weight_bv)[None] * (sv + c * uv)
    return _accumulate(*fs) + _bend_accumulate(gh, gv)


def _cross(a, b):
    return jnp.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _drag_forces(net, material, x, v, wind):
    consts = _frame_constants(net, material)
    return _cell_drag_forces(net, material, _padded(x), _padded(v), consts, wind)


def _external_forces(net, material, x, v, gravity, wind):
    mass = node_mass(net, material)
    return mass[None] * gravity[:, None, None] + _drag_forces(net, material, x, v, wind)


# ---------------------------------------------------------------------------------------------
# public forms: (rows, cols, 3) in, (rows, cols, 3) out


def spring_forces(net: Net, material: Material, x, v):
    """Structural and shear spring forces with Rayleigh damping, N, (rows, cols, 3)."""
    return from_planar(_spring_forces(net, material, to_planar(x), to_planar(v)))


def bend_forces(net: Net, material: Material, x, v):
    """Bending forces (quadratic discrete-curvature energy on skip-one triplets), N."""
    return from_planar(_bend_forces(net, material, to_planar(x), to_planar(v)))


def internal_forces(net: Net, material: Material, x, v):
    """All internal (spring + bend) forces; they sum to zero and are invariant to rigid motion."""
    return from_planar(_internal_forces(net, material, to_planar(x), to_planar(v)))


def internal_force_differential(net: Net, material: Material, x, dx, dv):
    """Linearised internal force change for position change dx and velocity change dv (PSD model)."""
    p = to_planar
    return from_planar(_internal_force_differential(net, material, p(x), p(dx), p(dv)))


def node_mass(net: Net, material: Material):
    """Lumped node masses, kg, (rows, cols): density * area (differentiable in density)."""
    if hasattr(material, "node_mass"):  # another force model (physics.massspring)
        return material.node_mass(net)
    return material.density * net.area


def drag_forces(net: Net, material: Material, x, v, wind):
    """Aerodynamic drag on the net's cells, relative to the wind, N, (rows, cols, 3).

    Each cell (two triangles) has vector area a = 1/2 (p11 - p00) x (p01 - p10) (the sum of its two
    triangles' area vectors, for either diagonal), area A = |a|, unit normal n = a / A, and relative
    velocity u = mean of its 4 corner velocities - wind:
    f = -A (drag_normal (u.n) n + drag_tangent (u - (u.n) n)), shared equally by its 4 corners, so a
    node's share of drag follows its lumped area (and mass) exactly.
    """
    return from_planar(_drag_forces(net, material, to_planar(x), to_planar(v), wind))


def external_forces(net: Net, material: Material, x, v, gravity, wind):
    """Gravity and aerodynamic drag, N, (rows, cols, 3)."""
    return from_planar(_external_forces(net, material, to_planar(x), to_planar(v), gravity, wind))


def total_forces(net: Net, material: Material, x, v, gravity, wind):
    """Everything that acts on the free nodes, N, (rows, cols, 3)."""
    return from_planar(_total_forces(net, material, to_planar(x), to_planar(v), gravity, wind))


# ---------------------------------------------------------------------------------------------
# energies


def elastic_energy(net: Net, material: Material, x):
    """Spring + bending potential energy, J. Its negative gradient is `internal_forces` at v = 0."""
    kh, kv, kd = _stiffness(net, material)
    rests = (net.rest_h, net.rest_v, net.rest_d1, net.rest_d2)
    ks = (kh, kv, kd, kd)
    xp = to_planar(x)
    e = 0.0
    for d, r, k in zip(_pairs(xp), rests, ks, strict=True):
        length, _ = _direction_planar(d)
        e = e + 0.5 * jnp.sum(k * (length - r) ** 2)
    sh, sv = _second_diff(xp)
    e = e + 0.5 * material.bend * jnp.sum(net.weight_bh * _dot(sh, sh))
    e = e + 0.5 * material.bend * jnp.sum(net.weight_bv * _dot(sv, sv))
    return e


def potential_energy(net: Net, material: Material, x, gravity):
    """Elastic energy plus gravitational energy -sum m g.x, J."""
    mass = node_mass(net, material)
    return elastic_energy(net, material, x) - jnp.sum(mass[..., None] * x * gravity[None, None, :])


def kinetic_energy(net: Net, material: Material, v):
    """sum 1/2 m |v|^2, J (pinned nodes included)."""
    return 0.5 * jnp.sum(node_mass(net, material) * jnp.sum(v * v, -1))


# ---------------------------------------------------------------------------------------------
# reference: gather + scatter-add over explicit spring lists


def make_gather_forces(net: Net):
    """A reference `internal_forces(material, x, v)` using gathers and scatter-adds over spring lists.

    Same physics as `internal_forces`; kept to test the shifted-slice version and for benchmarks.
    """
    pairs, kind, rest, weight = spring_list(net)
    trip, bweight = bend_triplets(net)
    dtype = net.rest.dtype
    i0, i1 = jnp.asarray(pairs[:, 0]), jnp.asarray(pairs[:, 1])
    is_shear = jnp.asarray(kind == 1)
    rest = jnp.asarray(rest, dtype)
    weight = jnp.asarray(weight, dtype)
    ta, tb, tc = (jnp.asarray(trip[:, i]) for i in range(3))
    bweight = jnp.asarray(np.asarray(bweight), dtype)
    n_nodes = net.rows * net.cols

    def forces(material: Material, x, v):
        xf, vf = x.reshape(-1, 3), v.reshape(-1, 3)
        k = jnp.where(is_shear, material.shear, material.stretch) * weight
        f = _pair_force((xf[i1] - xf[i0]).T, (vf[i1] - vf[i0]).T, rest, k, material.damping * k).T
        out = jnp.zeros((n_nodes, 3), x.dtype).at[i0].add(f).at[i1].add(-f)
        s = xf[ta] - 2.0 * xf[tb] + xf[tc]
        s_v = vf[ta] - 2.0 * vf[tb] + vf[tc]
        g = (material.bend * bweight)[:, None] * (s + material.damping * s_v)
        out = out.at[ta].add(-g).at[tb].add(2.0 * g).at[tc].add(-g)
        return out.reshape(x.shape)

    return forces


def max_node_stiffness(net: Net, material: Material) -> float:
    """Gershgorin bound (N/m) on the largest eigenvalue of the stiffness matrix at rest, eager."""
    kh = np.asarray(material.stretch * net.weight_h)
    kv = np.asarray(material.stretch * net.weight_v)
    kd = np.asarray(material.shear * net.weight_d)
    row = np.zeros((net.rows, net.cols))
    for k, (t, b, l, r) in (
        (kh, (0, 0, 0, 1)),
        (kh, (0, 0, 1, 0)),
        (kv, (0, 1, 0, 0)),
        (kv, (1, 0, 0, 0)),
        (kd, (0, 1, 0, 1)),
        (kd, (1, 0, 1, 0)),
        (kd, (0, 1, 1, 0)),
        (kd, (1, 0, 0, 1)),
    ):
        row += 2.0 * np.pad(k, ((t, b), (l, r)))
    bh = np.asarray(material.bend * net.weight_bh)
    bv = np.asarray(material.bend * net.weight_bv)
    for b, axis in ((bh, 1), (bv, 0)):
        for shift, coef in ((0, 4.0), (1, 8.0), (2, 4.0)):
            pad = [(0, 0), (0, 0)]
            pad[axis] = (shift, 2 - shift)
            row += coef * np.pad(b, pad)
    return float(row.max())


__all__ = [
    "spring_forces",
    "bend_forces",
    "internal_forces",
    "internal_force_differential",
    "drag_forces",
    "external_forces",
    "total_forces",
    "node_mass",
    "elastic_energy",
    "potential_energy",
    "kinetic_energy",
    "make_gather_forces",
    "max_node_stiffness",
]
