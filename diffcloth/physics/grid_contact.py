"""Self-contact of the grid control net: a penalty impulse with Coulomb friction between layers
and a conservative per-point displacement bound (continuous collision check), every substep.

The net's quads are split into two triangles each, (i, j)-(i, j+1)-(i+1, j+1) and
(i, j)-(i+1, j+1)-(i+1, j); its edges are the structural springs and those diagonals. The mesh
cloth's broad phase and distances (`mesh.selfcontact.find_pairs`, `gap`) run on that triangle
net under jit with a fixed capacity: vertex-triangle and edge-edge pairs, pairs that share a
vertex excluded. Each substep, from its start positions x:

1. Pairs: each point's reach in the substep is r_k = 1.5 h |v_k| + M (v_k the velocity the
   substep drifts with; the implicit integrator adds h^2 |g|, as its v_k is the start velocity;
   M = `SelfContact.step_fraction` x the mean rest structural length). The broad phase finds
   every pair closer than d_hat + b_a + b_b at positions x_ref, b_k = r_k + 2 M each point's
   budget (b of a side: its points' largest; r_k alone where the wider search overflows the
   capacity), and its pairs are kept (`PairCache`) until a
   point could leave its budget: it runs again (lax.cond) when |x_k - x_ref,k| + r_k > b_k
   for some k, so a resting net keeps its pairs for many substeps.
2. Response (velocities, before the drift): each pair closer than d_hat (unsigned distance d,
   unit gap direction n, closest-point weights w_k, relative velocity u = sum_k w_k v_k) gets the
   normal impulse J = max(J_pen, s(d) (-u.n) / W): J_pen = h kappa A (d_hat - d)^2 / d_hat, a
   smooth penalty (C1 at d_hat; kappa = `SelfContact.stiffness` N/m^3, A the pair's area),
   W = sum_k w_k^2 / m_k (pinned points: 1/m = 0), and s(d) a C1 ramp from 0 at d_hat to 1 at
   d_hat / 2 that removes the approaching relative speed (fully from d_hat / 2 in). Friction is
   the colliders' Coulomb rule: the tangential relative speed shrinks by mu x the normal speed
   change (J_t = min(|u_T| / W, mu J)), mu = material.friction x `SelfContact.friction`. Point k
   gets w_k / m_k (J n - J_t t); a point in several pairs takes the mean of their changes,
   weighted by s(d) |w_k|. Edge-edge impulses carry IPC's mollifier
   (`mesh.selfcontact_energy.mollifier`): nearly parallel edges, whose closest points jump,
   hand the response to the vertex-triangle pairs.
3. Filter (positions, after the drift, the pins and the colliders): each free point's
   displacement is shortened to at most min(r_k, 0.45 d_min), d_min the distance, at the
   substep's start, of the closest kept pair that contains it (and it never leaves its budget
   around x_ref); a shortened point's velocity becomes its displacement / h. Within a substep
   every point moves on a straight line, so a kept pair keeps at least a tenth of its distance,
   and a pair not kept (d >= d_hat + b_a + b_b at x_ref, each point within b of x_ref) stays
   farther than d_hat: a net free of self-intersection at the start of a substep is free of it
   at its end (pinned points are not shortened; the guarantee needs them to move less than
   0.45 d per substep towards the cloth, and to stay within their budget).

A broad phase overflow (more candidates than `SelfContact.capacity` allows) makes the substep's
positions NaN: the frame fails, and `check_overflow` names `[sim] self_contact_capacity`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import safe_norm
from diffcloth.physics.mesh.selfcontact import (
    Pairs,
    SelfContact,
    check_pairs,
    find_pairs,
    make_self_contact,
    min_triangle_height,
    weights,
)
from diffcloth.physics.mesh.selfcontact_energy import mollifier

__all__ = [
    "GridTriangles",
    "Hooks",
    "PairCache",
    "check_overflow",
    "contact_pairs",
    "failure_note",
    "filter_step",
    "grid_triangles",
    "make_grid_self_contact",
    "max_step",
    "planar_hooks",
    "reach",
    "respond",
]

#: a pair's points each move at most this fraction of its distance in a substep
SHARE = 0.45


class GridTriangles(NamedTuple):
    """The triangle net of a grid (what `find_pairs` and `mollifier` read): faces (m, 3) and
    edges (e, 2) int32 node indices (row-major, i * cols + j), rest (n, 3) m."""

    faces: jax.Array
    edges: jax.Array
    rest: jax.Array


def _topology(rows: int, cols: int):
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    edges = np.concatenate([
        np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
        np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1),
        np.stack([a, d], 1),
    ])  # fmt: skip
    return faces.astype(np.int32), edges.astype(np.int32)


def grid_triangles(net) -> GridTriangles:
    """The net's quads as two triangles each (module docstring); faces and edges are constants
    built once in numpy from the static shape.
    Shapes: net (rows, cols) -> faces (2 (rows-1)(cols-1), 3), edges (e, 2), rest (n, 3)."""
    faces, edges = _topology(net.rows, net.cols)
    return GridTriangles(jnp.asarray(faces), jnp.asarray(edges), net.rest.reshape(-1, 3))


def min_rest_height(net) -> float:
    """The shortest altitude of the net's rest triangles, m (numpy, eager).
    Shapes: net (rows, cols) -> float."""
    faces, _ = _topology(net.rows, net.cols)
    return min_triangle_height(np.asarray(net.rest).reshape(-1, 3), faces)


def make_grid_self_contact(
    thickness: float = 2e-3,
    *,
    stiffness: float = 1e5,
    friction: float = 1.0,
    capacity: int = 16,
    step_fraction: float = 0.1,
    net=None,
    dtype=None,
) -> SelfContact:
    """Validated `SelfContact` for a grid net (pass it as `SimSettings.self_contact`).
    thickness: m (> 0; with `net`, below half its shortest rest triangle height);
    stiffness: N/m^3, the penalty's kappa; friction: scale of the material's coefficient;
    capacity: broad-phase pairs per node and per edge; step_fraction: how far a point may move
    in a substep beyond 1.5 h |v|, in mean rest structural lengths (`reach`).
    Shapes: scalars -> SelfContact of () leaves."""
    sc = make_self_contact(thickness, stiffness=stiffness, friction=friction, capacity=capacity,
                           step_fraction=step_fraction, dtype=dtype)  # fmt: skip
    if net is not None:
        h = min_rest_height(net)
        if not float(thickness) < 0.5 * h:
            raise ValueError(
                f"self_contact.thickness = {thickness!r} m must be below half the shortest rest "
                f"triangle height of the net ({0.5 * h:.3g} m): lower it or use fewer rows/cols"
            )
    return sc


def max_step(net, sc: SelfContact):
    """() m, M: how far a point may move in a substep beyond 1.5 h |v| (`step_fraction` x the
    mean rest structural spring length).
    Shapes: net (rows, cols) -> ()."""
    total = jnp.sum(net.rest_h) + jnp.sum(net.rest_v)
    return sc.step_fraction * total / (net.rest_h.size + net.rest_v.size)


def reach(net, sc: SelfContact, v, h, accel=0.0):
    """(n,) m, the most each point moves in the substep: 1.5 h |v| + h^2 accel + `max_step`
    (accel m/s^2, the gravity for the implicit integrator, whose v is the start
    velocity, not the kicked one).
    Shapes: v (n, 3) m/s, h () s, accel () -> (n,)."""
    return 1.5 * h * safe_norm(v) + h * h * accel + max_step(net, sc)


def contact_pairs(net, sc: SelfContact, x, motion) -> Pairs:
    """The pairs a substep from x can bring within the thickness: closer than d_hat plus the
    largest `reach` (motion) of each side's points.
    Shapes: x (n, 3) row-major nodes, motion (n,) m -> Pairs with P = capacity x (n + edges)."""
    return find_pairs(grid_triangles(net), sc, x, sc.thickness, motion)


def _pair_area(area, pairs: Pairs):
    a = area[pairs.idx]
    return jnp.where(pairs.kind == 0, a[:, 0], 0.125 * jnp.sum(a, axis=1))


def _closest(x, pairs: Pairs):
    """(P, 4) weights, (P, 3) gap vectors and (P,) distances at x."""
    q = x[pairs.idx]
    w = weights(q, pairs.kind)
    g = jnp.einsum("pk,pki->pi", w, q)
    return w, g, safe_norm(g)


def respond(net, sc: SelfContact, pairs: Pairs, x, v, inv_mass, friction, h):
    """Velocities after the substep's contact impulses (module docstring, step 2).
    x, v: (n, 3) m, m/s at the substep's start; inv_mass: (n,) 1/kg (0 where pinned);
    friction: () the material's Coulomb coefficient; h: () s.
    Shapes: x, v (n, 3), inv_mass (n,) -> (n, 3)."""
    w, g, d = _closest(x, pairs)
    dhat = sc.thickness
    active = pairs.valid & (d < dhat) & ~pairs.overflow
    nrm = g / jnp.maximum(d, 1e-30)[:, None]
    u = jnp.einsum("pk,pki->pi", w, v[pairs.idx])
    un = jnp.sum(u * nrm, axis=1)
    im = inv_mass[pairs.idx]
    big_w = jnp.sum(w * w * im, axis=1)
    ok = active & (big_w > 0)
    big_w = jnp.where(ok, big_w, 1.0)
    tri = grid_triangles(net)
    moll = mollifier(tri, x, pairs)
    depth = jnp.where(ok, dhat - d, 0.0)
    area = _pair_area(net.area.reshape(-1), pairs)
    j_pen = h * sc.stiffness * area * depth * depth / dhat
    t = jnp.clip(2.0 * depth / dhat, 0.0, 1.0)
    ramp = t * t * (3.0 - 2.0 * t)  # 0 at d_hat, 1 from d_hat / 2 in (C1)
    jn = moll * jnp.maximum(j_pen, ramp * -un / big_w)
    ut = u - un[:, None] * nrm
    ut_len = safe_norm(ut)
    mu = friction * sc.friction
    jt = jnp.minimum(ut_len / big_w, mu * jn)
    tdir = ut / jnp.maximum(ut_len, 1e-30)[:, None]
    imp = jnp.where(ok[:, None], jn[:, None] * nrm - jt[:, None] * tdir, 0.0)  # (P, 3) N s
    dv = (w * im)[:, :, None] * imp[:, None, :]  # (P, 4, 3)
    n = x.shape[0]
    # each point takes the mean of its pairs' changes, weighted by ramp x mollifier x |w_k|
    c = jnp.where(ok, moll * ramp, 0.0)[:, None] * jnp.abs(w)  # (P, 4)
    seg = lambda a: jax.ops.segment_sum(a, pairs.idx.reshape(-1), num_segments=n)
    total = seg((c[:, :, None] * dv).reshape(-1, 3))
    weight = seg(c.reshape(-1))
    return v + total / jnp.where(weight > 0, weight, 1.0)[:, None]


def filter_step(pairs: Pairs, x, x1, v1, motion, free, h):
    """Positions and velocities after the displacement bound (module docstring, step 3); NaN
    positions when the broad phase overflowed.
    x, x1: (n, 3) m at the substep's start and end; v1: (n, 3) m/s; motion: (n,) m, the reach
    the pairs were found with; free: (n,) bool; h: () s.
    Shapes: x, x1, v1 (n, 3), motion, free (n,) -> ((n, 3), (n, 3))."""
    _, _, d = _closest(x, pairs)
    n = x.shape[0]
    dd = jnp.broadcast_to(jnp.where(pairs.valid, d, jnp.inf)[:, None], pairs.idx.shape)
    dmin = jax.ops.segment_min(dd.reshape(-1), pairs.idx.reshape(-1), num_segments=n)
    cap = jnp.minimum(motion, SHARE * dmin)
    disp = x1 - x
    size = safe_norm(disp)
    short = free & (size > cap)
    scale = jnp.where(short, cap / jnp.where(short, size, 1.0), 1.0)
    x2 = x + scale[:, None] * disp
    v2 = jnp.where(short[:, None], (x2 - x) / h, v1)
    x2 = jnp.where(pairs.overflow, jnp.nan, x2)
    return x2, v2


def check_overflow(net, sim, x, v=None) -> None:
    """Eager: raise ValueError naming `[sim] self_contact_capacity` when the grid's broad phase
    overflows at positions x and velocities v (None: at rest), e.g. the last finite frame of a
    failed rollout; nothing when self-contact is off or x is not finite.
    Shapes: x, v (rows, cols, 3) m, m/s."""
    sc = getattr(sim, "self_contact", None)
    if sc is None or not np.all(np.isfinite(np.asarray(x))):
        return
    x = jnp.asarray(x).reshape(-1, 3)
    v = jnp.zeros_like(x) if v is None else jnp.asarray(v, x.dtype).reshape(-1, 3)
    v = jnp.where(jnp.isfinite(v), v, 0.0)
    h = sim.dt / sim.num_substeps
    accel = jnp.sqrt(jnp.sum(sim.gravity**2)) if sim.integrator == "implicit" else 0.0
    pairs = jax.jit(contact_pairs)(net, sc, x, reach(net, sc, v, h, accel))
    check_pairs(pairs, "grid self-contact")


def failure_note(net, sim, x, v=None) -> str:
    """Eager: what to add to a failed grid rollout's message: "" with self-contact off; the
    overflow (naming `[sim] self_contact_capacity`) when the broad phase overflows at x, v, the
    last finite frame's state; else a hint that an overflow within the frame is possible.
    Shapes: x, v (rows, cols, 3) m, m/s -> str."""
    if getattr(sim, "self_contact", None) is None:
        return ""
    try:
        check_overflow(net, sim, x, v)
    except ValueError as err:
        return f"; {err}"
    return (
        "; with [sim] self_contact on, a broad-phase overflow within the frame also gives a "
        "non-finite frame: raise [sim] self_contact_capacity"
    )


class PairCache(NamedTuple):
    """The pairs of the last broad phase and what they cover: pairs (Pairs), x_ref (n, 3) m, the
    positions they were found at, and budget (n,) m, how far each node may move from x_ref
    before they must be found again (a pair not among them was farther than d_hat plus its two
    sides' budgets at x_ref)."""

    pairs: Pairs
    x_ref: jax.Array
    budget: jax.Array


class Hooks(NamedTuple):
    """The integrators' self-contact stages (`planar_hooks`)."""

    empty: object
    refresh: object
    respond: object
    bound: object


def planar_hooks(net, sc: SelfContact, material, mass, free, h, accel=0.0) -> Hooks:
    """The integrators' self-contact stages on planar (3, rows, cols) arrays:
    empty(x) -> PairCache that the first refresh replaces; refresh(cache, x, v) -> (cache,
    reach (n,)): the broad phase again (lax.cond), with each node's budget its reach + 2 M (its
    reach alone when that overflows the capacity), only when a node could leave its budget in
    this substep (a resting net keeps its pairs for many substeps); respond(cache, x, v) -> v
    (step 2); bound(cache, reach, x, x1, v1) -> (x1, v1) (step 3, each node also kept within
    its budget of x_ref). respond and bound are checkpointed.
    Shapes: mass, free (rows, cols); x, v (3, rows, cols) -> as described."""
    flat = lambda a: a.reshape(3, -1).T
    back = lambda a: a.T.reshape(3, net.rows, net.cols)
    free_f = free.reshape(-1)
    inv_mass = jnp.where(free_f, 1.0 / jnp.where(free_f, mass.reshape(-1), 1.0), 0.0)
    skin = 2.0 * jax.lax.stop_gradient(max_step(net, sc))
    ng = jax.lax.stop_gradient

    def find(x, budget):
        return PairCache(contact_pairs(net, sc, ng(x), budget), ng(x), budget)

    def build(x, r):  # flat x (n, 3), reach r (n,); without the skin if that overflows
        wide = find(x, ng(r) + skin)
        return jax.lax.cond(wide.pairs.overflow, lambda: find(x, ng(r)), lambda: wide)

    def empty(x):
        xf = ng(flat(x))
        shapes = jax.eval_shape(lambda a: find(a, jnp.zeros(a.shape[:1], a.dtype)), xf)
        zero = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)
        return zero._replace(x_ref=xf, budget=jnp.full(xf.shape[:1], -1.0, xf.dtype))

    def refresh(cache, x, v):
        xf = flat(x)
        r = reach(net, sc, flat(v), h, accel)
        moved = safe_norm(ng(xf) - cache.x_ref)
        stale = jnp.any(moved + ng(r) > cache.budget)
        return jax.lax.cond(stale, lambda: build(xf, r), lambda: cache), r

    def react(cache, x, v):
        p = cache.pairs
        return back(respond(net, sc, p, flat(x), flat(v), inv_mass, material.friction, h))

    def bound(cache, r, x, x1, v1):
        xf = flat(x)
        room = jnp.maximum(cache.budget - safe_norm(ng(xf) - cache.x_ref), 0.0)
        cap = jnp.minimum(r, room)
        x2, v2 = filter_step(cache.pairs, xf, flat(x1), flat(v1), cap, free_f, h)
        return back(x2), back(v2)

    ck = lambda f: jax.checkpoint(f, prevent_cse=False)
    return Hooks(empty, refresh, ck(react), ck(bound))
