"""Deferred shading of per-pixel G-buffers: every lighting mode of the seed (Wloka slides 8-23).

Shading is independent of rasterization: a rasterizer (or an analytic construction, see
`gbuffer_quad` / `gbuffer_sphere`) fills a `ShadingBuffer`; `shade` makes an (H, W, 4) image.
All parameters (lights, appearance, textures, spheres, eye) are differentiable arrays; the mode is a
static string.

Notation (as in the slides): N unit normal, E unit vector from the surface point toward the eye,
L unit vector toward a light, H = normalize(L + E), R = -(E - 2 (E.N) N) the reflected eye vector.
"""

# ruff: noqa: F401  (re-exports: names moved to sibling modules stay importable here)
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import materialize, safe_div, static_zero
from diffcloth.render.lights import Appearance, Lights, light_vectors
from diffcloth.render.rays import ray_sphere
from diffcloth.render.textures import (
    MINNAERT_EPS,
    CubeMap,
    Textures,
    minnaert_table,
    sample_2d,
    sample_cube,
    sample_mip,
    sky_cube_map,
    uv_lod,
)
from diffcloth.render.vectors import (
    _bc,
    _dot,
    _normalize,
    _pow,
    _sum_axis,
    reflect,
    refract,
    refract_shortened,
    view_vectors,
)
from diffcloth.shapes import Sphere

MODES = (
    "flat",
    "gouraud",
    "phong",
    "bump_diffuse",
    "minnaert",
    "minnaert_table",
    "blinn_bump_reflection",
    "second_pass",
    "sphere_reflection",
    "reflect_refract",
)
REFRACTIONS = ("shortened", "snell")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ShadingBuffer:
    """Per-pixel surface attributes, the contract between rasterizer and shader.

    What a rasterizer must supply (all interpolated perspective-correctly with the barycentrics of
    the front-most triangle at each pixel centre; values at uncovered pixels are ignored but must be
    finite):
      position: (H, W, 3) world position in m.
      normal: (H, W, 3) interpolated vertex normal (need not be unit; renormalised here).
      tangent: (H, W, 3) interpolated dP/du (need not be unit or orthogonal to the normal).
      bitangent: (H, W, 3) interpolated dP/dv (only its side relative to N x T is used).
      uv: (H, W, 2) texture coordinates.
      mask: (H, W) coverage in [0, 1] (hard 0/1 or antialiased fraction).
      face_normal: (H, W, 3) geometric normal of the covering triangle, constant per triangle
        (cross product of its world-space edges, oriented like the vertex normals); needed only by
        mode "flat".
      color: (H, W, 3) interpolated per-vertex lit colour from `light_vertices`; needed only by mode
        "gouraud".
      visibility: optional (H, W, nl) shadow visibility of each light in [0, 1] (from
        `shadows.shadow_visibility`); multiplies every light's radiance. None: no shadows.
      ambient_visibility: optional (H, W) visible fraction of the ambient environment in [0, 1]
        (from `sky.sky_visibility`, ambient occlusion); multiplies the ambient term. None: 1.
    """

    position: jax.Array
    normal: jax.Array
    tangent: jax.Array
    bitangent: jax.Array
    uv: jax.Array
    mask: jax.Array
    face_normal: jax.Array | None = None
    color: jax.Array | None = None
    visibility: jax.Array | None = None
    ambient_visibility: jax.Array | None = None


# ----------------------------------------------------------------------------- vector helpers


# ----------------------------------------------------------------------------- lighting


def _light_at(lights, positions, visibility):
    """`light_vectors` with the radiance scaled by the shadow visibility (..., nl) if given."""
    l, rad = light_vectors(lights, positions)
    if visibility is not None:
        rad = rad * visibility[..., None].astype(rad.dtype)
    return l, rad


def blinn_phong(normals, eyes, positions, lights: Lights, appearance: Appearance, visibility=None):
    """Summed diffuse and specular light at each point.

    visibility: optional (..., nl) shadow visibility per light (None: unshadowed).
    Returns:
      (diffuse, specular), each (..., 3): sum_i radiance_i max(N.L_i, 0) and
      sum_i radiance_i [N.L_i > 0] max(N.H_i, eps)^shininess (clamped before pow; finite grads).
    """
    l, rad = _light_at(lights, positions, visibility)
    n = normals[..., None, :]
    nl = _dot(n, l)
    h = _normalize(l + eyes[..., None, :])
    nh = jnp.maximum(_dot(n, h), 0.0)
    spec = jnp.where(nl > 0, _pow(nh, appearance.shininess), 0.0)
    diffuse = _sum_axis(rad * jnp.maximum(nl, 0.0)[..., None], -2)
    specular = _sum_axis(rad * spec[..., None], -2)
    return diffuse, specular


