"""The sphere contact of the "impact" rule (projection + `collide._impact_contact`) with a
hand-written reverse-mode derivative.

XLA's CPU backend runs every fusion as a kernel launch of its own (about a microsecond), and on a
small net (130 nodes on the main job) the contact costs launches, not arithmetic. Differentiated
by JAX (`contact_jac`'s per-node Jacobian, or plain autodiff), one substep's contact took about 90
launches forward and backward. Here the contact is written per component on (R, C) planes (dot
products are elementwise, nothing is stacked or broadcast along a vector axis) and its VJP is
derived by hand, mirroring the forward, so XLA sees a few long elementwise programs. Values are
those of `collide` (projection onto the sphere, then `_impact_contact`); derivatives agree with
autodiff to rounding (tests/test_physics_sphere_contact.py, float64).

Reverse mode only (`jax.custom_vjp`): `collide` uses it when the stencil forces carry their
hand-written VJP too (outside `autodiff_forces` and forward-sensitivity tracing).
Cotangents of the sphere, friction and substep length are computed only for inputs that are
being differentiated (`symbolic_zeros`), so a fit of material stiffness pays for none of them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from diffcloth._math import dtype_eps, in_place


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _vec(a):
    """Planar (3, ...) array or (3,) vector -> tuple of its three components."""
    return (a[0], a[1], a[2])


def _length(sq):
    """(|w|, 1 / |w|) from |w|^2, both 0 where |w|^2 <= eps (the `_direction_planar` rule)."""
    ok = sq > dtype_eps(sq)
    root = jnp.sqrt(jnp.where(ok, sq, 1.0))
    return jnp.where(ok, root, 0.0), jnp.where(ok, 1.0 / root, 0.0)


def _keep(tree):
    return tree


def _pack(tree):
    """The arrays of `tree` (all (R, C), float or bool) computed once, into one stacked buffer:
    XLA's CPU fusion would otherwise recompute each cheap-looking chain in every consumer."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    dt = next(a.dtype for a in leaves if a.dtype != jnp.bool_)
    shape = jnp.broadcast_shapes(*(jnp.shape(a) for a in leaves))
    stacked = in_place(jnp.stack([jnp.broadcast_to(a.astype(dt), shape) for a in leaves]))
    out = [stacked[i] > 0.5 if a.dtype == jnp.bool_ else stacked[i] for i, a in enumerate(leaves)]
    return jax.tree_util.tree_unflatten(treedef, out)


def _coulomb(w, n, f):
    """One Coulomb contact on relative velocity w (tuple) against normal n (tuple).

    Returns (a, b, aux): tangential part a = s wt (tuple), normal part b = max(w.n, 0), and what
    the backward needs."""
    wn = _dot(w, n)
    wt = tuple(wi - wn * ni for wi, ni in zip(w, n, strict=True))
    length, inv = _length(_dot(wt, wt))
    m = jnp.maximum(-wn, 0.0)
    okr = jnp.abs(length) > dtype_eps(length)
    ratio = jnp.where(okr, f * m * inv, 0.0)
    s = jnp.maximum(1.0 - ratio, 0.0)
    a = tuple(s * c for c in wt)
    return a, jnp.maximum(wn, 0.0), (wn, wt, inv, m, okr, ratio, s)


def _coulomb_bwd(w, n, f, aux, ga, gb):
    """Cotangents (w, n, f) of `_coulomb` for the output cotangents ga (tuple), gb."""
    wn, wt, inv, m, okr, ratio, s = aux
    g_s = _dot(ga, wt)
    g_ratio = jnp.where(ratio < 1.0, -g_s, 0.0)
    g_f = jnp.where(okr, g_ratio * m * inv, 0.0)
    g_m = jnp.where(okr, g_ratio * f * inv, 0.0)
    # d ratio / d L = -f m / L^2; d L / d wt = wt / L
    g_len = jnp.where(okr, -g_ratio * f * m * inv * inv, 0.0)
    g_wt = tuple(s * g + g_len * inv * c for g, c in zip(ga, wt, strict=True))
    g_wn = jnp.where(wn < 0.0, -g_m, 0.0) + jnp.where(wn > 0.0, gb, 0.0) - _dot(g_wt, n)
    g_w = tuple(g + g_wn * c for g, c in zip(g_wt, n, strict=True))
    g_n = tuple(-wn * g + g_wn * c for g, c in zip(g_wt, w, strict=True))
    return g_w, g_n, g_f


