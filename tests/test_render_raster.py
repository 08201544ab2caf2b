"""Rasterizer: analytic images, interpolation, silhouette/occlusion gradients vs finite differences,
and ROBUSTNESS rows 18 (zero-area), 19 (near plane / behind camera) and 21 (empty scene)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import camera as C
from diffcloth.render import raster as R

SIZE = 32
QUAD_FACES = jnp.array([[0, 1, 2], [0, 2, 3]])


def pixel_camera(size=SIZE):
    """Orthographic camera where one world unit is one pixel, x in [-16, 16], looking down -z."""
    view = C.look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    h = size / 2
    proj = C.orthographic(-h, h, -h, h, 0.1, 10.0)
    return C.camera_from_matrices(
        view, proj, width=size, height=size, near=0.1, far=10.0, kind="orthographic"
    )


def persp_camera(size=SIZE):
    return C.make_camera(
        (0.3, 0.2, 4.0), (0.0, 0.0, 0.0), (0, 1, 0), width=size, height=size, fov_y=40.0
    )


def quad(x0, x1, y0, y1, z=0.0):
    return jnp.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])


NV, NF = 16, 18  # every test mesh is padded to this size (degenerate faces) to share compiles


def pad(positions, faces, colors):
    n, m = positions.shape[0], faces.shape[0]
    positions = jnp.concatenate([positions, jnp.zeros((NV - n, 3), positions.dtype)])
    colors = jnp.concatenate([colors, jnp.zeros((NV - n, colors.shape[1]), colors.dtype)])
    faces = jnp.concatenate([jnp.asarray(faces, jnp.int32), jnp.zeros((NF - m, 3), jnp.int32)])
    return positions, faces, colors


@jax.jit
def _render(positions, faces, colors, camera):
    return R.render_mesh(positions, faces, camera, colors)


@jax.jit
def _render_hard(positions, faces, colors, camera):
    return R.render_mesh(positions, faces, camera, colors, antialiased=False)


def _weighted(positions, faces, colors, camera, weights):
    return jnp.sum(weights * R.render_mesh(positions, faces, camera, colors))


def _weighted_hard(positions, faces, colors, camera, weights):
    return jnp.sum(weights * R.render_mesh(positions, faces, camera, colors, antialiased=False))


_grad = jax.jit(jax.grad(_weighted, argnums=(0, 2)))
_grad_hard = jax.jit(jax.grad(_weighted_hard, argnums=(0, 2)))
_value_hard = jax.jit(_weighted_hard)
_frags = jax.jit(lambda p, f, c: R.rasterize(p, f, c))


def render(positions, faces, colors, camera):
    return _render(*pad(positions, faces, colors), camera)


def render_hard(positions, faces, colors, camera):
    return _render_hard(*pad(positions, faces, colors), camera)


def grad(positions, faces, colors, camera, weights=None):
    """d sum(weights * image) / d (positions, colors), unpadded."""
    weights = jnp.ones((camera.height, camera.width, 4)) if weights is None else weights
    n = positions.shape[0]
    gp, gc = _grad(*pad(positions, faces, colors), camera, weights)
    return gp[:n], gc[:n]


WHITE = jnp.ones((4, 3))


def test_pixel_aligned_square_exact_count():
    pos = quad(-4.0, 6.0, -3.0, 5.0)
    hard = render_hard(pos, QUAD_FACES, WHITE, pixel_camera())
    assert int((hard[..., 3] > 0).sum()) == 80
    soft = render(pos, QUAD_FACES, WHITE, pixel_camera())
    np.testing.assert_allclose(float(soft[..., 3].sum()), 80.0, atol=1e-9)
    # exactly the expected pixels: columns 12..21, rows 11..18
    want = np.zeros((SIZE, SIZE), bool)
    want[11:19, 12:22] = True
    np.testing.assert_array_equal(np.asarray(hard[..., 3] > 0), want)


def test_unaligned_square_area():
    pos = quad(-4.3, 3.4, -2.2, 5.1)
    area = 7.7 * 7.3
    hard = render_hard(pos, QUAD_FACES, WHITE, pixel_camera())
    assert abs(float(hard[..., 3].sum()) - area) <= 8.0  # within one pixel row
    soft = render(pos, QUAD_FACES, WHITE, pixel_camera())
    assert abs(float(soft[..., 3].sum()) - area) < 0.5  # only the four corner pixels are off


@pytest.mark.parametrize("near_first", [True, False])
def test_overlapping_squares_show_the_nearer(near_first):
    near = quad(-6.0, 2.0, -6.0, 2.0, z=1.0)
    far = quad(-2.0, 6.0, -2.0, 6.0, z=0.0)
    red, green = jnp.tile(jnp.array([1.0, 0, 0]), (4, 1)), jnp.tile(jnp.array([0, 1.0, 0]), (4, 1))
    parts = [(near, red), (far, green)] if near_first else [(far, green), (near, red)]
    pos = jnp.concatenate([p for p, _ in parts])
    col = jnp.concatenate([c for _, c in parts])
    faces = jnp.concatenate([QUAD_FACES, QUAD_FACES + 4])
    img = np.asarray(render_hard(pos, faces, col, pixel_camera()))
    # pixel (row 16, col 16) is centred at (0.5, -0.5): inside both -> red (near)
    np.testing.assert_allclose(img[16, 16], [1, 0, 0, 1])
    np.testing.assert_allclose(img[12, 20], [0, 1, 0, 1])  # (4.5, 3.5): only the far square
    np.testing.assert_allclose(img[20, 12], [1, 0, 0, 1])  # (-3.5, -4.5): only the near square
    np.testing.assert_allclose(img[2, 2], [0, 0, 0, 0])


SLANTED = jnp.array([[-1.0, -1.0, 0.5], [1.2, -1.0, 0.5], [1.0, 1.0, -2.5], [-1.1, 1.0, -2.5]])


def test_perspective_correct_interpolation():
    cam = persp_camera()
    p, f, _ = pad(SLANTED, QUAD_FACES, SLANTED)
    frags = _frags(p, f, cam)
    world = R.interpolate(p, frags, f)
    mask = np.asarray(frags.triangle_id >= 0)
    assert mask.sum() > 100
    o, d = C.pixel_rays(cam)
    # perspective-correct: the interpolated world point lies on the pixel's ray
    off = np.cross(np.asarray(world - o), np.asarray(d))
    np.testing.assert_allclose(off[mask], 0.0, atol=1e-9)
    # and its view depth is the fragment depth
    _, depth = C.project(jnp.asarray(world[mask]), cam)
    np.testing.assert_allclose(depth, np.asarray(frags.depth)[mask], rtol=1e-9)
    np.testing.assert_allclose(np.asarray(frags.barycentric).sum(-1)[mask], 1.0, atol=1e-12)


def test_interior_gradients_match_finite_differences():
    cam = persp_camera()
    rng = np.random.default_rng(1)
    weights = jnp.asarray(rng.uniform(size=(SIZE, SIZE, 4)))
    colors = jnp.asarray(rng.uniform(size=(4, 3)))
    p, f, c = pad(SLANTED, QUAD_FACES, colors)
    g_pos, g_col = _grad_hard(p, f, c, cam, weights)
    assert np.abs(g_pos).max() > 0 and np.abs(g_col).max() > 0
    eps = 1e-6
    for idx in [(0, 0), (1, 2), (2, 1), (3, 0), (2, 2)]:
        e = jnp.zeros_like(p).at[idx].set(eps)
        fd = (_value_hard(p + e, f, c, cam, weights) - _value_hard(p - e, f, c, cam, weights)) / (
            2 * eps
        )
        np.testing.assert_allclose(g_pos[idx], fd, rtol=1e-5, atol=1e-8)
    e = jnp.zeros_like(c).at[2, 1].set(eps)
    fd = (_value_hard(p, f, c + e, cam, weights) - _value_hard(p, f, c - e, cam, weights)) / (
        2 * eps
    )
    np.testing.assert_allclose(g_col[2, 1], fd, rtol=1e-6)


def _check_silhouette_gradient(base, faces, colors, camera, weights, moving, h=0.05):
    """AD vs central FD of d sum(weights * image(base + dx * moving)) / d dx at dx = 0."""
    gp, _ = grad(base, faces, colors, camera, weights)
    g = float(jnp.sum(gp[:, 0] * moving))

    def loss(dx):
        return float(
            jnp.sum(weights * render(base.at[:, 0].add(dx * moving), faces, colors, camera))
        )

    fd = (loss(h) - loss(-h)) / (2 * h)
    assert abs(fd) > 1e-3, fd
    assert abs(g - fd) <= 0.05 * abs(fd), (g, fd)
    return g, fd


@pytest.mark.parametrize(
    "camera_fn",
    [pixel_camera, pytest.param(persp_camera, marks=[pytest.mark.slow, pytest.mark.gate])],
)  # perspective: 8 s
def test_silhouette_gradient_translating_square(camera_fn):
    cam = camera_fn()
    scale = 1.0 if cam.kind == "orthographic" else 0.12
    base = quad(-30.0, 4.3, -6.2, 7.7) * scale  # left part off-screen: coverage changes with x
    ones = jnp.ones((SIZE, SIZE, 4))
    g, fd = _check_silhouette_gradient(
        base, QUAD_FACES, WHITE, cam, ones, jnp.ones(4), h=0.05 * scale
    )
    if cam.kind == "orthographic":  # d(area)/dx = edge length (13.9 px) x 4 channels
        assert abs(g / 4 - 13.9) <= 1.0
    ramp = jnp.broadcast_to(jnp.linspace(0.0, 2.0, SIZE)[None, :, None], (SIZE, SIZE, 4))
    _check_silhouette_gradient(base, QUAD_FACES, WHITE, cam, ramp, jnp.ones(4), h=0.05 * scale)


def test_occlusion_edge_gradient():
    cam = pixel_camera()
    pos, faces, colors = _occlusion_scene()
    moving = jnp.array([1.0, 1, 1, 1, 0, 0, 0, 0])
    weights = jnp.ones((SIZE, SIZE, 4)).at[..., 3].set(0.0)
    g, fd = _check_silhouette_gradient(pos, faces, colors, cam, weights, moving)
    # colour difference (1.2 - 1.5) x edge length 11.7 px (rows whose centre the edge spans: 11)
    assert abs(g / (1.2 - 1.5) - 11.7) <= 1.0


def _occlusion_scene():
    back = quad(-20.0, 20.0, -20.0, 20.0, z=0.0)
    front = quad(-30.0, 3.6, -5.3, 6.4, z=1.0)
    pos = jnp.concatenate([front, back])
    faces = jnp.concatenate([QUAD_FACES, QUAD_FACES + 4])
    colors = jnp.concatenate(
        [jnp.tile(jnp.array([1.0, 0.2, 0.0]), (4, 1)), jnp.tile(jnp.array([0.0, 0.5, 1.0]), (4, 1))]
    )
    return pos, faces, colors


def _value_budget(positions, faces, colors, camera, weights, budget):
    img = R.render_mesh(positions, faces, camera, colors, silhouette_budget=budget)
    return jnp.sum(weights * img)


_value_and_grad_budget = jax.jit(
    jax.value_and_grad(_value_budget, argnums=(0, 2)), static_argnums=(5,)
)


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_compact_silhouette_search_matches_full_image_search():
    """The compacted pair list (default from 128 x 128 up) gives the full search's image and
    gradients exactly."""
    cam = pixel_camera()
    pos, faces, colors = _occlusion_scene()
    p, f, c = pad(pos, faces, colors)
    need = int(jax.jit(R.silhouette_pairs)(p, f, cam))
    assert 0 < need <= 160  # so a budget of 160 (< 2 H W = 2048) takes the compact path
    weights = jnp.asarray(np.random.default_rng(3).uniform(size=(SIZE, SIZE, 4)))
    v, (gp, gc) = _value_and_grad_budget(p, f, c, cam, weights, 160)
    gp_full, gc_full = _grad(p, f, c, cam, weights)
    assert np.abs(gp_full).max() > 0
    np.testing.assert_allclose(float(v), float(jnp.sum(weights * _render(p, f, c, cam))), 1e-12)
    np.testing.assert_allclose(gp, gp_full, atol=1e-12)
    np.testing.assert_allclose(gc, gc_full, atol=1e-12)


@pytest.mark.slow
def test_second_silhouette_list_matches_full_image_search():
    """A frame needing more pairs than the budget but at most 4 x that takes the second
    compacted list: same image and gradients as the full search."""
    cam = pixel_camera()
    p, f, c = pad(*_occlusion_scene())
    need = int(jax.jit(R.silhouette_pairs)(p, f, cam))
    budget = need // 2
    assert budget < need <= 4 * budget < 2 * SIZE * SIZE
    weights = jnp.asarray(np.random.default_rng(5).uniform(size=(SIZE, SIZE, 4)))
    v, (gp, gc) = _value_and_grad_budget(p, f, c, cam, weights, budget)
    gp_full, gc_full = _grad(p, f, c, cam, weights)
    np.testing.assert_allclose(float(v), float(jnp.sum(weights * _render(p, f, c, cam))), 1e-12)
    np.testing.assert_allclose(gp, gp_full, atol=1e-12)
    np.testing.assert_allclose(gc, gc_full, atol=1e-12)


@pytest.mark.slow
def test_silhouette_budget_overflow_falls_back_to_full_search():
    cam = pixel_camera()
    p, f, c = pad(*_occlusion_scene())
    weights = jnp.asarray(np.random.default_rng(4).uniform(size=(SIZE, SIZE, 4)))
    v, (gp, _) = _value_and_grad_budget(p, f, c, cam, weights, 2)  # needs more than 2 pairs
    np.testing.assert_allclose(float(v), float(jnp.sum(weights * _render(p, f, c, cam))), 1e-12)
    np.testing.assert_allclose(gp, _grad(p, f, c, cam, weights)[0], atol=1e-12)
    with pytest.raises(ValueError, match="silhouette_budget"):
        R.rasterize(p, f, cam, silhouette_budget=-1)


# ROBUSTNESS row 21: empty scene -> background, finite loss, zero (not NaN) gradients
@pytest.mark.slow  # ~40 s of compile (10-minute budget); test_robustness's row-21 test is default
def test_empty_scene():
    cam = persp_camera()
    behind = quad(-1.0, 1.0, -1.0, 1.0, z=6.0)  # behind the eye (eye at z = 4)
    aside = quad(30.0, 31.0, -1.0, 1.0)
    pos = jnp.concatenate([behind, aside])
    faces = jnp.concatenate([QUAD_FACES, QUAD_FACES + 4])
    colors = jnp.ones((8, 3))

    img = render(pos, faces, colors, cam)
    np.testing.assert_array_equal(np.asarray(img), 0.0)
    assert np.isfinite(float(jnp.sum((img - 0.3) ** 2)))
    gp, gc = grad(pos, faces, colors, cam)
    np.testing.assert_array_equal(np.asarray(gp), 0.0)
    np.testing.assert_array_equal(np.asarray(gc), 0.0)
    none = R.render_mesh(jnp.zeros((0, 3)), jnp.zeros((0, 3), jnp.int32), cam, jnp.zeros((0, 3)))
    np.testing.assert_array_equal(np.asarray(none), 0.0)


# ROBUSTNESS row 18: zero-area / sliver triangles are skipped with finite gradients
def test_zero_area_triangles():
    cam = pixel_camera()
    good = jnp.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [0.0, 5.0, 0.0]])
    repeated = jnp.array([[1.0, 1.0, 0.5], [1.0, 1.0, 0.5], [4.0, -2.0, 0.5]])  # two equal vertices
    collinear = jnp.array([[-8.0, 0.0, 0.7], [0.0, 0.0, 0.7], [8.0, 0.0, 0.7]])
    edge_on = jnp.array(
        [[-3.0, 2.0, 1.0], [-3.0, 2.0, -1.0], [3.0, 2.0, 0.0]]
    )  # same screen XY pair
    pos = jnp.concatenate([good, repeated, collinear, edge_on])
    faces = jnp.arange(12).reshape(4, 3)
    colors = jnp.tile(jnp.array([[1.0, 0.0, 0.0]]), (12, 1)).at[3:].set(jnp.array([0.0, 1.0, 0.0]))
    img = render(pos, faces, colors, cam)
    alone = render(good, faces[:1], colors[:3], cam)
    assert np.all(np.isfinite(img))
    np.testing.assert_allclose(np.asarray(img), np.asarray(alone), atol=1e-12)
    g, _ = grad(
        pos, faces, colors, cam, jnp.linspace(0.0, 1.0, SIZE * SIZE * 4).reshape(SIZE, SIZE, 4)
    )
    assert np.all(np.isfinite(g)) and np.abs(g[:3]).max() > 0
    np.testing.assert_array_equal(np.asarray(g[3:]), 0.0)


# ROBUSTNESS row 19: geometry straddling the near plane / behind the camera
def test_near_plane_crossing_floor():
    cam = C.make_camera(
        (0.0, 0.0, 0.0), (0.0, -0.3, -1.0), (0, 1, 0), width=SIZE, height=SIZE, near=0.1, far=100.0
    )
    floor = jnp.array(
        [[-50.0, -1.0, 50.0], [50.0, -1.0, 50.0], [50.0, -1.0, -50.0], [-50.0, -1.0, -50.0]]
    )
    colors = jnp.ones((4, 3))
    frags = _frags(*pad(floor, QUAD_FACES, colors)[:2], cam)
    o, d = C.pixel_rays(cam)
    t = (-1.0 - o[..., 1]) / jnp.where(d[..., 1] < 0, d[..., 1], -1.0)
    hit = o + t[..., None] * d
    want = np.asarray((d[..., 1] < 0) & (jnp.abs(hit[..., 0]) < 50) & (jnp.abs(hit[..., 2]) < 50))
    got = np.asarray(frags.triangle_id >= 0)
    assert want.sum() > 100 and (want != got).sum() <= SIZE  # at most the horizon row differs
    img = render(floor, QUAD_FACES, colors, cam)
    g, _ = grad(floor, QUAD_FACES, colors, cam)
    assert np.all(np.isfinite(img)) and np.all(np.isfinite(g))
    # a triangle with a vertex exactly at the eye and one through it: finite
    tri = jnp.array([[0.0, 0.0, 0.0], [1.0, -1.0, -3.0], [-1.0, -1.0, 3.0]])
    img = render(tri, jnp.array([[0, 1, 2]]), jnp.ones((3, 3)), cam)
    g, _ = grad(tri, jnp.array([[0, 1, 2]]), jnp.ones((3, 3)), cam)
    assert np.all(np.isfinite(img)) and np.all(np.isfinite(g))


def test_camera_inside_cloth_bounding_box():
    cam = C.make_camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0, 1, 0), width=SIZE, height=SIZE)
    u, v = np.meshgrid(np.linspace(-2, 2, 4), np.linspace(-2, 2, 4))
    pos = jnp.asarray(
        np.stack([u, 0.3 * np.sin(3 * u), v], -1).reshape(-1, 3)
    )  # sheet through the eye
    idx = np.arange(16).reshape(4, 4)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
    faces = jnp.asarray(
        np.concatenate([np.stack([a, b, c], -1), np.stack([c, b, d], -1)]).reshape(-1, 3)
    )
    img = render(pos, faces, jnp.ones((16, 3)), cam)
    g, _ = grad(pos, faces, jnp.ones((16, 3)), cam)
    assert np.all(np.isfinite(img)) and np.all(np.isfinite(g)) and float(img[..., 3].sum()) > 0


def test_full_screen_triangle():
    cam = persp_camera()
    big = jnp.array([[-100.0, -100.0, 0.0], [100.0, -100.0, 0.0], [0.0, 100.0, 0.0]])
    img = render_hard(big, jnp.array([[0, 1, 2]]), jnp.ones((3, 3)), cam)
    assert int((img[..., 3] > 0).sum()) == SIZE * SIZE
    two = jnp.concatenate([big, big.at[:, 2].set(-1.0)])
    frags = _frags(*pad(two, jnp.array([[0, 1, 2], [3, 4, 5]]), two)[:2], cam)
    np.testing.assert_array_equal(np.asarray(frags.triangle_id), 0)  # the nearer one everywhere
    need = int(R.required_tiles(two, jnp.array([[0, 1, 2], [3, 4, 5]]), cam))
    assert need <= R.default_max_tiles(2, SIZE, SIZE)


@jax.jit
def _two_buffers(a, b, cam):
    ga = R.rasterize_gbuffer(
        a, QUAD_FACES, cam, {"color": jnp.tile(jnp.array([1.0, 0, 0]), (4, 1))}
    )
    gb = R.rasterize_gbuffer(
        b,
        QUAD_FACES,
        cam,
        {"color": jnp.tile(jnp.array([0, 1.0, 0]), (4, 1)), "uv": jnp.ones((4, 2))},
    )
    g = R.composite(gb, ga)
    out = R.antialias(jnp.concatenate([g.attributes["color"], g.mask[..., None] * 1.0], -1), g)
    return g, out


def test_gbuffer_composite_and_antialias():
    a = quad(-6.0, 2.0, -6.0, 2.0, z=1.0)
    b = quad(-2.0, 6.0, -2.0, 6.0, z=0.0)
    g, out = _two_buffers(a, b, pixel_camera())
    assert set(g.attributes) == {"color", "uv"}
    np.testing.assert_allclose(g.attributes["color"][16, 16], [1, 0, 0])
    np.testing.assert_allclose(g.attributes["uv"][16, 16], [0, 0])  # a has no uv -> zeros
    np.testing.assert_allclose(g.attributes["uv"][12, 20], [1, 1])
    assert int(g.mask.sum()) == 64 + 64 - 16
    np.testing.assert_allclose(float(out[..., 3].sum()), 112.0, atol=1e-9)


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_vmap_over_cameras_and_float32():
    eyes = jnp.array([[0.0, 0.0, 4.0], [0.5, 0.3, 4.0]])
    up = jnp.array([0.0, 1.0, 0.0])
    cams = jax.vmap(lambda e: C.make_camera(e, jnp.zeros(3), up, width=8, height=8))(eyes)
    p, f, c = pad(SLANTED, QUAD_FACES, jnp.ones((4, 3)))
    imgs = jax.jit(jax.vmap(lambda cam: R.render_mesh(p, f, cam, c)))(cams)
    for i in range(2):
        cam = C.make_camera(eyes[i], jnp.zeros(3), up, width=8, height=8)
        np.testing.assert_allclose(imgs[i], _render(p, f, c, cam), atol=1e-12)
    assert float(jnp.abs(imgs[0] - imgs[1]).max()) > 0.1
    f32 = C.make_camera(
        jnp.array([0.0, 0.0, 4.0], jnp.float32),
        jnp.zeros(3, jnp.float32),
        up.astype(jnp.float32),
        width=8,
        height=8,
    )
    img = _render(p.astype(jnp.float32), f, c.astype(jnp.float32), f32)
    assert img.dtype == jnp.float32
    np.testing.assert_allclose(img, imgs[0], atol=1e-4)


def test_edge_neighbors():
    faces = jnp.array([[0, 1, 2], [0, 2, 3], [2, 1, 4]])
    want = np.array([[2, 1, -1], [-1, -1, 0], [-1, -1, 0]])
    np.testing.assert_array_equal(np.asarray(R.edge_neighbors(faces)), want)
    np.testing.assert_array_equal(np.asarray(jax.jit(R.edge_neighbors)(faces)), want)


def _brute_force_ids(pos, faces, size):
    """numpy z-buffer over every (pixel, triangle) of the pixel camera (depth = 5 - z)."""
    p = np.asarray(pos, np.float64)
    ids = np.full((size, size), -1)
    best = np.full((size, size), np.inf)
    jj, ii = np.meshgrid(np.arange(size) - size / 2 + 0.5, size / 2 - 0.5 - np.arange(size))
    for t, f in enumerate(np.asarray(faces)):
        a, b, c = p[f]
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        w = [
            ((q1[0] - jj) * (q2[1] - ii) - (q1[1] - ii) * (q2[0] - jj)) / area
            for q1, q2 in ((b, c), (c, a), (a, b))
        ]
        inside = (w[0] >= 0) & (w[1] >= 0) & (w[2] >= 0)
        depth = 5.0 - (w[0] * a[2] + w[1] * b[2] + w[2] * c[2])
        better = inside & (depth < best)
        best = np.where(better, depth, best)
        ids = np.where(better, t, ids)
    return ids


@jax.jit
def _ids_and_windows(positions, faces, camera):
    """Visible triangle per pixel with the default window budgets, the windows needed, the ids
    with a window budget of 8 (drops windows) and which triangles are tested directly."""
    s = R._setup(positions, faces, camera, False)
    ids = R._visibility(
        s, camera, 2, R.default_max_tiles(faces.shape[0], camera.width, camera.height)
    )
    direct = R._tile_counts(s, 1)[1] <= R.DIRECT_PIXELS
    need = R.required_tiles(positions, faces, camera)
    return ids.reshape(camera.height, camera.width), need, R._visibility(s, camera, 2, 8), direct


@pytest.mark.parametrize("big", [pytest.param(False, marks=pytest.mark.slow), True])  # False: 13 s
def test_visibility_of_mixed_triangle_sizes_matches_brute_force(big):
    """128 x 128 pixels. Sub-pixel triangles (tested directly) and larger ones (windows): without
    the two big triangles the windows fit in the smallest budget, with them (behind, covering
    most of the screen) the max_tiles pass runs. A window budget of 8 drops windows, so there
    only the pixels the direct triangles win must agree."""
    size = 128
    rng = np.random.default_rng(3)
    n = 40
    centres = rng.uniform(-0.45 * size, 0.45 * size, (n, 2))
    scale = np.concatenate([rng.uniform(1.2, 2.2, n - 10), rng.uniform(2, 6, 8), [size, size]])
    scale = scale if big else np.minimum(scale, 3.0)
    corners = centres[:, None] + scale[:, None, None] * rng.uniform(-1, 1, (n, 3, 2))
    z = rng.uniform(-1, 1, (n, 3, 1)) - 2.0 * (scale[:, None, None] > 10)  # big ones behind
    pos = jnp.asarray(np.concatenate([corners, z], -1).reshape(-1, 3))
    faces = jnp.arange(3 * n).reshape(n, 3)
    cam = pixel_camera(size)
    got, need, dropped, direct = map(np.asarray, _ids_and_windows(pos, faces, cam))
    budgets = R.window_budgets(size, size, R.default_max_tiles(n, size, size))
    assert len(budgets) == 3 and (need <= budgets[0]) != big and (need > budgets[-2]) == big
    want = _brute_force_ids(pos, faces, size)
    assert len(np.unique(want)) > 20
    np.testing.assert_array_equal(got, want)
    # dropping windows only removes candidates: pixels won by a direct triangle stay
    won = np.isin(want, np.nonzero(direct)[0])
    dropped = dropped.reshape(size, size)
    assert won.sum() > 3 and np.any(dropped != want)
    np.testing.assert_array_equal(dropped[won], want[won])


def test_reach_matches_a_breadth_first_search():
    """`_reach` (a dilation over the neighbour columns) against a breadth-first search that
    crosses only internal edges: reached within `walk` steps of a silhouette edge."""
    rng = np.random.default_rng(3)
    n = 9  # a 9 x 9 grid of quads, two triangles each, some culled or turned away
    v = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = v[:-1, :-1].ravel(), v[:-1, 1:].ravel(), v[1:, :-1].ravel(), v[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    m = faces.shape[0]
    nbr = np.asarray(R.edge_neighbors(faces))
    valid, front = rng.random(m) > 0.03, rng.random(m) > 0.05
    zeros = jnp.zeros((m, 9))
    s = R._Setup(zeros, zeros[:, :3], jnp.asarray(valid), jnp.asarray(front), None, None)
    sil = np.asarray(R._silhouette(s, jnp.asarray(nbr)))
    for walk in (0, 1, 3):
        _, reach = R._reach(s, jnp.asarray(nbr), walk)
        dist = np.where(sil.any(1), 0, 10**6)
        for _ in range(walk):  # relax across internal (non-silhouette) edges
            for t in range(m):
                for k in range(3):
                    if not sil[t, k]:
                        dist[t] = min(dist[t], dist[nbr[t, k]] + 1)
        np.testing.assert_array_equal(np.asarray(reach), dist <= walk)
    assert 0 < int(np.sum(reach)) < m
