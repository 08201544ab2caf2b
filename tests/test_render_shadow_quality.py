"""Shadow quality presets (render/shadow_quality.py): "fit" map sizes and filters, the config key,
the analytic sphere form factor of ambient occlusion, and the gradient of a whole simulated and
rendered video with shadows and occlusion on at the "fit" preset vs central FD in float64."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render.shadow_quality import FIT_SKY_MIN, shadow_settings
from diffcloth.render.sky import sky_maps, sky_visibility, sphere_form_factor
from diffcloth.shapes import make_sphere

CONFIG = {
    "net": {
        "rows": 4,
        "cols": 4,
        "width": 0.6,
        "height": 0.6,
        "center": [0.0, 0.5, 0.0],
        "pinned": "top_corners",
    },
    "sim": {"num_frames": 2, "num_substeps": 4, "integrator": "implicit"},
    "spheres": [{"center": [0.1, 0.22, 0.05], "radius": 0.15}],
    "planes": [{"normal": [0.0, 1.0, 0.0], "offset": 0.0}],
    "render": {
        "width": 20,
        "height": 20,
        "level": 2,
        "draw_planes": True,
        "ambient_occlusion": 8,
        "shadow_quality": "fit",
    },
    "camera": {"eye": [0.3, 1.6, 1.3], "target": [0.0, 0.25, 0.0]},
    "lights": {
        "ambient": [0.3, 0.3, 0.3],
        "directional": [{"direction": [0.3, 1.0, 0.2], "shadows": True, "softness": 3.0}],
    },
}


def test_fit_preset_sizes_and_validation():
    full = shadow_settings("full", 256, 64)
    assert (full.map_size, full.taps, full.sky_size, full.analytic_spheres) == (256, 4, 128, False)
    for image, light, sky, discs in (
        (64, 32, FIT_SKY_MIN, 12),
        (32, 32, FIT_SKY_MIN, 8),
        (128, 64, 32, 16),
        (100, 52, 32, 16),
        (512, 256, 128, 16),
    ):
        st = shadow_settings("fit", 256, image)
        assert (st.map_size, st.sky_size, st.taps, st.sky_taps) == (light, sky, 1, 1)
        assert st.disc_grid == discs
        assert st.analytic_spheres and st.light_per_vertex
    assert not full.light_per_vertex
    with pytest.raises(ValueError, match="shadow_quality must be one of"):
        shadow_settings("fast", 256, 64)


def test_config_key():
    from diffcloth.config import ConfigError, parse_config
    from diffcloth.scene import build_scene

    scene = build_scene(parse_config(CONFIG))
    assert scene.shadow_quality == "fit" and scene.ambient_occlusion == 8
    assert build_scene(parse_config({**CONFIG, "render": {}})).shadow_quality == "full"
    with pytest.raises(ConfigError, match="shadow_quality"):
        parse_config({**CONFIG, "render": {"shadow_quality": "fast"}})


def test_sphere_form_factor_is_the_many_direction_limit():
    """The analytic form factor against the per-direction estimate with 256 sky directions, for
    normals from facing the sphere to facing away (through the horizon-crossing branch)."""
    sph = make_sphere([(0.0, 0.5, 0.0)], [0.25])
    a = np.linspace(0.0, math.pi, 13)
    nrm = jnp.asarray(np.stack([np.sin(a), np.cos(a), 0 * a], -1))
    pts = jnp.zeros_like(nrm)
    ff = np.asarray(sphere_form_factor(pts, nrm, sph))[:, 0]
    est = 1.0 - np.asarray(sky_visibility(sky_maps(256, spheres=sph), pts, nrm))
    np.testing.assert_allclose(ff, est, atol=3e-3)
    assert ff[0] == pytest.approx(0.25) and ff[-1] == 0.0  # (r / d)^2 straight above
    fast = sky_maps(8, spheres=sph, analytic_spheres=True)
    assert fast.shadows is None  # no shadow maps at all for a sphere-only scene
    np.testing.assert_allclose(sky_visibility(fast, pts, nrm), 1.0 - ff, atol=1e-6)

    def f(t):
        return sphere_form_factor(pts[:1], jnp.stack([jnp.sin(t), jnp.cos(t), 0.0])[None], sph)[
            0, 0
        ]

    for t in (0.3, 1.2, 1.6, 2.0):  # above the horizon, crossing it
        fd = (f(t + 1e-6) - f(t - 1e-6)) / 2e-6
        np.testing.assert_allclose(jax.grad(f)(t), fd, rtol=1e-6)


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_video_gradient_with_fit_shadows_and_occlusion_matches_fd():
    """d(video loss) / d(stretch (through the rollout), light direction, sphere collider centre)
    with a shadowed light and 8-direction occlusion at the "fit" preset, float64, vs central FD;
    each parameter separately (a sum could hide one wrong term)."""
    from diffcloth import pipeline
    from diffcloth.config import parse_config
    from diffcloth.scene import build_scene

    scene = build_scene(parse_config(CONFIG), dtype=jnp.float64)
    w = jnp.asarray(np.random.default_rng(7).uniform(0.5, 1.5, (1, 2, 20, 20, 3)))

    def loss(p):
        sph = dataclasses.replace(scene.spheres, center=p["center"])
        col = dataclasses.replace(
            scene.colliders,
            spheres=dataclasses.replace(scene.colliders.spheres, center=p["center"]),
        )
        sc = dataclasses.replace(scene, spheres=sph, colliders=col)
        params = {"stretch": p["stretch"], "light_direction": p["dir"]}
        return jnp.sum(w * pipeline.simulate_and_render(sc, params))

    x = {
        "stretch": jnp.asarray(scene.material.stretch),
        "dir": jnp.asarray(scene.lights.direction),
        "center": jnp.asarray(scene.spheres.center),
    }
    g = jax.jit(jax.grad(loss))(x)
    f = jax.jit(loss)
    rng = np.random.default_rng(3)
    results = {}
    for name in x:
        # a relative step (the stiffness is in the hundreds): d/d(log stretch) for a scalar
        scale = max(1.0, float(jnp.abs(x[name]).max()))
        v = jnp.asarray(rng.normal(size=np.shape(x[name])) if np.ndim(x[name]) else 1.0) * scale
        ad = float(jnp.vdot(g[name], v))
        eps = 1e-6
        step = lambda s, name=name, v=v: {**x, name: x[name] + s * v}  # noqa: E731
        fd = (float(f(step(eps))) - float(f(step(-eps)))) / (2 * eps)
        results[name] = (ad, fd)
    for name, (ad, fd) in results.items():
        assert abs(ad) > 1e-3, results  # not vacuous
        # 1e-3: the stiffness moves the image little (d/d log stretch ~ 3e-3), so the FD's
        # round-off is ~1e-4 of it
        np.testing.assert_allclose(ad, fd, rtol=1e-3, err_msg=f"{name}: {results}")


def test_analytic_sky_under_a_cloth_square_matches_the_form_factor():
    """The "fit" occlusion (no maps: the mesh as discs, the ground plane's half): the ground
    under a flat square sees 1 - F (F the analytic form factor of the square), far away 1; the
    square's own top 1; a wall receiver above the ground about 1/2."""
    from test_render_ambient_occlusion import _square_form_factor
    from test_render_shadows import square

    from diffcloth.shapes import make_plane

    pos, faces = square((0.0, 0.5, 0.0), 0.5, n=16)
    sky = sky_maps(8, mesh=(pos, faces), planes=make_plane((0, 1, 0), 0.0), analytic=True)
    assert sky.shadows is None
    pts = jnp.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 1.0, 0.0]])
    nrm = jnp.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    a = np.asarray(sky_visibility(sky, pts, nrm))
    np.testing.assert_allclose(a[0], 1.0 - _square_form_factor(0.5, 0.5), atol=0.01)
    assert a[1] > 0.998 and abs(a[2] - 0.5) < 0.01
    top = sky_visibility(sky, pos, jnp.broadcast_to(jnp.array([0.0, 1.0, 0.0]), pos.shape))
    np.testing.assert_allclose(top, 1.0)


