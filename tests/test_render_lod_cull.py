"""LOD level selection and object-level frustum culling reachable from the config (issue 14)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import render, scene, surface


def _conf(render_extra, eye):
    return {
        "net": {"rows": 6, "cols": 6, "width": 1.0, "height": 1.0, "center": [0.0, 0.5, 0.0]},
        "sim": {"num_frames": 2},
        "render": {"width": 128, "height": 128, **render_extra},
        "camera": {"eye": eye, "target": [0.0, 0.5, 0.0]},
    }


def _scene(render_extra, eye=(0.0, 1.5, 1.5)):
    return scene.build_scene(cfg.parse_config(_conf(render_extra, list(eye))), dtype=jnp.float64)


def test_lod_auto_picks_the_level_from_the_projected_size():
    fixed = _scene({"level": 5})
    assert fixed.level == 5
    near = _scene({"lod": "auto"}, eye=(0.0, 1.5, 0.9))
    far = _scene({"lod": "auto"}, eye=(0.0, 8.0, 12.0))
    assert far.level < near.level
    assert far.level == 2 and near.level in (4, 8, 16)
    # ~4 px per segment: segments of the near scene project to a few pixels
    n = near.level * 3  # 3 patches of a 6 x 6 B-spline net
    assert 2 <= 128 / n <= 16
    with pytest.raises(cfg.ConfigError, match=r"\[render\] lod"):
        _scene({"lod": "sometimes"})


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_cull_from_config_and_in_the_renderer():
    assert _scene({"cull": True}).cull and not _scene({}).cull
    with pytest.raises(cfg.ConfigError, match=r"\[render\] cull"):
        _scene({"cull": "yes"})
    u, v = jnp.meshgrid(jnp.linspace(-0.5, 0.5, 5), jnp.linspace(-0.5, 0.5, 5))
    surf = surface.tessellate(jnp.stack([u, jnp.zeros_like(u), v], -1), 2, flip=True)
    look = render.make_camera(
        (0.0, 1.5, 1.5), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), width=32, height=32
    )
    away = render.make_camera(
        (0.0, 1.5, 1.5), (0.0, 3.0, 5.0), (0.0, 1.0, 0.0), width=32, height=32
    )
    lights, app = render.make_lights(), render.make_appearance()
    f = jax.jit(
        lambda cam, cull: render.render(surf, cam, lights, "phong", app, cull=cull),
        static_argnums=1,
    )
    seen, seen_culled = np.asarray(f(look, False)), np.asarray(f(look, True))
    np.testing.assert_array_equal(seen, seen_culled)  # in view: culling changes nothing
    assert seen[..., 3].sum() > 10
    gone = np.asarray(f(away, True))
    assert gone[..., 3].max() == 0.0  # outside the frustum: nothing drawn
    np.testing.assert_array_equal(gone, np.asarray(f(away, False)))  # and nothing was visible
