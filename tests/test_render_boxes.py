"""Box rigid bodies drawn with the cloth (issue 14 item 4): occlusion both ways, the spheres'
material, gradients w.r.t. pose against central FD (float64), and through `simulate_and_render`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import pipeline, render, scene, surface
from diffcloth.physics.rigid import make_body, quat_from_axis_angle
from diffcloth.render.boxes import BoxPoses, box_mesh, box_triangles

N = 32
CAM = render.make_camera((0.0, 0.6, 2.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), width=N, height=N)
LIGHTS = render.make_lights(ambient=(0.2, 0.2, 0.2))
APP = render.make_appearance(diffuse=(0.1, 0.2, 0.9), sphere_color=(0.9, 0.6, 0.1))


def _cloth(z):
    """A flat 0.8 m square cloth facing the camera at depth z."""
    u, v = jnp.meshgrid(jnp.linspace(-0.6, 0.6, 5), jnp.linspace(-0.6, 0.6, 5))
    net = jnp.stack([u, v, jnp.full_like(u, z)], axis=-1)
    return surface.tessellate(net, 2)


def _poses(pos, angle=0.0, half=(0.15, 0.15, 0.15)):
    q = quat_from_axis_angle(jnp.asarray([0.3, 1.0, 0.2]), angle)
    return BoxPoses(jnp.asarray([pos]), q[None], jnp.asarray([half]))


_render_jit = jax.jit(
    lambda surf, boxes, app: render.render(surf, CAM, LIGHTS, "phong", app, boxes=boxes)
)


def render_jit(surf, boxes, app=APP):
    """The shared render: one compile per boxes / no-boxes structure (the appearance is an
    argument, so a second material reuses the compile)."""
    return _render_jit(surf, boxes, app)


def test_box_mesh_is_closed_outward_and_matches_the_body():
    body = make_body("box", mass=1.0, half_extents=(0.1, 0.2, 0.3), position=(1.0, 2.0, 3.0))
    verts, faces = box_triangles([body])
    assert verts.shape == (24, 3) and faces.shape == (12, 3)
    np.testing.assert_allclose(verts.min(0), [0.9, 1.8, 2.7], atol=1e-12)
    np.testing.assert_allclose(verts.max(0), [1.1, 2.2, 3.3], atol=1e-12)
    p = verts[faces]
    fn = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    outward = jnp.sum(fn * (p.mean(1) - body.position[None, :]), axis=-1)
    assert bool(jnp.all(outward > 0))
    # total area = 2 (ab + bc + ca) of the full box
    area = 0.5 * float(jnp.sum(jnp.linalg.norm(fn, axis=-1)))
    np.testing.assert_allclose(area, 2 * (0.2 * 0.4 + 0.4 * 0.6 + 0.6 * 0.2), rtol=1e-12)
    assert box_triangles([make_body("sphere", mass=1.0, radius=0.1)])[0].shape == (0, 3)


@pytest.mark.slow  # 9 s; moved out of the default suite (10-minute budget)
def test_box_occludes_the_cloth_and_is_occluded_by_it():
    cloth_back, cloth_front = _cloth(-0.3), _cloth(0.5)
    box = _poses((0.0, 0.0, 0.0))
    centre = (N // 2, N // 2)
    in_front = np.asarray(render_jit(cloth_back, box))
    behind = np.asarray(render_jit(cloth_front, box))
    plain = np.asarray(render_jit(cloth_back, None))
    # box in front: the box colour (sphere_color: orange, red > blue); cloth alone: blue
    assert in_front[centre][0] > in_front[centre][2]
    assert plain[centre][2] > plain[centre][0]
    # box behind the cloth: hidden, the image equals the cloth alone
    np.testing.assert_allclose(behind, np.asarray(render_jit(cloth_front, None)), atol=1e-12)
    # the box covers a patch of pixels around the centre, and nothing far away changes
    changed = np.abs(in_front - plain).max(-1) > 1e-9
    assert 10 < changed.sum() < N * N // 2
    assert not changed[0].any() and not changed[-1].any()


def test_box_pixels_use_the_sphere_material():
    img = np.asarray(render_jit(_cloth(-0.3), _poses((0.0, 0.0, 0.0))))
    app2 = render.make_appearance(diffuse=(0.1, 0.2, 0.9), sphere_color=(0.45, 0.3, 0.05))
    img2 = np.asarray(render_jit(_cloth(-0.3), _poses((0.0, 0.0, 0.0)), app2))
    c = N // 2
    # halving sphere_color removes half of albedo * (ambient + diffuse) under white light: the
    # difference is proportional to sphere_color (specular unchanged); the cloth's diffuse unused
    lit = img[c, c, :3] - img2[c, c, :3]
    ratio = lit / np.asarray([0.45, 0.3, 0.05])
    assert ratio[0] > 0.05
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)


@pytest.mark.slow  # ~10 s on the idle 2-core machine; runs with the slow tests
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_box_pose_gradient_matches_fd():
    cloth = _cloth(-0.3)
    w = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (N, N, 4)))
    d_pos = jnp.asarray([0.6, -0.4, 0.3])

    def loss(p):
        b = _poses(jnp.asarray([0.05, 0.02, 0.0]) + p[0] * d_pos, 0.4 + p[1])
        return jnp.sum(w * render.render(cloth, CAM, LIGHTS, "phong", APP, boxes=b))

    vg = jax.jit(jax.value_and_grad(loss))
    p0 = jnp.zeros(2)
    g = np.asarray(vg(p0)[1])
    for k in range(2):
        e = jnp.zeros(2).at[k].set(1.0)
        fds = [
            (float(vg(p0 + h * e)[0]) - float(vg(p0 - h * e)[0])) / (2 * h) for h in (1e-6, 1e-7)
        ]
        assert abs(g[k]) > 1e-3, (k, g)
        for fd in fds:
            assert abs(fd - g[k]) <= 1e-4 * abs(g[k]), (k, g[k], fds)


BOX_SCENE = {
    "net": {"rows": 5, "cols": 5, "width": 0.8, "height": 0.8, "center": [0.0, 0.9, 0.0]},
    "sim": {"dt": 1.0 / 30.0, "num_frames": 2, "num_substeps": 8},
    "render": {"width": 32, "height": 32, "level": 2},
    "camera": {"eye": [0.0, 0.8, 2.2], "target": [0.0, 0.4, 0.0]},
    "bodies": [
        {
            "shape": "box",
            "half_extents": [0.15, 0.15, 0.15],
            "position": [0.0, 0.3, 0.6],
            "mass": 1.0,
        },
    ],
    "appearance": {"sphere_color": [0.9, 0.6, 0.1]},
}


@pytest.mark.slow  # compiles the coupled rollout and the renderer (~30 s)
def test_simulate_and_render_draws_box_bodies():
    sc = scene.build_scene(cfg.parse_config(BOX_SCENE), dtype=jnp.float64)
    f = jax.jit(pipeline.simulate_and_render)
    seen = np.asarray(f(sc))
    away = np.asarray(f(sc, {"body_position": jnp.asarray([[5.0, 0.3, 0.6]])}))
    diff = np.abs(seen - away).max(-1)[0, -1]
    assert diff.sum() > 0 and (diff > 1e-6).sum() > 10
    # where the box is drawn, the colour is the sphere material's orange (red > blue)
    ys, xs = np.nonzero(diff > 0.1)
    assert (seen[0, -1, ys, xs, 0] > seen[0, -1, ys, xs, 2]).mean() > 0.9


def test_box_mesh_follows_a_trajectory_axis():
    b = make_body("box", mass=1.0, half_extents=(0.1, 0.1, 0.1))
    traj = [jax.tree.map(lambda a: jnp.stack([a, a]), b)]
    poses = render.boxes.box_poses(traj)
    assert poses.position.shape == (2, 1, 3)
    verts, _, faces = box_mesh(jax.tree.map(lambda a: a[0], poses))
    assert verts.shape == (24, 3) and faces.shape == (12, 3)