def test_disc_occlusion_derivatives_equal_the_closed_forms_in_both_modes():
    """`sky_discs.disc_occlusion`'s custom JVP against autodiff of the closed form written out
    here (float64), reverse and forward mode, with receivers on a disc centre (excluded pairs),
    discs behind receivers (clipped cosines) and an input held constant (a symbolic zero)."""
    from diffcloth.render.sky_discs import disc_occlusion

    def closed_form(points, normals, discs):
        centre, dn, area = discs
        v = centre[None] - points[:, None]
        d2 = jnp.sum(v * v, axis=-1)
        ok = d2 > 1e-12
        inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, d2, 1.0)), 0.0)
        cos_r = jnp.maximum(jnp.sum(v * normals[:, None], -1) * inv, 0.0)
        cos_e = jnp.abs(jnp.sum(v * dn[None], -1)) * inv
        return jnp.sum(area[None] * cos_e * cos_r / (np.pi * d2 + area[None]), -1)

    rng = np.random.default_rng(3)
    p = rng.normal(size=(30, 3))
    n = rng.normal(size=(30, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    c = rng.normal(size=(20, 3))
    c[:4] = p[:4]  # receivers sitting on disc centres
    args = [jnp.asarray(x) for x in (p, n, c, rng.normal(size=(20, 3)), rng.uniform(size=20))]
    w = jnp.asarray(rng.uniform(size=30))
    ours = lambda *x: jnp.sum(w * disc_occlusion(x[0], x[1], x[2:]))
    ref = lambda *x: jnp.sum(w * closed_form(x[0], x[1], x[2:]))
    np.testing.assert_allclose(ours(*args), ref(*args), rtol=1e-12)
    grads = jax.grad(ours, range(5))(*args), jax.grad(ref, range(5))(*args)
    for g, h in zip(*grads, strict=True):
        np.testing.assert_allclose(g, h, rtol=1e-9, atol=1e-12)
    # forward mode: every input moving, then subsets (the others held: symbolic zeros)
    tangents = [jnp.asarray(rng.normal(size=a.shape)) for a in args]
    for moving in ((0, 1, 2, 3, 4), (0,), (1, 3), (2, 4)):

        def along(fn, moving=moving):
            def f(*m):
                full = [m[moving.index(i)] if i in moving else a for i, a in enumerate(args)]
                return fn(full[0], full[1], full[2:])

            sub = tuple(args[i] for i in moving)
            return jax.jvp(f, sub, tuple(tangents[i] for i in moving))[1]

        np.testing.assert_allclose(along(disc_occlusion), along(closed_form), rtol=1e-9, atol=1e-12)
    assert float(jnp.max(jnp.abs(grads[1][0]))) > 0 and args[0].dtype == jnp.float64


@pytest.mark.parametrize("side", [9, 17])
def test_fit_preset_looks_the_cloth_light_up_per_vertex_close_to_per_pixel(side):
    """The "fit" preset's cloth visibility is looked up at the vertices and interpolated by the
    rasterizer: on a tessellated sheet half in a sphere's shadow it stays within a few per cent
    of the per-pixel lookup on average (it differs only across the shadow's edge), and both see
    the shadow. side 17: the tessellated grid has more vertex rows than the map has texels, so
    the lookup runs on a coarse sub-grid, interpolated along the grid (`grid_coarse`)."""
    from diffcloth.render import lights as Lm
    from diffcloth.render.camera import make_camera
    from diffcloth.render.frame import surface_gbuffer
    from diffcloth.render.shadows import shadow_maps
    from diffcloth.surface import tessellate

    x, z = np.meshgrid(np.linspace(-0.5, 0.5, side), np.linspace(-0.5, 0.5, side))
    net = jnp.asarray(np.stack([x, 0.02 * np.sin(4 * x), z], -1), jnp.float32)
    surf = tessellate(net, 4)
    assert (max(surf.grid_shape) > 32) == (side == 17)  # the map below has 32 texels a side
    lights = Lm.make_lights(directional=[((0.2, 1.0, 0.1), (1.0, 1.0, 1.0), 2.0)],
                            shadows=True, dtype=jnp.float32)  # fmt: skip
    sph = make_sphere([(0.15, 0.3, 0.0)], [0.15], dtype=jnp.float32)
    cam = make_camera((0.0, 1.5, 0.8), (0.0, 0.0, 0.0), (0, 1, 0), width=64, height=64)
    app = Lm.make_appearance(dtype=jnp.float32)
    vis = {}
    for per_vertex in (False, True):
        # jitted: run op by op, the rasterizer's many small programs compiled one by one

        @jax.jit
        def gbuffer(s, per_vertex=per_vertex):
            maps = shadow_maps(lights, mesh=(s.positions, s.faces), spheres=sph, size=32,
                               taps=1, fast=True, per_vertex=per_vertex)  # fmt: skip
            gb = surface_gbuffer(s, cam, lights, app, shadows=maps)[0]
            return gb.mask, gb.visibility

        mask, visibility = gbuffer(surf)
        m = np.asarray(mask) > 0.5
        vis[per_vertex] = np.asarray(visibility)[..., 0][m]
    shaded = vis[False] < 0.5
    assert 0.05 < shaded.mean() < 0.6, shaded.mean()  # the shadow is on the sheet
    assert np.mean(np.abs(vis[True] - vis[False])) < 0.03
    assert np.mean(vis[True][shaded]) < 0.3  # the umbra stays dark per vertex
