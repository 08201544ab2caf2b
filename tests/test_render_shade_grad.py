"""Gradients of an image loss w.r.t. lights and appearance, per mode, vs central FD (float64)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import lights as Lm
from diffcloth.render import shade as S
from diffcloth.render import textures as T
from diffcloth.shapes import make_sphere

N = 8
EYE = jnp.array([0.2, 0.1, 1.0, 0.0])
BALL = S.gbuffer_sphere(N, N, radius=0.9)
QUAD = S.gbuffer_quad(N, N)
WEIGHTS = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, size=(N, N, 4)))
LIGHTS = Lm.make_lights(
    ambient=(0.1, 0.1, 0.1),
    directional=[((0.3, 0.5, 0.8), (1.0, 0.9, 0.8), 1.2)],
    point=[((-1.0, 1.0, 2.0), (0.5, 0.6, 0.7), 2.0, 0.1)],
)
APP = Lm.make_appearance(minnaert_k=0.7, refraction_s=0.6, bump_strength=2.0)
TEX = T.make_textures(
    height=T.weave_height(16, 2), env=T.sky_cube_map(8), color=T.checker(16, 2), tiling=(1.0, 1.0)
)


def fd_check(loss, x, *, eps=1e-6, rtol=1e-5):
    """Reverse-mode gradient of `loss` at pytree `x` vs central differences along random v."""
    leaves, tree = jax.tree.flatten(x)
    rng = np.random.default_rng(1)
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
    assert abs(ad) > 1e-6, "gradient is zero: the check would pass vacuously"
    np.testing.assert_allclose(ad, fd, rtol=rtol, atol=1e-8)
    # and every leaf has a non-zero gradient
    for name, a in zip(x, jax.tree.leaves(g), strict=True) if isinstance(x, dict) else []:
        assert float(jnp.abs(a).max()) > 0, name


def image_loss(mode, gb=BALL, spheres=None, refraction="shortened"):
    def loss(p):
        lights = dataclasses.replace(
            LIGHTS, **{k[6:]: v for k, v in p.items() if k.startswith("light.")}
        )
        app = dataclasses.replace(
            APP, **{k: v for k, v in p.items() if not k.startswith(("light.", "sphere."))}
        )
        sph = spheres
        if "sphere.center" in p:
            sph = dataclasses.replace(spheres, center=p["sphere.center"], radius=p["sphere.radius"])
        img = S.shade(
            gb, EYE, lights, app, mode=mode, textures=TEX, spheres=sph, refraction=refraction
        )
        return jnp.sum(WEIGHTS * img)

    return loss


def test_phong_grad_lights_and_colours():
    p = {
        "light.direction": LIGHTS.direction,
        "light.point_position": LIGHTS.point_position,
        "light.direction_color": LIGHTS.direction_color,
        "diffuse": APP.diffuse,
        "specular": APP.specular,
        "shininess": APP.shininess,
    }
    fd_check(image_loss("phong"), p)


def test_bump_diffuse_grad_strength_and_light():
    fd_check(
        image_loss("bump_diffuse"),
        {"bump_strength": APP.bump_strength, "light.direction": LIGHTS.direction},
    )


@pytest.mark.parametrize("mode", ["minnaert", "minnaert_table"])
def test_minnaert_grad_exponent(mode):
    fd_check(image_loss(mode), {"minnaert_k": APP.minnaert_k, "diffuse": APP.diffuse})


def test_reflect_refract_grad_s():
    spheres = make_sphere([0.0, 0.3, 2.0], 0.7)
    p = {
        "refraction_s": APP.refraction_s,
        "refraction_blend": APP.refraction_blend,
        "reflectance": APP.reflectance,
    }
    fd_check(image_loss("reflect_refract", spheres=spheres), p)


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_reflect_refract_snell_grad_ior():
    fd_check(image_loss("reflect_refract", refraction="snell"), {"ior": jnp.asarray(0.8)})


def test_sphere_reflection_grad_sphere_and_blend():
    spheres = make_sphere([0.1, 0.2, 2.0], 0.8)
    p = {
        "sphere.center": spheres.center,
        "sphere.radius": spheres.radius,
        "sphere_color": APP.sphere_color,
        "sphere_distance_falloff": APP.sphere_distance_falloff,
        "sphere_rim_power": APP.sphere_rim_power,
    }
    fd_check(image_loss("sphere_reflection", gb=QUAD, spheres=spheres), p)


def test_second_pass_grad():
    p = {
        "second_pass_alpha": APP.second_pass_alpha,
        "bump_strength": APP.bump_strength,
        "specular": APP.specular,
    }
    fd_check(image_loss("second_pass"), p)


def test_gouraud_vertex_lighting_grad():
    pos, nrm = BALL.position.reshape(-1, 3), BALL.normal.reshape(-1, 3)

    def loss(p):
        lights = dataclasses.replace(LIGHTS, direction=p["dir"])
        app = dataclasses.replace(APP, diffuse=p["diffuse"])
        return jnp.sum(
            S.light_vertices(pos, nrm, EYE, lights, app) * WEIGHTS[..., :3].reshape(-1, 3)
        )

    fd_check(loss, {"dir": LIGHTS.direction, "diffuse": APP.diffuse})
