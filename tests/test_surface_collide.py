"""Per-vertex sphere collision: projection, untouched outside, centre fallback, radius rules."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffcloth.shapes import Sphere, make_sphere
from diffcloth.surface import collide_surface, push_out_of_spheres, tessellate

C = jnp.asarray([0.1, -0.2, 0.3])
R = jnp.asarray(0.5)


@jax.jit
def push(p, center, radius):
    return push_out_of_spheres(p, Sphere(center, radius))


def test_inside_points_land_on_sphere_along_centre_ray():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    depth = rng.uniform(0.01, 0.49, size=(50, 1))
    p = jnp.asarray(np.asarray(C) + depth * d)
    q = np.asarray(push(p, C, R))
    np.testing.assert_allclose(np.linalg.norm(q - np.asarray(C), axis=1), 0.5, atol=1e-12)
    np.testing.assert_allclose(q - np.asarray(C), 0.5 * d, atol=1e-12)  # same ray from the centre


def test_outside_and_surface_points_are_untouched():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = np.asarray(C) + rng.uniform(0.51, 3.0, size=(40, 1)) * d
    p = np.concatenate([p, np.asarray(C) + np.array([[0.0, 0.5, 0.0]])])  # exactly on the surface
    q = push(jnp.asarray(p), C, R)
    np.testing.assert_array_equal(np.asarray(q), p)


def test_vertex_at_centre_is_pushed_along_fallback_with_finite_gradient():
    p = jnp.stack([C, C + jnp.asarray([0.0, 0.0, 2.0])])
    q = push(p, C, R)
    np.testing.assert_allclose(q[0], C + jnp.asarray([0.0, 0.5, 0.0]), atol=1e-15)
    jac_p, jac_c, jac_r = jax.jacrev(push, argnums=(0, 1, 2))(p, C, R)
    for j in (jac_p, jac_c, jac_r):
        assert np.all(np.isfinite(j))
    np.testing.assert_allclose(jac_r[0], [0.0, 1.0, 0.0])  # moving outward as r grows


def test_radius_zero_is_a_noop():
    p = jnp.stack([C, C + 1e-3, C + 1.0])
    np.testing.assert_array_equal(push(p, C, jnp.asarray(0.0)), p)
    g = jax.grad(lambda r: jnp.sum(push(p, C, r) ** 2))(jnp.asarray(0.0))
    assert np.isfinite(g)


def test_negative_radius_raises():
    with pytest.raises(ValueError, match="radius"):
        push_out_of_spheres(jnp.zeros((2, 3)), Sphere(C, jnp.asarray(-0.1)))
    with pytest.raises(ValueError, match="radius"):
        make_sphere([0.0, 0.0, 0.0], -1.0)
    with pytest.raises(TypeError, match="Sphere"):
        push_out_of_spheres(jnp.zeros((2, 3)), (C, R))


def test_gradient_matches_finite_differences_at_generic_points():
    rng = np.random.default_rng(2)
    p = jnp.asarray(np.asarray(C) + rng.uniform(-0.6, 0.6, size=(12, 3)))
    w = jnp.asarray(rng.normal(size=(12, 3)))

    def loss(p, c, r):
        return jnp.sum(w * push(p, c, r))

    check_grads(loss, (p, C, R), order=1, modes=("rev",), atol=1e-6, rtol=1e-6)
    g = jax.grad(loss, argnums=(1, 2))(p, C, R)
    assert abs(float(g[1])) > 1e-3 and np.abs(g[0]).max() > 1e-3


def test_cloth_deep_inside_sphere_projects_in_one_step():
    # a whole surface inside a big sphere, some vertices at or very near the centre
    x, z = np.meshgrid(np.linspace(-0.3, 0.3, 6), np.linspace(-0.3, 0.3, 6))
    net = jnp.asarray(np.stack([x, np.zeros_like(x), z], -1))
    center, radius = jnp.zeros(3), jnp.asarray(2.0)

    @jax.jit
    def run(net, radius):
        s = tessellate(net, 3)
        return collide_surface(s, Sphere(center, radius))

    s = run(net, radius)
    dist = np.linalg.norm(np.asarray(s.positions), axis=1)
    np.testing.assert_allclose(dist, 2.0, atol=1e-12)
    assert np.all(np.abs(np.asarray(s.positions)) < 1e5)
    assert np.all(np.isfinite(s.normals))
    g = jax.grad(lambda n: jnp.sum(run(n, radius).positions[:, 1]))(net)
    assert np.all(np.isfinite(g))


def test_several_spheres_in_order():
    sph = make_sphere([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], [1.0, 0.5])
    p = jnp.asarray([[0.5, 0.0, 0.0], [2.0, 0.2, 0.0], [5.0, 0.0, 0.0]])
    q = np.asarray(push_out_of_spheres(p, sph))
    np.testing.assert_allclose(q[0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(q[1], [2.0, 0.5, 0.0])
    np.testing.assert_allclose(q[2], [5.0, 0.0, 0.0])


def test_traced_radius_is_accepted_under_jit():
    out = jax.jit(lambda r: push_out_of_spheres(jnp.zeros((1, 3)), Sphere(jnp.zeros(3), r)))(0.7)
    np.testing.assert_allclose(out, [[0.0, 0.7, 0.0]])


@pytest.fixture(scope="module")
def draped():
    """A wavy net pressed into a sphere below it: some vertices are pushed, others not."""
    x, z = np.meshgrid(np.linspace(-1.0, 1.0, 7), np.linspace(-1.0, 1.0, 7))
    y = 0.2 * np.cos(2.0 * x) * np.cos(2.0 * z)
    net = jnp.asarray(np.stack([x, y, z], -1))
    sphere = Sphere(jnp.asarray([0.0, -0.5, 0.0]), jnp.asarray(0.8))
    s = jax.jit(tessellate, static_argnums=1)(net, 4)
    return s, sphere


@pytest.mark.parametrize("mode", ["sphere", "grid"])
def test_collide_surface_updates_frames_consistently(draped, mode):
    s, sphere = draped
    c = jax.jit(collide_surface, static_argnames="normals")(s, sphere, normals=mode)
    pushed = np.linalg.norm(np.asarray(s.positions) - np.asarray(sphere.center), axis=1) < 0.8
    assert 0 < pushed.sum() < len(pushed)
    n, t, b = (np.asarray(a) for a in (c.normals, c.tangents, c.bitangents))
    for a in (n, t, b):
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(n * t, 1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(n, t), b, atol=1e-12)
    out = (np.asarray(c.positions) - np.asarray(sphere.center)) / 0.8
    if mode == "sphere":
        # pushed: the sphere normal, on the side of the old normal; others unchanged
        np.testing.assert_allclose(np.abs(np.sum(n[pushed] * out[pushed], 1)), 1.0, atol=1e-12)
        assert np.all(np.sum(n[pushed] * np.asarray(s.normals)[pushed], 1) >= 0)
        np.testing.assert_array_equal(n[~pushed], np.asarray(s.normals)[~pushed])
    else:
        # grid normals of pushed interior vertices follow the sphere closely
        vr, vc = s.grid_shape
        interior = np.zeros((vr, vc), bool)
        interior[1:-1, 1:-1] = True
        deep = pushed & interior.ravel()
        assert np.abs(np.sum(n[deep] * out[deep], 1)).mean() > 0.9


def test_float32_strict_promotion(draped):
    s, sphere = draped
    s32 = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, s
    )
    sph32 = Sphere(sphere.center.astype(jnp.float32), sphere.radius.astype(jnp.float32))
    with jax.numpy_dtype_promotion("strict"):
        c = jax.jit(collide_surface)(s32, sph32)
    assert c.positions.dtype == c.normals.dtype == c.tangents.dtype == jnp.float32
