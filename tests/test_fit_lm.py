"""The Levenberg-Marquardt engine, coarse-to-fine schedules, ties and FitSettings."""

import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.fit import identifiability
from diffcloth.fit.identifiability import identifiability_from_jacobian
from diffcloth.fit.lm import fit_lm, fit_lm_multistart, lm_jacobian
from diffcloth.fit.scene_fit import choose_method, video_loss
from diffcloth.fit.schedule import (
    Schedule,
    Stage,
    make_schedule,
    num_pyramid_levels,
    stage_weights,
    video_residuals,
)
from diffcloth.fit.settings import FitSettings, resolve_settings
from diffcloth.fit.ties import parse_tie, parse_ties

RNG = np.random.default_rng(0)
A = RNG.normal(size=(40, 3))
B = RNG.normal(size=40)


def _linear(p, a, b):
    return a @ jnp.stack([p["x"], p["y"], p["z"]]) - b


def test_lm_linear_least_squares_is_exact():
    exact = np.linalg.lstsq(A, B, rcond=None)[0]
    res = fit_lm(
        _linear,
        {"x": 0.0, "y": 0.0, "z": 0.0},
        loss_args=(jnp.asarray(A), jnp.asarray(B)),
        progress=False,
    )
    got = np.array([float(res.params[k]) for k in "xyz"])
    print(
        f"linear LSQ: {res.evaluations} evaluations, status {res.status}, error "
        f"{np.max(np.abs(got - exact)):.2e}"
    )
    assert res.method == "lm"
    assert res.status == "converged", res.message
    np.testing.assert_allclose(got, exact, rtol=0, atol=1e-9)
    assert res.loss == pytest.approx(float(np.sum((A @ exact - B) ** 2)), rel=1e-10)
    assert res.evaluations <= 8  # one Gauss-Newton step solves a linear problem


def _decay(p, t, y):
    return p["a"] * jnp.exp(-p["k"] * t) + p["c"] - y


def test_lm_nonlinear_exponential_decay_positive_constraints():
    t = jnp.linspace(0.0, 4.0, 30)
    y = 2.5 * jnp.exp(-1.3 * t) + 0.4
    res = fit_lm(
        _decay,
        {"a": 1.0, "k": 0.3, "c": 1.0},
        {"a": "positive", "k": "positive", "c": "positive"},
        loss_args=(t, y),
        progress=False,
        steps=100,
    )
    assert res.status == "converged", res.message
    for name, true in (("a", 2.5), ("k", 1.3), ("c", 0.4)):
        assert float(res.params[name]) == pytest.approx(true, rel=1e-6)
    # the history is monotone (LM only accepts decreasing steps) and starts at the initial value
    assert res.history.loss[0] > res.history.loss[-1]
    assert np.all(np.diff(res.history.loss) <= 1e-15)
    assert float(res.history.params["a"][0]) == pytest.approx(1.0)


def _rosen(p):
    return jnp.stack([10.0 * (p["y"] - p["x"] ** 2), 1.0 - p["x"]])


def test_lm_multistart_keeps_independent_starts_and_picks_the_best():
    inits = [{"x": -1.2, "y": 1.0}, {"x": 2.0, "y": -1.0}, {"x": 0.5, "y": 0.5}]
    multi = fit_lm_multistart(_rosen, inits, progress=False, steps=200)
    assert len(multi.results) == 3
    for r in multi.results:
        assert r.status == "converged", r.message
        assert float(r.params["x"]) == pytest.approx(1.0, abs=1e-5)
    assert multi.best.loss == min(multi.losses)


def _nan_after(p, limit):
    return jnp.where(p["x"] > limit, jnp.nan, p["x"] - 3.0)[None]


def test_lm_nonfinite_start_and_hook_interrupt():
    bad = fit_lm(_nan_after, {"x": 1.0}, loss_args=(0.5,), progress=False)
    assert bad.status == "nonfinite"
    assert float(bad.params["x"]) == pytest.approx(1.0)  # never moved to a NaN point

    seen = []

    def hook(step, info):
        seen.append((step, info["status"], info["method"]))
        if step == 2:
            raise KeyboardInterrupt

    res = fit_lm(_rosen, {"x": -1.2, "y": 1.0}, progress=False, hook=hook)
    assert res.status == "interrupted"
    assert [s for s, _, _ in seen] == [1, 2]
    assert np.isfinite(res.loss) and res.loss <= res.history.loss[0]


