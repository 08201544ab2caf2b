"""The stencil forces with a hand-written reverse-mode derivative (custom_vjp), and the
`autodiff_forces` switch back to the plain form."""

from __future__ import annotations

import contextlib
import functools

import jax
import jax.numpy as jnp

from diffcloth._math import dtype_eps, in_place
from diffcloth.physics.planar import _cross, _dot
from diffcloth.physics.stencil import (
    _CELLS,
    _ENDS,
    _SETS,
    _frame_constants,
    _fs,
    _ns,
    _padded,
    _spring_coef,
)

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
    """Springs + bending (+ drag when cfg says so) (3, R, C) from the stencil parameters.

    The cell drag is written per component (no stacked cross product): XLA then makes it one loop
    ending in the division (materialised once) instead of four (0.65-0.7x forward time at 13 x 10,
    0.95x gradient time at 128 x 128, same-process A/B).
    """
    R, C, drag = cfg
    k, rest, ck, kbh, kbv, kbhc, kbvc, ac, bc, wf = params
    xp, vp = _padded(x), _padded(v)
    fs = lambda a, di, dj: _fs(a, di, dj, R, C)
    coef = []
    for i, (a, b) in enumerate(_SETS):
        d = fs(xp, *b) - fs(xp, *a)
        dv = fs(vp, *b) - fs(vp, *a)
        coef.append(_spring_coef(d, dv, rest[i], k[i], ck[i]))
    xn = _ns(xp, 0, 0, R, C)
    f = jnp.zeros_like(x)
    for s, so, no in _ENDS:
        f = f + _ns(coef[s], *so, R, C, pad=1)[None] * (_ns(xp, *no, R, C) - xn)
    f = f + _bend_stencil(xp, vp, kbh, kbv, kbhc, kbvc, R, C)
    if drag:
        p = fs(xp, 1, 1) - fs(xp, 0, 0)
        q = fs(xp, 0, 1) - fs(xp, 1, 0)
        an = [0.5 * (p[1] * q[2] - p[2] * q[1]), 0.5 * (p[2] * q[0] - p[0] * q[2])]
        an.append(0.5 * (p[0] * q[1] - p[1] * q[0]))
        uc = fs(vp, 0, 0) + fs(vp, 0, 1) + fs(vp, 1, 0) + fs(vp, 1, 1)
        u = [0.25 * uc[i] - wf[i] for i in range(3)]
        aa = an[0] * an[0] + an[1] * an[1] + an[2] * an[2]
        ok = aa > dtype_eps(aa)
        safe = jnp.where(ok, aa, 1.0)
        c1 = ac * aa
        c2 = bc * (u[0] * an[0] + u[1] * an[1] + u[2] * an[2])
        root = jnp.sqrt(safe)
        fc = jnp.stack([jnp.where(ok, c1 * u[i] + c2 * an[i], 0.0) / root for i in range(3)])
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
        ok = dd > dtype_eps(d)
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
        ok = aa > dtype_eps(an)
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


def _stencil(cfg, params, x, v):
    """The stencil forces (3, R, C): with the hand-written VJP, or, while tracing forward
    sensitivities (`_PLAIN_STENCIL`), the same primal under plain autodiff (forward mode works)."""
    if _PLAIN_STENCIL[0]:
        return _stencil_primal(cfg, params, x, v)
    return _stencil_hand(cfg, params, x, v)


#: [True] while tracing forward sensitivities (`physics.sensitivity.forward_tracing`)
_PLAIN_STENCIL = [False]


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _stencil_hand(cfg, params, x, v):
    return _stencil_primal(cfg, params, x, v)


def _stencil_fwd(cfg, params, x, v):
    return _stencil_primal(cfg, params, x, v), (params, x, v)


def _stencil_bwd(cfg, res, g):
    # The node cotangents are written once into buffers of their own (`in_place`): otherwise
    # XLA's CPU fusion inlines this cheap-looking pad-and-slice program into the consumers of
    # ct_x and ct_v (the contact's backward reads them per component) and recomputes it there
    # (0.78x the physics gradient of drape_material, 0.89x of the main job, same process).
    ct_params, ct_x, ct_v = _stencil_vjp(cfg, *res, g)
    return ct_params, in_place(ct_x), in_place(ct_v)


_stencil_hand.defvjp(_stencil_fwd, _stencil_bwd)
