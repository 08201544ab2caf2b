"""Footage losses (robust residuals, silhouette losses) and capture nuisance parameters:
values, residual forms and gradients against central finite differences in float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import pipeline, scene
from diffcloth.fit import footage, masks, robust
from diffcloth.fit.scene_fit import default_constraint

jax.config.update("jax_enable_x64", True)


def _fd(f, x, eps):
    """Central finite differences of scalar f at array x (float64), same shape as x."""
    x = np.asarray(x, np.float64)
    g = np.zeros_like(x)
    for i in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[i] = eps
        g[i] = (float(f(x + e)) - float(f(x - e))) / (2 * eps)
    return g


# ----------------------------------------------------------------------------- robust


@pytest.mark.parametrize("kind", robust.ROBUST_KINDS)
def test_robust_residuals_square_to_rho_and_match_closed_forms(kind):
    s = 0.1
    r = jnp.array([-3.0, -0.2, -0.1, -1e-5, 0.0, 1e-9, 0.05, 0.1, 0.3, 2.0])
    psi = robust.robust_residuals(r, kind, s)
    rho = robust.robust_rho(r, kind, s)
    np.testing.assert_allclose(psi**2, rho, rtol=1e-12, atol=1e-30)
    a = np.abs(np.asarray(r))
    closed = {
        "l2": a**2,
        "huber": np.where(a <= s, a**2, 2 * s * a - s**2),
        # 2 s^2 (sqrt(1 + u^2) - 1), written without the cancellation at small u
        "charbonnier": 2 * a**2 / (np.sqrt(1 + (a / s) ** 2) + 1),
        "cauchy": s**2 * np.log1p((a / s) ** 2),
    }[kind]
    np.testing.assert_allclose(rho, closed, rtol=1e-9, atol=1e-30)
    assert np.all(np.sign(psi) == np.sign(r))  # psi keeps the residual's sign
    if kind != "l2":
        assert float(rho[0]) < 0.2 * float(r[0] ** 2)  # outliers count far less than in l2


@pytest.mark.parametrize("kind", robust.ROBUST_KINDS)
def test_robust_residual_gradients_match_fd_and_are_one_at_zero(kind):
    g = jax.vmap(jax.grad(lambda x: robust.robust_residuals(x, kind, 0.1)))
    pts = np.array([-0.7, -0.1 - 1e-3, -0.03, 0.02, 0.1 + 1e-3, 0.4, 1.5])
    fd = np.array([_fd(lambda x: robust.robust_residuals(x, kind, 0.1), p, 1e-6) for p in pts])
    np.testing.assert_allclose(g(jnp.asarray(pts)), fd, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(g(jnp.zeros(3)), 1.0)  # smooth at 0: no sqrt kink, no NaN


def test_robust_rejects_bad_kind_and_scale():
    with pytest.raises(ValueError, match="robust kind"):
        robust.robust_residuals(jnp.ones(2), "tukey", 0.1)
    with pytest.raises(ValueError, match="scale"):
        robust.robust_residuals(jnp.ones(2), "huber", 0.0)


# ----------------------------------------------------------------------------- masks


def test_soft_iou_equals_hard_iou_on_binary_masks():
    rng = np.random.default_rng(0)
    a = rng.random((5, 12, 10)) > 0.5
    b = rng.random((5, 12, 10)) > 0.3
    hard = (a & b).sum(axis=(1, 2)) / (a | b).sum(axis=(1, 2))
    np.testing.assert_allclose(masks.soft_iou(a.astype(float), b.astype(float)), hard)
    np.testing.assert_allclose(masks.soft_iou(a * 1.0, a * 1.0), 1.0)
    assert float(masks.soft_iou(np.zeros((4, 4)), np.zeros((4, 4)))) == 1.0  # both empty


def _soft_masks(rng, shape=(2, 7, 6)):
    return jnp.asarray(rng.random(shape)), jnp.asarray((rng.random(shape) > 0.5) * 1.0)


def test_iou_loss_and_residual_gradients_match_fd():
    rng = np.random.default_rng(1)
    p, t = _soft_masks(rng)
    loss = jax.jit(lambda p: jnp.sum(masks.iou_loss(p, t)))
    res = masks.iou_residuals(p, t)
    assert res.shape == (2, 1)
    np.testing.assert_allclose(jnp.sum(res**2, axis=-1), masks.iou_loss(p, t), rtol=1e-12)
    np.testing.assert_allclose(jax.grad(loss)(p), _fd(loss, p, 1e-6), rtol=1e-6, atol=1e-10)
    rsum = jax.jit(lambda p: jnp.sum(masks.iou_residuals(p, t)))
    np.testing.assert_allclose(jax.grad(rsum)(p), _fd(rsum, p, 1e-6), rtol=1e-6, atol=1e-10)
    # a perfect match: zero loss, a finite (zero) Jacobian for least squares
    jac = jax.jacfwd(lambda q: masks.iou_residuals(q, t))(t)
    assert float(jnp.sum(masks.iou_loss(t, t))) == 0.0 and np.all(np.isfinite(jac))


def test_distance_transform_loss_values_residuals_and_gradients():
    t = np.zeros((1, 9, 9))
    t[0, 3:6, 3:6] = 1.0
    d_out, d_in = masks.target_distances(t)
    assert d_out[0, 4, 0] == 3.0 and d_out[0, 4, 4] == 0.0  # 3 px left of the square
    assert d_in[0, 4, 4] == 2.0 and d_in[0, 0, 0] == 0.0  # centre: 2 px to the outside
    assert float(masks.distance_transform_loss(t, d_out, d_in)[0]) == 0.0
    far, near = np.zeros_like(t), np.zeros_like(t)
    far[0, 4, 0] = near[0, 4, 2] = 1.0  # one stray pixel 3 px / 1 px from the target
    lf = masks.distance_transform_loss(t + far, d_out, d_in)
    ln = masks.distance_transform_loss(t + near, d_out, d_in)
    np.testing.assert_allclose([lf[0], ln[0]], [3.0 / 81, 1.0 / 81])
    rng = np.random.default_rng(2)
    p = jnp.asarray(rng.random(t.shape))
    r = masks.distance_transform_residuals(p, d_out, d_in)
    np.testing.assert_allclose(jnp.sum(r**2, -1), masks.distance_transform_loss(p, d_out, d_in))
    loss = jax.jit(lambda p: jnp.sum(masks.distance_transform_loss(p, d_out, d_in)))
    np.testing.assert_allclose(jax.grad(loss)(p), _fd(loss, p, 1e-6), rtol=1e-6, atol=1e-10)


@pytest.mark.parametrize("kind", masks.MASK_LOSSES)
def test_mask_loss_residual_forms_agree(kind):
    p, t = _soft_masks(np.random.default_rng(3))
    r = masks.mask_residuals(p, t, kind)
    np.testing.assert_allclose(jnp.sum(r**2, axis=-1), masks.mask_loss(p, t, kind), rtol=1e-12)
    assert float(jnp.max(masks.mask_loss(t, t, kind))) == 0.0


# ----------------------------------------------------------------------------- scene level

SMALL = {
    "net": {"rows": 6, "cols": 6, "width": 0.8, "height": 0.8, "center": [0.0, 0.75, 0.0]},
    "material": {"stretch": 30.0, "shear": 10.0, "bend": 1e-3, "density": 0.3},
    "sim": {"dt": 1.0 / 30.0, "num_frames": 2, "num_substeps": 12},
    "render": {"width": 24, "height": 24, "level": 2},
    "cameras": [
        {"eye": [0.0, 2.0, 1.0], "target": [0.0, 0.5, 0.0]},
        {"eye": [1.4, 1.6, 0.3], "target": [0.0, 0.5, 0.0]},
    ],
    "lights": {
        "ambient": [0.1, 0.1, 0.1],
        "directional": [{"direction": [0.3, 1.0, 0.6], "intensity": 1.0}],
        "point": [{"position": [0.5, 1.5, 0.5], "intensity": 0.5}],
    },
}

NUISANCE = {
    "exposure": np.array([1.1, 0.9]),
    "camera_rotation": np.array([[0.01, -0.02, 0.005], [0.0, 0.01, -0.01]]),
    "camera_translation": np.array([[0.01, 0.0, -0.02], [-0.01, 0.02, 0.0]]),
    "background": np.array([[0.2, 0.3, 0.4], [0.1, 0.1, 0.1]]),
    "light_direction": np.array([[0.35, 1.0, 0.5]]),
    "light_intensity": np.array([1.2]),
    "point_light_intensity": np.array([0.6]),
    "point_light_position": np.array([[0.5, 1.4, 0.6]]),
    "ambient_light": np.array([0.12, 0.1, 0.08]),
    "diffuse": np.array([0.6, 0.3, 0.2]),  # the cloth's albedo
}


@pytest.fixture(scope="module")
def small():
    sc = scene.build_scene(cfg.parse_config(SMALL), dtype=jnp.float64)
    x = jax.jit(pipeline.simulate)(sc).x[-1]
    return sc, x


@pytest.fixture(scope="module")
def frame_fn():
    """Images and cloth masks of one frame of a scene with every nuisance parameter set (one
    compile: the params dict always has the same keys)."""

    def f(params, sc, x):
        return pipeline.render_frame(pipeline.apply_params(sc, params), x, with_mask=True)

    return jax.jit(f)


def _neutral(sc):
    return {k: np.asarray(pipeline.param_value(sc, k)) for k in NUISANCE}


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_neutral_capture_leaves_images_unchanged_and_masks_are_coverage(small, frame_fn):
    sc, x = small
    img0 = jax.jit(pipeline.render_frame)(sc, x)  # no capture at all
    img, mask = frame_fn(_neutral(sc), sc, x)
    np.testing.assert_allclose(img, img0, atol=1e-12)
    assert mask.shape == (2, 24, 24) and float(mask.min()) >= 0 and float(mask.max()) <= 1
    assert 0.05 < float(mask.mean()) < 0.95  # cloth covers part of each view
    assert 0 < float(jnp.mean((mask > 0) & (mask < 1)))  # soft (antialiased) silhouette pixels
    # where the mask is 0 the image is the background, where it is 1 it is not
    bg = np.asarray(sc.background)
    out = np.asarray(mask) == 0
    np.testing.assert_allclose(np.asarray(img)[out], np.broadcast_to(bg, (out.sum(), 3)))
    inside = np.asarray(mask) == 1
    assert np.all(np.abs(np.asarray(img)[inside] - bg).sum(-1) > 1e-3)


def test_per_camera_background_and_exposure(small, frame_fn):
    sc, x = small
    img0, mask = frame_fn(_neutral(sc), sc, x)
    bg = np.array([[0.2, 0.3, 0.4], [0.9, 0.1, 0.1]])
    p = {**_neutral(sc), "background": bg, "exposure": np.array([2.0, 0.5])}
    img, mask2 = frame_fn(p, sc, x)
    np.testing.assert_allclose(mask2, mask)
    for c, gain in enumerate((2.0, 0.5)):
        out = np.asarray(mask[c]) == 0
        want = np.broadcast_to(gain * bg[c], (out.sum(), 3))
        np.testing.assert_allclose(np.asarray(img[c])[out], want)
        inside = np.asarray(mask[c]) == 1
        np.testing.assert_allclose(np.asarray(img[c])[inside], gain * np.asarray(img0[c])[inside])
    # a small camera rotation moves the silhouette
    p = {**_neutral(sc), "camera_rotation": np.array([[0.0, 0.03, 0.0], [0.0, 0.0, 0.0]])}
    _, mask3 = frame_fn(p, sc, x)
    assert float(jnp.abs(mask3[0] - mask[0]).sum()) > 1.0
    np.testing.assert_allclose(mask3[1], mask[1])


def test_nuisance_ranges_and_constraints():
    sc = scene.build_scene(cfg.parse_config(SMALL), dtype=jnp.float64)
    with pytest.raises(ValueError, match=r"exposure .*range"):
        pipeline.apply_params(sc, {"exposure": -1.0})
    with pytest.raises(ValueError, match="camera_rotation"):
        pipeline.apply_params(sc, {"camera_rotation": np.full((2, 3), 0.5)})
    with pytest.raises(ValueError, match="background"):
        pipeline.apply_params(sc, {"background": 1.5})
    assert set(pipeline.NUISANCE_PARAMETERS) <= set(pipeline.PARAMETERS)
    assert set(pipeline.NUISANCE_RANGES) == set(pipeline.NUISANCE_PARAMETERS)
    assert pipeline.param_value(sc, "exposure").shape == (2,)
    assert pipeline.param_value(sc, "camera_rotation").shape == (2, 3)
    for name, (lo, hi) in pipeline.NUISANCE_RANGES.items():
        c = default_constraint(name)
        z = c.forward(jnp.asarray(5.0))  # raw values far out still map inside the range
        assert (lo is None or float(z) >= lo) and (hi is None or float(z) <= hi), name


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_nuisance_gradients_match_fd(small, frame_fn):
    """d/d(every nuisance parameter) of a Huber colour + IoU loss on one frame, AD vs central
    FD (the FD reads the images of `frame_fn`, so only the gradient compiles anew)."""
    sc, x = small
    target, tmask = frame_fn(NUISANCE, sc, x)
    target = np.asarray(target) + 0.05 * np.sin(np.arange(target.size)).reshape(target.shape)
    tmask = (np.asarray(tmask) > 0.5) * 1.0
    start = {
        k: v + 0.02 * np.cos(np.arange(v.size).reshape(v.shape) + 1.0) for k, v in NUISANCE.items()
    }

    def value(img, m):
        r = robust.robust_residuals(img - target, "huber", 0.05)
        return jnp.mean(r**2) + 0.5 * jnp.mean(masks.iou_loss(m, tmask))

    def loss(params):
        return value(*pipeline.render_frame(pipeline.apply_params(sc, params), x, with_mask=True))

    _, grad = jax.jit(jax.value_and_grad(loss))(start)
    for name, v in start.items():

        def one(z, name=name):
            return value(*frame_fn({**start, name: z}, sc, x))

        fd = _fd(one, v, 1e-6)
        np.testing.assert_allclose(grad[name], fd, rtol=2e-4, atol=1e-7, err_msg=name)
        assert np.any(np.abs(fd) > 1e-6), name  # each parameter does move the loss
    # the whole pipeline returns the masks too
    video, m = jax.jit(lambda s: pipeline.simulate_and_render(s, with_mask=True))(sc)
    assert video.shape == sc.video_shape and m.shape == sc.video_shape[:4]
    np.testing.assert_allclose(m[:, -1], frame_fn(_neutral(sc), sc, x)[1], atol=1e-12)


def test_footage_residuals_sum_to_loss_and_validate(small, frame_fn):
    sc, x = small
    a, ma = frame_fn(_neutral(sc), sc, x)
    b, mb = frame_fn(NUISANCE, sc, x)
    video, m = jnp.stack([a, b], axis=1), jnp.stack([ma, mb], axis=1)  # (cams, T = 2, ...)
    assert video.shape == sc.video_shape
    bump = 0.1 * (np.arange(video.size) % 7 == 0).reshape(video.shape)
    tv = np.clip(np.asarray(video) + bump, 0, 1)
    tm = (np.asarray(m) > 0.3) * 1.0
    for spec in (
        footage.FootageLoss(),
        footage.FootageLoss(color="cauchy", mask="iou", mask_weight=0.3),
        footage.FootageLoss(color="none", mask="distance"),
        footage.FootageLoss(color="huber", mask="l2"),
    ):
        prep = footage.prepare_targets(sc, tv, tm if spec.mask else None, spec)
        r = footage.footage_residuals(video, m, prep, spec)
        total = 0.0
        if spec.color != "none":
            total += float(jnp.mean(robust.robust_rho(video - prep.video, spec.color, 0.05)))
        if spec.mask is not None:
            if spec.mask == "distance":
                per = masks.distance_transform_loss(m, prep.d_out, prep.d_in)
            else:
                per = masks.mask_loss(m, prep.mask, spec.mask)
            total += spec.mask_weight * float(jnp.mean(per))
        np.testing.assert_allclose(float(jnp.sum(r**2)), total, rtol=1e-10)
    with pytest.raises(ValueError, match="mask"):
        footage.FootageLoss(mask="hausdorff")
    with pytest.raises(ValueError, match="color_scale"):
        footage.FootageLoss(color_scale=-1.0)
    with pytest.raises(ValueError, match="target_masks"):
        footage.prepare_targets(sc, tv, None, footage.FootageLoss(mask="iou"))


def test_cloth_mask_by_color():
    img = np.zeros((4, 4, 3))
    img[1:3, 1:3] = 0.3 * np.array([0.7, 0.15, 0.2])  # shaded cloth
    img[0, 0] = [0.4, 0.4, 0.4]  # grey floor
    m = footage.cloth_mask_by_color(img, (0.7, 0.15, 0.2))
    assert m.sum() == 4 and m[1, 1] == 1 and m[0, 0] == 0


def test_camera_background_and_exposure_config_keys():
    conf = {
        **SMALL,
        "cameras": [
            {**SMALL["cameras"][0], "background": [0.2, 0.3, 0.4], "exposure": 1.5},
            SMALL["cameras"][1],
        ],
    }
    sc = scene.build_scene(cfg.parse_config(conf), dtype=jnp.float64)
    np.testing.assert_allclose(sc.capture.exposure, [1.5, 1.0])
    np.testing.assert_allclose(sc.capture.background[0], [0.2, 0.3, 0.4])
    np.testing.assert_allclose(sc.capture.background[1], sc.background)
    assert scene.build_scene(cfg.parse_config(SMALL), dtype=jnp.float64).capture is None
    bad = {**SMALL, "cameras": [{**SMALL["cameras"][0], "background": [0.2, 1.3, 0.4]}]}
    with pytest.raises(cfg.ConfigError, match=r"cameras #0.*background"):
        cfg.parse_config(bad)
    bad = {**SMALL, "cameras": [{**SMALL["cameras"][0], "exposure": 0.0}]}
    with pytest.raises(cfg.ConfigError, match="exposure"):
        cfg.parse_config(bad)
