"""Occluded ambient light (render/sky.py): analytic sky visibility, unoccluded = the old ambient,
darker ambient under occluders, gradients vs central FD in float64, config validation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_render_shadows import fd_check, plane_points, square

from diffcloth.render.sky import sky_directions, sky_maps, sky_visibility
from diffcloth.shapes import Sphere, make_plane, make_sphere

UP = jnp.array([0.0, 1.0, 0.0])


def _square_form_factor(a, h):
    """Cosine-weighted fraction of the hemisphere of an upward receiver covered by a parallel
    square of half-size a centred at height h above it (four corner rectangles, the classic
    differential-area-to-rectangle form factor)."""
    x = y = a / h
    f = (
        x / math.sqrt(1 + x * x) * math.atan(y / math.sqrt(1 + x * x))
        + y / math.sqrt(1 + y * y) * math.atan(x / math.sqrt(1 + y * y))
    ) / (2 * math.pi)
    return 4 * f


def test_sky_directions_even_and_deterministic():
    d = sky_directions(32)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    np.testing.assert_array_equal(d, sky_directions(32))
    assert abs(d.mean(axis=0)).max() < 0.05  # spread over the whole sphere
    assert (d[:, 1] > 0).sum() == 16 and np.abs(d[:, 1]).min() > 0  # none on the horizon


@jax.jit
def _plane_sphere_vis(center, pts, nrm):
    sky = sky_maps(64, spheres=Sphere(center, jnp.asarray(0.25)), planes=make_plane((0, 1, 0), 0.0))
    return sky_visibility(sky, pts, nrm)


def test_unoccluded_is_the_old_ambient_and_occluders_darken():
    """Far from the sphere an upward receiver sees the whole sky (A = 1 exactly: the old
    ambient); a wall above the floor about half; the ground beside the sphere and a point under
    it less; a sphere point facing down sees only the floor (A = 0)."""
    c = jnp.array([0.0, 0.5, 0.0])
    pts = jnp.array([[5.0, 0.0, 5.0], [5.0, 1.0, 5.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.0]])
    nrm = jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    a = np.asarray(_plane_sphere_vis(c, pts, nrm))
    assert a[0] == 1.0
    assert 0.4 < a[1] < 0.6
    assert 0.5 < a[2] < 0.97 and a[3] < a[2]
    # analytic: a sphere of radius r at distance D above the receiver covers sin^2 = (r/D)^2 of
    # the cosine-weighted hemisphere
    np.testing.assert_allclose(a[3], 1.0 - (0.25 / 0.5) ** 2, atol=0.05)
    down = np.asarray(_plane_sphere_vis(c, jnp.array([[0.0, 0.25, 0.0]]), -UP[None]))
    assert down[0] == 0.0


@jax.jit
def _mesh_vis(pos, faces, pts, nrm):
    return sky_visibility(sky_maps(64, mesh=(pos, faces), size=64), pts, nrm)


@pytest.mark.slow  # compiles the shadow-map rasterizer (~10-20 s CPU)
def test_sky_visibility_under_a_cloth_square_matches_the_form_factor():
    """Ground under a flat cloth square (shadow maps of the K directions): A = 1 - F, F the
    analytic form factor of the square; the cloth's own top sees the whole sky."""
    pos, faces = square((0.0, 0.5, 0.0), 0.5, n=4)
    pts = jnp.concatenate([jnp.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]]), pos])
    a = np.asarray(_mesh_vis(pos, faces, pts, jnp.broadcast_to(UP, pts.shape)))
    np.testing.assert_allclose(a[0], 1.0 - _square_form_factor(0.5, 0.5), atol=0.04)
    assert a[1] == 1.0
    np.testing.assert_allclose(a[2:], 1.0, atol=1e-3)  # the top of the cloth itself


WEIGHTS = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, size=(9 * 9,)))