def _ambient(appearance, lights, like, ambient_visibility=None):
    """Ambient light (..., 3) shaped like `like`, times the occlusion (...) if given."""
    amb = _bc(appearance.ambient * lights.ambient, like)
    return amb if ambient_visibility is None else amb * ambient_visibility[..., None]


def lambert(normals, positions, lights: Lights, visibility=None):
    """Diffuse light (..., 3): sum_i radiance_i max(N.L_i, 0) (`blinn_phong`'s first output)."""
    l, rad = _light_at(lights, positions, visibility)
    nl = _dot(normals[..., None, :], l)
    return _sum_axis(rad * jnp.maximum(nl, 0.0)[..., None], -2)


def _lit(albedo, normals, eyes, positions, lights, appearance, visibility=None, amb_vis=None):
    if static_zero(appearance.specular):  # fixed matte material: no highlight (nor eye vectors)
        diffuse = lambert(normals, positions, lights, visibility)
        return _bc(albedo, diffuse) * (_ambient(appearance, lights, diffuse, amb_vis) + diffuse)
    diffuse, specular = blinn_phong(normals, eyes, positions, lights, appearance, visibility)
    ambient = _ambient(appearance, lights, diffuse, amb_vis)
    return (
        _bc(albedo, diffuse) * (ambient + diffuse) + _bc(appearance.specular, specular) * specular
    )


def light_vertices(
    positions, normals, eye, lights: Lights, appearance: Appearance, visibility=None, amb_vis=None
):
    """Per-vertex Blinn-Phong colour for Gouraud shading (slide "per-vertex diffuse").

    Args:
      positions: (n, 3) vertex positions in m.
      normals: (n, 3) vertex normals (renormalised).
      eye: (3,) or (4,) eye, see `view_vectors`.
      visibility: optional (n, nl) shadow visibility per vertex and light.
      amb_vis: optional (n,) ambient occlusion per vertex (`sky.sky_visibility`).
    Returns:
      (n, 3) colour = diffuse * (ambient * ambient_light + sum radiance max(N.L, 0))
      + specular * sum radiance max(N.H, 0)^shininess. Rasterize it as an attribute into
      `ShadingBuffer.color` and shade with mode="gouraud".
    """
    n = _normalize(normals)
    e = view_vectors(eye, positions)
    return _lit(appearance.diffuse, n, e, positions, lights, appearance, visibility, amb_vis)


def minnaert_factor(nl, ne, k):
    """Analytic Minnaert F(N.L, N.E) = max(N.L, eps)^(k-1) max(N.E, eps)^(k-1) (eps = 1e-3).
    Cosines are clamped before pow, so k < 1 at grazing angles stays finite (ROBUSTNESS row 22)."""
    return _pow(nl, k - 1.0, MINNAERT_EPS) * _pow(ne, k - 1.0, MINNAERT_EPS)


# ----------------------------------------------------------------------------- frames and bumps


def tbn_frame(normal, tangent, bitangent):
    """Orthonormal (T, B, N): N normalised, T Gram-Schmidt against N, B = +-(N x T) on the side of
    the given bitangent (the seed: bi-normal = normal x tangent). Degenerate inputs fall back
    to +y directions; always finite."""
    n = _normalize(normal)
    t = _normalize(tangent - _dot(tangent, n)[..., None] * n)
    b = _cross(n, t)
    side = jnp.where(_dot(bitangent, b) < 0, -1.0, 1.0)
    return t, side[..., None] * b, n


