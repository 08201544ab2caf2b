"""Tessellation: seed vertex count, frames, winding, dtypes, degenerate nets, gradients, errors."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffcloth.surface import Surface, grid_frames, tessellate, vertex_grid_shape

RNG = np.random.default_rng(1)


def flat_net(rows, cols, dtype=jnp.float64):
    x, z = np.meshgrid(np.linspace(0, 1.2, cols), np.linspace(0, 0.9, rows))
    return jnp.asarray(np.stack([x, np.zeros_like(x), z], -1), dtype)


def wavy_net(rows=6, cols=7, seed=2):
    net = np.array(flat_net(rows, cols))
    net[..., 1] = 0.15 * np.random.default_rng(seed).normal(size=(rows, cols))
    return jnp.asarray(net)


@functools.partial(jax.jit, static_argnames=("level", "basis", "flip"))
def tess(net, level=3, basis="bspline", flip=False):
    return tessellate(net, level, basis, flip=flip)


def test_seed_example_vertex_count():
    net = flat_net(10, 13, jnp.float32)
    s = tess(net, level=13)
    assert isinstance(s, Surface)
    assert s.grid_shape == (91, 130) == vertex_grid_shape(net.shape, 13)
    assert s.positions.shape == (11830, 3)
    for a in (s.normals, s.tangents, s.bitangents):
        assert a.shape == (11830, 3) and a.dtype == jnp.float32
    assert s.positions.dtype == jnp.float32 and s.uv.dtype == jnp.float32
    assert s.uv.shape == (11830, 2)
    assert s.faces.shape == (2 * 90 * 129, 3) and s.faces.dtype == jnp.int32
    assert int(s.faces.min()) == 0 and int(s.faces.max()) == 11829
    np.testing.assert_allclose(s.uv.min(0), 0.0)
    np.testing.assert_allclose(s.uv.max(0), 1.0)


def test_float64_in_float64_out_and_strict_promotion():
    with jax.numpy_dtype_promotion("strict"):
        for dtype in (jnp.float32, jnp.float64):
            s = jax.jit(tessellate, static_argnums=1)(flat_net(4, 5, dtype), 2)
            assert all(a.dtype == dtype for a in (s.positions, s.normals, s.tangents, s.uv))


def test_flat_net_gives_flat_surface_with_constant_normal():
    s = tess(flat_net(5, 6))
    np.testing.assert_allclose(s.positions[:, 1], 0.0, atol=1e-15)
    # rows run along +z, columns along +x: dP/du x dP/dv = x x z = -y
    np.testing.assert_allclose(
        s.normals, np.tile([0.0, -1.0, 0.0], (len(s.normals), 1)), atol=1e-12
    )
    np.testing.assert_allclose(s.tangents[:, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(s.bitangents[:, 2], 1.0, atol=1e-12)


@pytest.mark.parametrize("basis", ["bspline", "bezier", "clamped"])
def test_frames_are_orthonormal_and_right_handed(basis):
    s = tess(wavy_net(7, 7), level=4, basis=basis)
    n, t, b = (np.asarray(a) for a in (s.normals, s.tangents, s.bitangents))
    for a in (n, t, b):
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose((n * t).sum(1), 0.0, atol=1e-12)
    np.testing.assert_allclose((n * b).sum(1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(n, t), b, atol=1e-12)


def test_analytic_frames_match_mesh_differences():
    s = tess(wavy_net(), level=12)
    n_fd, t_fd, _ = grid_frames(s.positions, s.grid_shape)
    vr, vc = s.grid_shape
    inner = np.zeros((vr, vc), bool)
    inner[1:-1, 1:-1] = True
    inner = inner.ravel()
    cos_n = np.sum(np.asarray(s.normals)[inner] * np.asarray(n_fd)[inner], 1)
    cos_t = np.sum(np.asarray(s.tangents)[inner] * np.asarray(t_fd)[inner], 1)
    assert cos_n.min() > 0.999 and cos_t.min() > 0.999


@pytest.mark.parametrize("flip", [False, True])
def test_winding_agrees_with_normals(flip):
    s = tess(wavy_net(), level=3, flip=flip)
    p = np.asarray(s.positions)
    f = np.asarray(s.faces)
    fn = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    vn = np.asarray(s.normals)[f].mean(1)
    assert np.all(np.sum(fn * vn, 1) > 0)


def test_flip_negates_normals_only():
    a, b = tess(wavy_net()), tess(wavy_net(), flip=True)
    np.testing.assert_allclose(b.normals, -a.normals, atol=1e-12)
    np.testing.assert_allclose(b.tangents, a.tangents, atol=1e-12)
    np.testing.assert_allclose(b.positions, a.positions)


@pytest.mark.parametrize(
    "make",
    [
        lambda: jnp.zeros((4, 5, 3)),  # every control point coincident
        lambda: jnp.broadcast_to(
            jnp.linspace(0.0, 1.0, 4)[:, None, None] * jnp.ones((1, 1, 3)), (4, 5, 3)
        ),
        lambda: jnp.broadcast_to(  # every row collinear along x: dP/dv = 0
            jnp.stack([jnp.linspace(0.0, 1.0, 5), jnp.zeros(5), jnp.zeros(5)], -1), (4, 5, 3)
        ),
    ],
    ids=["coincident", "rows-equal", "collinear"],
)
def test_degenerate_net_gives_finite_unit_frames_and_gradients(make):
    net = make() * 1.0
    s = tess(net, level=2)
    for a in (s.normals, s.tangents, s.bitangents):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(s.normals * s.tangents, 1), 0.0, atol=1e-12)
    assert np.all(np.isfinite(_shade_grad(net)))


@jax.jit
@jax.grad
def _shade_grad(net):
    s = tessellate(net, 2)
    light = jnp.asarray([0.3, 0.8, 0.5], net.dtype)
    return jnp.sum(jnp.maximum(s.normals @ light, 0.0)) + jnp.sum(s.tangents * s.bitangents)


@jax.jit
def _surface_loss(net):
    s = tessellate(net, 3)
    w = jnp.sin(jnp.arange(s.positions.size, dtype=net.dtype)).reshape(s.positions.shape)
    return jnp.sum(w * s.positions) + jnp.sum(w * s.normals) + jnp.sum(s.tangents[:, 1] ** 2)


def test_gradient_matches_finite_differences():
    net = wavy_net(4, 5)
    check_grads(_surface_loss, (net,), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)
    g = jax.grad(_surface_loss)(net)
    assert np.abs(np.asarray(g)).max() > 1e-3


def test_one_compile_for_new_values():
    traces = []

    @jax.jit
    def f(net):
        traces.append(1)
        return tessellate(net, 3).positions

    f(wavy_net(seed=3))
    f(wavy_net(seed=4))
    assert len(traces) == 1


@pytest.mark.parametrize("level", [0, 1, -3])
def test_level_below_two_raises_with_minimum(level):
    with pytest.raises(ValueError, match="minimum 2"):
        tessellate(flat_net(4, 4), level)


def test_level_must_be_int():
    with pytest.raises(ValueError, match="level must be an int"):
        tessellate(flat_net(4, 4), 2.5)


@pytest.mark.parametrize("shape", [(3, 5, 3), (5, 2, 3)])
def test_net_smaller_than_spline_order_raises_with_minimum(shape):
    with pytest.raises(ValueError, match="minimum 4"):
        tessellate(jnp.zeros(shape), 4)


def test_bad_bezier_net_bad_basis_bad_shape():
    with pytest.raises(ValueError, match="3\\*m \\+ 1"):
        tessellate(jnp.zeros((5, 4, 3)), 4, "bezier")
    with pytest.raises(ValueError, match="basis"):
        tessellate(jnp.zeros((4, 4, 3)), 4, "nurbs")
    with pytest.raises(ValueError, match="rows, cols, 3"):
        tessellate(jnp.zeros((4, 4, 2)), 4)


def test_vmap_over_frames():
    nets = jnp.stack([wavy_net(seed=5), wavy_net(seed=6)])
    pos = jax.jit(jax.vmap(lambda n: tessellate(n, 3).positions))(nets)
    np.testing.assert_allclose(pos[1], tess(nets[1]).positions, atol=1e-12)
