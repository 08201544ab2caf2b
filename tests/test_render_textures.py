"""Textures: bilinear / mip sampling, seamless cube maps, procedural textures, files."""

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render import textures as T

# jit once per module: eager op-by-op dispatch dominates small tests
sample_2d = jax.jit(T.sample_2d, static_argnames="wrap")
sample_mip = jax.jit(T.sample_mip, static_argnames="wrap")
sample_cube = jax.jit(T.sample_cube)
sample_latlong = jax.jit(T.sample_latlong)
uv_lod = jax.jit(T.uv_lod, static_argnums=2)


def test_sample_2d_texel_centres_and_midpoints():
    tex = jnp.arange(12.0).reshape(3, 4, 1)
    i, j = np.meshgrid(np.arange(3), np.arange(4), indexing="ij")
    uv = jnp.stack([(j + 0.5) / 4, (i + 0.5) / 3], -1)
    np.testing.assert_allclose(sample_2d(tex, uv)[..., 0], tex[..., 0], atol=1e-12)
    mid = sample_2d(tex, jnp.array([1.0 / 4, 1.0 / 3]))  # between texels (0,0),(0,1),(1,0),(1,1)
    np.testing.assert_allclose(mid[0], (0 + 1 + 4 + 5) / 4, atol=1e-12)


def test_sample_2d_wrap_and_clamp():
    tex = jnp.array([[[0.0], [10.0]]])  # 1 x 2
    left_edge = jnp.array([0.0, 0.5])  # halfway between texel 1 (wrapped) and texel 0
    assert float(sample_2d(tex, left_edge, wrap="repeat")[0]) == pytest.approx(5.0)
    assert float(sample_2d(tex, left_edge, wrap="clamp")[0]) == pytest.approx(0.0)
    # repeat is periodic
    uv = jnp.array([0.3, 0.5])
    np.testing.assert_allclose(sample_2d(tex, uv), sample_2d(tex, uv + jnp.array([2.0, -1.0])))
    with pytest.raises(ValueError, match="wrap"):
        sample_2d(tex, uv, wrap="mirror")


def test_sample_2d_float32_stays_float32():
    tex = jnp.ones((4, 4, 3), jnp.float32)
    assert sample_2d(tex, jnp.full((5, 2), 0.3, jnp.float32)).dtype == jnp.float32


def test_mip_pyramid_and_lod():
    tex = T.checker(16, 16, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))  # one texel per square
    pyr = T.mip_pyramid(tex)
    assert [p.shape[0] for p in pyr] == [16, 8, 4, 2, 1]
    np.testing.assert_allclose(pyr[1][..., :3], 0.5, atol=1e-12)  # box filter of a 1-texel checker
    uv = jnp.full((3, 2), 0.37)
    np.testing.assert_allclose(sample_mip(pyr, uv, jnp.full(3, 2.0))[..., :3], 0.5, atol=1e-12)
    np.testing.assert_allclose(sample_mip(pyr, uv, jnp.zeros(3)), sample_2d(tex, uv), atol=1e-12)
    # uv footprint: neighbouring pixels 4 texels apart -> lod 2
    H = W = 8
    i, j = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    uv_img = jnp.stack([j * 4.0 / 16, i * 4.0 / 16], -1)
    lod = uv_lod(uv_img, jnp.ones((H, W)), tex.shape)
    np.testing.assert_allclose(lod, 2.0, atol=1e-12)
    # a fine uv gradient (less than one texel per pixel) -> lod 0
    np.testing.assert_allclose(uv_lod(uv_img / 8, jnp.ones((H, W)), tex.shape), 0.0, atol=1e-12)


