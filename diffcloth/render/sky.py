"""Occluded ambient light ("sky visibility", ambient occlusion) from K fixed sky directions.

The ambient light of `Lights` stands for a uniform environment: radiance `ambient` arriving from
every direction, so an unoccluded Lambertian point reflects albedo * ambient whatever its normal.
With ambient occlusion the environment is blocked by the scene: the cloth (and extra occluder
triangles such as boxes), analytic spheres and ground planes. The visible fraction of the
cosine-weighted hemisphere around the normal N is estimated from K fixed, deterministic directions
d_k spread evenly over the whole sphere (a Fibonacci lattice):

    A(p, N) = sum_k w_k V_k(p) / sum_k w_k,   w_k = max(N . d_k, 0),

with V_k in [0, 1] the visibility along d_k: the shadow machinery of `render.shadows` (one
orthographic soft shadow map of the triangle occluders per direction, percentage-closer filtered,
times the analytic sphere occlusion), each direction treated as a disc light of the angular radius
of its share of the sphere (acos(1 - 2/K), capped at the softness range), times the planes'
occlusion: an (infinite) plane hides the directions that point into it from its free side, with a
smooth ramp over dot(d, n_plane) in [-1/K, 0] (continuous in the plane's normal; for a plane
normal along +-y no lattice direction lies inside the ramp, so it equals the hard cut). The
shaders multiply
the ambient term by A. An unoccluded point gets A = 1 exactly (the old ambient, bitwise for the
ratio of two equal sums up to rounding), a point under an occluder less; A is smooth in the
geometry wherever the soft shadows are (no hard jumps: PCF edges, smoothstep sphere discs).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import fast_acos, fast_atan2, safe_div, safe_norm, safe_normalize, safe_sqrt
from diffcloth.render.grid_coarse import on_coarse_grid
from diffcloth.render.lights import SOFTNESS_RANGE, Lights
from diffcloth.render.shadows import ShadowMaps, shadow_maps, shadow_visibility
from diffcloth.render.sky_discs import disc_occlusion, mesh_discs, plane_openness
from diffcloth.shapes import Plane, Sphere

#: allowed number of sky directions (0 = off)
AO_RANGE = (0, 256)
#: filter taps per axis of each direction's shadow-map lookup (AO is low-frequency)
SKY_TAPS = 3
#: grid lines a side on which `vertex_sky_attribute` evaluates a grid's occlusion
COARSE_GRID = 16


def sky_directions(k: int) -> np.ndarray:
    """(k, 3) unit directions spread evenly over the sphere (Fibonacci lattice, +y up),
    deterministic. Heights z_i = 1 - (2 i + 1) / k, so none is exactly horizontal for even k."""
    i = np.arange(k, dtype=np.float64)
    y = 1.0 - (2.0 * i + 1.0) / k
    r = np.sqrt(np.maximum(1.0 - y * y, 0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=-1)


def sky_softness(k: int) -> float:
    """Angular radius in degrees of one direction's share of the sphere (a cap of area 4 pi / k),
    clipped to the lights' softness range.

    Shapes: none (a Python int in, a Python float out).
    """
    lo, hi = SOFTNESS_RANGE
    return float(np.clip(math.degrees(math.acos(1.0 - 2.0 / k)), lo, hi))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SkyMaps:
    """Per-frame occlusion data of the K sky directions.

    Attributes:
      shadows: ShadowMaps of K directional 'sky lights' (cloth/occluder maps, spheres), or None
        when there is no triangle or sphere occluder.
      directions: (K, 3) unit sky directions.
      plane_normal: (npl, 3) unit normals of the occluding planes, or None.
      ramp: () 1/K: width in dot(d, n_plane) of the planes' horizon ramp.
      spheres: the sphere occluders taken analytically (`sphere_form_factor`) instead of per
        direction, or None.
      per_vertex: static; the cloth's A is evaluated at its vertices (both sides) and
        interpolated by the rasterizer (`pixel_sky_visibility`) instead of at every pixel.
      layer_stride: static; the ray-cast layers (spheres, planes) evaluate A at every
        layer_stride-th pixel and upsample it bilinearly (`layer_sky_visibility`); 1: every pixel.
      discs: with `analytic`, the occluder mesh as discs (`sky_discs.mesh_discs`), or None.
      analytic: static; A from closed forms (`render.sky_discs`: mesh discs, sphere form
        factors, plane halves) instead of the K directions' maps.
    """

    shadows: ShadowMaps | None
    directions: jax.Array
    plane_normal: jax.Array | None
    ramp: jax.Array
    spheres: Sphere | None = None
    per_vertex: bool = dataclasses.field(default=False, metadata={"static": True})
    layer_stride: int = dataclasses.field(default=1, metadata={"static": True})
    discs: tuple | None = None
    analytic: bool = dataclasses.field(default=False, metadata={"static": True})


def sky_maps(
    k: int,
    *,
    mesh=None,
    spheres: Sphere | None = None,
    planes: Plane | None = None,
    size: int = 128,
    dtype=None,
    taps: int = SKY_TAPS,
    analytic_spheres: bool = False,
    per_vertex: bool = False,
    layer_stride: int = 1,
    analytic: bool = False,
) -> SkyMaps | None:
    """Build the sky-visibility data of one frame.

    Args:
      k: static number of sky directions (AO_RANGE; 0: None is returned, AO off).
      mesh: optional triangle occluder (positions (n, 3), faces (m, 3)[, neighbors (m, 3)]), m.
      spheres: optional analytic sphere occluders.
      planes: optional planes; each hides the directions pointing into it (receivers are taken
        to lie on its free side).
      size: static shadow-map size in texels of each direction's map.
      dtype: float dtype (default: the mesh's, else JAX's default float).
      taps: static filter taps per axis of each direction's lookup (1: one bilinear tap).
      analytic_spheres: static; the spheres' occlusion as their exact cosine-weighted form
        factor (`sphere_form_factor`, multiplied in) instead of per sky direction: exact at any
        K, and cheaper.
      per_vertex: static; the cloth's occlusion per vertex, interpolated (`SkyMaps.per_vertex`).
      layer_stride: static pixel stride of the spheres' and planes' occlusion (`SkyMaps`).
      analytic: static; no maps: the closed forms of `render.sky_discs` (k only turns it on).
    Returns:
      SkyMaps or None (k == 0).
    """
    lo, hi = AO_RANGE
    if not isinstance(k, int | np.integer) or isinstance(k, bool) or not lo <= k <= hi:
        raise ValueError(f"ambient_occlusion must be an int in [{lo}, {hi}] (0 = off), got {k!r}")
    if k == 0:
        return None
    if dtype is None:
        dtype = mesh[0].dtype if mesh is not None else jnp.zeros(()).dtype
    dirs = jnp.asarray(sky_directions(int(k)), dtype)
    pn = None if planes is None else safe_normalize(planes.batched().normal.astype(dtype))
    ramp = jnp.asarray(1.0 / k, dtype)
    if analytic:
        discs = (
            None if mesh is None else mesh_discs(mesh[0], jnp.asarray(mesh[1]).astype(jnp.int32))
        )
        sph = None if spheres is None else spheres.batched()
        return SkyMaps(None, dirs, pn, ramp, sph, bool(per_vertex), int(layer_stride), discs, True)
    soft = sky_softness(int(k))
    maps = None
    analytic = spheres.batched() if analytic_spheres and spheres is not None else None
    if analytic is not None:
        spheres = None
    if mesh is not None or spheres is not None:
        z = jnp.zeros((0,), dtype)
        sky = Lights(
            ambient=jnp.zeros((3,), dtype),
            direction=dirs,
            direction_color=jnp.ones((k, 3), dtype),
            direction_intensity=jnp.ones((k,), dtype),
            point_position=jnp.zeros((0, 3), dtype),
            point_color=jnp.zeros((0, 3), dtype),
            point_intensity=z,
            point_attenuation=z,
            direction_softness=jnp.full((k,), soft, dtype),
            point_softness=z,
            shadows=(True,) * int(k),
        )
        maps = shadow_maps(sky, mesh=mesh, spheres=spheres, size=int(size), taps=int(taps))
    return SkyMaps(maps, dirs, pn, ramp, analytic, bool(per_vertex), int(layer_stride))


def _ramp(x):
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def sky_visibility(sky: SkyMaps | None, points, normals):
    """Fraction A of the cosine-weighted environment visible at receivers.

    Args:
      sky: from `sky_maps` (None: no ambient occlusion).
      points: (..., 3) world positions in m; normals: (..., 3) normals of the lit side (need not
        be unit). Differentiable.
    Returns:
      (...,) A in [0, 1] (module docstring); None when sky is None.
    """
    if sky is None:
        return None
    # one flat receiver axis: XLA's CPU code for the (H, W, discs) broadcasts and their
    # reductions ran about 15x slower per receiver than for (N, discs)
    batch = points.shape[:-1]
    points, normals = points.reshape(-1, 3), normals.reshape(-1, 3)
    n = safe_normalize(normals)
    if sky.analytic:
        a = jnp.ones(n.shape[:-1], n.dtype)
        if sky.discs is not None:
            a = jnp.clip(1.0 - disc_occlusion(points, n, sky.discs), 0.0, 1.0)
        if sky.plane_normal is not None:
            a = a * plane_openness(n, sky.plane_normal)
    else:
        w = jnp.maximum(jnp.einsum("...c,kc->...k", n, sky.directions), 0.0)  # (..., K)
        vis = jnp.ones_like(w)
        if sky.shadows is not None:
            vis = shadow_visibility(sky.shadows, points, normals)
        if sky.plane_normal is not None:
            cos = sky.directions @ sky.plane_normal.T  # (K, npl)
            pv = jnp.prod(_ramp(cos / sky.ramp + 1.0), axis=-1)  # (K,)
            vis = vis * jnp.reshape(pv, (1,) * (vis.ndim - 1) + pv.shape)
        a = safe_div(jnp.sum(w * vis, -1), jnp.sum(w, -1))
    if sky.spheres is not None:
        a = a * jnp.prod(1.0 - sphere_form_factor(points, n, sky.spheres), axis=-1)
    return jnp.clip(a, 0.0, 1.0).reshape(batch)


def vertex_sky_attribute(sky: SkyMaps | None, points, normals, grid_shape=None):
    """A per-vertex attribute (n, 2): A of the front (normal) and back side of each vertex, for
    a `sky.per_vertex` SkyMaps; None otherwise (A is then evaluated per pixel). With the
    (vrows, vcols) `grid_shape` of a tessellated grid, A is evaluated on at most COARSE_GRID
    vertex rows and columns of it and interpolated linearly along the grid to the others
    (`grid_coarse.on_coarse_grid`).

    Shapes: points (n, 3) m, normals (n, 3) -> (n, 2).
    """
    if sky is None or not sky.per_vertex:
        return None

    def both(p, n):  # one lookup for both sides
        a = sky_visibility(sky, jnp.stack([p, p]), jnp.stack([n, -n]))
        return jnp.moveaxis(a, 0, -1)

    return on_coarse_grid(both, points, normals, grid_shape, COARSE_GRID)


def pixel_sky_visibility(sky: SkyMaps | None, attributes: dict, points, normals, back):
    """A per pixel: the interpolated `vertex_sky_attribute` ("sky" in the rasterizer's
    attributes; its back side where `back`) or `sky_visibility` at the pixels.

    Shapes: points (H, W, 3) m, normals (H, W, 3), back (H, W, 1) bool -> (H, W).
    """
    if sky is None:
        return None
    if "sky" in attributes:
        a = attributes["sky"]
        return jnp.where(back[..., 0], a[..., 1], a[..., 0])
    return sky_visibility(sky, points, normals)


def layer_sky_receivers(sky: SkyMaps | None, points, normals):
    """The receivers `layer_sky_visibility` evaluates and the map back to the pixels:
    (points', normals', upsample); with `sky.layer_stride` f > 1 every f-th pixel of every f-th
    row, upsample bilinear; otherwise the pixels themselves and the identity.

    Shapes: points (..., H, W, 3) m, normals (..., H, W, 3) -> (..., H', W', 3) twice, and
    upsample: (..., H', W') -> (..., H, W).
    """
    f = 1 if sky is None else sky.layer_stride
    if f <= 1:
        return points, normals, lambda a: a
    *lead, H, W = points.shape[:-1]
    o = f // 2
    return (
        points[..., o::f, o::f, :],
        normals[..., o::f, o::f, :],
        lambda low: jax.image.resize(low, (*lead, H, W), "linear"),
    )


def layer_sky_visibility(sky: SkyMaps | None, points, normals):
    """A of a ray-cast layer (spheres, planes): at every pixel, or with `sky.layer_stride` f > 1
    at every f-th pixel of every f-th row, bilinearly upsampled (A is low-frequency; continuous
    in the receivers, so in the parameters, either way).

    Shapes: points (..., H, W, 3) m, normals (..., H, W, 3) -> (..., H, W); None when sky is
    None.
    """
    if sky is None:
        return None
    p, n, upsample = layer_sky_receivers(sky, points, normals)
    return upsample(sky_visibility(sky, p, n))


def sphere_form_factor(points, normals, spheres: Sphere):
    """Cosine-weighted fraction of the hemisphere around each normal that each sphere covers.

    Exact (the differential-area-to-sphere form factor): cos(beta) / h^2 while the sphere lies
    wholly above the receiver's horizon (h = distance to the centre / radius, beta the angle
    between the normal and the centre), 0 wholly below, and the closed form of Lagarde and de
    Rousiers ("Moving Frostbite to PBR", 2014) in between, which meets both continuously.
    Receivers inside a sphere are taken as on its surface.

    Shapes: points (..., 3) m, normals (..., 3) unit, spheres (k,) -> (..., k) in [0, 1].
    """
    sph = spheres.batched()
    lead = (1,) * (points.ndim - 1)
    v = jnp.reshape(sph.center, lead + sph.center.shape) - points[..., None, :]  # (..., k, 3)
    dist = safe_norm(v, axis=-1)
    h = jnp.maximum(dist / jnp.reshape(sph.radius, lead + sph.radius.shape), 1.0 + 1e-3)
    cb = jnp.clip(safe_div(jnp.sum(v * normals[..., None, :], -1), dist), -1.0, 1.0)
    h2 = h * h
    x = jnp.sqrt(h2 - 1.0)
    # horizon-crossing branch on safe inputs (the others' infinite slopes would make NaNs)
    crossing = jnp.abs(h * cb) < 1.0
    c = jnp.where(crossing, cb, 0.0)
    sb = jnp.sqrt(1.0 - c * c)
    y = jnp.clip(-x * c / sb, -1.0, 1.0)
    sy = safe_sqrt(1.0 - y * y)
    part = (c * fast_acos(jnp.where(crossing, y, 0.0)) - x * sb * sy) / (math.pi * h2)
    part = part + fast_atan2(sb * sy, x) / math.pi
    full = jnp.maximum(cb, 0.0) / h2
    return jnp.clip(jnp.where(crossing, part, jnp.where(h * cb >= 1.0, full, 0.0)), 0.0, 1.0)


def frame_sky_maps(
    surface,
    k: int,
    *,
    spheres=None,
    occluders=None,
    planes=None,
    size: int = 128,
    taps: int = SKY_TAPS,
    analytic_spheres: bool = False,
    per_vertex: bool = False,
    layer_stride: int = 1,
    analytic: bool = False,
) -> SkyMaps | None:
    """Sky data of one frame: the cloth `surface` (plus `occluders` triangles (positions (q, 3),
    faces (r, 3))) as the mesh occluder, `spheres` and `planes` analytic; None when k == 0.
    Shapes as `sky_maps`."""
    from diffcloth.render.frame import _occluder_mesh

    if not k:
        return None
    return sky_maps(
        k,
        mesh=_occluder_mesh(surface, occluders),
        spheres=spheres,
        planes=planes,
        size=size,
        dtype=surface.positions.dtype,
        taps=taps,
        analytic_spheres=analytic_spheres,
        per_vertex=per_vertex,
        layer_stride=layer_stride,
        analytic=analytic,
    )