def test_lm_callback_stops():
    res = fit_lm(_rosen, {"x": -1.2, "y": 1.0}, progress=False, callback=lambda k, i: k >= 3)
    assert res.status == "stopped"
    assert res.iterations == 3 and len(res.history) == 4  # the start point and three steps
    assert res.evaluations == 4  # the probe at the start (initial damping) and three steps
    assert res.stages[0]["status"] == "stopped"


def test_lm_stages_warm_start():
    """Two stages with different weights: the second starts at the first's result."""
    t = jnp.linspace(0.0, 4.0, 30)
    y = 2.5 * jnp.exp(-1.3 * t) + 0.4

    def weighted(p, t, y, w):
        return w * _decay(p, t, y)

    w1 = jnp.where(t < 1.0, 1.0, 0.0)
    w2 = jnp.ones_like(t)
    res = fit_lm(
        weighted,
        {"a": 1.0, "k": 0.3, "c": 1.0},
        {"a": "positive", "k": "positive", "c": "positive"},
        loss_args=(t, y),
        stages=[(w1,), (w2,)],
        stage_names=["early", "all"],
        progress=False,
        steps=100,
    )
    assert [s["name"] for s in res.stages] == ["early", "all"]
    assert res.status == "converged"
    assert float(res.params["k"]) == pytest.approx(1.3, rel=1e-6)


def test_lm_jacobian_and_identifiability_from_it():
    p = {"x": 0.3, "y": -0.2, "z": 0.5}
    r, jac = lm_jacobian(_linear, p, loss_args=(jnp.asarray(A), jnp.asarray(B)))
    np.testing.assert_allclose(jac, A, atol=1e-12)  # raw == physical (no constraint)
    np.testing.assert_allclose(r, A @ np.array([0.3, -0.2, 0.5]) - B, atol=1e-12)
    a = identifiability(lambda q: _linear(q, jnp.asarray(A), jnp.asarray(B)), p, noise_sigma=0.1)
    b = identifiability_from_jacobian(jac, p, noise_sigma=0.1)
    np.testing.assert_allclose(a.std, b.std, rtol=1e-10)
    np.testing.assert_allclose(a.correlation, b.correlation, atol=1e-12)


def test_video_residuals_equal_the_video_losses():
    video = jnp.asarray(RNG.uniform(size=(2, 3, 16, 16, 3)))
    target = jnp.asarray(RNG.uniform(size=(2, 3, 16, 16, 3)))
    levels = num_pyramid_levels((16, 16), 4)
    from diffcloth.fit.losses import gaussian_pyramid

    assert levels == len(gaussian_pyramid(video, 4)) == 4  # 16, 8, 4, 2
    for loss in ("l2", "pyramid"):
        lw, fw = stage_weights(loss, levels, 3, None, np.float64)
        r = video_residuals(video, target, lw, fw, levels)
        ref = video_loss(video, target, loss) if loss == "l2" else _pyr(video, target, levels)
        assert float(jnp.sum(r**2)) == pytest.approx(float(ref), rel=1e-12)
    lw, fw = stage_weights("pyramid", levels, 3, Stage(min_level=1, frames=0.5), np.float64)
    np.testing.assert_allclose(lw, [0.0, 1 / 3, 1 / 3, 1 / 3])
    np.testing.assert_allclose(fw, [0.5, 0.5, 0.0])  # ceil(0.5 * 3) = 2 frames


def _pyr(video, target, levels):
    from diffcloth.fit.losses import pyramid_loss

    flat_v = video.reshape((-1,) + video.shape[-3:])
    flat_t = target.reshape((-1,) + target.shape[-3:])
    return jnp.mean(pyramid_loss(flat_v, flat_t, num_levels=levels))


def test_schedule_specs():
    assert make_schedule("none") == Schedule(stages=())
    s = make_schedule([{"min_level": 2, "frames": 0.5}, {"frames": 1.0}])
    assert s.stages == (Stage(2, 0.5), Stage(0, 1.0))
    with pytest.raises(ValueError, match="frames"):
        Stage(0, 1.5)
    with pytest.raises(ValueError, match="keys"):
        make_schedule([{"level": 2}])