def _primal(x, v, xs, vs, c, vel, r, free, f, h, mat=_keep):
    """Components in, components out, plus the values the backward reuses. `mat` (`_pack` in
    the backward) materializes the intermediate values at three points."""
    e = tuple(xi - ci for xi, ci in zip(x, c, strict=True))
    dist, inv = _length(_dot(e, e))
    okd = inv > 0
    n = (jnp.where(okd, e[0] * inv, 0.0), jnp.where(okd, e[1] * inv, 1.0))
    n = (*n, jnp.where(okd, e[2] * inv, 0.0))
    finite = jnp.isfinite(x[0]) & jnp.isfinite(x[1]) & jnp.isfinite(x[2])
    inside = (dist < r) & free & finite
    xp = tuple(jnp.where(inside, ci + r * ni, xi) for xi, ci, ni in zip(x, c, n, strict=True))
    d1 = dist - r
    e0 = tuple(a - ci + vi * h for a, ci, vi in zip(xs, c, vel, strict=True))
    len0, inv0 = _length(_dot(e0, e0))
    d0 = len0 - r
    started = d0 <= 0
    gap = d0 - d1
    okg = ~started & (gap > 0)
    safe_gap = jnp.where(okg, gap, 1.0)
    q = -d1 / safe_gap
    beta = jnp.where(started, 1.0, jnp.clip(q, 0.0, 1.0))
    dv = tuple(a - b for a, b in zip(v, vs, strict=True))
    k = tuple(beta * d for d in dv)
    u = tuple(a - b for a, b in zip(v, vel, strict=True))
    un0 = _dot(u, n)
    approach = inside & (un0 < 0)
    w1 = tuple(a - b for a, b in zip(u, k, strict=True))
    (e, inv, okd, n, inside, d1, e0, inv0, started, okg, safe_gap, q, beta, dv, k, u, un0,
     approach, w1, xp) = mat((e, inv, okd, n, inside, d1, e0, inv0, started, okg, safe_gap, q,
                              beta, dv, k, u, un0, approach, w1, xp))  # fmt: skip
    a1, b1, aux1 = _coulomb(w1, n, f)
    w2 = tuple(a + b1 * ni + ki for a, ni, ki in zip(a1, n, k, strict=True))
    w2, b1, aux1 = mat((w2, b1, aux1))
    a2, b2, aux2 = _coulomb(w2, n, f)
    p = tuple(a - (ui - un0 * ni) + b2 * ni for a, ui, ni in zip(a2, u, n, strict=True))
    a2, b2, aux2, p = mat((a2, b2, aux2, p))
    bh = beta * h
    x_out = tuple(jnp.where(approach, a + bh * b, a) for a, b in zip(xp, p, strict=True))
    v_out = tuple(
        jnp.where(approach, vi + a + b2 * ni, vv)
        for vi, a, ni, vv in zip(vel, a2, n, v, strict=True)
    )
    saved = dict(
        e=e, inv=inv, okd=okd, n=n, inside=inside, d1=d1, e0=e0, inv0=inv0, started=started,
        okg=okg, safe_gap=safe_gap, q=q, beta=beta, dv=dv, k=k, u=u, un0=un0, approach=approach,
        w1=w1, aux1=aux1, b1=b1, w2=w2, aux2=aux2, b2=b2, p=p, xp=xp,
    )  # fmt: skip
    return x_out, v_out, saved


