"""Silhouette coverage equals a box-filtered pixel's (issue 14 item 2: agreement with a path
tracer), the antialiased fringe survives compositing over ray-cast planes, and `render_mesh`
lights any mesh with smooth (area-weighted) vertex normals (issue 14 item 4)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import render, surface
from diffcloth.render.camera import project
from diffcloth.render.coverage import edge_coverage
from diffcloth.render.fringe import fringe_depth
from diffcloth.render.mesh import vertex_normals
from diffcloth.shapes import Plane

S = 24
CAM = render.make_camera((0.0, 0.0, 3.0), (0, 0, 0), (0, 1, 0), width=S, height=S, fov_y=40.0)


def test_edge_coverage_is_the_exact_pixel_area():
    n = 200
    g = (np.arange(n) + 0.5) / n - 0.5
    x, y = np.meshgrid(g, g)
    rng = np.random.default_rng(0)
    sig = rng.uniform(-1.0, 1.0, 60)
    k = np.where(np.arange(60) % 4 == 0, 0.0, rng.uniform(0.0, 1.0, 60))
    got = np.asarray(edge_coverage(jnp.asarray(sig), jnp.asarray(k)))
    # the edge line crosses the pair axis at distance sig from the centre, slope k
    want = [np.mean(x + kk * y >= -s) for s, kk in zip(sig, k, strict=True)]
    np.testing.assert_allclose(got, want, atol=4e-3)
    np.testing.assert_allclose(got[k == 0], np.clip(0.5 + sig[k == 0], 0, 1), atol=1e-12)
    # continuous derivative in sigma (what the silhouette gradients are made of)
    d = jax.vmap(jax.grad(edge_coverage))(jnp.linspace(-1.0, 1.0, 801), jnp.full(801, 0.6))
    assert np.max(np.abs(np.diff(np.asarray(d)))) < 0.02


def _square(angle=0.3, n=9):
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n))
    x = np.cos(angle) * u - np.sin(angle) * v
    y = np.sin(angle) * u + np.cos(angle) * v
    return surface.tessellate(jnp.asarray(np.stack([x, y, np.zeros_like(x)], -1)), 3)


def _exact_coverage(corners, sub=16):
    """Box-filtered coverage of the convex screen polygon of `corners` (4, 3), supersampled."""
    clip, _ = project(jnp.asarray(corners), CAM)
    clip = np.asarray(clip)
    px = 0.5 * (clip[:, 0] / clip[:, 3] + 1) * S - 0.5
    py = 0.5 * (1 - clip[:, 1] / clip[:, 3]) * S - 0.5
    g = (np.arange(S * sub) + 0.5) / sub - 0.5
    X, Y = np.meshgrid(g, g)
    inside = np.ones_like(X, bool)
    signs = []
    for i in range(4):
        j = (i + 1) % 4
        signs.append((px[j] - px[i]) * (Y - py[i]) - (py[j] - py[i]) * (X - px[i]))
    signs = np.stack(signs)
    inside = np.all(signs >= 0, 0) | np.all(signs <= 0, 0)
    return inside.reshape(S, sub, S, sub).mean((1, 3))


@functools.cache
def _square_images():
    surf = _square()
    ones = jnp.ones((surf.positions.shape[0], 1))
    alpha = render.render_mesh(surf.positions, surf.faces, CAM, ones)[..., 1]
    k = int(round(np.sqrt(surf.positions.shape[0])))
    grid = np.asarray(surf.positions).reshape(k, k, 3)
    corners = grid[[0, 0, -1, -1], [0, -1, -1, 0]]
    return surf, np.asarray(alpha), _exact_coverage(corners)


@pytest.mark.slow  # compiles render_mesh (~20 s); the formula test above stays in the default run
def test_slanted_silhouette_coverage_matches_the_box_filter():
    """Sub-pixel triangles, edges at 0.3 rad: every rim pixel's antialiased coverage equals the
    exact area (nvdiffrast's |t - 1/2| with a walk of 1 was off by 0.08 on average, and left
    90 % of the pixels whose centre lies outside empty)."""
    _, alpha, exact = _square_images()
    band = (exact > 0.01) & (exact < 0.99)
    assert band.sum() > 30
    err = alpha - exact
    assert np.abs(err[band]).mean() < 0.01, np.abs(err[band]).mean()
    assert np.abs(err).max() < 0.06
    outside = band & (exact < 0.5)
    assert np.all(alpha[outside] > 0.0)  # the fringe beyond the pixel centres is drawn


@pytest.mark.slow  # compiles render.render (~20 s CPU); runs with -m slow
def test_fringe_survives_a_plane_behind_the_cloth():
    surf, alpha, _ = _square_images()
    wall = Plane(jnp.asarray([[0.0, 0.0, 1.0]]), jnp.asarray([-1.0]))  # z = -1, facing +z
    lights, app = render.make_lights(), render.make_appearance()
    _, cloth = render.render(
        surf, CAM, lights, "flat", app, planes=wall, two_sided=True, return_cloth_mask=True
    )
    np.testing.assert_allclose(np.asarray(cloth), alpha, atol=1e-5)
    cov = jnp.asarray([[True, False, False]])
    d = jnp.asarray([[2.0, 7.0, 7.0]])
    np.testing.assert_array_equal(fringe_depth(cov, d), [[2.0, 2.0, 7.0]])


@pytest.mark.slow  # forward + gradient compiles (~40 s CPU); runs with -m slow
def test_render_mesh_lights_smooth_vertex_normals():
    """A lit sphere mesh: smooth (area-weighted) normals give the analytic sphere's Lambert
    shading far better than the faces do, and the image has gradients w.r.t. the positions."""
    th = np.linspace(0, np.pi, 13)[1:-1]
    ph = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    t, p = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]]) * 0.8
    idx = lambda i, j: 1 + i * 24 + (j % 24)
    faces = []
    for j in range(24):
        faces += [[0, idx(0, j + 1), idx(0, j)], [len(verts) - 1, idx(10, j), idx(10, j + 1)]]
        faces += [
            f
            for i in range(10)
            for f in ([idx(i, j), idx(i, j + 1), idx(i + 1, j + 1)],
                      [idx(i, j), idx(i + 1, j + 1), idx(i + 1, j)])
        ]  # fmt: skip
    verts, faces = jnp.asarray(verts), jnp.asarray(faces)
    light = jnp.asarray([0.3, 0.5, 1.0])
    ones = jnp.ones((verts.shape[0], 1))
    f = jax.jit(lambda v: render.render_mesh(v, faces, CAM, ones, light_dir=light))
    img = np.asarray(f(verts))
    # the exact sphere's Lambert factor at each pixel centre's ray hit
    o, dirs = (np.asarray(a) for a in render.pixel_rays(CAM))
    b = np.sum(o * dirs, -1)
    disc = b**2 - (np.sum(o * o, -1) - 0.8**2)
    hit = disc > 0.05
    pts = o + (-b - np.sqrt(np.maximum(disc, 0)))[..., None] * dirs
    want = np.maximum(np.sum(pts / 0.8 * np.asarray(light / jnp.linalg.norm(light)), -1), 0)
    inner = hit & (img[..., 1] > 0.999)
    assert inner.sum() > 100
    assert np.abs(img[..., 0][inner] - want[inner]).mean() < 0.02
    given = render.render_mesh(
        verts, faces, CAM, ones, light_dir=light, normals=vertex_normals(verts, faces)
    )
    np.testing.assert_allclose(np.asarray(given), img, atol=1e-6)
    g = jax.grad(lambda v: jnp.sum(f(v)[..., 0]))(verts)
    assert np.isfinite(np.asarray(g)).all() and np.abs(np.asarray(g)).max() > 0


def test_pair_share_sums_to_one_is_hard_outside_the_band_and_has_fd_gradient():
    """The two pair directions' shares of an edge sum to 1, are 1 / 0 away from 45 degrees
    (nvdiffrast's choice) and move smoothly inside the band (the image does not jump there)."""
    from diffcloth.render.coverage import pair_share

    ang = jnp.linspace(0.0, jnp.pi / 2, 181)
    a, b = jnp.abs(jnp.cos(ang)), jnp.abs(jnp.sin(ang))
    s_h, s_v = pair_share(a, b), pair_share(b, a)
    np.testing.assert_allclose(s_h + s_v, 1.0, atol=1e-6)
    u = a / (a + b)
    assert bool(jnp.all(jnp.where(u >= 0.55, s_h == 1.0, True)))
    assert bool(jnp.all(jnp.where(u <= 0.45, s_h == 0.0, True)))
    assert float(jnp.max(jnp.abs(jnp.diff(s_h)))) < 0.1  # no jump between 0.5-degree steps
    f = lambda t: pair_share(jnp.cos(t), jnp.sin(t))
    t0, h = 0.8, 1e-3  # inside the band (45.8 degrees)
    fd = (f(t0 + h) - f(t0 - h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(f)(t0), fd, rtol=1e-3)