@pytest.mark.parametrize(
    "wrap", [pytest.param("repeat", marks=pytest.mark.slow), ("clamp", "repeat")]
)  # repeat: 8 s
def test_sample_mip_equals_blend_of_every_level_with_gradients(wrap):
    """The packed two-level lookup equals sum_l max(0, 1 - |lod - l|) sample_2d(level l): values
    and gradients w.r.t. texels and uv for lod below 0, between levels, on a level and above; the
    gradient w.r.t. lod between levels."""
    rng = np.random.default_rng(3)
    pyr = T.mip_pyramid(jnp.asarray(rng.uniform(size=(16, 8, 2))))
    uv = jnp.asarray(rng.uniform(-0.3, 1.3, size=(40, 2)))
    lod = jnp.asarray(np.r_[-1.0, 0.0, 1.0, 2.5, 3.0, 9.0, rng.uniform(0, 3, size=34)])

    def reference(pyr, uv, lod):
        lod = jnp.clip(lod, 0.0, len(pyr) - 1.0)
        return sum(
            jnp.maximum(0.0, 1.0 - jnp.abs(lod - k))[..., None] * T.sample_2d(t, uv, wrap=wrap)
            for k, t in enumerate(pyr)
        )

    np.testing.assert_allclose(sample_mip(pyr, uv, lod, wrap=wrap), reference(pyr, uv, lod),
                               atol=1e-12)  # fmt: skip
    w = jnp.asarray(rng.normal(size=(40, 2)))
    loss = lambda f: jax.jit(jax.grad(lambda *a: jnp.sum(w * f(*a)), argnums=(0, 1, 2)))
    got = loss(lambda *a: T.sample_mip(*a, wrap=wrap))(pyr, uv, lod)
    want = loss(reference)(pyr, uv, lod)
    for g, r in zip(jax.tree.leaves(got[:2]), jax.tree.leaves(want[:2]), strict=True):
        np.testing.assert_allclose(g, r, atol=1e-10)
    # d/dlod: equal away from the kinks at whole levels and the clip ends (any subgradient there)
    smooth = np.asarray((lod > 0) & (lod < len(pyr) - 1) & (lod != jnp.round(lod)))
    assert smooth.sum() > 30
    np.testing.assert_allclose(got[2][smooth], want[2][smooth], atol=1e-10)


def test_mip_reduces_aliasing_of_minified_checker():
    tex = T.checker(64, 32, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    pyr = T.mip_pyramid(tex)
    H = W = 16  # 4 texels per pixel: point-ish bilinear sampling aliases, mip gives ~grey
    i, j = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    uv = jnp.stack([(j + 0.3) / W, (i + 0.3) / H], -1)
    lod = uv_lod(uv, jnp.ones((H, W)), tex.shape)
    plain = sample_2d(tex, uv)[..., 0]
    filtered = sample_mip(pyr, uv, lod)[..., 0]
    # aliasing: the plain lookup is far from the true mean 0.5 (here a uniform moire)
    assert float(jnp.std(plain)) > 0.3 or abs(float(jnp.mean(plain)) - 0.5) > 0.3
    assert float(jnp.std(filtered)) < 0.05
    np.testing.assert_allclose(float(jnp.mean(filtered)), 0.5, atol=0.05)


def _direction_cube(size):
    d = T.face_directions(size)
    return T.make_cube_map(jnp.asarray(0.5 + 0.5 * d))


def test_cube_map_faces_and_seamless():
    cube = _direction_cube(16)
    centres = jnp.asarray(np.concatenate([np.eye(3), -np.eye(3)])[[0, 3, 1, 4, 2, 5]])
    np.testing.assert_allclose(sample_cube(cube, centres), 0.5 + 0.5 * centres, atol=0.01)
    # everywhere, edges and corners included, the lookup tracks the smooth function 0.5 + 0.5 d
    d = np.random.default_rng(0).normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    edge = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0], [0.0, -1.0, 1.0], [-1.0, 0.0, -1.0]])
    d = np.concatenate([d, edge / np.linalg.norm(edge, axis=-1, keepdims=True)])
    err = np.abs(np.asarray(sample_cube(cube, jnp.asarray(d))) - (0.5 + 0.5 * d))
    assert err.max() < 0.06  # ~ one texel of a 16-texel face


def test_cube_map_continuous_across_edges():
    rng = np.random.default_rng(1)
    cube = T.make_cube_map(jnp.asarray(rng.uniform(size=(6, 8, 8, 3))))
    # a great circle crossing +z -> +x -> -z -> -x, in tiny steps: no jumps at the face edges
    a = np.linspace(0, 2 * np.pi, 20001)
    d = np.stack([np.sin(a), 0.3 * np.ones_like(a), np.cos(a)], -1)
    vals = np.asarray(sample_cube(cube, jnp.asarray(d)))
    assert np.abs(np.diff(vals, axis=0)).max() < 0.02


def test_cube_map_poles_and_zero_direction_row24():
    cube = _direction_cube(8)
    for d in ([0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0]):
        d = jnp.asarray(d)
        val = sample_cube(cube, d)
        g = jax.jacrev(lambda x: sample_cube(cube, x).sum())(d)
        assert jnp.all(jnp.isfinite(val)) and jnp.all(jnp.isfinite(g))
    # the zero direction looks up +y (safe normalize fallback)
    np.testing.assert_allclose(
        sample_cube(cube, jnp.zeros(3)), sample_cube(cube, jnp.array([0.0, 1, 0]))
    )
    tex = jnp.asarray(np.random.default_rng(2).uniform(size=(8, 16, 3)))
    for d in ([0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0]):
        d = jnp.asarray(d)
        g = jax.jacrev(lambda x: sample_latlong(tex, x).sum())(d)
        assert jnp.all(jnp.isfinite(sample_latlong(tex, d))) and jnp.all(jnp.isfinite(g))