def _cross(a, b):
    """jnp.cross over a last axis of 3, written out (no stack / transpose of the components)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def bump_normal(normal, tangent, bitangent, slopes, strength):
    """Per-pixel normal from height-map slopes in tangent space.

    Args:
      normal, tangent, bitangent: (..., 3) interpolated frame.
      slopes: (..., 2) height differences per texel along u and v (from `Textures.bump`).
      strength: () bump strength (0 gives the unperturbed normal).
    Returns:
      (..., 3) unit normal normalize(N - strength (h_u T + h_v B)); a zero result falls back to +y.
    """
    t, b, n = tbn_frame(normal, tangent, bitangent)
    offset = slopes[..., 0:1] * t + slopes[..., 1:2] * b
    return _normalize(n - strength * offset)


# ----------------------------------------------------------------------------- spheres


def trace_spheres(origins, directions, spheres: Sphere, lights: Lights, appearance: Appearance):
    """Reflected-ray trace against analytic spheres (slides 17-18), per pixel.

    Args:
      origins: (..., 3) ray origins (the cloth points) in m.
      directions: (..., 3) unit ray directions (reflected eye vectors).
      spheres: one or more spheres.
    Returns:
      (color, blend): color (..., 3) the nearest hit point lit by the lights (ambient + Lambert with
      `appearance.sphere_color`); blend (...) = 0 without a hit, else
      sphere_reflectivity / (1 + sphere_distance_falloff * t) * (disc / r^2)^sphere_rim_power,
      which fades continuously to 0 at the sphere's rim. Finite values and gradients.
    """
    sph = spheres.batched()

    def one(center, radius):
        t, hit, disc = ray_sphere(origins, directions, _bc(center, origins), radius)
        hit = hit & (t > 1e-4 * radius)
        rim = jnp.clip(safe_div(disc, radius * radius), 0.0, 1.0)
        return t, hit, rim

    if sph.center.shape[0] == 1:  # one sphere: no nearest-of selection (no per-pixel gathers)
        t, any_hit, rim = one(sph.center[0], sph.radius[0])
        center = _bc(sph.center[0], origins)
    else:
        t, hit, rim = jax.vmap(one)(sph.center, sph.radius)  # (ns, ...)
        big = jnp.asarray(1e10, t.dtype)
        nearest = jnp.argmin(jnp.where(hit, t, big), axis=0)
        t = jnp.take_along_axis(t, nearest[None], axis=0)[0]
        rim = jnp.take_along_axis(rim, nearest[None], axis=0)[0]
        any_hit = jnp.take_along_axis(hit, nearest[None], axis=0)[0]
        center = sph.center[nearest]
    t = jnp.where(any_hit, t, 0.0)
    point = origins + t[..., None] * directions
    n = _normalize(point - center)
    l, rad = light_vectors(lights, point)
    diffuse = _sum_axis(rad * jnp.maximum(_dot(n[..., None, :], l), 0.0)[..., None], -2)
    color = _bc(appearance.sphere_color, diffuse) * (
        _bc(appearance.ambient * lights.ambient, diffuse) + diffuse
    )
    blend = (
        appearance.sphere_reflectivity
        / (1.0 + appearance.sphere_distance_falloff * t)
        * _pow(rim, appearance.sphere_rim_power, 1e-12)
    )
    return color, jnp.where(any_hit, blend, 0.0)


# ----------------------------------------------------------------------------- shade


@functools.lru_cache(maxsize=4)
def _default_sky(dtype_name: str) -> CubeMap:
    # concrete even when first called under a trace: a cached tracer would leak into the next jit
    with jax.ensure_compile_time_eval():
        return sky_cube_map(32, dtype=jnp.dtype(dtype_name))


def _check_mode(mode, refraction):
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if refraction not in REFRACTIONS:
        raise ValueError(f"refraction must be one of {REFRACTIONS}, got {refraction!r}")


def shade(
    gbuffer: ShadingBuffer,
    eye,
    lights: Lights,
    appearance: Appearance,
    *,
    mode: str,
    textures: Textures | None = None,
    spheres: Sphere | None = None,
    refraction: str = "shortened",
):
    """Shade a G-buffer with one of the seed's lighting modes.

    Args:
      gbuffer: per-pixel attributes (see `ShadingBuffer` for what each mode needs).
      eye: (3,) eye position or (4,) homogeneous eye (w = 0: direction toward the viewer, for
        orthographic cameras); see `view_vectors`.
      lights, appearance: differentiable parameters.
      mode: static; one of MODES:
        "flat"      Blinn-Phong with `gbuffer.face_normal` (one normal per triangle).
        "gouraud"   `gbuffer.color`, the interpolated output of `light_vertices`.
        "phong"     Blinn-Phong per pixel with the interpolated normal.
        "bump_diffuse"  albedo * texture * (ambient + sum rad max(N'.L, 0)), N' the bumped normal.
        "minnaert"  albedo * texture * (ambient + sum rad F(N'.L, N'.E) max(N'.L, 0)), analytic F
                    with exponent appearance.minnaert_k (k = 1 is Lambert).
        "minnaert_table"  the same with F sampled bilinearly from a 2-D table (textures.minnaert,
                    else generated from minnaert_k; differentiable w.r.t. k).
        "blinn_bump_reflection"  reflectance * env(R(N')), blended with the sphere trace if spheres.
        "second_pass"  first pass as above; second pass specular + a * albedo * texture rgb, with
                    a = second_pass_alpha * texture alpha, blended over: first (1 - a) + second.
        "sphere_reflection"  per-pixel Phong cloth blended with the lit sphere hit of the reflected
                    eye ray (blend from `trace_spheres`); requires spheres.
        "reflect_refract"  reflectance * ((1 - b) refl + b env(R')) + specular; refl = env(R)
                    blended with the sphere trace, R' the shortened-normal refraction
                    (refraction_s) or Snell with appearance.ior (refraction="snell"; total internal
                    reflection falls back to the mirror direction).
      textures: colour / bump / environment / Minnaert textures; environment lookups fall back to
        a procedural sky when textures.env is None; colour and bump are optional.
      spheres: analytic spheres seen in reflections.
      refraction: static, "shortened" (the seed's) or "snell".
    Returns:
      (H, W, 4) premultiplied RGBA: rgb * mask and alpha = mask. Colours are not clipped to [0, 1].
    """
    _check_mode(mode, refraction)
    if mode == "flat" and gbuffer.face_normal is None:
        raise ValueError("mode 'flat' needs gbuffer.face_normal (per-triangle normal per pixel)")
    if mode == "gouraud" and gbuffer.color is None:
        raise ValueError("mode 'gouraud' needs gbuffer.color (rasterized light_vertices output)")
    if mode == "sphere_reflection" and spheres is None:
        raise ValueError("mode 'sphere_reflection' needs spheres, got None")
    tex = textures if textures is not None else Textures()
    g = gbuffer
    dtype = g.position.dtype
    mask = g.mask
    covered = mask > 0
    p = g.position
    vis, av = g.visibility, g.ambient_visibility
    e = view_vectors(eye, p)
    n = _normalize(g.normal)

    tiling = tex.tiling if tex.tiling is not None else jnp.ones(2, dtype)
    uv = g.uv * _bc(tiling, g.uv)

    def texture_rgba():
        if tex.color is None:
            return jnp.ones((*mask.shape, 4), dtype)
        lod = uv_lod(uv, mask, tex.color[0].shape)
        # materialized: XLA's CPU fusion would otherwise redo every lookup per consumer/channel
        return materialize(sample_mip(tex.color, uv, lod, wrap="repeat"))

    def bumped():
        if tex.bump is None:
            return n
        lod = uv_lod(uv, mask, tex.bump[0].shape)
        slopes = materialize(sample_mip(tex.bump, uv, lod, wrap="repeat"))
        nb = bump_normal(g.normal, g.tangent, g.bitangent, slopes, appearance.bump_strength)
        return materialize(nb)  # read by several lighting terms: computed once

    env = tex.env if tex.env is not None else _default_sky(jnp.dtype(dtype).name)
    ambient = _ambient(appearance, lights, p, av)
    diffuse_color = _bc(appearance.diffuse, p)
    specular_color = _bc(appearance.specular, p)
    reflectance = _bc(appearance.reflectance, p)

    def reflection_pass(normal):
        r = reflect(e, normal)
        color = sample_cube(env, r)
        if spheres is not None:
            sphere_color, blend = trace_spheres(p, r, spheres, lights, appearance)
            color = color + blend[..., None] * (sphere_color - color)
        return color

    if mode == "flat":
        albedo = diffuse_color * texture_rgba()[..., :3]
        rgb = _lit(albedo, _normalize(g.face_normal), e, p, lights, appearance, vis, av)
    elif mode == "gouraud":
        rgb = g.color
    elif mode == "phong":
        rgb = _lit(diffuse_color * texture_rgba()[..., :3], n, e, p, lights, appearance, vis, av)
    elif mode == "bump_diffuse":
        diffuse, _ = blinn_phong(bumped(), e, p, lights, appearance, vis)
        rgb = diffuse_color * texture_rgba()[..., :3] * (ambient + diffuse)
    elif mode in ("minnaert", "minnaert_table"):
        nb = bumped()
        l, rad = _light_at(lights, p, vis)
        nl = _dot(nb[..., None, :], l)
        ne = jnp.broadcast_to(_dot(nb, e)[..., None], nl.shape)
        if mode == "minnaert":
            f = minnaert_factor(nl, ne, appearance.minnaert_k)
        else:
            table = (
                tex.minnaert if tex.minnaert is not None else minnaert_table(appearance.minnaert_k)
            )
            f = sample_2d(table, jnp.stack([nl, ne], axis=-1), wrap="clamp")[..., 0]
        light = _sum_axis(rad * (f * jnp.maximum(nl, 0.0))[..., None], -2)
        rgb = diffuse_color * texture_rgba()[..., :3] * (ambient + light)
    elif mode == "blinn_bump_reflection":
        rgb = reflectance * reflection_pass(bumped())
    elif mode == "second_pass":
        nb = bumped()
        first = reflectance * reflection_pass(nb)
        _, specular = blinn_phong(nb, e, p, lights, appearance, vis)
        rgba = texture_rgba()
        a = jnp.clip(appearance.second_pass_alpha * rgba[..., 3:4], 0.0, 1.0)
        rgb = first * (1.0 - a) + a * diffuse_color * rgba[..., :3] + specular_color * specular
    elif mode == "sphere_reflection":
        albedo = diffuse_color * texture_rgba()[..., :3]
        base = _lit(albedo, n, e, p, lights, appearance, vis, av)
        sphere_color, blend = trace_spheres(p, reflect(e, n), spheres, lights, appearance)
        rgb = base + blend[..., None] * (reflectance * sphere_color - base)
    else:  # reflect_refract
        refl = reflection_pass(n)
        if refraction == "shortened":
            t = refract_shortened(e, n, appearance.refraction_s)
        else:
            t = refract(-e, n, appearance.ior)
        refr = sample_cube(env, t)
        _, specular = blinn_phong(n, e, p, lights, appearance, vis)
        b = appearance.refraction_blend
        rgb = reflectance * (refl + b * (refr - refl)) + specular_color * specular
    rgb = jnp.where(covered[..., None], rgb, 0.0) * mask[..., None]
    return jnp.concatenate([rgb, mask[..., None]], axis=-1).astype(dtype)


# ----------------------------------------------------------------------------- analytic G-buffers


def _pixel_grid(height, width, half_size):
    x = (np.arange(width) + 0.5) / width * 2 - 1
    y = 1 - (np.arange(height) + 0.5) / height * 2
    yy, xx = np.meshgrid(y * half_size, x * half_size, indexing="ij")
    return xx, yy


def gbuffer_quad(height: int, width: int, *, half_size: float = 1.0, dtype=None) -> ShadingBuffer:
    """Analytic G-buffer of the square z = 0, [-half_size, half_size]^2, filling an orthographic
    view down -z (eye (0, 0, 1, 0)). uv = pixel centre / size (u right, v down); normal +z,
    tangent +x, bitangent -y."""
    dtype = dtype or jnp.zeros(()).dtype
    xx, yy = _pixel_grid(height, width, half_size)
    pos = np.stack([xx, yy, np.zeros_like(xx)], -1)
    one = np.ones_like(xx)[..., None]
    uv = np.stack([(xx / half_size + 1) / 2, (1 - yy / half_size) / 2], -1)
    arr = lambda a: jnp.asarray(a, dtype)
    normal = one * np.array([0.0, 0.0, 1.0])
    return ShadingBuffer(
        position=arr(pos),
        normal=arr(normal),
        tangent=arr(one * np.array([1.0, 0.0, 0.0])),
        bitangent=arr(one * np.array([0.0, -1.0, 0.0])),
        uv=arr(uv),
        mask=arr(one[..., 0]),
        face_normal=arr(normal),
    )


def gbuffer_sphere(
    height: int, width: int, *, radius: float = 0.9, half_size: float = 1.0, dtype=None
) -> ShadingBuffer:
    """Analytic G-buffer of a sphere at the origin seen by an orthographic camera down -z
    (eye (0, 0, 1, 0)); a material-preview ball. uv: u = 0.5 + atan2(x, z) / 2 pi, v = polar
    angle / pi; tangent along increasing u; bitangent along increasing v; mask 1 inside the disc."""
    dtype = dtype or jnp.zeros(()).dtype
    xx, yy = _pixel_grid(height, width, half_size)
    r2 = xx**2 + yy**2
    inside = r2 < radius**2
    zz = np.sqrt(np.maximum(radius**2 - r2, 0.0))
    pos = np.stack([xx, yy, zz], -1)
    normal = pos / radius
    tangent = np.stack([zz, np.zeros_like(zz), -xx], -1)
    tangent = np.where(
        np.linalg.norm(tangent, axis=-1, keepdims=True) > 1e-12, tangent, [1.0, 0.0, 0.0]
    )
    bitangent = np.cross(tangent, normal)  # points toward increasing polar angle (down)
    u = 0.5 + np.arctan2(xx, zz) / (2 * math.pi)
    v = np.arccos(np.clip(yy / radius, -1, 1)) / math.pi
    arr = lambda a: jnp.asarray(a, dtype)
    return ShadingBuffer(
        position=arr(pos),
        normal=arr(normal),
        tangent=arr(tangent),
        bitangent=arr(bitangent),
        uv=arr(np.stack([u, v], -1)),
        mask=arr(inside.astype(float)),
        face_normal=arr(normal),
    )