def test_sky_visibility_gradient_wrt_sphere_matches_fd():
    """Ground ambient occlusion under a sphere: d/d(centre, radius) vs central FD (float64)."""
    pts, nrm = plane_points(-0.6, 0.6, -0.6, 0.6, 9)

    def loss(p):
        sph = make_sphere([(0.0, 0.4, 0.0)], [0.2])
        sph = type(sph)(p["c"], p["r"])
        sky = sky_maps(16, spheres=sph, planes=make_plane((0, 1, 0), 0.0))
        return jnp.sum(WEIGHTS * sky_visibility(sky, pts, nrm))

    x = {"c": jnp.array([[0.03, 0.4, -0.02]]), "r": jnp.array([0.2])}
    fd_check(loss, x, eps=1e-6, rtol=1e-5)


@pytest.mark.slow  # compiles the shadow-map rasterizer under grad (~30 s CPU)
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_sky_visibility_gradient_wrt_cloth_offset_matches_fd():
    """Ground ambient occlusion under a cloth square moving sideways: d/d(shift) vs FD."""
    pts, nrm = plane_points(-0.6, 0.6, -0.6, 0.6, 9)
    base, faces = square((0.0, 0.4, 0.0), 0.3)

    def loss(p):
        sky = sky_maps(8, mesh=(base + p["shift"][None], faces), size=32)
        return jnp.sum(WEIGHTS * sky_visibility(sky, pts, nrm))

    fd_check(loss, {"shift": jnp.array([0.013, 0.02, -0.011])}, eps=1e-5, rtol=1e-5)


def test_ambient_occlusion_key_and_validation():
    from diffcloth.config import ConfigError, parse_config
    from diffcloth.render import render

    assert parse_config({}).render.ambient_occlusion == 0
    assert parse_config({"render": {"ambient_occlusion": 32}}).render.ambient_occlusion == 32
    for bad, match in (
        (-1, r"\[render\] ambient_occlusion = -1 is out of range"),
        (300, r"ambient_occlusion = 300 is out of range"),
        (2.5, r"ambient_occlusion = 2.5"),
    ):
        with pytest.raises(ConfigError, match=match):
            parse_config({"render": {"ambient_occlusion": bad}})
    with pytest.raises(ValueError, match=r"ambient_occlusion must be an int in \[0, 256\]"):
        sky_maps(-3)
    assert sky_maps(0) is None
    assert "ambient_occlusion" in __import__("inspect").signature(render).parameters


@pytest.mark.slow  # compiles render.render three times (~60 s CPU)
def test_render_ambient_occlusion_on_and_off():
    """A flat cloth square facing up, seen from above, nothing else: the same image with AO on
    and off (float tolerance: shadow-map bias at grazing sky directions); with a sphere under
    the cloth lit by ambient light only, the sphere's visible pixels get darker."""
    from diffcloth import render as R
    from diffcloth.surface import tessellate

    u = np.linspace(-0.4, 0.4, 5)
    x, z = np.meshgrid(u, u, indexing="ij")
    net = jnp.asarray(np.stack([x, np.full_like(x, 0.5), z], -1))
    surf = tessellate(net, 2, "bspline", flip=True)
    cam = R.make_camera((0.0, 2.0, 0.3), (0.0, 0.5, 0.0), (0.0, 1.0, 0.0), width=24, height=24)
    lights = R.make_lights(ambient=(0.3, 0.3, 0.3))
    app = R.make_appearance(specular=(0.0, 0.0, 0.0))
    off = R.render(surf, cam, lights, "phong", app)
    on = R.render(surf, cam, lights, "phong", app, ambient_occlusion=16, shadow_map_size=64)
    np.testing.assert_allclose(on, off, atol=2e-4)
    amb = R.make_lights(ambient=(0.5, 0.5, 0.5), directional=())
    side = R.make_camera((1.6, 0.3, 0.0), (0.0, 0.3, 0.0), (0.0, 1.0, 0.0), width=24, height=24)
    ball = make_sphere((0.0, 0.25, 0.0), 0.2)
    kw = dict(spheres=ball, shadow_map_size=64)
    off = np.asarray(R.render(surf, side, amb, "phong", app, **kw))
    on = np.asarray(R.render(surf, side, amb, "phong", app, ambient_occlusion=16, **kw))
    assert np.all(on[..., :3] <= off[..., :3] + 1e-6)
    assert (off - on)[..., :3].max() > 0.05
