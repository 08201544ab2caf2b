"""Differentiable triangle rasterizer with analytic silhouette antialiasing (nvdiffrast-style).

Pipeline (everything pure JAX; jit, vmap and grad work; no Python loops over pixels/triangles):

1. Setup, per triangle: screen-space homogeneous vertex columns c_k = (x_pix * w, y_pix * w, w)
   (pixel units, pixel centre (j, i) at (j, i), row 0 at the top). The adjugate rows
   E_k = sign(det) (c_{k+1} x c_{k+2}) are the homogeneous edge functions: at pixel p = (x, y, 1)
   e = E p is >= 0 in all three components exactly where the triangle covers p *in front of the
   eye* (Olano & Greer's clipless 2-D homogeneous rasterization), and e / sum(e) are the
   perspective-correct barycentrics. So no near-plane clipping and no divide by w is needed:
   triangles crossing the near plane or the eye plane are drawn where they are in front of the near
   plane (pixels whose interpolated view depth is < near or > far are rejected) and nothing behind
   the camera shows. Zero-area / edge-on triangles (|det| tiny relative to the vertex scale) are
   skipped before anything is divided.
2. Visibility (no gradient): a triangle whose clamped screen bounding box holds at most
   DIRECT_PIXELS (2) pixel centres (nearly every cloth triangle: sub-pixel at 256 x 256) is
   tested at those pixels directly, per triangle, without any allocation. Larger triangles get
   tile_size x tile_size pixel windows covering their box, allocated by a prefix sum from a
   static budget: the smallest of `window_budgets` (1/4 or 1 screen of windows, else
   `max_tiles`, default: triangles + 2 full screens of windows) that holds the frame's
   windows (lax.switch; under a vmap whose axes are named in `batch_axes` the smallest that
   holds every image's windows, pmax over the batch, else every budget runs; below 128 x 128
   only `max_tiles`). `.at[].min` scatters the candidates' depths into a
   z-buffer, and a second `.at[].max` scatter of the triangle id among candidates that equal
   the z-buffer depth resolves the id (ties: larger id). The bounding box of a triangle
   crossing the near plane is that of its part in front of it (vertices and edge/near-plane
   intersections). Windows beyond the budget are dropped (`required_tiles` tells how many a
   scene needs).
3. Differentiable resolve: with the visible triangle per pixel fixed, barycentrics and depth are
   recomputed from the positions, so attributes interpolate with gradients w.r.t. attributes and
   vertex positions (interior gradients).
4. Silhouette gradients (`antialias`): for every horizontal / vertical pair of neighbouring pixels
   that show different surfaces, the nearer pixel's triangle edge crossing the segment between the
   centres is found (fraction t of the way, from the linear edge functions); if that edge is a
   silhouette (boundary edge, or its neighbour faces the other way or is culled) and is more
   perpendicular to this pair's direction than to the other one, both pixels are blended by
   their exact box-filter coverage by that straight edge (its slope k relative to the pair:
   `coverage.edge_coverage`; k = 0 is nvdiffrast's |t - 1/2| on one pixel). The blended image's
   coverage then equals the true pixel area covered by a straight edge, so d(image)/d(vertex)
   is the derivative of the area; as pixels shrink the image converges to the hard image.
   Edges between triangles of one surface are not blended. Limitation: silhouettes made of
   triangles that cover no pixel centre get no gradient there (as in nvdiffrast).

Design choices, measured (benchmarks/render.py: the seed's 11,830-vertex / 23,220-triangle
cloth, float32, shared 2-core CPU under heavy load, so upper bounds): direct tests for boxes
of <= 2 pixel centres (19,887 of the 23,220 triangles of the draped seed cloth of
benchmarks/peers/mitsuba_render.py at 256 x 256 hold 0-2; the rest need
1,981 2 x 2 windows, against 19,866 windows = 79,464 candidates when every triangle took
windows, evaluated from a 55,988-window budget): visibility 3.6 -> 1.5 ms;
silhouette_walk 8 (1 found 97% of a flat cloth's boundary crossings, but near a contour
seen at a grazing angle the foreshortened triangles are slivers: on the Mitsuba agreement drape at
128 x 128, walk 1 / 2 / 4 / 8 gave a cloth-mask IoU of 0.980 / 0.985 / 0.985 / 0.988; the
compacted search keeps the cost: 891 of the 1,024-pair budget at 128^2, 3,327 of 4,096 at 256^2
on the seed cloth). Pair weights are the exact box-filter coverage of a straight edge of the
found slope (`coverage.edge_coverage`; nvdiffrast's |t - 1/2| is its perpendicular case).
The silhouette search runs only on pairs whose front triangle has a silhouette
edge within reach (1,616 of 131,072 pairs at 256 x 256, 4,249 of 524,288 at 512 x 512),
compacted by a log-depth scan into a static list (`silhouette_budget`, H W / 16), a second
one of 4 x that size and a full-image fallback, chosen by lax.switch (one for the whole batch
under named vmap axes, as for the windows; not below 128 x 128) (the wavy cloth of
benchmarks/render.py needs 6,139 pairs at 256 x 256 with walk 8: it ran the full search, now
the second list: forward 0.31x, forward + backward 0.67x). Per-triangle tables are
materialized (a scatter) before per-pixel gathers: XLA's CPU fusion otherwise recomputes them
for every pixel. A/B against the previous version, same process, CPU time per call (median /
min, load ~14): 256 x 256 forward 43 / 34 -> 20 / 18 ms, forward + backward 55 / 52 -> 36 / 33 ms;
512 x 512 forward 241 / 195 -> 98 / 87 ms, forward + backward 317 / 260 -> 190 / 154 ms. Images identical.
The antialiasing weights are computed per searched pair in the compact list and scattered into
(4, H, W) (`Fragments.weights`; `antialias` reads them, so jit drops the per-pixel crossings);
the walk keeps one int32 state per pair; `_compact` ranks by word popcounts; the setup is two
materialized tables. A/B against the previous version, same process, 256 x 256 Mitsuba drape,
30 interleaved rounds on the loaded 2-core machine: forward 0.81x (median; min 0.72x, CPU time
0.83x), forward + backward 0.73x (min 0.72x, CPU 0.74x). Images and gradients bitwise equal.
"""

# ruff: noqa: F401  (re-exports: every name stays importable from diffcloth.render.raster)
from diffcloth.render.raster.buffers import BACKGROUND_DEPTH, Fragments, GBuffer
from diffcloth.render.raster.gbuffer import (
    antialias,
    antialias_weights,
    composite,
    rasterize_gbuffer,
    render_mesh,
)
from diffcloth.render.raster.resolve import _resolve, interpolate, rasterize, silhouette_pairs
from diffcloth.render.raster.scan import _compact, _cummax, _cumsum
from diffcloth.render.raster.silhouette import (
    _STEPS,
    _crossings,
    _edge_crossing,
    _pair_weights,
    _pairs,
    _reach,
    _search,
    _silhouette,
    _walk,
    default_silhouette_budget,
)
from diffcloth.render.raster.topology import _edge_neighbors_jnp, edge_neighbors
from diffcloth.render.raster.triangle_setup import (
    DIRECT_PIXELS,
    _cross,
    _Setup,
    _setup,
    _tile_counts,
    _vertex_table,
    default_max_tiles,
    required_tiles,
)
from diffcloth.render.raster.visibility import (
    _candidate_depth,
    _visibility,
    _windows,
    window_budgets,
)