def _backward(x, v, xs, vs, c, vel, r, free, f, h, gx, gv, want):
    """Cotangents of (x, v, xs, vs, c, vel, r, f, h) for output cotangents gx, gv (tuples).

    Per-node cotangents of the scalar inputs (c, vel, r, f, h) are summed only where `want`
    (a dict name -> bool) asks for them; otherwise None."""
    _, _, s = _primal(x, v, xs, vs, c, vel, r, free, f, h, mat=_pack)
    n, inside, approach, beta = s["n"], s["inside"], s["approach"], s["beta"]
    zero = jnp.zeros_like(x[0])
    A = approach
    g_unew = tuple(jnp.where(A, g, zero) for g in gv)
    g_dx = tuple(jnp.where(A, g, zero) for g in gx)
    # dx = beta h p, p = a2 - (u - un0 n) + b2 n
    g_p = tuple(beta * h * g for g in g_dx)
    gdp = _dot(g_dx, s["p"])
    g_beta = h * gdp
    g_h = beta * gdp
    g_a2 = tuple(a + b for a, b in zip(g_p, g_unew, strict=True))
    g_b2 = _dot(g_p, n) + _dot(g_unew, n)
    g_ut = tuple(-g for g in g_p)
    g_un0 = -_dot(g_ut, n)
    g_n = tuple(
        s["b2"] * (a + b) - s["un0"] * gu for a, b, gu in zip(g_p, g_unew, g_ut, strict=True)
    )
    g_u = tuple(a + g_un0 * ni for a, ni in zip(g_ut, n, strict=True))
    g_n = tuple(a + g_un0 * ui for a, ui in zip(g_n, s["u"], strict=True))
    # second contact, w2 = a1 + b1 n + k
    g_w2, gn2, g_f2 = _coulomb_bwd(s["w2"], n, f, s["aux2"], g_a2, g_b2)
    g_w2, gn2, g_f2, g_n, g_u, g_beta, g_h = _pack((g_w2, gn2, g_f2, g_n, g_u, g_beta, g_h))
    g_a1 = g_w2
    g_b1 = _dot(g_w2, n)
    g_n = tuple(a + b + s["b1"] * g for a, b, g in zip(g_n, gn2, g_w2, strict=True))
    g_k = g_w2
    # first contact, w1 = u - k
    g_w1, gn1, g_f1 = _coulomb_bwd(s["w1"], n, f, s["aux1"], g_a1, g_b1)
    g_w1, gn1, g_f1, g_n, g_k = _pack((g_w1, gn1, g_f1, g_n, g_k))
    g_n = tuple(a + b for a, b in zip(g_n, gn1, strict=True))
    g_u = tuple(a + b for a, b in zip(g_u, g_w1, strict=True))
    g_k = tuple(a - b for a, b in zip(g_k, g_w1, strict=True))
    # k = beta dv, dv = v - vs, u = v - vel
    g_beta = g_beta + _dot(g_k, s["dv"])
    g_dv = tuple(beta * g for g in g_k)
    g_v = tuple(
        jnp.where(A, a + b, g) for a, b, g in zip(g_dv, g_u, gv, strict=True)
    )  # not approaching: v passes through
    g_vs = tuple(-g for g in g_dv)
    g_vel = tuple(a - b for a, b in zip(g_unew, g_u, strict=True))
    # beta = started ? 1 : clip(q, 0, 1), q = -d1 / gap, gap = d0 - d1
    q, safe_gap, okg = s["q"], s["safe_gap"], s["okg"]
    g_q = jnp.where(~s["started"] & (q > 0.0) & (q < 1.0), g_beta, 0.0)
    g_d1 = -g_q / safe_gap
    g_gap = jnp.where(okg, g_q * s["d1"] / (safe_gap * safe_gap), 0.0)
    g_d0 = g_gap
    g_d1 = g_d1 - g_gap
    # d0 = |e0| - r, e0 = xs - c + vel h
    g_e0 = tuple(g_d0 * s["inv0"] * a for a in s["e0"])
    # xp = inside ? c + r n : x
    g_xp = gx
    g_n = tuple(a + jnp.where(inside, r * g, 0.0) for a, g in zip(g_n, g_xp, strict=True))
    # n = e / |e|, d1 = |e| - r
    inv, okd = s["inv"], s["okd"]
    gnn = _dot(g_n, n)
    g_e = tuple(
        jnp.where(okd, inv * (a - gnn * ni) + g_d1 * ni, 0.0) for a, ni in zip(g_n, n, strict=True)
    )
    g_x = tuple(a + jnp.where(inside, 0.0, g) for a, g in zip(g_e, g_xp, strict=True))
    out = dict(x=g_x, v=g_v, xs=g_e0, vs=g_vs)
    total = lambda a: jnp.sum(a)
    if want["c"]:
        out["c"] = tuple(
            total(jnp.where(inside, g, 0.0) - ge - g0)
            for g, ge, g0 in zip(g_xp, g_e, g_e0, strict=True)
        )
    if want["vel"]:
        out["vel"] = tuple(total(a + h * b) for a, b in zip(g_vel, g_e0, strict=True))
    if want["r"]:
        out["r"] = total(jnp.where(inside, _dot(g_xp, n), 0.0) - g_d0 - g_d1)
    if want["f"]:
        out["f"] = total(g_f1 + g_f2)
    if want["h"]:
        out["h"] = total(g_h + _dot(g_e0, vel))
    return out


