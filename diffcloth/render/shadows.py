"""Differentiable soft shadows: analytic sphere occlusion plus a triangle-mesh shadow map per light.

Two kinds of occluder, each with the method that suits it (see docs/shading.md, "Shadows"):

* Spheres (analytic, exact silhouettes): seen from a lit point p, a sphere (centre c, radius r)
  covers a disc of angular radius alpha = atan(r / sqrt(|c - p|^2 - r^2)) at angle beta from the
  light, and the light is a disc of angular radius theta (its `softness`). The occluded fraction
  of the light is approximated by min(alpha, theta)^2 / theta^2 * S(x), S the C1 smoothstep and
  x = (alpha + theta - beta) / (2 min(alpha, theta)): 0 where the discs just touch
  (beta = alpha + theta), full where the smaller disc lies inside the larger
  (beta = |alpha - theta|). Smooth in p, c, r and the light, with no shadow map and no bias.
* Triangle meshes (the cloth; box bodies as triangles): a shadow map rasterized from the light with
  the ordinary rasterizer (orthographic along a directional light, perspective from a point light,
  fitted to the occluder's bounding sphere). Each texel stores premultiplied (coverage * depth,
  coverage), antialiased by `raster.antialias`, so texels on the occluder's silhouette carry
  fractional coverage with gradients w.r.t. the edge position. A receiver looks the map up with
  percentage-closer filtering: a blocker search (taps over the region the light's disc can
  reach) estimates the mean blocker depth d_b, the penumbra radius is tan(theta) (z - d_b)
  (percentage-closer soft shadows), and K x K bilinear taps over it each count
  coverage * smoothstep((z - bias - depth) / tau): a smooth depth test, so gradients flow to the
  receiver and occluder depths too. Self-shadowing acne is removed by a normal offset of one texel
  plus a slope-scaled depth bias.

The visibility of light l at a point is V_mesh * prod_spheres V_sphere (in [0, 1]); the shaders
multiply every light's radiance by it (diffuse and specular: a Lambertian point in full shadow gets
only the ambient term). Lights without `shadows` keep V = 1, and with no shadow-casting light
nothing here runs (images bitwise equal to the unshadowed renderer).
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import (
    fast_atan2,
    materialize,
    materialize_grad,
    safe_div,
    safe_norm,
    safe_normalize,
    safe_sqrt,
)
from diffcloth.render.camera import Camera, look_at, orthographic, perspective
from diffcloth.render.grid_coarse import on_coarse_grid
from diffcloth.render.lights import Lights
from diffcloth.render.raster import antialias, edge_neighbors, rasterize
from diffcloth.shapes import Sphere

#: receiver offset along its (light-facing) normal, in shadow-map texels
NORMAL_OFFSET = 1.0
#: constant depth bias, in texels (of world size at the receiver)
DEPTH_BIAS = 1.0
#: width of the smooth depth test above the bias, in texels
DEPTH_SOFTNESS = 1.0
#: slope-scaled bias is capped at this tan(angle between normal and light)
MAX_SLOPE = 8.0
#: largest filter radius in texels (wider penumbrae are clamped)
MAX_RADIUS = 12.0


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ShadowMaps:
    """Everything a receiver needs to look up its visibility for one frame.

    Attributes:
      lights: the lights (softness, directions, positions).
      spheres: analytic sphere occluders (batched) or None.
      maps: (k, S, S, 2) premultiplied (coverage * view depth, coverage) from each shadow-casting
        light's camera (k = shadow-casting lights, directional first), or None without a mesh.
      view, projection: (k, 4, 4) the light cameras.
      texel: (k,) world size of a texel: orthographic, in m; perspective, in m per m of depth.
      zmin: (k,) smallest occluder view depth (blocker-search extent).
      casting: static tuple of the light indices (0..nl-1, directional first) that cast shadows.
      num_directional: static count of the casting lights that are directional (the first ones).
      size: static shadow-map size S in texels.
      taps: static filter taps per axis of the lookups (`shadow_visibility`); 1: one bilinear
        tap (no blocker search, penumbra about a texel wide), the fast setting.
      fast: static; the sphere discs' angles from `_math.fast_atan2` (a polynomial) instead of
        XLA's atan2 (a scalar library call: most of the lookup's cost on the CPU).
      layer_stride: static; f > 1: the ray-cast layers (spheres, planes) look up their
        visibility once per f x f pixel block, upsampled bilinearly (`layer_shadow_visibility`).
      per_vertex: static; the cloth's visibility is looked up at its vertices and interpolated
        by the rasterizer (`frame.surface_gbuffer`) instead of at every pixel (the "fit"
        preset: the lookup is independent of the normal's sign, so one value serves both
        sides).
    """

    lights: Lights
    spheres: Sphere | None
    maps: jax.Array | None
    view: jax.Array | None
    projection: jax.Array | None
    texel: jax.Array | None
    zmin: jax.Array | None
    casting: tuple = dataclasses.field(metadata={"static": True})
    num_directional: int = dataclasses.field(metadata={"static": True})
    size: int = dataclasses.field(metadata={"static": True})
    taps: int = dataclasses.field(default=4, metadata={"static": True})
    fast: bool = dataclasses.field(default=False, metadata={"static": True})
    layer_stride: int = dataclasses.field(default=1, metadata={"static": True})
    per_vertex: bool = dataclasses.field(default=False, metadata={"static": True})


def _smoothstep(x):
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _bound(positions):
    """Bounding sphere (centre (3,), radius ()) of a point set. Differentiable (a.e.): the map's
    framing is part of the sampled function, so its derivative belongs to the true gradient."""
    p = positions
    lo, hi = jnp.min(p, axis=0), jnp.max(p, axis=0)
    c = 0.5 * (lo + hi)
    r = jnp.max(safe_norm(p - c[None], axis=-1))
    return c, 1.02 * r + 1e-3


def _up_for(d):
    """An up vector not parallel to d (3,)."""
    y = jnp.asarray([0.0, 1.0, 0.0], d.dtype)
    x = jnp.asarray([1.0, 0.0, 0.0], d.dtype)
    return jnp.where(jnp.abs(d[1]) < 0.9, y, x)


def _directional_camera(direction, center, radius, size):
    l = safe_normalize(direction)
    eye = center + 2.0 * radius * l
    view = look_at(eye, center, _up_for(l))
    proj = orthographic(-radius, radius, -radius, radius, 0.5 * radius, 3.5 * radius)
    cam = Camera(view, proj, 0.5 * radius, 3.5 * radius, size, size, "orthographic")
    return cam, 2.0 * radius / size


def _point_camera(position, center, radius, size):
    to_c = center - position
    dist = safe_norm(to_c)
    half = jnp.arcsin(jnp.clip(radius / jnp.maximum(dist, 1e-9), 0.0, 0.96)) * 1.05
    half = jnp.minimum(half, jnp.deg2rad(75.0))
    near = jnp.maximum(dist - radius, 0.02 * dist) * 0.9
    far = dist + 1.5 * radius
    view = look_at(position, position + to_c, _up_for(safe_normalize(to_c)))
    proj = perspective(jnp.rad2deg(2.0 * half), 1.0, near, far)
    cam = Camera(view, proj, near, far, size, size, "perspective")
    return cam, 2.0 * jnp.tan(half) / size


def _render_map(positions, faces, neighbors, cam):
    """(S, S, 2) antialiased premultiplied (coverage * depth, coverage) and the min depth."""
    fr = rasterize(positions, faces, cam, neighbors=neighbors, silhouette_budget=None)
    cov = fr.triangle_id >= 0
    img = jnp.stack([jnp.where(cov, fr.depth, 0.0), cov.astype(fr.depth.dtype)], axis=-1)
    zmin = jnp.min(jnp.where(cov, fr.depth, jnp.inf))
    zmin = jnp.where(jnp.isfinite(zmin), zmin, 0.0)
    return antialias(img, fr), zmin


def shadow_maps(
    lights: Lights,
    *,
    mesh=None,
    spheres: Sphere | None = None,
    size: int = 256,
    taps: int = 4,
    fast: bool = False,
    layer_stride: int = 1,
    per_vertex: bool = False,
) -> ShadowMaps | None:
    """Build the per-frame shadow data of every shadow-casting light.

    Args:
      lights: Lights with `shadows` flags (None is returned when no light casts shadows).
      mesh: optional occluder triangle mesh: (positions (n, 3), faces (m, 3)) or
        (positions, faces, neighbors (m, 3) from `raster.edge_neighbors`); the cloth, with box
        bodies' triangles appended. Differentiable in the positions.
      spheres: optional analytic sphere occluders; differentiable.
      size: static shadow-map size in texels (maps cover the mesh's bounding sphere).
      taps: static filter taps per axis of every lookup of these maps (see `shadow_visibility`).
      fast: static; polynomial arctangents in the sphere occlusion (`ShadowMaps.fast`).
      layer_stride: static; `ShadowMaps.layer_stride`.
      per_vertex: static; `ShadowMaps.per_vertex`.
    Returns:
      ShadowMaps, or None when no light casts shadows.
    """
    if not lights.casts_shadows:
        return None
    nd = lights.direction.shape[0]
    nl = nd + lights.point_position.shape[0]
    if len(lights.shadows) != nl:
        raise ValueError(
            f"lights.shadows must hold {nl} flags (one per light), got {lights.shadows}"
        )
    if not isinstance(size, int | np.integer) or size < 8:
        raise ValueError(f"shadow map size must be an int >= 8, got {size!r}")
    if not isinstance(taps, int | np.integer) or not 1 <= taps <= 8:
        raise ValueError(f"shadow taps must be an int in [1, 8], got {taps!r}")
    casting = tuple(i for i, f in enumerate(lights.shadows) if f)
    n_dir = sum(1 for i in casting if i < nd)
    sph = spheres.batched() if spheres is not None else None
    settings = (casting, n_dir, int(size), int(taps), fast, int(layer_stride), bool(per_vertex))
    if mesh is None or mesh[1].shape[0] == 0:
        return ShadowMaps(lights, sph, None, None, None, None, None, *settings)
    positions, faces = mesh[0], jnp.asarray(mesh[1]).astype(jnp.int32)
    neighbors = mesh[2] if len(mesh) > 2 and mesh[2] is not None else edge_neighbors(faces)
    center, radius = _bound(positions)
    # one camera per casting light: orthographic along a directional light, perspective from a
    # point light; both are plain matrices, so one lax.map rasterizes every map (one compiled
    # rasterizer whatever the light mix)
    cams, texels = [], []
    dir_idx = [i for i in casting if i < nd]
    pt_idx = [i - nd for i in casting if i >= nd]
    if dir_idx:
        c, t = jax.vmap(lambda d: _directional_camera(d, center, radius, int(size)))(
            lights.direction[np.asarray(dir_idx)]
        )
        cams.append(c)
        texels.append(t)
    if pt_idx:
        c, t = jax.vmap(lambda p: _point_camera(p, center, radius, int(size)))(
            lights.point_position[np.asarray(pt_idx)]
        )
        cams.append(c)
        texels.append(t)
    cat = lambda xs: jnp.concatenate(xs, axis=0)
    view = cat([c.view for c in cams])
    proj = cat([c.projection for c in cams])
    near = cat([c.near for c in cams])
    far = cat([c.far for c in cams])
    texel = cat(texels)

    def one(args):
        cam = Camera(*args, int(size), int(size))
        return _render_map(positions, faces, neighbors, cam)

    maps, zmin = jax.lax.map(one, (view, proj, near, far))
    return ShadowMaps(lights, sph, maps, view, proj, texel, zmin, *settings)


def _bilinear(tex, u, v):
    """Sample a (S, S, C) map at continuous texel coordinates (texel (j, i) centre at (j, i));
    zero outside the map. u, v: (...). Returns (..., C).

    One gather per lookup: the map, zero-padded, as a table of each texel's 2 x 2 footprint
    (4 C values a row; XLA's CPU gathers cost about 25 ns a row whatever their width, and the
    backward's scatter-adds likewise). The coordinates are clamped to the padding (where the
    value is 0 with a zero derivative either way)."""
    S, C = tex.shape[0], tex.shape[-1]
    pad = jnp.pad(tex, ((1, 2), (1, 2), (0, 0)))  # texel (j, i) at (j + 1, i + 1)
    quad = jnp.concatenate([pad[:-1, :-1], pad[:-1, 1:], pad[1:, :-1], pad[1:, 1:]], axis=-1)
    u, v = jnp.clip(u, -1.0, float(S)), jnp.clip(v, -1.0, float(S))
    x0, y0 = jnp.floor(u), jnp.floor(v)
    fx, fy = (u - x0)[..., None], (v - y0)[..., None]
    rows = (y0.astype(jnp.int32) + 1) * (S + 2) + (x0.astype(jnp.int32) + 1)
    q = quad.reshape(-1, 4 * C)[materialize(rows)]
    c00, c01, c10, c11 = (q[..., k * C : (k + 1) * C] for k in range(4))
    top = c00 * (1 - fx) + c01 * fx
    bot = c10 * (1 - fx) + c11 * fx
    return top * (1 - fy) + bot * fy


def _grid(k, dtype):
    """(k*k, 2) tap offsets on a regular grid over [-1, 1]^2."""
    t = np.linspace(-1.0, 1.0, k) if k > 1 else np.zeros(1)
    g = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    return jnp.asarray(g, dtype)


def _light_coords(view, proj, points):
    """(N, 4) light-camera (clip x, clip y, clip w, view depth) of points (N, 3): one matrix
    product (its backward two more; per-component sums over the receivers, as `project`
    writes them, became one reduction over all receivers per matrix entry in the backward)."""
    m = proj @ view
    rows = jnp.stack([m[0], m[1], m[3], -view[2]])
    return points @ rows[:, :3].T + rows[None, :, 3]


def _map_visibility(tex, view, proj, texel, zmin, tan_t, is_point, pts, nrm, to_light, taps):
    # is_point: static bool (texel grows with depth under a perspective light camera)
    """Visibility (N,) of one light's mesh shadow map at receivers pts (N, 3) with unit normals
    nrm (N, 3) and unit vectors to the light to_light (N, 3)."""
    S = tex.shape[0]
    cos = jnp.sum(nrm * to_light, axis=-1)
    side = jnp.where(cos < 0, -1.0, 1.0)
    cos_abs = jnp.abs(cos)
    slope = jnp.minimum(safe_sqrt(1.0 - cos_abs * cos_abs) / jnp.maximum(cos_abs, 1e-3), MAX_SLOPE)
    if is_point:
        tx = texel * jnp.maximum(_light_coords(view, proj, pts)[:, 3], 1e-6)
    else:
        tx = jnp.broadcast_to(texel, cos.shape)
    p = pts + (side * NORMAL_OFFSET * tx)[:, None] * nrm
    q = _light_coords(view, proj, p)
    w, z = q[:, 2], q[:, 3]
    ok = w > 1e-9
    w = jnp.where(ok, w, 1.0)
    u = 0.5 * (q[:, 0] / w + 1.0) * S - 0.5
    v = 0.5 * (1.0 - q[:, 1] / w) * S - 0.5
    # their cotangents computed once (XLA's CPU fusion recomputed the lookup's backward chain in
    # every consumer: 256^2 render gradient with a shadowed light 299 -> 184 ms with the sphere
    # terms' likewise, benchmarks/shading.py scene)
    u, v, z = materialize_grad(u), materialize_grad(v), materialize_grad(z)
    bias0 = DEPTH_BIAS * tx
    tau = DEPTH_SOFTNESS * tx

    def sample(radius, grid):
        """Coverage, depth, bias per tap: (N, T)."""
        du = grid[None, :, 0] * radius[:, None]
        dv = grid[None, :, 1] * radius[:, None]
        # not materialized: doing so halves the forward lookup (1.44 -> 0.69 s for 2 lights at
        # 256^2 receivers) but slows value-and-gradient (0.74 -> 0.87-0.98 s at 128^2; loaded
        # 2-core CPU, same-process A/B), and fits need the gradient
        s = _bilinear(tex, u[:, None] + du, v[:, None] + dv)
        cov = s[..., 1]
        depth = safe_div(s[..., 0], cov)
        dist = safe_sqrt(du * du + dv * dv)
        bias = bias0[:, None] + tx[:, None] * slope[:, None] * (1.0 + dist)
        return cov, depth, bias

    if taps == 1:
        # one bilinear tap at the receiver (its 2 x 2 texels): the filter radius multiplies a
        # zero offset, so the blocker search that sets it would change nothing; skipped
        cov, depth, bias = sample(jnp.zeros_like(z), _grid(1, tx.dtype))
    else:
        # blocker search over the region the light's disc can reach from the receiver
        search = jnp.clip(tan_t * jnp.maximum(z - zmin, 0.0) / tx, 1.0, MAX_RADIUS)
        cov, depth, bias = sample(search, _grid(max(taps - 1, 2), tx.dtype))
        wb = cov * _smoothstep((z[:, None] - bias - depth) / tau[:, None])
        wsum = jnp.sum(wb, axis=-1)
        d_block = safe_div(jnp.sum(wb * depth, axis=-1), wsum)
        radius = jnp.where(wsum > 0, tan_t * jnp.maximum(z - d_block, 0.0) / tx, 1.0)
        radius = jnp.clip(radius, 1.0, MAX_RADIUS)
        cov, depth, bias = sample(radius, _grid(taps, tx.dtype))
    occ = cov * _smoothstep((z[:, None] - bias - depth) / tau[:, None])
    vis = 1.0 - jnp.clip(jnp.mean(occ, axis=-1), 0.0, 1.0)
    return jnp.where(ok, vis, 1.0)


def sphere_visibility(
    points, to_light, spheres: Sphere, tan_theta, light_distance=None, *, fast: bool = False
):
    """Fraction of a disc light visible past analytic spheres.

    Args:
      points: (N, 3) receivers in m; to_light: (N, 3) unit vectors toward the light.
      spheres: Sphere batch (s,).
      tan_theta: () tan of the light's angular radius (> 0).
      light_distance: optional (N,) distance to a point light (spheres whose centre is farther
        than the light do not occlude it).
      fast: static; angles from `_math.fast_atan2` (|error| < 3e-7 rad) instead of atan2.
    Returns:
      (N,) visibility in [0, 1]: prod over spheres of 1 - occluded fraction (module docstring).
    """
    theta = jnp.arctan(tan_theta)
    atan2 = fast_atan2 if fast else jnp.arctan2

    def one(c, r):
        v = c[None] - points
        t = jnp.sum(v * to_light, axis=-1)
        d = safe_norm(v - t[:, None] * to_light, axis=-1)
        dist2 = jnp.sum(v * v, axis=-1)
        t, d, dist2 = materialize_grad(t), materialize_grad(d), materialize_grad(dist2)
        beta = atan2(d, t)
        alpha = atan2(r, safe_sqrt(dist2 - r * r))
        small = jnp.maximum(jnp.minimum(alpha, theta), 1e-6)
        frac = jnp.minimum(small / theta, 1.0) ** 2
        occ = frac * _smoothstep((alpha + theta - beta) / (2.0 * small))
        if light_distance is not None:
            occ = jnp.where(dist2 < light_distance * light_distance, occ, 0.0)
        return 1.0 - occ

    return jnp.prod(jax.vmap(one)(spheres.center, spheres.radius), axis=0)


def shadow_visibility(maps: ShadowMaps | None, points, normals, *, taps: int | None = None):
    """Per-light visibility at receivers.

    Args:
      maps: from `shadow_maps` (None: no shadows).
      points: (..., 3) world positions in m; normals: (..., 3) surface normals (either side; need
        not be unit). Both differentiable.
      taps: static filter taps per axis (taps^2 filter taps, (taps - 1)^2 blocker-search taps;
        1: one bilinear tap, no blocker search); None: the maps' own `taps`.
    Returns:
      (..., nl) visibility in [0, 1] of every light (directional first); 1 for lights without
      shadows. None when maps is None.
    """
    if maps is None:
        return None
    taps = maps.taps if taps is None else int(taps)
    lights = maps.lights
    nd = lights.direction.shape[0]
    nl = nd + lights.point_position.shape[0]
    batch = points.shape[:-1]
    # the receivers' cotangents (sums over every light, sphere and tap) computed once
    pts = materialize_grad(points.reshape(-1, 3))
    nrm = materialize_grad(safe_normalize(normals.reshape(-1, 3)))
    dsoft, psoft = lights.softness_degrees()
    tan_all = jnp.tan(jnp.deg2rad(jnp.concatenate([dsoft, psoft])))
    idx = np.asarray(maps.casting, np.int32)
    # unit vectors toward each casting light, (k, N, 3), and point-light distances
    dirs = safe_normalize(lights.direction)
    to_pt = lights.point_position[None] - pts[:, None]  # (N, np, 3)
    pt_dist = safe_norm(to_pt, axis=-1)
    pt_l = safe_normalize(to_pt)
    vecs, dists = [], []
    for i in maps.casting:  # static, per light: tiny (k, N, 3) assembly
        if i < nd:
            vecs.append(jnp.broadcast_to(dirs[i], pts.shape))
            dists.append(None)
        else:
            vecs.append(pt_l[:, i - nd])
            dists.append(pt_dist[:, i - nd])
    to_light = materialize_grad(jnp.stack(vecs))
    tan_t = tan_all[idx]
    vis = jnp.ones((len(idx), pts.shape[0]), pts.dtype)
    if maps.maps is not None:
        # one lookup per casting light (static loop: a point light's texel grows with depth)
        vis = vis * jnp.stack(
            [
                _map_visibility(
                    maps.maps[k],
                    maps.view[k],
                    maps.projection[k],
                    maps.texel[k],
                    maps.zmin[k],
                    tan_t[k],
                    i >= nd,
                    pts,
                    nrm,
                    to_light[k],
                    taps,
                )
                for k, i in enumerate(maps.casting)
            ]
        )
    if maps.spheres is not None:
        inf = jnp.full(pts.shape[:1], jnp.inf, pts.dtype)
        ldist = jnp.stack([inf if d is None else d for d in dists])
        vis = vis * jax.vmap(
            lambda tl, tt, ld: sphere_visibility(pts, tl, maps.spheres, tt, ld, fast=maps.fast)
        )(to_light, tan_t, ldist)
    # scatter the casting lights into all nl slots (others fully visible)
    full = jnp.ones((nl, pts.shape[0]), pts.dtype).at[idx].set(vis)
    return jnp.moveaxis(full, 0, -1).reshape(*batch, nl)


def vertex_shadow_visibility(maps: ShadowMaps | None, points, normals, grid_shape=None):
    """`shadow_visibility` at a surface's vertices (`maps.per_vertex`); on a tessellated grid
    (`grid_shape` (vrows, vcols)) at most `maps.size` vertex rows and columns of it (about one a
    texel: the map holds no finer detail), interpolated along the grid (`grid_coarse`).

    Shapes: points (n, 3) m, normals (n, 3) -> (n, nl); None when maps is None.
    """
    if maps is None:
        return None
    return on_coarse_grid(partial(shadow_visibility, maps), points, normals, grid_shape, maps.size)


def layer_shadow_receivers(maps: ShadowMaps | None, points, normals):
    """The receivers `layer_shadow_visibility` looks up and the map back to the pixels:
    (points', normals', upsample); with `maps.layer_stride` f > 1 (and the image's sides
    multiples of f) the f x f blocks' mean points and normals, upsample bilinear; otherwise the
    pixels themselves and the identity.

    Shapes: points (..., H, W, 3) m, normals (..., H, W, 3) -> (..., H', W', 3) twice, and
    upsample: (..., H', W', k) -> (..., H, W, k).
    """
    f = 1 if maps is None else maps.layer_stride
    *lead, H, W = points.shape[:-1]
    if f <= 1 or H % f or W % f:
        return points, normals, lambda a: a

    def block_mean(a):
        return jnp.mean(a.reshape(*lead, H // f, f, W // f, f, 3), axis=(-4, -2))

    def upsample(low):
        return jax.image.resize(low, (*lead, H, W, low.shape[-1]), "linear")

    return block_mean(points), block_mean(normals), upsample


def layer_shadow_visibility(maps: ShadowMaps | None, points, normals):
    """`shadow_visibility` of a ray-cast layer (spheres, planes): per pixel, or with
    `maps.layer_stride` f > 1 (and the image's sides multiples of f) once per f x f pixel block,
    at the block's mean point and normal, upsampled bilinearly to the pixels (the "fit" preset:
    its light map has about one texel per two pixels, so the lookup has no finer detail; one
    quarter of the receivers). Continuous in the receivers, so in the parameters.

    Shapes: points (..., H, W, 3) m, normals (..., H, W, 3) -> (..., H, W, nl); None when maps
    is None.
    """
    if maps is None:
        return None
    p, n, upsample = layer_shadow_receivers(maps, points, normals)
    return upsample(shadow_visibility(maps, p, n))
