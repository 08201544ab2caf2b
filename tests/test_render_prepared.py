"""prepare_frame + render_prepared (static geometry, many appearances) give render()'s image and
appearance gradients."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import lights as Lm
from diffcloth.render.camera import make_camera
from diffcloth.render.frame import render
from diffcloth.render.prepared import prepare_frame, render_prepared
from diffcloth.surface import tessellate

N = 24
BG = (0.1, 0.2, 0.3)


@pytest.fixture(scope="module")
def scene():
    # a bent cloth seen obliquely: silhouettes (antialiased pairs) and both sides in view
    u, v = np.meshgrid(np.linspace(-1.6, 1.6, 5), np.linspace(1.6, -1.6, 5))
    net = jnp.asarray(np.stack([u, v, 0.5 * np.sin(1.5 * u)], -1))
    surf = tessellate(net, 3)
    cam = make_camera((1.2, 0.6, 2.4), (0, 0, 0), (0, 1, 0), width=N, height=N, fov_y=50.0)
    lights = Lm.make_lights(
        ambient=(0.1, 0.1, 0.1), directional=[((0.3, 0.8, 0.5), (1.0, 0.9, 0.8), 1.0)]
    )
    app = Lm.make_appearance(diffuse=(0.7, 0.3, 0.2), specular=(0.3, 0.3, 0.3))
    return surf, cam, lights, app


@pytest.fixture(scope="module")
def prep(scene):
    surf, cam, _, _ = scene
    return jax.jit(prepare_frame)(surf, cam)


def test_render_prepared_equals_render_with_appearance_gradient(scene, prep):
    surf, cam, lights, app = scene

    def loss_full(diffuse):
        img = render(surf, cam, lights, "phong", dataclasses.replace(app, diffuse=diffuse),
                     background=BG)  # fmt: skip
        return jnp.sum(img[..., :3] ** 2), img

    def loss_prep(diffuse, prep):
        img = render_prepared(prep, lights, "phong", dataclasses.replace(app, diffuse=diffuse),
                              background=BG)  # fmt: skip
        return jnp.sum(img[..., :3] ** 2), img

    (_, img), g = jax.jit(jax.value_and_grad(loss_full, has_aux=True))(app.diffuse)
    (_, img_p), g_p = jax.jit(jax.value_and_grad(loss_prep, has_aux=True))(app.diffuse, prep)
    img, img_p = np.asarray(img), np.asarray(img_p)
    alpha = img[..., 3]
    # the scene has silhouettes (fractional coverage) and cloth and background pixels
    assert np.sum((alpha > 0.02) & (alpha < 0.98)) > 5
    assert np.sum(alpha > 0.999) > 100 and np.sum(alpha < 1e-6) > 50
    np.testing.assert_allclose(img_p, img, atol=1e-5)
    assert float(np.max(np.abs(np.asarray(g)))) > 1.0
    np.testing.assert_allclose(np.asarray(g_p), np.asarray(g), rtol=1e-5, atol=1e-4)


def test_render_prepared_refuses_what_it_cannot_shade(scene, prep):
    surf, cam, lights, app = scene
    with pytest.raises(ValueError, match="gouraud"):
        prepare_frame(surf, cam, shading="gouraud")
    with pytest.raises(ValueError, match="shading must be one of"):
        prepare_frame(surf, cam, shading="toon")
    shadowed = Lm.make_lights(directional=[((0.3, 0.8, 0.5), (1.0, 1.0, 1.0), 1.0)], shadows=True)
    with pytest.raises(ValueError, match="shadows"):
        render_prepared(prep, shadowed, "phong", app)
    with pytest.raises(ValueError, match="flat"):  # prepared for "phong": no face normals
        render_prepared(prep, lights, "flat", app)
    with pytest.raises(ValueError, match="gouraud"):
        render_prepared(prep, lights, "gouraud", app)
