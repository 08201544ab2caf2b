"""Silhouette search (raster step 4): pixel pairs showing different surfaces, the walk across
internal edges to the first silhouette edge, and its differentiable crossing fraction."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth._math import materialize, materialize_grad, materialize_value, safe_div
from diffcloth.render.coverage import edge_coverage, pair_share
from diffcloth.render.raster.buffers import BACKGROUND_DEPTH
from diffcloth.render.raster.scan import _batch_max, _compact, _ranks
from diffcloth.render.raster.triangle_setup import _Setup, setup_table

_STEPS = ((1, 0), (-1, 0), (0, 1), (0, -1))  # +x, -x, +y, -y


def _silhouette(s: _Setup, neighbors):
    """(m, 3) bool: edge k of triangle is a silhouette (boundary, or neighbour culled/turned)."""
    nb = jnp.maximum(neighbors, 0)
    return (neighbors < 0) | ~s.valid[nb] | (s.front[nb] != s.front[:, None])


def _reach(s: _Setup, neighbors, walk: int):
    """(m, 3) silhouette flags and (m,) bool: a silhouette edge lies on the triangle or on one
    reachable from it across at most `walk` internal (non-silhouette) edges.

    A dilation over the neighbour columns, each step materialized (fused, XLA recomputed the
    earlier steps inside each later one). Crossing a silhouette edge needs no mask: a triangle
    with one is reached from the start, and so is one with a boundary edge (neighbour -1)."""
    silm = _silhouette(s, neighbors)
    nb = [materialize(jnp.maximum(neighbors[:, k], 0)) for k in range(3)]
    reach = materialize(silm[:, 0] | silm[:, 1] | silm[:, 2])
    for _ in range(walk):
        reach = materialize(reach | reach[nb[0]] | reach[nb[1]] | reach[nb[2]])
    return silm, reach


def _walk(s: _Setup, sil, nbr, start, active, a_front, vertical, px, py, walk: int):
    """`_search`'s walk, without gradient: (found, sel) per pair, sel the flat index
    3 * triangle + k of the silhouette edge found (0 where none is).

    The walk+1 levels loop over one int32 state per pair (c >= 0: the triangle being crossed;
    -1: stopped without a silhouette; -2 - sel: found edge sel): a level is one or two fusions
    (four carries ran about nine small fusions per level; unrolled, XLA's fusion recomputes
    the levels' chains inside each other)."""
    dtype = s.edge.dtype
    table = jax.lax.stop_gradient(setup_table(s))  # origin at 12, 13
    # the triangle across each flat edge, -1 where the edge is a silhouette (the walk stops)
    nxt = materialize(jnp.where(sil, -1, nbr).astype(jnp.int32))
    one = jnp.ones((), dtype)
    ux = jnp.where(vertical, 0.0, one)
    uy = jnp.where(vertical, one, 0.0)
    sx = px + jnp.where(a_front, 0.0, ux)  # front pixel centre
    sy = py + jnp.where(a_front, 0.0, uy)
    sgn = jnp.where(a_front, one, -one)
    dx, dy = sgn * ux, sgn * uy  # direction from front to back
    shape = jnp.broadcast_shapes(start.shape, sx.shape)

    def level(c):
        cur = jnp.maximum(c, 0)
        tab = table[cur]  # (..., 14)
        lx, ly = sx - tab[..., 12], sy - tab[..., 13]
        best = jnp.full(shape, jnp.inf, dtype)
        k = jnp.zeros(shape, jnp.int32)
        for j in range(3):
            a, b, e = tab[..., 3 * j], tab[..., 3 * j + 1], tab[..., 3 * j + 2]
            ef = a * lx + b * ly + e
            slope = dx * a + dy * b
            ex = (ef + slope < 0) & (slope < 0)
            root = jnp.where(ex, ef / jnp.where(ex, -slope, 1.0), jnp.inf)
            better = root < best
            best = jnp.where(better, root, best)
            k = jnp.where(better, j, k)
        idx = cur * 3 + k
        n = nxt[idx]
        step = jnp.where(best < jnp.inf, jnp.where(n < 0, -2 - idx, n), -1)
        return jnp.where(c < 0, c, step)

    c = jnp.where(active, jnp.maximum(start, 0), -1).astype(jnp.int32)
    c = jax.lax.fori_loop(0, walk + 1, lambda _, c: level(c), c)
    found = c <= -2
    return found, jnp.where(found, -2 - c, 0)


@jax.checkpoint
def _edge_crossing(s: _Setup, found, sel, a_front, vertical, px, py):
    """`_search`'s differentiable crossing (t, k, share) of the edges `sel` found by `_walk`.
    Recomputed in the backward pass (jax.checkpoint: cheap elementwise work), so that its only
    residuals are its inputs: inside `_crossings`' lax.switch every branch returns the union of
    all branches' residuals, zero-filled in the branches not taken."""
    m = s.edge.shape[0]
    dtype = s.edge.dtype
    one = jnp.ones((), dtype)
    ux = jnp.where(vertical, 0.0, one)
    uy = jnp.where(vertical, one, 0.0)
    sx = px + jnp.where(a_front, 0.0, ux)
    sy = py + jnp.where(a_front, 0.0, uy)
    sgn = jnp.where(a_front, one, -one)
    dx, dy = sgn * ux, sgn * uy
    r = s.edge.reshape(m * 3, 3)[sel]  # (..., 3) differentiable row of the edge found
    o = s.origin[sel // 3]
    ef = r[..., 0] * (sx - o[..., 0]) + r[..., 1] * (sy - o[..., 1]) + r[..., 2]
    slope = -(dx * r[..., 0] + dy * r[..., 1])
    # the edge's normal along / across the pair direction: its slope k relative to the pair (0:
    # perpendicular), for `edge_coverage`, and this direction's share of the edge (`pair_share`:
    # near 45 degrees both directions blend, so the image does not jump as the edge turns)
    along, across = jnp.abs(r[..., 0]), jnp.abs(r[..., 1])
    along, across = jnp.where(vertical, across, along), jnp.where(vertical, along, across)
    share = pair_share(along, across)
    found = found & (jax.lax.stop_gradient(share) > 0)
    t = jnp.where(found, jnp.clip(safe_div(ef, jnp.where(found, slope, 1.0)), 0.0, 1.0), -1.0)
    k = jnp.where(found, jnp.clip(safe_div(across, jnp.where(found, along, 1.0)), 0.0, 1.0), 0.0)
    share = jnp.where(found, share, 0.0)
    # the crossing's cotangents are computed once per pair (materialize_grad): otherwise XLA's
    # CPU fusion recomputes the whole weight and coverage backward chain (and this function's
    # rematerialized forward) for each of the 3 components of the edge row's cotangent (main
    # job's 64^2 full search: that fusion 30 -> 4.3 ms of thunk time, render gradient 0.74x CPU)
    t, k, share = materialize_grad(t), materialize_grad(k), materialize_grad(share)
    # each weight computed in a loop fusion of its own (its value materialized; derivatives
    # untouched): concatenated for the scatter, the chain ran as one branch per entry
    w_a, w_b = _pair_weights(t, k, share, a_front)
    return (t, k, share, materialize_value(w_a), materialize_value(w_b))


def _pair_weights(t, k, share, a_front):
    """`antialias` weights of a pixel pair (a, b) from its crossing (t, k, share) (t < 0: none):
    (w_a, w_b), a's move toward b's colour and b's toward a's. The front pixel moves toward the
    back colour by its uncovered area 1 - A(t), the back pixel toward the front colour by its
    covered area A(t - 1), A the exact coverage by the straight edge of slope k
    (`edge_coverage`; k = 0 gives nvdiffrast's 1/2 - t on the front pixel when t < 1/2, else
    t - 1/2 on the back one); both scaled by this pair direction's share of the edge."""
    ok = jax.lax.stop_gradient(t) >= 0
    wf = jnp.where(ok, share * (1.0 - edge_coverage(t, k)), 0.0)
    wb = jnp.where(ok, share * edge_coverage(t - 1.0, k), 0.0)
    return jnp.where(a_front, wf, wb), jnp.where(a_front, wb, wf)


def _search(s: _Setup, sil, nbr, start, active, a_front, vertical, px, py, walk: int):
    """Silhouette crossing for pixel pairs given as arrays of any (common) shape.

    start: front triangle; active: search here; a_front: the first pixel of the pair (at (px,
    py)) is the nearer one; vertical: the partner is below (else to the right). Returns the
    fraction t in [0, 1] from the front pixel's centre toward the back one's where the silhouette
    edge is crossed (differentiable), -1 where none is found or the edge belongs to the other
    pair direction; the edge's slope k in [0, 1] relative to the pair direction (0 where none);
    this pair direction's share of the edge (`pair_share`, 0 where none); and the pair's
    antialiasing weights (w_a, w_b) (`_pair_weights`).
    """
    found, sel = _walk(s, sil, nbr, start, active, a_front, vertical, px, py, walk)
    return _edge_crossing(s, found, sel, a_front, vertical, px, py)


def _chunked_walk(s: _Setup, sil, nbr, start, active, a_front, X, Y, walk: int):
    """`_walk` of the full-image search over (2, H, W) pairs, run on the active pairs only:
    compacted into lists of H W / 4 pairs, walked one list after another (a while loop; one
    list for every frame of the main job, whose 64^2 images need at most 651 of 8,192 pairs)
    and scattered back. Returns (found, sel) (2, H, W), the values `_walk` gives on the dense
    pairs (each pair's walk is independent). No gradient."""
    H, W = X.shape
    n = 2 * H * W
    size = max(H * W // 4, 1)
    flags = active.reshape(-1)
    rank = _ranks(flags)
    count = jnp.sum(flags.astype(jnp.int32))
    s = jax.tree_util.tree_map(jax.lax.stop_gradient, s)
    start_f, front_f = start.reshape(-1), a_front.reshape(-1)
    entry = jnp.arange(n, dtype=jnp.int32)

    def body(carry):
        off, found, sel = carry
        slot = rank - off
        here = flags & (slot >= 0) & (slot < size)
        idx = jnp.zeros((size,), jnp.int32).at[jnp.where(here, slot, size)].set(entry, mode="drop")
        act = jnp.arange(size, dtype=jnp.int32) < count - off
        rem = idx % (H * W)
        py, px = (rem // W).astype(X.dtype), (rem % W).astype(X.dtype)
        f, e = _walk(s, sil, nbr, start_f[idx], act, front_f[idx], idx >= H * W, px, py, walk)
        at = jnp.where(act, idx, n)
        found = found.at[at].set(f, mode="drop")
        sel = sel.at[at].set(e, mode="drop")
        return off + size, found, sel

    init = (jnp.zeros((), jnp.int32), jnp.zeros((n,), bool), jnp.zeros((n,), jnp.int32))
    _, found, sel = jax.lax.while_loop(lambda c: c[0] < count, body, init)
    return found.reshape(2, H, W), sel.reshape(2, H, W)


def default_silhouette_budget(width: int, height: int) -> int:
    """Default size of the compacted silhouette-pair list: H W / 16 (with walk 8 the Mitsuba
    benchmark drape needs H W / 21 at 256 x 256; the wavy cloth of benchmarks/render.py, H W / 11,
    takes the second list of 4 x the budget); below 128 x 128 pixels the full-image search
    (budget 2 H W), whose walk runs on the active pairs only (`_chunked_walk`) and whose
    differentiable crossing on a list of the found ones (H W / 4, every pair beyond): one copy
    of the walk compiled instead of three (also for a batch: see `visibility.window_budgets`;
    the main job's 64^2 frames need at most 651 of 8,192 pairs).

    Shapes: none (Python ints).
    """
    n = width * height
    return int(n // 16) if n >= 128 * 128 else int(2 * n)


def _pairs(s: _Setup, tri, ok, depth, neighbors, walk: int):
    """Neighbouring pixel pairs (partner to the right: [0], below: [1]), (2, H, W) each, to search
    for a silhouette: they show different triangles and the front one has a silhouette edge
    within `walk` internal edges. Returns the flat silhouette-edge flags and neighbour table and
    the front triangle, search flag and "this pixel is the nearer one" per pair."""
    H, W = tri.shape
    silm, reach = _reach(s, neighbors, walk)
    sil = materialize(silm.reshape(-1))
    reach = materialize(reach)
    nbr = jnp.maximum(neighbors, 0).reshape(-1)
    ids = jnp.where(ok, tri, -1)
    big = jnp.asarray(BACKGROUND_DEPTH, depth.dtype)
    ids_n = jnp.stack(
        [
            jnp.pad(ids[:, 1:], ((0, 0), (0, 1)), constant_values=-1),
            jnp.pad(ids[1:], ((0, 1), (0, 0)), constant_values=-1),
        ]
    )
    dep_n = jnp.stack(
        [
            jnp.pad(depth[:, 1:], ((0, 0), (0, 1)), constant_values=big),
            jnp.pad(depth[1:], ((0, 1), (0, 0)), constant_values=big),
        ]
    )
    a_front = depth[None] < dep_n  # the pixel itself is the nearer one
    start = jnp.where(a_front, ids[None], ids_n)
    # (pairs with the partner outside the image have ids_n = -1 but are excluded by `inner`)
    inner = jnp.stack(
        [jnp.ones((H, W), bool).at[:, -1].set(False), jnp.ones((H, W), bool).at[-1].set(False)]
    )
    # the front triangle's reach, looked up once per pixel (materialized; per pair it was a
    # gather of its own) and read from the pair's front pixel
    here = materialize(ok & reach[tri])
    here_n = jnp.stack(
        [jnp.pad(here[:, 1:], ((0, 0), (0, 1))), jnp.pad(here[1:], ((0, 1), (0, 0)))]
    )
    active = (ids[None] != ids_n) & inner & jnp.where(a_front, here[None], here_n)
    return sil, nbr, start, active, a_front


def _crossings(
    s: _Setup, tri, ok, depth, X, Y, neighbors, walk: int, budget: int | None, batch_axes=()
):
    """Silhouette crossings (H, W, 12) and antialiasing weights (4, H, W).

    Crossings: fraction toward the (+x, -x, +y, -y) neighbour's centre where the surface's
    silhouette lies, set only on the nearer pixel of each neighbouring pair showing different
    triangles (-1 elsewhere), then the slopes of those edges and the pair direction's share of
    each (0 elsewhere). Weights: `antialias_weights` of these crossings, computed per searched
    pair (a consumer that reads only the weights, as `antialias` does, never builds the
    per-pixel crossings: jit removes them).

    Walks from the front pixel's triangle across internal edges (up to `walk` further triangles)
    along the segment to the neighbour's centre and stops at the first silhouette edge. Only
    pairs whose front triangle has a silhouette edge within reach are searched; they are
    compacted into a static list of `budget` pairs, or of 4 `budget` pairs when more need it (a
    full-image search runs beyond that; with a budget of at least 2 H W, the default below
    128 x 128, the full search walks the active pairs in compacted chunks, `_chunked_walk`).
    The search has no gradient; the crossing of the edge found is recomputed differentiably.
    """
    H, W = tri.shape
    n = 2 * H * W
    sil, nbr, start, active, a_front = _pairs(s, tri, ok, depth, neighbors, walk)
    vertical = jnp.arange(2)[:, None, None] == 1

    def dense(t, k, share, w_a, w_b):
        # w_a on the pair's first pixel (+x / +y slot), w_b on its partner (-x / -y slot)
        weights = jnp.stack(
            [
                w_a[0],
                jnp.pad(w_b[0, :, :-1], ((0, 0), (1, 0))),
                w_a[1],
                jnp.pad(w_b[1, :-1], ((1, 0), (0, 0))),
            ]
        )
        return t, k, share, weights

    def full(_):
        return dense(
            *_search(s, sil, nbr, start, active, a_front, vertical, X[None], Y[None], walk)
        )

    def spread(idx, act, vert, t, k, share, w_a, w_b):
        """A compacted list's crossings and weights (K,) -> dense (2, H, W) / (4, H, W)."""
        K = idx.shape[0]
        at = jnp.where(act, idx, n)
        out = jnp.full((n,), -1.0, t.dtype).at[at].set(t, mode="drop")
        out_k = jnp.zeros((n,), k.dtype).at[at].set(k, mode="drop")
        out_s = jnp.zeros((n,), share.dtype).at[at].set(share, mode="drop")
        # weights (4, H, W) flat: w_a at slot 2 d of the pixel, w_b at slot 2 d + 1 of the
        # partner; unused entries go to distinct indices past the end (dropped), so the indices
        # are unique: the scatter's derivative is then a plain scatter / gather (otherwise JAX
        # scatters entry ids to find which duplicate wins: fwd + bwd 256^2 0.9x). Two scatter-adds
        # on disjoint slots (their transposes are gathers), not one of the concatenated pair:
        # XLA's CPU backend evaluates a concatenate entry by entry, here with the whole crossing
        # and coverage chain inlined (0.35 ms of the 256^2 forward)
        past = 2 * n + jnp.arange(K, dtype=idx.dtype)
        wa_at = jnp.where(act, idx + vert * (H * W), past)
        wb_at = jnp.where(act, idx + (vert + 1) * (H * W) + jnp.where(vert, W, 1), past)
        weights = jnp.zeros((2 * n,), w_a.dtype)
        for at, w in ((wa_at, w_a), (wb_at, w_b)):
            weights = weights.at[at].add(w, mode="drop", unique_indices=True)
        dense = (out.reshape(2, H, W), out_k.reshape(2, H, W), out_s.reshape(2, H, W))
        return dense + (weights.reshape(4, H, W),)

    def listed(flags, K):
        """The first K flagged pairs: (idx, act, vert, px, py)."""
        idx, act = _compact(flags.reshape(-1), K)
        rem = idx % (H * W)
        py = (rem // W).astype(depth.dtype)
        px = (rem % W).astype(depth.dtype)
        return idx, act, idx >= H * W, px, py

    def compact(K):
        idx, act, vert, px, py = listed(active, K)
        start_k, front_k = start.reshape(-1)[idx], a_front.reshape(-1)[idx]
        crossing = _search(s, sil, nbr, start_k, act, front_k, vert, px, py, walk)
        return spread(idx, act, vert, *crossing)

    K = n if budget is None else min(int(budget), n)
    # compacted lists of K and 4 K pairs (a frame whose silhouettes need more than K pairs,
    # e.g. walk 8 on a cloth seen at a grazing angle, stays far below the full search's cost)
    sizes = [b for b in (K, 4 * K) if b < n]
    if not sizes:
        # full search (small images): the walk runs on the active pairs only (`_chunked_walk`,
        # one copy of it compiled); the differentiable crossing on a list of the found pairs
        # (H W / 4 of them), or on every pair when more are found (one lax.switch over the
        # crossing alone: its backward over all 2 H W pairs cost the main job's render gradient
        # about a fifth, the search in full 8 levels of gathers over every pair)
        found, sel = _chunked_walk(s, sil, nbr, start, active, a_front, X, Y, walk)
        Kf = max(H * W // 4, 1)

        def found_list(_):
            idx, act, vert, px, py = listed(found, Kf)
            sel_k, front_k = sel.reshape(-1)[idx], a_front.reshape(-1)[idx]
            return spread(idx, act, vert, *_edge_crossing(s, act, sel_k, front_k, vert, px, py))

        def every_pair(_):
            return dense(*_edge_crossing(s, found, sel, a_front, vertical, X[None], Y[None]))

        level = _batch_max((jnp.sum(found) > Kf).astype(jnp.int32), batch_axes)
        t, k, share, weights = jax.lax.switch(level, [found_list, every_pair], None)
    else:
        level = _batch_max(jnp.sum(jnp.sum(active) > jnp.asarray(sizes)), batch_axes)
        branches = [lambda _, b=b: compact(b) for b in sizes] + [full]
        t, k, share, weights = jax.lax.switch(level, branches, None)

    def slots(v, none):
        v_a = jnp.where(a_front, v, none)  # stored on this pixel (+x / +y slot)
        v_b = jnp.where(a_front, none, v)  # stored on the partner (-x / -y slot)
        minus_x = jnp.pad(v_b[0, :, :-1], ((0, 0), (1, 0)), constant_values=none)
        minus_y = jnp.pad(v_b[1, :-1], ((1, 0), (0, 0)), constant_values=none)
        return [v_a[0], minus_x, v_a[1], minus_y]

    cross = jnp.stack(slots(t, -1.0) + slots(k, 0.0) + slots(share, 0.0), axis=-1)
    return cross, weights
