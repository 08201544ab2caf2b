"""Frustum culling by bounding sphere, backface culling by winding."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import camera as C
from diffcloth.render import culling as K
from diffcloth.render import raster as R


@pytest.fixture(scope="module")
def cam():
    return C.make_camera(
        (0.0, 0.0, 5.0),
        (0.0, 0.0, 0.0),
        (0, 1, 0),
        width=16,
        height=16,
        fov_y=60.0,
        near=1.0,
        far=20.0,
    )


def test_frustum_planes_outward(cam):
    planes = K.frustum_planes(cam)
    assert planes.shape == (6, 4)
    np.testing.assert_allclose(np.linalg.norm(planes[:, :3], axis=-1), 1.0, atol=1e-12)
    inside = jnp.array([0.0, 0.0, 0.0, 1.0])
    assert np.all(planes @ inside < 0)
    # near plane at view depth 1 -> world z = 4; far at z = -15
    np.testing.assert_allclose(planes[4] @ jnp.array([0.0, 0.0, 4.0, 1.0]), 0.0, atol=1e-9)
    np.testing.assert_allclose(planes[5] @ jnp.array([0.0, 0.0, -15.0, 1.0]), 0.0, atol=1e-9)


@pytest.mark.parametrize(
    "center,radius,visible",
    [
        ((0.0, 0.0, 0.0), 0.5, True),  # in front
        ((0.0, 0.0, 8.0), 0.5, False),  # behind the camera
        ((0.0, 0.0, 8.0), 4.5, True),  # behind, but large enough to reach the near plane
        ((20.0, 0.0, 0.0), 1.0, False),  # far to the right
        ((3.2, 0.0, 0.0), 0.5, True),  # straddles the right plane (tan 30 * 5 = 2.89)
        ((0.0, -4.0, 0.0), 0.5, False),  # below the bottom plane
        ((0.0, 0.0, -30.0), 1.0, False),  # beyond far
    ],
)
def test_sphere_in_frustum(cam, center, radius, visible):
    planes = K.frustum_planes(cam)
    assert bool(K.sphere_in_frustum(jnp.asarray(center), jnp.asarray(radius), planes)) is visible


def test_sphere_in_frustum_batched_and_bounding_sphere(cam):
    planes = K.frustum_planes(cam)
    centers = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 8.0]])
    np.testing.assert_array_equal(
        K.sphere_in_frustum(centers, jnp.array([0.5, 0.5]), planes), [True, False]
    )
    pts = jnp.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    c, r = K.bounding_sphere(pts)
    assert np.all(np.linalg.norm(pts - c[None], axis=-1) <= float(r) + 1e-12)


TRI = jnp.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])


@jax.jit
def _coverage(positions, faces, cam):
    """Covered pixels with and without backface culling, and whether any is front-facing."""
    culled = R.rasterize(positions, faces, cam, cull_backfaces=True)
    both = R.rasterize(positions, faces, cam)
    n = lambda f: jnp.sum(f.triangle_id >= 0)
    return n(culled), n(both), jnp.any(both.front_facing)


@pytest.mark.parametrize("projection", ["perspective", "orthographic", "isometric"])
def test_backface(projection):
    cam = C.make_camera(
        (0.3, 0.2, 5.0), (0.0, 0.0, 0.0), (0, 1, 0), width=16, height=16, projection=projection
    )
    faces = jnp.array([[0, 1, 2], [0, 2, 1]])  # counter-clockwise seen from +z, then clockwise
    np.testing.assert_array_equal(K.facing_camera(TRI, faces, cam), [True, False])
    np.testing.assert_allclose(K.triangle_normals(TRI, faces)[0], [0, 0, 1], atol=1e-12)
    # the rasterizer's screen winding agrees; backface culling drops only the clockwise one
    front_culled, front_both, front_facing = _coverage(TRI, faces[:1], cam)
    back_culled, back_both, back_facing = _coverage(TRI, faces[1:], cam)
    assert int(front_culled) > 10 and int(back_culled) == 0
    assert int(back_both) == int(front_both) == int(front_culled)  # two-sided by default
    assert bool(front_facing) and not bool(back_facing)


def test_degenerate_triangle_not_facing(cam):
    flat = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    assert not bool(K.facing_camera(flat, jnp.array([[0, 1, 2]]), cam)[0])
