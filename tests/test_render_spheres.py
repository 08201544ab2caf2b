"""Analytic ray-cast spheres: silhouettes, attributes, depth compositing with meshes, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import camera as C
from diffcloth.render import raster as R
from diffcloth.render.spheres import raycast_spheres
from diffcloth.shapes import Sphere

SIZE = 32


def pixel_camera():
    view = C.look_at((0.0, 0.0, 20.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    proj = C.orthographic(-16.0, 16.0, -16.0, 16.0, 0.1, 40.0)
    return C.camera_from_matrices(
        view, proj, width=SIZE, height=SIZE, near=0.1, far=40.0, kind="orthographic"
    )


CAM = pixel_camera()
QUAD = jnp.array([[-10.0, -10.0, 0.0], [10.0, -10.0, 0.0], [10.0, 10.0, 0.0], [-10.0, 10.0, 0.0]])
QUAD_FACES = jnp.array([[0, 1, 2], [0, 2, 3]])


def _scene(center, radius, quad_z):
    """Premultiplied RGBA of a red sphere composited with a blue quad at depth quad_z."""
    sph = raycast_spheres(Sphere(center, radius), CAM, {"color": jnp.array([[1.0, 0.0, 0.0]])})
    quad = R.rasterize_gbuffer(
        QUAD.at[:, 2].set(quad_z),
        QUAD_FACES,
        CAM,
        {"color": jnp.tile(jnp.array([0.0, 0.0, 1.0]), (4, 1))},
    )
    g = R.composite(quad, sph)
    rgba = jnp.concatenate([g.attributes["color"], g.mask[..., None].astype(jnp.float64)], axis=-1)
    return R.antialias(rgba, g), g


def _sphere_only(center, radius):
    g = raycast_spheres(Sphere(center, radius), CAM)
    return R.antialias(g.mask[..., None].astype(jnp.float64), g)[..., 0], g


sphere_only = jax.jit(_sphere_only)
area_grad = jax.jit(jax.grad(lambda c, r: jnp.sum(_sphere_only(c, r)[0]), argnums=(0, 1)))


def _red(c, r, z):
    """(sum of red - blue, the composited image): the occlusion-edge loss and its image."""
    img = _scene(c, r, z)[0]
    return jnp.sum(jnp.asarray([1.0, 0.0, -1.0, 0.0])[None, None] * img), img


# one compile serves the images, the loss and its gradient (a separate forward jit of _scene
# was a second compile of the same rasterizer)
red_value_and_grad = jax.jit(jax.value_and_grad(_red, argnums=(0, 1), has_aux=True))


def scene(c, r, z):
    """The composited image (H, W, 4) (through the shared compile)."""
    return red_value_and_grad(c, r, z)[0][1]


def test_silhouette_area_and_attributes():
    center, radius = jnp.array([0.3, -0.2, 0.0]), jnp.asarray(6.0)
    alpha, g = sphere_only(center, radius)
    hard = int(g.mask.sum())
    area = np.pi * 36.0
    assert abs(hard - area) < 6.0
    assert abs(float(alpha.sum()) - area) < 0.01 * area
    pos, nrm = g.attributes["position"], g.attributes["normal"]
    m = np.asarray(g.mask)
    np.testing.assert_allclose(
        np.linalg.norm(np.asarray(pos - center[None, None]), axis=-1)[m], 6.0, atol=1e-9
    )
    np.testing.assert_allclose(
        np.asarray(nrm)[m], np.asarray((pos - center[None, None]) / 6.0)[m], atol=1e-9
    )
    np.testing.assert_allclose(np.asarray(g.depth)[m], 20.0 - np.asarray(pos[..., 2])[m], atol=1e-9)
    assert np.all(np.asarray(nrm)[m][:, 2] > 0)  # visible hemisphere faces the camera


def test_silhouette_gradients():
    center, radius = jnp.array([0.3, -0.2, 0.0]), jnp.asarray(6.0)
    gc, gr = area_grad(center, radius)
    h = 0.25  # antialiased area of a curved rim is exact to first order only: FD over a few steps
    fd_r = (
        float(sphere_only(center, radius + h)[0].sum())
        - float(sphere_only(center, radius - h)[0].sum())
    ) / (2 * h)
    # curved rims: pixel-pair antialiasing is first-order, AD within 10% of FD and the perimeter
    np.testing.assert_allclose(float(gr), fd_r, rtol=0.1)
    np.testing.assert_allclose(float(gr), 2 * np.pi * 6.0, rtol=0.12)  # d(area)/dr = perimeter
    # partly off-screen: moving right reveals area
    h = 0.05
    edge = jnp.array([-15.0, 1.0, 0.0])
    gc, _ = area_grad(edge, radius)
    e = jnp.array([h, 0.0, 0.0])
    fd = (
        float(sphere_only(edge + e, radius)[0].sum())
        - float(sphere_only(edge - e, radius)[0].sum())
    ) / (2 * h)
    assert fd > 1.0
    np.testing.assert_allclose(float(gc[0]), fd, rtol=0.05)


@pytest.mark.slow  # ~19 s; the silhouette-gradient test stays in the default suite
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_composite_by_depth_and_occlusion_gradient():
    center, radius = jnp.array([-9.0, 2.0, 0.0]), jnp.asarray(5.0)
    img = scene(center, radius, -3.0)  # quad behind the sphere
    np.testing.assert_allclose(img[14, 7], [1, 0, 0, 1])  # sphere centre pixel
    np.testing.assert_allclose(img[25, 25], [0, 0, 1, 1])  # quad only
    img2 = scene(center, radius, 6.0)  # quad in front hides the part of the sphere it covers
    np.testing.assert_allclose(img2[14, 7], [0, 0, 1, 1])
    assert float(img2[14, 2, 0]) > 0.9  # part of the sphere left of the quad (x < -10) still shows
    # occlusion edge: sphere over the quad, moving in x changes red vs blue coverage
    (_, _), (gc, gr) = red_value_and_grad(center, radius, -3.0)

    def red(c):
        im = scene(c, radius, -3.0)
        return float(jnp.sum(im[..., 0] - im[..., 2]))

    h = 0.05
    e = jnp.array([h, 0.0, 0.0])
    fd = (red(center + e) - red(center - e)) / (2 * h)
    assert abs(fd) > 1.0
    np.testing.assert_allclose(float(gc[0]), fd, rtol=0.05)


@pytest.mark.slow  # 7 s; moved out of the default suite (10-minute budget)
def test_perspective_silhouette_and_empty():
    cam = C.make_camera((0.0, 0.0, 6.0), (0.0, 0.0, 0.0), (0, 1, 0), width=16, height=16)
    sph = Sphere(jnp.array([[0.0, 0.0, 0.0], [0.6, 0.3, 1.5]]), jnp.array([1.0, 0.4]))
    g = jax.jit(raycast_spheres, static_argnums=())(sph, cam)
    o, d = C.pixel_rays(cam)
    for i, (c, r) in enumerate(zip(np.asarray(sph.center), np.asarray(sph.radius), strict=True)):
        oc = np.asarray(o) - c
        dist2 = np.sum(oc * oc, -1) - np.sum(oc * np.asarray(d), -1) ** 2
        hits = dist2 < r * r
        assert np.all(np.asarray(g.mask)[hits])
        if i == 1:  # the nearer small sphere wins where both are hit
            assert np.all(np.asarray(g.surface_id)[hits] == 1)

    # behind the camera: nothing drawn, gradients zero and finite
    def behind(c):
        g = raycast_spheres(Sphere(c, jnp.asarray(1.0)), cam)
        return jnp.sum(R.antialias(g.mask[..., None] * 1.0, g))

    c = jnp.array([0.0, 0.0, 9.0])
    value, gb = jax.jit(jax.value_and_grad(behind))(c)
    assert float(value) == 0.0
    np.testing.assert_array_equal(np.asarray(gb), 0.0)