def test_ties_parse_safely():
    assert parse_tie("shear", "stretch").scale == 1.0
    assert parse_tie("bend", "1e-4 * stretch").scale == pytest.approx(1e-4)
    assert parse_tie("bend", "stretch * 2.5").scale == pytest.approx(2.5)
    assert parse_tie("bend", "stretch / 4").scale == pytest.approx(0.25)
    assert parse_tie("bend", {"of": "stretch", "scale": 3e-5}).scale == pytest.approx(3e-5)
    for bad in ("__import__('os').system('true')", "stretch + 1", "2 ** stretch", "stretch / 0"):
        with pytest.raises(ValueError, match="ties.bend"):
            parse_tie("bend", bad)
    ties = parse_ties({"shear": "stretch", "bend": "1e-4 * stretch"}, ["stretch", "shear"])
    out = ties.expand({"stretch": 40.0})
    assert out == {"stretch": 40.0, "shear": 40.0, "bend": pytest.approx(4e-3)}
    with pytest.raises(ValueError, match="must be free"):
        parse_ties({"shear": "stretch"}, ["bend"])
    with pytest.raises(ValueError, match="unknown parameter"):
        parse_ties({"shear": "strech"})
    with pytest.raises(ValueError, match="also the source"):
        parse_ties({"shear": "stretch", "bend": "shear"})


def test_fit_settings_and_method_choice():
    s = resolve_settings(FitSettings(steps=10), {"lm_patience": 3})
    assert (s.steps, s.lm_patience, s.method) == (10, 3, "auto")
    with pytest.raises(TypeError, match="unknown fit option"):
        resolve_settings(None, {"stepz": 3})
    with pytest.raises(ValueError, match="method"):
        FitSettings(method="newton")
    assert choose_method("auto", "pyramid", 2) == "lm"
    assert choose_method("auto", "l1", 2) == "adam"
    assert choose_method("auto", "l2", 17) == "adam"
    assert choose_method("auto", "l2", 2, optimizer=object()) == "adam"
    with pytest.raises(ValueError, match="least-squares"):
        choose_method("lm", "l1", 2)


TINY = {
    "net": {
        "rows": 6,
        "cols": 6,
        "width": 0.8,
        "height": 0.8,
        "center": [0.0, 0.75, 0.0],
        "plane": "xz",
    },
    "material": {
        "stretch": 30.0,
        "shear": 10.0,
        "bend": 1e-3,
        "damping": 1e-4,
        "density": 0.3,
        "drag_normal": 0.6,
        "friction": 0.3,
    },
    "sim": {"dt": 1.0 / 30.0, "num_frames": 8, "num_substeps": 10},
    "spheres": [{"center": [0.05, 0.35, 0.0], "radius": 0.25}],
    "render": {"width": 24, "height": 24, "level": 2, "frame_stride": 2},
    "camera": {"eye": [0.0, 1.2, 1.6], "target": [0.0, 0.45, 0.0]},
}
TRUTH = {"bend": 2e-3, "drag_normal": 1.0}


def _first_within(history, truth, rel):
    """Index of the first history entry with every parameter within `rel` of the truth."""
    ok = np.ones(len(history), bool)
    for k, v in truth.items():
        ok &= np.abs(history.params[k] - v) <= rel * abs(v)
    hits = np.flatnonzero(ok)
    return int(hits[0]) if hits.size else None


