"""Rasterizer under a named vmap (`batch_axes`): one budget branch for the whole batch (pmax over
the axis), images and gradients equal to rendering each frame alone, also when the frames of the
batch need different window budgets and silhouette lists."""

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import camera as C
from diffcloth.render import raster as R

SIZE = (
    128  # the smallest size with budget ladders: windows 1024 / 4096 / max, pairs 1024 / 4096 / all
)
N = 6  # grid of N x N quads, 2 N^2 triangles


def _grid():
    u = jnp.linspace(-1.0, 1.0, N + 1)
    X, Y = jnp.meshgrid(u, u, indexing="xy")
    # a gentle fold, so that the grid is not planar (depth varies, some pixel pairs occlude)
    pos = jnp.stack([X, Y, 0.3 * jnp.sin(2.0 * X)], axis=-1).reshape(-1, 3)
    i = jnp.arange(N)[:, None] * (N + 1) + jnp.arange(N)[None, :]
    a, b, c, d = i, i + 1, i + N + 2, i + N + 1
    faces = jnp.concatenate(
        [jnp.stack([a, b, c], -1).reshape(-1, 3), jnp.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return pos, faces.astype(jnp.int32)


POS, FACES = _grid()
NEIGHBORS = R.edge_neighbors(np.asarray(FACES))
CAM = C.make_camera((0.2, 0.3, 3.0), (0.0, 0.0, 0.0), (0, 1, 0), width=SIZE, height=SIZE)
COLORS = jax.random.uniform(jax.random.PRNGKey(0), (POS.shape[0], 3))
# a tiny far cloth (no windows, few silhouette pairs), a mid-size one and one filling the screen
FRAMES = jnp.stack([POS * 0.08, POS * 0.5 + jnp.array([[0.1, 0.0, 0.0]]), POS * 1.4])
WEIGHTS = jax.random.normal(jax.random.PRNGKey(1), (3, SIZE, SIZE, 3))


def _image(p, axes, budget=None):
    fr = R.rasterize(p, FACES, CAM, neighbors=NEIGHBORS, batch_axes=axes, silhouette_budget=budget)
    return R.antialias(R.interpolate(COLORS, fr, FACES), fr), fr.triangle_id


def _batched(ps):
    return jax.vmap(lambda p: _image(p, ("b",)), axis_name="b")(ps)


# each frame alone, with the full-image silhouette search (one branch: compiles faster)
_alone = jax.jit(lambda p: _image(p, (), 2 * SIZE * SIZE))


def _loss_batched(ps):
    img, ids = _batched(ps)
    return jnp.sum(img * WEIGHTS), (img, ids)


def _loss_alone(p, w):
    img, ids = _image(p, ())
    return jnp.sum(img * w), (img, ids)


@pytest.mark.slow  # two more rasterizer compiles; checks that the tests below straddle the ladder
def test_frames_need_different_budgets():
    # the batch straddles the ladder: windows (32, 256, max) and silhouette pairs (64, 256, all)
    counts = jax.jit(
        jax.vmap(
            lambda p: (
                R.required_tiles(p, FACES, CAM),
                R.silhouette_pairs(p, FACES, CAM, neighbors=NEIGHBORS),
            )
        )
    )
    tiles, pairs = (np.asarray(c).tolist() for c in counts(FRAMES))
    budgets = R.window_budgets(SIZE, SIZE, R.default_max_tiles(FACES.shape[0], SIZE, SIZE))
    assert budgets[:2] == (1024, 4096)
    assert tiles[0] <= 1024 < tiles[1] <= 4096 < tiles[2], tiles
    K = R.default_silhouette_budget(SIZE, SIZE)
    assert K == 1024
    assert pairs[0] <= K < pairs[2], pairs


def test_batch_axis_keeps_one_switch_branch():
    # the budget index is reduced over the named axis: the switches stay conditionals (a batched
    # index turns each into a select that runs every branch)
    prims = set()

    def walk(jaxpr):
        for e in jaxpr.eqns:
            prims.add(e.primitive.name)
            for sub in jax.extend.core.jaxprs_in_params(e.params):
                walk(sub)

    walk(jax.make_jaxpr(_batched)(FRAMES).jaxpr)
    assert "cond" in prims and "pmax" in prims


@pytest.mark.slow  # ~15 s idle (42 s loaded); the default suite is near its 10-minute budget
def test_batched_images_equal_each_frame_alone():
    img, ids = jax.jit(_batched)(FRAMES)
    for t in range(FRAMES.shape[0]):
        img_1, ids_1 = _alone(FRAMES[t])
        np.testing.assert_array_equal(ids[t], ids_1)
        np.testing.assert_allclose(img[t], img_1, rtol=0, atol=1e-6)
    assert int(jnp.sum(ids[2] >= 0)) > 10 * int(jnp.sum(ids[0] >= 0)) > 0


@pytest.mark.slow  # two gradient compiles of the rasterizer (~40 s of CPU)
def test_batched_gradients_equal_each_frame_alone():
    (_, (img, ids)), grad_b = jax.jit(jax.value_and_grad(_loss_batched, has_aux=True))(FRAMES)
    step_1 = jax.jit(jax.value_and_grad(_loss_alone, has_aux=True))
    for t in range(FRAMES.shape[0]):
        (_, (img_1, ids_1)), g1 = step_1(FRAMES[t], WEIGHTS[t])
        np.testing.assert_array_equal(ids[t], ids_1)
        np.testing.assert_allclose(img[t], img_1, rtol=0, atol=1e-6)
        assert float(jnp.abs(g1).max()) > 0
        np.testing.assert_allclose(grad_b[t], g1, rtol=1e-5, atol=1e-6)
