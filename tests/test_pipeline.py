"""End to end: the whole pipeline's gradient against finite differences, a small fit, bad input."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffcloth as dc
from diffcloth import config as cfg
from diffcloth import pipeline, scene
from diffcloth.physics.material import MATERIAL_FIELDS

SMALL = {
    "net": {"rows": 8, "cols": 8, "width": 0.8, "height": 0.8, "center": [0.0, 0.75, 0.0]},
    "material": {
        "stretch": 30.0,
        "shear": 10.0,
        "bend": 1e-3,
        "damping": 1e-4,
        "density": 0.3,
        "drag_normal": 0.8,
        "drag_tangent": 0.2,
        "friction": 0.4,
    },
    "sim": {"dt": 1.0 / 30.0, "num_frames": 10, "num_substeps": 12, "wind": [1.0, 0.0, 0.5]},
    "spheres": [{"center": [0.05, 0.4, 0.0], "radius": 0.25}],
    "render": {"width": 64, "height": 64, "level": 2, "frame_stride": 2},
    "camera": {"eye": [0.0, 1.2, 1.6], "target": [0.0, 0.45, 0.0]},
}


TRACES = []


def _counted_render(sc):
    TRACES.append(1)  # runs once per trace, not per call
    return pipeline.simulate_and_render(sc)


RENDER = jax.jit(_counted_render)


@pytest.fixture(scope="module")
def small_scene():
    return scene.build_scene(cfg.parse_config(SMALL), dtype=jnp.float64)


@pytest.fixture(scope="module")
def video_loss_and_grad():
    def loss(params, sc, target):
        return jnp.mean((pipeline.simulate_and_render(sc, params) - target) ** 2)

    # one compiled program for both: the finite differences read its value (saves a compile)
    return jax.jit(jax.value_and_grad(loss))


def test_video_shape_and_range(small_scene):
    video = RENDER(small_scene)
    assert video.shape == small_scene.video_shape == (1, 5, 64, 64, 3)
    assert video.dtype == jnp.float64
    assert np.all(np.isfinite(video))
    # the cloth is in view and moves: frames differ
    assert float(jnp.abs(video[0, -1] - video[0, 0]).mean()) > 1e-3


@pytest.mark.slow  # 45-70 s, nearly all compile (10-minute budget); CI's slow stage runs it
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_whole_pipeline_gradient_matches_finite_differences(small_scene, video_loss_and_grad):
    """d(video loss)/d(each material parameter), AD vs central FD in float64 (log-space steps)."""
    value_and_grad = video_loss_and_grad
    target = jnp.zeros(small_scene.video_shape, jnp.float64) + 0.2
    params = {n: small_scene.material.__dict__[n] for n in MATERIAL_FIELDS}
    _, g = value_and_grad(params, small_scene, target)

    def loss(p):
        return float(value_and_grad(p, small_scene, target)[0])

    for name in MATERIAL_FIELDS:
        v = float(params[name])
        h = 1e-5 * v  # small: a larger step crosses contact events (onset of sphere contact)
        up = dict(params, **{name: jnp.float64(v + h)})
        dn = dict(params, **{name: jnp.float64(v - h)})
        fd = (loss(up) - loss(dn)) / (2 * h)
        ad = float(g[name])
        assert np.isfinite(ad), name
        scale = max(abs(fd), abs(ad))
        assert scale > 0, f"{name}: zero gradient"
        assert abs(ad - fd) <= 0.05 * scale + 1e-9, f"{name}: AD {ad:.6g} vs FD {fd:.6g}"


@pytest.mark.slow  # ~35 s, mostly compiling the fit's step (CI runs it: .ci/run runs -m slow too)
def test_small_fit_recovers_bending_stiffness(small_scene):
    truth = {"bend": 2e-3}
    targets = dc.fit.make_targets(small_scene, truth)
    result = dc.fit.fit(
        small_scene,
        targets,
        ["bend"],
        steps=40,
        init={"bend": 5e-3},
        method="lm",
        learning_rate=0.15,
        patience=None,
        progress=False,
        loss_tol=1e-12,
    )
    assert result.ok
    rel = abs(float(result.params["bend"]) - 2e-3) / 2e-3
    assert rel < 0.02, f"bend fitted {float(result.params['bend']):.5g}, relative error {rel:.3%}"


def test_bad_input_is_rejected_before_compilation(small_scene):
    good = np.zeros(small_scene.video_shape)
    with pytest.raises(ValueError, match="targets"):
        dc.fit.fit(small_scene, good[:, :3], ["bend"], steps=1, progress=False)
    with pytest.raises(ValueError, match="targets"):
        dc.fit.fit(small_scene, np.zeros((1, 5, 32, 32, 3)), ["bend"], steps=1, progress=False)
    with pytest.raises(ValueError, match="unknown parameter.*stifness"):
        dc.fit.fit(small_scene, good, ["stifness"], steps=1, progress=False)
    bad = good.copy()
    bad[0, 0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN|non-finite|finite"):
        dc.fit.fit(small_scene, bad, ["bend"], steps=1, progress=False)


def test_truth_out_of_range_is_a_config_error(tmp_path):
    from diffcloth.experiment import parse_fit

    with pytest.raises(cfg.ConfigError, match=r"\[truth\] stretch = -1.0 is out of range"):
        parse_fit({"fit": {"free": ["stretch"]}, "truth": {"stretch": -1.0}})
    with pytest.raises(cfg.ConfigError, match="unknown parameter"):
        parse_fit({"fit": {"free": ["strech"]}, "truth": {"stretch": 1.0}})
    with pytest.raises(cfg.ConfigError, match=r"\[fit\] unknown key 'stepz'"):
        parse_fit({"fit": {"free": ["stretch"], "stepz": 3}, "truth": {"stretch": 1.0}})


def test_apply_params_keeps_dtype_and_rejects_unknown(small_scene):
    s = pipeline.apply_params(small_scene, {"stretch": 3.0, "diffuse": [0.1, 0.2, 0.3]})
    assert s.material.stretch.dtype == small_scene.material.stretch.dtype
    np.testing.assert_allclose(s.appearance.diffuse, [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="unknown parameter"):
        pipeline.apply_params(small_scene, {"nope": 1.0})
    assert dataclasses.replace(small_scene) == small_scene


def test_same_config_is_bitwise_deterministic_and_not_retraced(small_scene):
    """A fresh but equal scene reuses the compiled program; results are bitwise equal (CPU)."""
    first = np.asarray(RENDER(small_scene))
    fresh = scene.build_scene(cfg.parse_config(SMALL), dtype=jnp.float64)
    second = np.asarray(RENDER(fresh))
    np.testing.assert_array_equal(first, second)
    assert len(TRACES) == 1, f"traced {len(TRACES)} times"


def test_diagnose_names_the_stage_that_broke(small_scene):
    msg = pipeline.diagnose(small_scene, {"bend": float("nan")})
    assert msg.startswith("parameters: bend")
    # far too stiff for the explicit step: the physics blows up, diagnose says where
    msg = pipeline.diagnose(small_scene, {"stretch": 1e9})
    assert msg.startswith("physics: non-finite or blown-up cloth or body state from frame "), msg
    assert "num_substeps" in msg
