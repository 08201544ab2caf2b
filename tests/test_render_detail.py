"""bump_strength at low resolution (issue 14): the mip-filtered weave loses its slopes, a texture
scale ([render] texture_tiling) brings them back, and a fit of bump_strength is warned."""

import warnings

import jax
import jax.numpy as jnp
import pytest

from diffcloth import config as cfg
from diffcloth import render, scene, surface
from diffcloth.render.detail import BumpDetailWarning, bump_detail, check_bump_detail

CAM = render.make_camera((0.0, 1.3, 1.2), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), width=64, height=64)
LIGHTS = render.make_lights()


def _cloth():
    u, v = jnp.meshgrid(jnp.linspace(-0.5, 0.5, 6), jnp.linspace(-0.5, 0.5, 6))
    return surface.tessellate(jnp.stack([u, 0.02 * u * v, v], axis=-1), 4, flip=True)


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_texture_tiling_controls_bump_detail_and_gradient():
    surf = _cloth()

    @jax.jit
    def grad(tex):
        def loss(b):
            app = render.make_appearance()
            app = app.__class__(**{**app.__dict__, "bump_strength": b})
            img = render.render(surf, CAM, LIGHTS, "bump_diffuse", app, textures=tex)
            return jnp.mean(img[..., :3])

        return jax.grad(loss)(jnp.float64(1.0))

    fine = render.default_textures(tiling=(4.0, 4.0))  # the default: 64 threads across ~50 px
    coarse = render.default_textures(tiling=(0.5, 0.5))  # 8 threads across the cloth
    assert bump_detail(surf, CAM, fine) < 0.1
    assert bump_detail(surf, CAM, coarse) > 0.5
    g_fine, g_coarse = abs(float(grad(fine))), abs(float(grad(coarse)))
    assert g_coarse > 1e-4
    assert g_coarse > 20 * g_fine, (g_fine, g_coarse)


def _scene(tiling):
    conf = {
        "net": {"rows": 5, "cols": 5, "width": 1.0, "height": 1.0, "center": [0.0, 0.0, 0.0]},
        "sim": {"num_frames": 2},
        "render": {"width": 64, "height": 64, "textures": "default", "texture_tiling": tiling},
        "camera": {"eye": [0.0, 1.3, 1.2], "target": [0.0, 0.0, 0.0]},
    }
    return scene.build_scene(cfg.parse_config(conf), dtype=jnp.float64)


def test_fitting_bump_strength_warns_when_the_bump_is_filtered_away():
    with pytest.warns(BumpDetailWarning, match="texture_tiling"):
        assert check_bump_detail(_scene([4, 4]), ["bump_strength", "bend"]) < 0.1
    with warnings.catch_warnings():
        warnings.simplefilter("error", BumpDetailWarning)
        assert check_bump_detail(_scene([0.5, 0.5]), ["bump_strength"]) > 0.5
        assert check_bump_detail(_scene([4, 4]), ["bend"]) is None


@pytest.mark.parametrize("bad", [[0, 1], [1], "4", [1, float("inf")]])
def test_texture_tiling_config_errors(bad):
    with pytest.raises(cfg.ConfigError, match=r"\[render\] texture_tiling"):
        _scene(bad)
