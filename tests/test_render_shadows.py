"""Shadows: analytic images (sphere umbra, cloth-square shadow), no acne, and gradients w.r.t.
light direction and occluder position vs central finite differences in float64."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import lights as Lm
from diffcloth.render.camera import make_camera
from diffcloth.render.frame import render
from diffcloth.render.shadows import shadow_maps, shadow_visibility, sphere_visibility
from diffcloth.shapes import make_plane, make_sphere

UP = jnp.array([0.0, 1.0, 0.0])


def plane_points(x0, x1, z0, z1, n):
    """(n*n, 3) receivers on the ground y = 0 and their normals."""
    x, z = np.meshgrid(np.linspace(x0, x1, n), np.linspace(z0, z1, n), indexing="ij")
    p = np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3)
    return jnp.asarray(p), jnp.broadcast_to(UP, p.shape)


def square(center, half, n=4):
    """A flat cloth square (positions (n*n, 3), faces) at `center`, normal +y."""
    u = np.linspace(-half, half, n)
    x, z = np.meshgrid(u, u, indexing="ij")
    pos = np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3) + np.asarray(center)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            f += [[a, b, d], [a, d, c]]
    return jnp.asarray(pos), jnp.asarray(np.array(f, np.int32))


def lights_toward(direction, softness, shadows=True):
    return Lm.make_lights(
        ambient=(0.1, 0.1, 0.1),
        directional=[(direction, (1.0, 1.0, 1.0), 1.0)],
        shadows=shadows,
        softness=softness,
    )


# ----------------------------------------------------------------------------- configuration


def test_make_lights_shadow_flags_and_validation():
    lights = Lm.make_lights(
        directional=[((0, 1, 0), (1, 1, 1), 1.0)],
        point=[((0, 2, 0), (1, 1, 1), 1.0)],
        shadows=[False, True],
        softness=[1.0, 3.0],
    )
    assert lights.shadows == (False, True) and lights.casts_shadows
    np.testing.assert_allclose(lights.point_softness, [3.0])
    assert Lm.make_lights().shadows == () and not Lm.make_lights().casts_shadows
    with pytest.raises(ValueError, match="shadows"):
        Lm.make_lights(shadows=[True, True])
    with pytest.raises(ValueError, match="softness"):
        Lm.make_lights(shadows=True, softness=0.0)
    with pytest.raises(ValueError, match="softness"):
        Lm.make_lights(shadows=True, softness=[1.0, 2.0])


# ----------------------------------------------------------------------------- analytic images


@jax.jit
def _map_vis(lights, pos, faces, pts, nrm):
    """Mesh shadow visibility; the cloth-square and acne tests share it (one compile)."""
    return shadow_visibility(shadow_maps(lights, mesh=(pos, faces), size=64), pts, nrm)


def test_sphere_umbra_where_the_math_says():
    """Sphere (c, r) above the ground, directional light L: the shadow is the ellipse around
    c - (c_y / L_y) L with semi-axes r / L_y' along the light's ground direction and r across."""
    c, r = np.array([0.1, 0.5, -0.05]), 0.2
    ldir = np.array([0.5, 1.0, 0.0]) / np.linalg.norm([0.5, 1.0, 0.0])
    center = c - c[1] / ldir[1] * ldir
    along = r / ldir[1]  # semi-axis along x (ground projection of L)
    ts = np.array([0.0, 0.5, 0.9, 1.1, 1.5])
    pts = np.concatenate(
        [center + np.outer(ts * along, [1, 0, 0]), center + np.outer(ts * r, [0, 0, 1])]
    )
    sph = make_sphere([c], [r])
    pts = np.concatenate([pts, [center + [along, 0, 0], center + [0, 0, r]]])
    vis = np.asarray(
        jax.jit(sphere_visibility)(
            jnp.asarray(pts),
            jnp.broadcast_to(jnp.asarray(ldir), pts.shape),
            sph.batched(),
            jnp.tan(jnp.deg2rad(0.5)),
        )
    )
    for k in (0, 5):  # along, across
        np.testing.assert_allclose(vis[k : k + 3], 0.0, atol=1e-9)  # umbra
        np.testing.assert_allclose(vis[k + 3 : k + 5], 1.0, atol=1e-9)  # lit
    # at the analytic edge the light disc is half covered
    edge = vis[10:]
    np.testing.assert_allclose(edge, 0.5, atol=0.05)


def test_cloth_square_shadow_map_image():
    """A cloth square at height h casts its square shadow shifted by -h L_x / L_y on the ground;
    receivers well inside are dark, well outside lit."""
    h, half = 0.6, 0.3
    pos, faces = square((0.0, h, 0.0), half, 12)  # same shapes as the acne test: one compile
    ldir = np.array([0.4, 1.0, 0.0])
    shift = -h * ldir[0] / ldir[1]  # shadows fall away from the light
    lights = Lm.make_lights(
        directional=[(ldir, (1, 1, 1), 1.0)],
        point=[((0.0, 3.0, 0.0), (1, 1, 1), 1.0)],
        shadows=True,
        softness=1.0,
    )
    inside = np.array(
        [[shift + a * half, 0.0, b * half] for a in (-0.7, 0, 0.7) for b in (-0.7, 0, 0.7)]
    )
    outside = np.array(
        [
            [shift + a * half, 0.0, b * half]
            for a, b in ((1.3, 0), (-1.3, 0), (0, 1.3), (0, -1.3), (1.4, 1.4))
        ]
    )
    pts = np.concatenate([inside, outside])
    pts = jnp.asarray(np.concatenate([pts, np.repeat(pts[:1], 144 - len(pts), axis=0)]))
    vis = np.asarray(_map_vis(lights, pos, faces, pts, jnp.broadcast_to(UP, pts.shape)))[:14, 0]
    np.testing.assert_allclose(vis[:9], 0.0, atol=1e-6)
    np.testing.assert_allclose(vis[9:], 1.0, atol=1e-6)


def test_no_self_shadow_acne():
    """A gently curved cloth (slopes below the light's elevation) cannot shadow itself: its own
    vertices stay fully lit, for a directional and a point light."""
    n = 12
    x, z = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n), indexing="ij")
    y = 0.08 * np.sin(3 * x) * np.cos(2 * z)
    pos = jnp.asarray(np.stack([x, y, z], -1).reshape(-1, 3))
    _, faces = square((0, 0, 0), 0.5, n)
    gx = 0.24 * np.cos(3 * x) * np.cos(2 * z)
    gz = -0.16 * np.sin(3 * x) * np.sin(2 * z)
    nrm = jnp.asarray(np.stack([-gx, np.ones_like(x), -gz], -1).reshape(-1, 3))
    lights = Lm.make_lights(
        directional=[((0.3, 1.0, 0.2), (1, 1, 1), 1.0)],
        point=[((-0.4, 1.5, 0.3), (1, 1, 1), 1.0)],
        shadows=True,
        softness=2.0,
    )
    vis = np.asarray(_map_vis(lights, pos, faces, pos, nrm))
    assert vis.min() > 0.999, vis.min()
    # and the underside, seen from a light below, is lit too (two-sided receivers)
    below = Lm.make_lights(
        directional=[((0.2, -1.0, 0.1), (1, 1, 1), 1.0)],
        point=[((0.3, -1.5, 0.0), (1, 1, 1), 1.0)],
        shadows=True,
    )
    vis = np.asarray(_map_vis(below, pos, faces, pos, nrm))
    assert vis.min() > 0.999, vis.min()


def _plain_surface(pos, faces):
    """A Surface-like mesh (normals +y) for `render`."""
    from types import SimpleNamespace

    n = pos.shape[0]
    one = jnp.ones((n, 3))
    return SimpleNamespace(
        positions=pos,
        normals=one * UP[None],
        tangents=one * jnp.array([[1.0, 0, 0]]),
        bitangents=one * jnp.array([[0, 0, 1.0]]),
        uv=jnp.zeros((n, 2)),
        faces=faces,
    )


@pytest.mark.slow
def test_render_ground_plane_receives_sphere_shadow_only_ambient_in_umbra():
    """Top-down orthographic render of the ground (drawn from [[planes]]) under a sphere that is
    not drawn, light straight down: pixels inside the umbra disc are exactly plane albedo *
    ambient (a Lambertian surface in shadow gets only ambient light), pixels outside are albedo *
    (ambient + 1); without shadows every pixel is lit."""
    from diffcloth.render.camera import pixel_rays
    from diffcloth.render.frame import PLANE_COLOR

    pos, faces = square((3.0, 0.5, 3.0), 0.05, 2)  # a tiny cloth outside the view
    surf = _plain_surface(pos, faces)
    cam = make_camera(
        (0.0, 2.0, 0.0),
        (0.0, 0.0, 0.0),
        (0, 0, -1),
        width=24,
        height=24,
        projection="orthographic",
        fov_y=30.0,
    )
    app = Lm.make_appearance()
    sph = make_sphere([(0.0, 0.5, 0.0)], [0.3])

    @jax.jit
    def run(lights):
        return render(
            surf,
            cam,
            lights,
            "phong",
            app,
            spheres=sph,
            draw_spheres=False,
            planes=make_plane((0, 1, 0), 0.0),
            background=None,
            shadow_map_size=16,
        )

    img = np.asarray(run(lights_toward((0.0, 1.0, 0.0), 0.5)))
    flat = np.asarray(run(lights_toward((0.0, 1.0, 0.0), 0.5, shadows=False)))
    o, _ = pixel_rays(cam)
    r = np.hypot(np.asarray(o[..., 0]), np.asarray(o[..., 2]))
    albedo = np.asarray(PLANE_COLOR)
    np.testing.assert_allclose(img[..., 3], 1.0)  # the ground covers the view
    inside, outside = r < 0.27, r > 0.33
    assert inside.sum() > 20 and outside.sum() > 100
    np.testing.assert_allclose(
        img[inside][:, :3], np.broadcast_to(albedo * 0.1, (inside.sum(), 3)), atol=1e-9
    )
    np.testing.assert_allclose(
        img[outside][:, :3], np.broadcast_to(albedo * 1.1, (outside.sum(), 3)), atol=1e-9
    )
    np.testing.assert_allclose(
        flat[..., :3], np.broadcast_to(albedo * 1.1, flat[..., :3].shape), atol=1e-9
    )


# ----------------------------------------------------------------------------- gradients


def fd_check(loss, x, *, eps=1e-5, rtol=2e-3):
    """Reverse-mode directional derivative of `loss` at pytree `x` vs central differences."""
    leaves, tree = jax.tree.flatten(x)
    rng = np.random.default_rng(3)
    v = jax.tree.unflatten(tree, [jnp.asarray(rng.normal(size=np.shape(a))) for a in leaves])
    f = jax.jit(loss)
    g = jax.jit(jax.grad(loss))(x)
    assert all(bool(jnp.all(jnp.isfinite(a))) for a in jax.tree.leaves(g))
    ad = sum(
        float(jnp.vdot(a, b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v), strict=True)
    )
    plus = jax.tree.map(lambda a, b: a + eps * b, x, v)
    minus = jax.tree.map(lambda a, b: a - eps * b, x, v)
    fd = (float(f(plus)) - float(f(minus))) / (2 * eps)
    assert abs(ad) > 1e-3, "gradient is ~zero: the check would pass vacuously"
    np.testing.assert_allclose(ad, fd, rtol=rtol)
    for k, a in x.items() if isinstance(x, dict) else []:
        assert float(jnp.abs(a).max()) > 0, k
    return ad, fd


WEIGHTS = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, size=(15 * 15,)))


def test_sphere_shadow_gradients_match_fd():
    """Ground visibility under a sphere: d/d(light direction, sphere centre, radius, softness)."""
    pts, nrm = plane_points(-0.8, 0.4, -0.6, 0.6, 15)

    def loss(p):
        lights = dataclasses.replace(
            lights_toward((0.4, 1.0, 0.1), 4.0),
            direction=p["dir"][None],
            direction_softness=p["soft"][None],
        )
        sph = make_sphere([(0.0, 0.5, 0.0)], [0.25])
        sph = dataclasses.replace(sph, center=p["c"], radius=p["r"])
        maps = shadow_maps(lights, spheres=sph)
        return jnp.sum(WEIGHTS * shadow_visibility(maps, pts, nrm)[:, 0])

    x = {
        "dir": jnp.array([0.4, 1.0, 0.1]),
        "soft": jnp.array(4.0),
        "c": jnp.array([[0.02, 0.5, -0.03]]),
        "r": jnp.array([0.25]),
    }
    fd_check(loss, x, eps=1e-6, rtol=1e-5)


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_cloth_shadow_gradients_match_fd():
    """Ground visibility under a cloth square (shadow map): d/d(light direction, cloth
    position); the shadow edge moves smoothly (antialiased map coverage + bilinear PCF)."""
    pts, nrm = plane_points(-0.6, 0.8, -0.6, 0.6, 15)
    base, faces = square((0.0, 0.5, 0.0), 0.3)

    def loss(p):
        lights = dataclasses.replace(lights_toward((0.4, 1.0, 0.1), 3.0), direction=p["dir"][None])
        maps = shadow_maps(lights, mesh=(base + p["shift"][None], faces), size=32)
        return jnp.sum(WEIGHTS * shadow_visibility(maps, pts, nrm)[:, 0])

    x = {"dir": jnp.array([0.4, 1.0, 0.1]), "shift": jnp.array([0.013, 0.02, -0.011])}
    fd_check(loss, x, eps=1e-5, rtol=1e-5)


# ----------------------------------------------------------------------------- config, pipeline

SCENE_CONFIG = {
    "net": {"rows": 4, "cols": 4, "width": 0.6, "height": 0.6, "center": [0.0, 0.5, 0.0]},
    "sim": {"num_frames": 2, "num_substeps": 4, "integrator": "implicit"},
    "spheres": [{"center": [0.3, 0.25, 0.3], "radius": 0.12}],
    "planes": [{"normal": [0.0, 1.0, 0.0], "offset": 0.0}],
    "render": {"width": 16, "height": 16, "level": 2, "draw_planes": True, "shadow_map_size": 16},
    "camera": {"eye": [0.0, 2.0, 1.2], "target": [0.0, 0.0, 0.0]},
    "lights": {
        "ambient": [0.1, 0.1, 0.1],
        "directional": [{"direction": [0.2, 1.0, 0.1], "shadows": True, "softness": 3.0}],
        "point": [{"position": [1.0, 2.0, 0.0], "shadows": False}],
    },
}


def test_config_keys_build_shadowed_scene_and_validate():
    from diffcloth.config import ConfigError, parse_config
    from diffcloth.scene import build_scene

    scene = build_scene(parse_config(SCENE_CONFIG))
    assert scene.lights.shadows == (True, False) and scene.draw_planes
    assert scene.shadow_map_size == 16
    np.testing.assert_allclose(scene.lights.direction_softness, [3.0])
    plain = build_scene(parse_config({k: v for k, v in SCENE_CONFIG.items() if k != "lights"}))
    assert plain.lights.shadows == () and not plain.lights.casts_shadows
    bad = [
        ({"lights": {"directional": [{"softness": 0.0}]}}, r"softness = 0.0 is out of range"),
        ({"lights": {"point": [{"position": [0, 1, 0], "shadows": 1}]}}, r"shadows = 1 must be"),
        ({"render": {"shadow_map_size": 4}}, r"shadow_map_size = 4 is out of range"),
        ({"render": {"draw_planes": "yes"}}, r"draw_planes = 'yes' must be true or false"),
    ]
    for data, match in bad:
        with pytest.raises(ConfigError, match=match):
            parse_config(data)


@pytest.mark.slow
def test_simulate_and_render_every_mode_with_shadows():
    """Through the pipeline, the three shadow code paths (per-vertex gouraud, per-pixel
    light sum of minnaert, blinn_phong specular + environment of reflect_refract) render finite
    images with shadows, darker than without, never brighter anywhere. (All ten modes took 14
    min on the loaded CPU; the first six passed, the gallery renders all ten with shadows.)"""
    from diffcloth import pipeline
    from diffcloth.config import parse_config
    from diffcloth.render.shade import MODES
    from diffcloth.scene import build_scene

    scene = build_scene(parse_config(SCENE_CONFIG))
    off = dataclasses.replace(scene, lights=dataclasses.replace(scene.lights, shadows=()))
    traj = jax.jit(pipeline.simulate)(scene)
    xs = traj.x[-1:]
    for mode in ("gouraud", "minnaert", "reflect_refract"):
        assert mode in MODES
        run = jax.jit(
            lambda s, m=mode: pipeline.render_frames(dataclasses.replace(s, shading=m), xs)
        )
        lit, dark = np.asarray(run(off)), np.asarray(run(scene))
        assert np.all(np.isfinite(dark)), mode
        assert dark.sum() < lit.sum() - 0.5, (mode, lit.sum(), dark.sum())
        assert np.all(dark <= lit + 1e-6), mode  # shadows only remove light


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_render_gradients_through_shadows_match_fd():
    """Through `render`: a cloth square and a sphere (not drawn) shadow the drawn ground under a
    top-down camera; d(image loss)/d(light direction, sphere centre, cloth height) vs FD."""
    pos0, faces = square((0.25, 0.6, -0.2), 0.2, 4)
    cam = make_camera(
        (0.0, 2.0, 0.0),
        (0.0, 0.0, 0.0),
        (0, 0, -1),
        width=20,
        height=20,
        projection="orthographic",
        fov_y=40.0,
    )
    app = Lm.make_appearance()
    w = jnp.asarray(np.random.default_rng(5).uniform(0.5, 1.5, size=(20, 20, 4)))

    def loss(p):
        lights = dataclasses.replace(lights_toward((0.2, 1.0, 0.1), 4.0), direction=p["dir"][None])
        surf = _plain_surface(pos0 + jnp.stack([0.0, p["lift"], 0.0])[None], faces)
        img = render(
            surf,
            cam,
            lights,
            "phong",
            app,
            spheres=make_sphere([(0.0, 0.4, 0.0)], [0.2]).__class__(p["c"], jnp.array([0.2])),
            draw_spheres=False,
            planes=make_plane((0, 1, 0), 0.0),
            background=None,
            shadow_map_size=32,
        )
        return jnp.sum(w * img)

    x = {
        "dir": jnp.array([0.2, 1.0, 0.1]),
        "c": jnp.array([[-0.2, 0.4, 0.15]]),
        "lift": jnp.array(0.01),
    }
    fd_check(loss, x, eps=1e-5, rtol=1e-4)
