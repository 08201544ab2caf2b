"""Rigid bodies in a Scene: [[bodies]] config, coupled simulation, drawn balls, body parameters
as fit parameters with gradients checked against finite differences (float64)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import pipeline, scene

BALL_SCENE = {
    "net": {
        "rows": 5, "cols": 5, "width": 0.6, "height": 0.6, "center": [0.0, 0.0, 0.0],
        "plane": "xy", "pinned": "top_row",
    },
    "material": {"stretch": 20.0, "shear": 6.0, "bend": 1e-4, "density": 0.2},
    "sim": {"dt": 1.0 / 60.0, "num_frames": 6, "num_substeps": 8},
    "planes": [{"normal": [0.0, 1.0, 0.0], "offset": -0.3}],
    "bodies": [{
        "shape": "sphere", "radius": 0.11, "mass": 0.2, "position": [0.0, -0.2, 0.25],
        "velocity": [0.0, -1.0, -3.0], "restitution": 0.6,
    }],
    "render": {"width": 20, "height": 20, "level": 2, "flip": False},
    "camera": {"eye": [1.2, 0.0, 1.0], "target": [0.0, -0.2, 0.0]},
}  # fmt: skip


@pytest.fixture(scope="module")
def ball_scene():
    return scene.build_scene(cfg.parse_config(BALL_SCENE), dtype=jnp.float64)


def test_bodies_are_read_and_simulated_with_the_cloth(ball_scene):
    assert len(ball_scene.bodies) == 1 and ball_scene.two_way
    cloth, (ball,) = jax.jit(pipeline.simulate_all)(ball_scene)
    assert cloth.x.shape == (6, 5, 5, 3) and ball.position.shape == (6, 3)
    assert float(ball.position[-1, 2]) < 0.25  # it flew towards the cloth
    # the cloth was pushed: it moved further than under gravity alone (no bodies)
    alone = jax.jit(pipeline.simulate)(dataclasses.replace(ball_scene, bodies=()))
    assert float(jnp.max(jnp.abs(cloth.x[-1] - alone.x[-1]))) > 1e-3


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_ball_is_drawn_and_body_params_apply(ball_scene):
    render = jax.jit(pipeline.simulate_and_render)  # one compile: same structure both times
    with_ball = np.asarray(render(ball_scene))
    away = pipeline.apply_params(ball_scene, {"body_position": [[0.0, 50.0, 0.25]]})
    without = np.asarray(render(away))  # the ball thrown from far above the view
    assert with_ball.shape == ball_scene.video_shape
    assert np.abs(with_ball - without).max() > 0.1  # the ball shows up
    heavier = pipeline.apply_params(ball_scene, {"body_mass": 0.5, "body_restitution": [0.3]})
    assert float(heavier.bodies[0].mass) == 0.5 and float(heavier.bodies[0].restitution) == 0.3
    np.testing.assert_allclose(pipeline.param_value(heavier, "body_mass"), [0.5])


def test_body_params_without_bodies_and_bad_bodies_are_errors(ball_scene):
    empty = dataclasses.replace(ball_scene, bodies=())
    with pytest.raises(ValueError, match=r"body_mass: the scene has no rigid bodies"):
        pipeline.apply_params(empty, {"body_mass": 1.0})
    bad = dict(BALL_SCENE, bodies=[dict(BALL_SCENE["bodies"][0], mass=-1.0)])
    with pytest.raises(cfg.ConfigError, match=r"\[\[bodies\]\].*mass"):
        scene.build_scene(cfg.parse_config(bad))
    with pytest.raises(cfg.ConfigError, match="two_way"):
        scene.build_scene(cfg.parse_config(dict(BALL_SCENE, coupling={"two_way": "yes"})))


@pytest.mark.slow  # ~35 s, mostly compiling the gradient of the coupled rollout + render
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_video_gradient_wrt_body_mass_and_restitution_matches_fd(ball_scene):
    target = jax.jit(pipeline.simulate_and_render)(
        ball_scene, {"body_mass": 0.3, "body_restitution": 0.8}
    )

    def loss(p):
        return jnp.mean((pipeline.simulate_and_render(ball_scene, p) - target) ** 2)

    p0 = {"body_mass": jnp.array([0.2]), "body_restitution": jnp.array([0.6])}
    f, g = jax.jit(loss), jax.jit(jax.grad(loss))(p0)
    for name in p0:
        h = 1e-5 * float(p0[name][0])
        up = f({**p0, name: p0[name] + h})
        down = f({**p0, name: p0[name] - h})
        fd = float(up - down) / (2 * h)
        ad = float(g[name][0])
        assert np.isfinite(ad) and abs(ad) > 0, (name, ad, fd)
        np.testing.assert_allclose(ad, fd, rtol=2e-2, atol=1e-9, err_msg=name)


def test_fit_config_checks_body_truth_ranges():
    from diffcloth.experiment import parse_fit

    fit = {"free": ["body_mass"]}
    assert parse_fit({"fit": fit, "truth": {"body_mass": 0.3}}).truth["body_mass"] == 0.3
    with pytest.raises(cfg.ConfigError, match=r"body_restitution = 1.5 .* allowed \[0, 1\]"):
        parse_fit({"fit": fit, "truth": {"body_restitution": 1.5}})
    with pytest.raises(cfg.ConfigError, match=r"body_mass = 0.0 .* allowed \(0, inf\) kg"):
        parse_fit({"fit": fit, "truth": {"body_mass": 0.0}})


def test_a_ball_smaller_than_a_net_cell_warns():
    small = dict(BALL_SCENE, bodies=[dict(BALL_SCENE["bodies"][0], radius=0.05)])
    with pytest.warns(scene.SmallBodyWarning, match="half a net cell's diagonal"):
        scene.build_scene(cfg.parse_config(small))