@pytest.mark.slow  # two compiled fits of a tiny scene (~1-2 min on a loaded 2-core machine)
def test_scene_fit_lm_needs_fewer_evaluations_than_adam():
    import diffcloth as dc
    from diffcloth import config as cfg
    from diffcloth import scene

    sc = scene.build_scene(cfg.parse_config(TINY), dtype=jnp.float64)
    targets = dc.fit.make_targets(sc, TRUTH)
    init = {"bend": 1e-3, "drag_normal": 0.6}
    lm = dc.fit.fit(
        sc, targets, ["bend", "drag_normal"], steps=30, init=init, loss="pyramid", method="lm",
        progress=False,
    )  # fmt: skip
    adam = dc.fit.fit(
        sc,
        targets,
        ["bend", "drag_normal"],
        steps=150,
        init=init,
        loss="pyramid",
        method="adam",
        learning_rate=0.1,
        patience=None,
        progress=False,
    )
    assert (lm.method, adam.method) == ("lm", "adam")
    for k, v in TRUTH.items():
        assert abs(float(lm.params[k]) - v) <= 0.01 * v, (k, lm.params[k], lm.message)
    n_lm = _first_within(lm.history, TRUTH, 0.01)
    n_adam = _first_within(adam.history, TRUTH, 0.01)
    # evaluations: LM = its probe per stage + steps up to that entry (each a residual + J pass);
    # Adam = value_and_grad calls up to that entry
    stages_before = sum(1 for _ in lm.stages)  # upper bound on probes spent
    lm_evals = n_lm + stages_before
    adam_evals = np.inf if n_adam is None else n_adam + 1
    print(
        f"\n2-parameter scene fit to 1 %: LM {lm_evals} evaluations (residual + forward-mode "
        f"Jacobian), Adam {adam_evals} evaluations (loss + gradient); LM total "
        f"{lm.evaluations}, status {lm.status}"
    )
    assert lm_evals < adam_evals


@pytest.mark.slow  # one compiled LM fit of a tiny scene
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_scene_fit_with_ties():
    import diffcloth as dc
    from diffcloth import config as cfg
    from diffcloth import scene

    sc = scene.build_scene(cfg.parse_config(TINY), dtype=jnp.float64)
    targets = dc.fit.make_targets(sc, {"stretch": 40.0, "shear": 40.0, "bend": 4e-3})
    res = dc.fit.fit(
        sc,
        targets,
        ["stretch", "shear", "bend"],
        steps=30,
        init={"stretch": 25.0},
        loss="pyramid",
        method="lm",
        progress=False,
        ties={"shear": "stretch", "bend": "1e-4 * stretch"},
    )
    assert set(res.params) == {"stretch", "shear", "bend"}
    assert float(res.params["shear"]) == pytest.approx(float(res.params["stretch"]))
    assert float(res.params["bend"]) == pytest.approx(1e-4 * float(res.params["stretch"]))
    assert float(res.params["stretch"]) == pytest.approx(40.0, rel=0.01), res.message
    assert res.history.params["shear"].shape == res.history.params["stretch"].shape


def test_fit_config_keys_method_ties_stages():
    from diffcloth.config import ConfigError
    from diffcloth.config.fit import parse_fit

    base = {"free": ["stretch", "shear", "bend"]}
    truth = {"stretch": 40.0}
    fs = parse_fit(
        {
            "fit": {
                **base,
                "method": "lm",
                "ties": {"shear": "stretch"},
                "stages": [{"min_level": 2, "frames": 0.5}],
                "lm_stage_steps": 9,
            },
            "truth": truth,
        }
    )
    eng = fs.engine(progress=False)
    assert (eng.method, eng.lm_stage_steps, eng.ties, eng.progress) == (
        "lm",
        9,
        {"shear": "stretch"},
        False,
    )
    assert eng.stages == [{"min_level": 2, "frames": 0.5}]
    for bad, match in (
        ({"method": "newton"}, "method"),
        ({"ties": {"shear": "stretch + 1"}}, "ties.shear"),
        ({"ties": {"shear": "density"}}, "must be free"),
        ({"stages": [{"min_level": 2, "frames": 2.0}]}, "stages"),
        ({"lm_stage_steps": 0}, "lm_stage_steps"),
    ):
        with pytest.raises(ConfigError, match=match):
            parse_fit({"fit": {**base, **bad}, "truth": truth})


def test_lm_far_start_survives_a_run_of_rejected_steps():
    # one positive parameter 5x off: the first Gauss-Newton steps in log space overshoot and are
    # rejected until the trust region has shrunk; that must not end the fit as "stalled"
    t = jnp.linspace(0.0, 4.0, 30)
    seen = []
    res = fit_lm(
        lambda p, t: (p["a"] - 1.0) * t,
        {"a": 0.2},
        {"a": "positive"},
        loss_args=(t,),
        progress=False,
        steps=40,
        hook=lambda k, info: seen.append(info["loss"]),
    )
    assert res.status == "converged", res.message
    assert float(res.params["a"]) == pytest.approx(1.0, rel=1e-5)
    assert seen[1] == seen[0]  # the first step was indeed rejected