def test_latlong_known_directions():
    tex = jnp.asarray(np.random.default_rng(3).uniform(size=(8, 16, 1)))
    # -z is the centre column (u = 0.5); the equator is v = 0.5
    v = sample_latlong(tex, jnp.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(v, sample_2d(tex, jnp.array([0.5, 0.5]), wrap=("repeat", "clamp")))


def test_cube_map_validation():
    with pytest.raises(ValueError, match="shape"):
        T.make_cube_map(jnp.zeros((5, 4, 4, 3)))
    faces = np.zeros((6, 4, 4, 3))
    faces[2, 1, 1, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        T.make_cube_map(faces)


@pytest.mark.slow  # 7 s; moved out of the default suite (10-minute budget)
def test_procedural_textures():
    h = T.weave_height(32, 4)
    assert h.shape == (32, 32, 1) and float(h.min()) == 0.0 and float(h.max()) == 1.0
    slopes = T.height_slopes(h)
    assert float(jnp.abs(slopes).max()) > 0.05  # it has relief
    c = T.checker(8, 2, (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    np.testing.assert_allclose(c[0, 0], [1, 0, 0, 1])
    np.testing.assert_allclose(c[0, 4], [0, 0, 1, 1])
    n1 = T.value_noise(jax.random.PRNGKey(0), 16)
    n2 = T.value_noise(jax.random.PRNGKey(0), 16)
    assert n1.shape == (16, 16, 1) and bool(jnp.all((n1 >= 0) & (n1 <= 1)))
    np.testing.assert_array_equal(n1, n2)
    assert float(jnp.std(n1)) > 0.01
    sky = T.sky_cube_map(8)
    up, down = sample_cube(sky, jnp.array([0.0, 1, 0])), sample_cube(sky, jnp.array([0.0, -1, 0]))
    assert float(up[2]) > float(up[0])  # blue zenith
    assert float(down.sum()) < float(up.sum())  # darker ground
    np.testing.assert_allclose(T.minnaert_table(1.0, 8), 1.0)
    tab = T.minnaert_table(0.5, 8)
    assert float(tab[0, 0, 0]) > float(tab[-1, -1, 0])  # velvet: brighter at grazing angles


def test_load_texture_png_and_nan_row25(tmp_path):
    img = (np.arange(48).reshape(4, 4, 3) * 5).astype(np.uint8)
    iio.imwrite(tmp_path / "a.png", img)
    tex = T.load_texture(tmp_path / "a.png")
    np.testing.assert_allclose(tex, img / 255.0)
    grey = np.full((4, 4), 65535, np.uint16)
    iio.imwrite(tmp_path / "g.png", grey)
    assert T.load_texture(tmp_path / "g.png").shape == (4, 4, 1)
    bad = np.ones((4, 4), np.float32)
    bad[1, 2] = np.nan
    iio.imwrite(tmp_path / "bad.tiff", bad, plugin="pillow")
    with pytest.raises(ValueError, match="NaN"):
        T.load_texture(tmp_path / "bad.tiff", plugin="pillow")
    np.save(tmp_path / "bad.npy", bad)
    with pytest.raises(ValueError, match="NaN"):
        T.load_texture(tmp_path / "bad.npy")
    with pytest.raises(ValueError, match="finite"):
        T.make_textures(height=bad[..., None])
    with pytest.raises(ValueError, match="6 face"):
        T.load_cube_map([tmp_path / "a.png"] * 5)
    cube = T.load_cube_map([tmp_path / "a.png"] * 6)
    assert cube.faces.shape == (6, 6, 6, 3)


def test_make_textures_shapes_and_zero_height():
    t = T.make_textures(color=np.ones((8, 8, 3)), height=np.zeros((8, 8)), tiling=(2, 3))
    assert t.color[0].shape == (8, 8, 4) and len(t.color) == 4
    np.testing.assert_array_equal(t.bump[0], 0.0)  # zero height -> flat (row 25, graceful)
    with pytest.raises(ValueError, match="tiling"):
        T.make_textures(tiling=(0, 1))
    with pytest.raises(ValueError, match="color texture"):
        T.make_textures(color=np.ones((8, 8)))
    d = T.default_textures(size=16, threads=4)
    assert d.env is not None and d.bump is not None and d.color[0].shape == (16, 16, 4)