def _planar(t):
    return in_place(jnp.stack(t))


@jax.custom_vjp
def sphere_impact(x, v, x_start, v_start, center, velocity, radius, free, friction, h):
    """Project points out of one sphere and apply the "impact" contact (`collide`'s rule).

    Shapes: x, v, x_start, v_start planar (3, R, C) (m, m/s); center, velocity (3,) (the centre
    at the end of the substep, m; its velocity, m/s); radius () m (margin included); free (R, C)
    bool; friction (); h () s. Returns (x, v) planar (3, R, C).
    """
    args = (x, v, x_start, v_start)
    xo, vo, _ = _primal(*(_vec(a) for a in args), _vec(center), _vec(velocity), radius, free,
                        friction, h)  # fmt: skip
    return _planar(xo), _planar(vo)


_SCALARS = ("c", "vel", "r", "f", "h")


def _fwd(x, v, x_start, v_start, center, velocity, radius, free, friction, h):
    args = (x, v, x_start, v_start, center, velocity, radius, free, friction, h)
    vals = tuple(a.value for a in args)
    # which scalar inputs are differentiated, kept in the residuals' tree structure (static)
    want = tuple(() if a.perturbed else None for a in (center, velocity, radius, friction, h))
    return sphere_impact(*vals), (vals, want)


def _bwd(res, g):
    vals, flags = res
    want = {k: f is not None for k, f in zip(_SCALARS, flags, strict=True)}
    x, v, xs, vs, c, vel, r, free, f, h = vals
    gx, gv = (jnp.zeros_like(x) if isinstance(a, SymbolicZero) else a for a in g)
    comps = tuple(_vec(a) for a in (x, v, xs, vs, c, vel))
    out = _backward(*comps, r, free, f, h, _vec(gx), _vec(gv), want)
    cast = lambda a, like: jnp.asarray(a, jnp.result_type(like))
    scalar = lambda k, like: cast(jnp.stack(out[k]) if k in ("c", "vel") else out[k], like)
    zero = lambda like: jnp.zeros_like(like)
    return (
        _planar(out["x"]),
        _planar(out["v"]),
        _planar(out["xs"]),
        _planar(out["vs"]),
        scalar("c", c) if want["c"] else zero(c),
        scalar("vel", vel) if want["vel"] else zero(vel),
        scalar("r", r) if want["r"] else zero(r),
        None,
        scalar("f", f) if want["f"] else zero(f),
        scalar("h", h) if want["h"] else zero(h),
    )


sphere_impact.defvjp(_fwd, _bwd, symbolic_zeros=True)
