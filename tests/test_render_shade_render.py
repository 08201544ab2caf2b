"""render(): rasterize a Surface, shade, composite spheres, over a background."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth._math import static_zero
from diffcloth.render import lights as Lm
from diffcloth.render import shade as S
from diffcloth.render import textures as T
from diffcloth.render.camera import make_camera
from diffcloth.render.frame import render
from diffcloth.shapes import make_sphere
from diffcloth.surface import tessellate

N = 24
BG = (0.1, 0.2, 0.3)
L_DIR = np.array([0.2, 0.3, 0.9]) / np.linalg.norm([0.2, 0.3, 0.9])


@pytest.fixture(scope="module")
def scene():
    # flat square cloth in the z = 0 plane, normals +z, filling the middle of an orthographic view
    x, y = np.meshgrid(np.linspace(-0.8, 0.8, 5), np.linspace(0.8, -0.8, 5))
    net = jnp.asarray(np.stack([x, y, np.zeros_like(x)], -1))
    surf = tessellate(net, 4)
    if float(surf.normals[0, 2]) < 0:
        surf = tessellate(net, 4, flip=True)
    cam = make_camera((0, 0, 3), (0, 0, 0), (0, 1, 0), width=N, height=N, projection="orthographic")
    lights = Lm.make_lights(ambient=(0.0, 0.0, 0.0), directional=[(L_DIR, (1, 1, 1), 1.0)])
    app = Lm.make_appearance(specular=(0.0, 0.0, 0.0))
    return surf, cam, lights, app


render_jit = jax.jit(render, static_argnames=("shading", "draw_spheres", "antialiased"))


def test_render_phong_flat_cloth_and_sphere(scene):
    surf, cam, lights, app = scene
    sph = make_sphere([0.45, 0.45, 0.5], 0.25)  # in front of the cloth's upper-right part

    def loss(center, direction):
        lt = dataclasses.replace(lights, direction=direction[None])
        s = dataclasses.replace(sph, center=center)
        img = render(surf, cam, lt, "phong", app, spheres=s, background=BG)
        return jnp.sum(img**2), img

    # one compile for the image and the gradient (a forward jit beside it compiled twice)
    (_, img), g = jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))(
        sph.center, lights.direction[0]
    )
    img = np.asarray(img)
    assert img.shape == (N, N, 4) and np.all(np.isfinite(img))
    yy, xx = np.meshgrid(np.linspace(1, -1, N), np.linspace(-1, 1, N), indexing="ij")  # approx.
    far_from_sphere = (xx - 0.45) ** 2 + (yy - 0.45) ** 2 > 0.45**2
    inside = (img[..., 3] > 0.999) & far_from_sphere
    outside = (img[..., 3] < 1e-6) & far_from_sphere
    assert inside.sum() > 20 and outside.sum() > 20
    lam = np.asarray(app.diffuse) * L_DIR[2]
    np.testing.assert_allclose(
        img[inside][:, :3], np.broadcast_to(lam, (inside.sum(), 3)), atol=1e-6
    )
    np.testing.assert_allclose(
        img[outside][:, :3], np.broadcast_to(BG, (outside.sum(), 3)), atol=1e-9
    )
    # the sphere hides the cloth at its centre: lit sphere colour, normal +z there
    i, j = int(round((1 - 0.45) / 2 * N - 0.5)), int(round((1 + 0.45) / 2 * N - 0.5))
    sphere_front = np.asarray(app.sphere_color) * L_DIR[2]
    np.testing.assert_allclose(img[i, j, :3], sphere_front, atol=0.05)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)
    assert float(jnp.abs(g[0]).sum()) > 0 and float(jnp.abs(g[1]).sum()) > 0


@pytest.mark.slow
def test_render_every_mode_finite(scene):
    surf, cam, lights, app = scene
    tex = T.default_textures(size=16, threads=4)
    sph = make_sphere([0.5, 0.0, 0.5], 0.3)
    for mode in S.MODES:
        img = render_jit(surf, cam, lights, mode, app, spheres=sph, textures=tex)
        assert bool(jnp.all(jnp.isfinite(img))), mode
    flat = render_jit(surf, cam, lights, "flat", app)
    phong = render_jit(surf, cam, lights, "phong", app)
    gouraud = render_jit(surf, cam, lights, "gouraud", app)
    np.testing.assert_allclose(flat, phong, atol=1e-6)  # planar cloth: all three agree
    np.testing.assert_allclose(gouraud, phong, atol=1e-6)


def test_render_bad_mode(scene):
    surf, cam, lights, app = scene
    with pytest.raises(ValueError, match="shading"):
        render(surf, cam, lights, "toon", app)


def test_fixed_zero_specular_skips_the_highlight_with_the_same_image(scene):
    """A concrete all-zero specular colour leaves Blinn-Phong's highlight out of the program;
    the image and the gradient w.r.t. the diffuse colour equal those of the full model, whose
    specular is traced (here: passed as an argument) and zero."""
    surf, cam, lights, app = scene

    def image(spec, diffuse):
        a = dataclasses.replace(app, diffuse=diffuse, specular=spec)
        return render(surf, cam, lights, "phong", a, background=BG)

    def loss(spec, diffuse):
        return jnp.sum(image(spec, diffuse)[..., :3] ** 2)

    zero = jnp.zeros(3)
    fixed = jax.jit(jax.value_and_grad(lambda d: loss(zero, d)))
    traced = jax.jit(jax.value_and_grad(loss, argnums=1))
    assert static_zero(np.zeros(3)) and not static_zero(np.array([0.0, 0.1, 0.0]))
    (v0, g0), (v1, g1) = fixed(app.diffuse), traced(zero, app.diffuse)
    np.testing.assert_allclose(v0, v1, rtol=1e-6)
    np.testing.assert_allclose(g0, g1, rtol=1e-6, atol=1e-9)
    assert float(jnp.abs(g0).max()) > 0
    # the highlight is left out: no power (exp of a log) in the fixed program's shading
    assert "exponential" not in fixed.lower(app.diffuse).as_text()
    assert "exponential" in traced.lower(zero, app.diffuse).as_text()
