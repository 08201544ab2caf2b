"""[[deform]] waves / ripples from the config reach the rendered surface (issue 14)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import pipeline, scene, surface
from diffcloth.surface.deform import apply_deformations


def _conf(deform):
    return {
        "net": {"rows": 5, "cols": 5, "width": 1.0, "height": 1.0, "center": [0.0, 0.5, 0.0]},
        "sim": {"num_frames": 4},
        "render": {"width": 32, "height": 32, "level": 3, "frame_stride": 2},
        "camera": {"eye": [0.0, 1.4, 1.2], "target": [0.0, 0.5, 0.0]},
        "deform": deform,
    }


WAVE = {"kind": "waves", "amplitude": 0.05, "wavelength": 0.5, "speed": 1.0, "direction": [1, 0]}
RIPPLE = {"kind": "ripples", "amplitude": 0.03, "wavelength": 0.3, "decay": 2.0}


def test_deform_entries_parse_into_the_scene_and_displace_the_surface():
    sc = scene.build_scene(cfg.parse_config(_conf([WAVE, RIPPLE])), dtype=jnp.float64)
    assert [d.kind for d in sc.deform] == ["waves", "ripples"]
    surf = surface.tessellate(sc.state.x, sc.level, sc.basis, flip=sc.flip)
    t = 0.1
    moved = apply_deformations(surf, sc.deform, t)
    h = jnp.sum((moved.positions - surf.positions) * surf.normals, axis=-1)
    u, v = surf.uv[:, 0], surf.uv[:, 1]
    r = jnp.hypot(u - 0.5, v - 0.5)
    want = 0.05 * jnp.sin(2 * jnp.pi * (u - 1.0 * t) / 0.5) + 0.03 * jnp.exp(-2 * r) * jnp.sin(
        2 * jnp.pi * r / 0.3
    )
    np.testing.assert_allclose(h, want, atol=1e-12)
    assert apply_deformations(surf, (), t) is surf


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_deform_changes_the_video_and_travels_with_time():
    plain = scene.build_scene(cfg.parse_config(_conf([])), dtype=jnp.float64)
    wavy = scene.build_scene(cfg.parse_config(_conf([WAVE])), dtype=jnp.float64)
    f = jax.jit(pipeline.simulate_and_render)
    a, b = np.asarray(f(plain)), np.asarray(f(wavy))
    assert np.abs(a - b).max() > 0.02  # the waves are drawn
    np.testing.assert_allclose(pipeline.rendered_times(wavy), [2 / 30, 4 / 30])
    # a moving wave: the displacement differs between the two frames' times beyond the motion
    # of the cloth itself
    assert np.abs((b[0, 1] - a[0, 1]) - (b[0, 0] - a[0, 0])).max() > 0.02


@pytest.mark.parametrize(
    "entry, match",
    [
        ({"kind": "swirl"}, "kind"),
        ({"wavelength": 0}, "wavelength"),
        ({"direction": [0, 0]}, "direction"),
        ({"amplitud": 1}, "amplitud"),
    ],
)
def test_bad_deform_entries_are_config_errors(entry, match):
    with pytest.raises(cfg.ConfigError, match=rf"\[deform #0\].*{match}|{match}.*deform"):
        cfg.parse_config(_conf([entry]))
