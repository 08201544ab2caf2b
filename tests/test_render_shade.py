"""Shading modes against analytic expectations on a flat quad and a sphere (orthographic view)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import lights as Lm
from diffcloth.render import shade as S
from diffcloth.render import textures as T
from diffcloth.shapes import make_sphere

N = 12  # image side in pixels
EYE = jnp.array([0.0, 0.0, 1.0, 0.0])  # orthographic, looking down -z
shade = jax.jit(S.shade, static_argnames=("mode", "refraction"))
QUAD = S.gbuffer_quad(N, N)
BALL = S.gbuffer_sphere(N, N, radius=0.9)
L_DIR = np.array([0.3, 0.4, 0.866])
L_DIR = L_DIR / np.linalg.norm(L_DIR)
FACE_COLORS = np.array(
    [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0], [0, 1.0, 1.0], [1.0, 0, 1.0]]
)  # +x red, -x green, +y blue, -y yellow, +z cyan, -z magenta
CUBE = T.make_cube_map(np.broadcast_to(FACE_COLORS[:, None, None, :], (6, 4, 4, 3)))


def lambert_setup(**appearance):
    lights = Lm.make_lights(ambient=(0.0, 0.0, 0.0), directional=[(L_DIR, (1.0, 0.9, 0.8), 1.5)])
    app = Lm.make_appearance(specular=(0.0, 0.0, 0.0), **appearance)
    return lights, app


def lambert_expected(gb, lights, app):
    n = np.asarray(gb.normal)
    nl = np.maximum(n @ L_DIR, 0.0)
    rgb = np.asarray(app.diffuse) * np.asarray(lights.direction_color[0] * 1.5) * nl[..., None]
    return rgb * np.asarray(gb.mask)[..., None]


@pytest.mark.parametrize("mode", ["flat", "phong", "bump_diffuse", "minnaert", "minnaert_table"])
@pytest.mark.parametrize("gb", [QUAD, BALL], ids=["quad", "sphere"])
def test_lambert_modes(mode, gb):
    """Lambert = albedo * max(N.L, 0); Minnaert with exponent 1 equals Lambert."""
    lights, app = lambert_setup(minnaert_k=1.0)
    img = shade(gb, EYE, lights, app, mode=mode)
    np.testing.assert_allclose(img[..., :3], lambert_expected(gb, lights, app), atol=1e-9)
    np.testing.assert_array_equal(img[..., 3], gb.mask)


def test_output_float32_and_background():
    g32 = jax.tree.map(lambda x: x.astype(jnp.float32), BALL)
    lights, app = lambert_setup(dtype=jnp.float32)
    lights = jax.tree.map(lambda x: x.astype(jnp.float32), lights)
    img = shade(g32, EYE.astype(jnp.float32), lights, app, mode="phong")
    assert img.dtype == jnp.float32 and img.shape == (N, N, 4)
    assert float(jnp.abs(img[0, 0]).max()) == 0.0  # corner not covered: premultiplied zero


def test_blinn_phong_specular_and_point_light():
    # light straight above the quad centre; eye +z: H = normalize(L + E)
    lights = Lm.make_lights(
        ambient=(0.2, 0.2, 0.2), directional=[], point=[((0.0, 0.0, 2.0), (1, 1, 1), 3.0, 0.25)]
    )
    app = Lm.make_appearance(
        diffuse=(0.5, 0.4, 0.3), specular=(0.2, 0.3, 0.4), shininess=20.0, ambient=(1.0, 0.5, 1.0)
    )
    img = np.asarray(shade(QUAD, EYE, lights, app, mode="phong"))
    p = np.asarray(QUAD.position)
    to_l = np.array([0.0, 0.0, 2.0]) - p
    d2 = (to_l**2).sum(-1)
    l = to_l / np.sqrt(d2)[..., None]
    rad = 3.0 / (1 + 0.25 * d2)
    h = l + np.array([0, 0, 1.0])
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    expect = (
        np.array([0.5, 0.4, 0.3]) * (np.array([0.2, 0.1, 0.2]) + (rad * l[..., 2])[..., None])
        + np.array([0.2, 0.3, 0.4]) * (rad * h[..., 2] ** 20)[..., None]
    )
    np.testing.assert_allclose(img[..., :3], expect, atol=1e-9)
    # Gouraud: per-vertex lighting interpolated; on the exact pixel points it equals Phong
    colors = S.light_vertices(
        QUAD.position.reshape(-1, 3), QUAD.normal.reshape(-1, 3), EYE, lights, app
    )
    gb = dataclasses.replace(QUAD, color=colors.reshape(N, N, 3))
    np.testing.assert_allclose(shade(gb, EYE, lights, app, mode="gouraud"), img, atol=1e-12)


def test_flat_uses_face_normal():
    lights, app = lambert_setup()
    tilted = np.array([0.0, 0.6, 0.8])
    gb = dataclasses.replace(QUAD, face_normal=jnp.broadcast_to(jnp.asarray(tilted), (N, N, 3)))
    img = shade(gb, EYE, lights, app, mode="flat")
    expect = np.asarray(app.diffuse) * np.array([1.0, 0.9, 0.8]) * 1.5 * (tilted @ L_DIR)
    np.testing.assert_allclose(img[..., :3], np.broadcast_to(expect, (N, N, 3)), atol=1e-9)


def test_minnaert_analytic_matches_formula_and_table():
    lights, app = lambert_setup(minnaert_k=0.6)
    img = np.asarray(shade(BALL, EYE, lights, app, mode="minnaert"))
    n = np.asarray(BALL.normal)
    nl, ne = n @ L_DIR, n[..., 2]
    f = np.maximum(nl, 1e-3) ** -0.4 * np.maximum(ne, 1e-3) ** -0.4
    expect = (
        np.asarray(app.diffuse)
        * np.array([1.0, 0.9, 0.8])
        * 1.5
        * (f * np.maximum(nl, 0))[..., None]
    )
    expect *= np.asarray(BALL.mask)[..., None]
    np.testing.assert_allclose(img[..., :3], expect, atol=1e-9)
    # the table version approximates it (bilinear in a 32 x 32 table); brighter at grazing view
    table = np.asarray(shade(BALL, EYE, lights, app, mode="minnaert_table"))
    inner = np.asarray(BALL.normal[..., 2]) > 0.5
    np.testing.assert_allclose(table[inner], img[inner], rtol=0.1)
    lam = shade(BALL, EYE, *lambert_setup(), mode="phong")
    assert float(img[..., :3].sum()) > float(lam[..., :3].sum())  # velvet: k < 1 brightens


def test_minnaert_grazing_is_finite_row22():
    """cos = 0 exactly with k < 1: pow(0, k - 1) would be inf; cosines are clamped before pow."""
    lights = Lm.make_lights(
        ambient=(0.0, 0.0, 0.0), directional=[((1.0, 0.0, 0.0), (1, 1, 1), 1.0)]
    )
    app = Lm.make_appearance(minnaert_k=0.5)

    def loss(k, light_dir, mode):
        lt = dataclasses.replace(lights, direction=light_dir[None])
        return shade(QUAD, EYE, lt, dataclasses.replace(app, minnaert_k=k), mode=mode)[
            ..., :3
        ].sum()

    for mode in ("minnaert", "minnaert_table"):
        val = loss(app.minnaert_k, jnp.array([1.0, 0.0, 0.0]), mode)  # N.L = 0 exactly
        gk, gl = jax.grad(loss, argnums=(0, 1))(app.minnaert_k, jnp.array([1.0, 0.0, 0.0]), mode)
        assert (
            np.isfinite(float(val)) and np.isfinite(float(gk)) and bool(jnp.all(jnp.isfinite(gl)))
        )
        eye_grazing = jnp.array([1.0, 0.0, 0.0, 0.0])  # N.E = 0 too
        img = shade(QUAD, eye_grazing, lights, app, mode=mode)
        assert bool(jnp.all(jnp.isfinite(img)))


def test_mirror_reflects_cube_face():
    lights, app = lambert_setup()
    tex = T.make_textures(env=CUBE)
    img = np.asarray(shade(QUAD, EYE, lights, app, mode="blinn_bump_reflection", textures=tex))
    np.testing.assert_allclose(img[..., :3], np.broadcast_to(FACE_COLORS[4], (N, N, 3)), atol=1e-9)
    # on the ball, R = 2 (E.N) N - E: away from face edges each pixel shows the face R points at
    ball = np.asarray(shade(BALL, EYE, lights, app, mode="blinn_bump_reflection", textures=tex))
    n = np.asarray(BALL.normal)
    r = 2 * n[..., 2:3] * n - np.array([0, 0, 1.0])
    a = np.abs(r)
    major = np.argmax(a, -1)
    face = 2 * major + (np.take_along_axis(r, major[..., None], -1)[..., 0] < 0)
    second = np.sort(a, -1)[..., 1]
    clear = (np.asarray(BALL.mask) > 0) & (np.max(a, -1) > 1.6 * second)
    assert clear.sum() > 20 and len(set(face[clear].tolist())) >= 4
    np.testing.assert_allclose(ball[clear, :3], FACE_COLORS[face[clear]], atol=1e-9)


def test_reflect_refract_limits():
    lights, app0 = lambert_setup()
    tex = T.make_textures(env=CUBE)
    # s = 1: the shortened normal is the normal, refraction = reflection
    app = dataclasses.replace(
        app0, refraction_s=jnp.asarray(1.0), refraction_blend=jnp.asarray(0.7)
    )
    img = shade(BALL, EYE, lights, app, mode="reflect_refract", textures=tex)
    refl = shade(BALL, EYE, lights, app, mode="blinn_bump_reflection", textures=tex)
    np.testing.assert_allclose(img, refl, atol=1e-9)
    # s = 0 and full refraction: the ray goes straight through, -E = -z (magenta face)
    app = dataclasses.replace(
        app0, refraction_s=jnp.asarray(0.0), refraction_blend=jnp.asarray(1.0)
    )
    img = np.asarray(shade(QUAD, EYE, lights, app, mode="reflect_refract", textures=tex))
    np.testing.assert_allclose(img[..., :3], np.broadcast_to(FACE_COLORS[5], (N, N, 3)), atol=1e-9)
    # Snell with eta = 1: straight through as well; specular adds on top
    app = dataclasses.replace(app, ior=jnp.asarray(1.0), specular=jnp.asarray([0.1, 0.2, 0.3]))
    img = np.asarray(
        shade(QUAD, EYE, lights, app, mode="reflect_refract", textures=tex, refraction="snell")
    )
    h = L_DIR + np.array([0, 0, 1.0])
    spec = (
        np.array([0.1, 0.2, 0.3])
        * np.array([1.0, 0.9, 0.8])
        * 1.5
        * (h[2] / np.linalg.norm(h)) ** 32
    )
    np.testing.assert_allclose(
        img[..., :3], np.broadcast_to(FACE_COLORS[5] + spec, (N, N, 3)), atol=1e-9
    )


def test_snell_total_internal_reflection_row23():
    n = jnp.array([0.0, 0.0, 1.0])
    incident = jnp.array([0.9, 0.0, -jnp.sqrt(1 - 0.81)])  # grazing, glass -> air: eta = 1.5
    t = S.refract(incident, n, 1.5)
    np.testing.assert_allclose(t, incident * jnp.array([1.0, 1.0, -1.0]), atol=1e-12)  # mirror
    g = jax.jacrev(lambda eta, d: S.refract(d, n, eta).sum(), argnums=(0, 1))(1.5, incident)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)
    # exactly at the critical angle (sqrt argument 0): finite value and gradient
    crit = jnp.array([1 / 1.5, 0.0, -jnp.sqrt(1 - 1 / 2.25)])
    g = jax.jacrev(lambda d: S.refract(d, n, 1.5))(crit)
    assert bool(jnp.all(jnp.isfinite(g)))
    # below the critical angle: Snell's law sin_t = eta sin_i
    inc = jnp.array([0.3, 0.0, -jnp.sqrt(1 - 0.09)])
    np.testing.assert_allclose(float(S.refract(inc, n, 1.5)[0]), 0.45, atol=1e-12)


def _sphere_reflection_reference(gb, lights_np, app, center, radius):
    """Independent numpy reference of the per-pixel sphere reflection on a +z-facing quad."""
    p = np.asarray(gb.position)
    e = np.array([0.0, 0.0, 1.0])
    n = np.array([0.0, 0.0, 1.0])
    r = np.broadcast_to(2 * (e @ n) * n - e, p.shape)  # +z
    oc = p - center
    b = (oc * r).sum(-1)
    c = (oc * oc).sum(-1) - radius**2
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0))
    hit = (disc > 0) & (t > 0)
    q = p + t[..., None] * r
    ns = (q - center) / radius
    lpos, lcol = lights_np
    diffuse_at = lambda x, nn: (
        lcol
        * np.maximum((nn * (lpos - x)).sum(-1) / np.linalg.norm(lpos - x, axis=-1), 0)[..., None]
    )
    sphere = np.asarray(app.sphere_color) * diffuse_at(q, ns)
    to_l = lpos - p
    l = to_l / np.linalg.norm(to_l, axis=-1, keepdims=True)
    h = l + e
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    base = np.asarray(app.diffuse) * diffuse_at(p, n) + np.asarray(app.specular) * (
        lcol * (h[..., 2] ** float(app.shininess))[..., None]
    )
    blend = (
        float(app.sphere_reflectivity)
        / (1 + float(app.sphere_distance_falloff) * t)
        * np.clip(disc / radius**2, 0, 1) ** float(app.sphere_rim_power)
    )
    blend = np.where(hit, blend, 0.0)[..., None]
    return base + blend * (sphere - base), hit


def test_sphere_reflection_matches_reference():
    center, radius = np.array([0.1, -0.2, 2.0]), 0.6
    lights = Lm.make_lights(
        ambient=(0.0, 0.0, 0.0), directional=[], point=[((0.0, 0.0, 1.0), (1, 1, 1), 1.0)]
    )
    app = Lm.make_appearance(sphere_rim_power=0.7, sphere_distance_falloff=0.3)
    img = np.asarray(
        shade(QUAD, EYE, lights, app, mode="sphere_reflection", spheres=make_sphere(center, radius))
    )
    expect, hit = _sphere_reflection_reference(
        QUAD, (np.array([0.0, 0, 1]), np.ones(3)), app, center, radius
    )
    assert 10 < hit.sum() < N * N - 10
    np.testing.assert_allclose(img[..., :3], expect, atol=1e-9)
    # a second, farther sphere behind the first changes nothing; one elsewhere adds its own hits
    two = make_sphere([center, center + np.array([0, 0, 3.0])], [radius, radius])
    img2 = shade(QUAD, EYE, lights, app, mode="sphere_reflection", spheres=two)
    np.testing.assert_allclose(img2, img, atol=1e-12)
    with pytest.raises(ValueError, match="spheres"):
        S.shade(QUAD, EYE, lights, app, mode="sphere_reflection")


def test_second_pass_blend():
    lights, app = lambert_setup()
    app = dataclasses.replace(app, second_pass_alpha=jnp.asarray(0.25))
    tex = T.make_textures(env=CUBE)
    img = np.asarray(shade(QUAD, EYE, lights, app, mode="second_pass", textures=tex))
    expect = FACE_COLORS[4] * 0.75 + 0.25 * np.asarray(app.diffuse)  # specular is 0 here
    np.testing.assert_allclose(img[..., :3], np.broadcast_to(expect, (N, N, 3)), atol=1e-9)
    # with a colour texture the alpha comes from the texture: alpha 0 shows the first pass only
    color = np.concatenate([np.ones((4, 4, 3)) * 0.5, np.zeros((4, 4, 1))], -1)
    tex = T.make_textures(env=CUBE, color=color)
    img = np.asarray(shade(QUAD, EYE, lights, app, mode="second_pass", textures=tex))
    np.testing.assert_allclose(img[..., :3], np.broadcast_to(FACE_COLORS[4], (N, N, 3)), atol=1e-9)


def test_bump_map_normal():
    """A sinusoidal height map along u tilts the normal by -strength * slope * T."""
    size = N  # one texel per pixel (lod 0)
    u = (np.arange(size) + 0.5) / size
    height = np.broadcast_to((0.5 + 0.5 * np.sin(2 * np.pi * u))[None, :], (size, size))
    tex = T.make_textures(height=height)
    lights, app = lambert_setup(bump_strength=3.0)
    img = np.asarray(shade(QUAD, EYE, lights, app, mode="bump_diffuse", textures=tex))
    slope = 0.5 * np.cos(2 * np.pi * u) * np.sin(2 * np.pi / size)  # central difference per texel
    n = np.stack([-3.0 * slope, np.zeros(size), np.ones(size)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    row = np.asarray(app.diffuse) * np.array([1.0, 0.9, 0.8]) * 1.5 * (n @ L_DIR)[:, None]
    np.testing.assert_allclose(img[..., :3], np.broadcast_to(row, (N, N, 3)), atol=1e-9)
    # zero height and zero strength both give the plain Lambert image (row 25, graceful)
    flat = lambert_expected(QUAD, lights, app)
    zero = T.make_textures(height=np.zeros((8, 8)))
    np.testing.assert_allclose(
        shade(QUAD, EYE, lights, app, mode="bump_diffuse", textures=zero)[..., :3], flat, atol=1e-12
    )
    app0 = dataclasses.replace(app, bump_strength=jnp.asarray(0.0))
    np.testing.assert_allclose(
        shade(QUAD, EYE, lights, app0, mode="bump_diffuse", textures=tex)[..., :3], flat, atol=1e-12
    )


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_degenerate_frame_is_finite_row24_25():
    """Zero normals / tangents (perturbed normal of zero length) and a zero reflection vector."""
    zero = jnp.zeros((N, N, 3))
    gb = dataclasses.replace(QUAD, normal=zero, tangent=zero, bitangent=zero, face_normal=zero)
    lights, app = lambert_setup()
    tex = T.default_textures(size=16, threads=4)
    sph = make_sphere([0.0, 0.0, 2.0], 0.5)

    @jax.jit
    def every_mode(gb):  # one compile for the forward pass of every mode
        gbc = dataclasses.replace(gb, color=zero)
        return jnp.stack(
            [S.shade(gbc, EYE, lights, app, mode=m, textures=tex, spheres=sph) for m in S.MODES]
        )

    assert bool(jnp.all(jnp.isfinite(every_mode(gb))))

    @jax.jit
    def loss(
        app, gb
    ):  # gradients through bump, env lookups, specular, texture, zero reflection vector
        return S.shade(gb, EYE, lights, app, mode="second_pass", textures=tex, spheres=sph).sum()

    val, (ga, gg) = jax.value_and_grad(loss, argnums=(0, 1))(app, gb)
    assert np.isfinite(float(val))
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves((ga, gg)))


def test_bad_arguments():
    lights, app = lambert_setup()
    with pytest.raises(ValueError, match="mode"):
        S.shade(QUAD, EYE, lights, app, mode="toon")
    with pytest.raises(ValueError, match="refraction"):
        S.shade(QUAD, EYE, lights, app, mode="phong", refraction="exact")
    with pytest.raises(ValueError, match="face_normal"):
        S.shade(dataclasses.replace(QUAD, face_normal=None), EYE, lights, app, mode="flat")
    with pytest.raises(ValueError, match="color"):
        S.shade(QUAD, EYE, lights, app, mode="gouraud")
    with pytest.raises(ValueError, match="eye"):
        S.shade(QUAD, jnp.zeros(2), lights, app, mode="phong")
    with pytest.raises(ValueError, match="shininess"):
        Lm.make_appearance(shininess=0.0)
    with pytest.raises(ValueError, match="unknown"):
        Lm.make_appearance(glossiness=1.0)
    with pytest.raises(ValueError, match="intensity"):
        Lm.make_lights(directional=[((0, 1, 0), (1, 1, 1), -1.0)])
    with pytest.raises(ValueError, match="non-zero"):
        Lm.make_lights(directional=[((0, 0, 0), (1, 1, 1), 1.0)])
