"""Staged fits (diffcloth.fit.staged): per-stage free sets, held values, the scan, ties."""

import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.fit.settings import FitSettings
from diffcloth.fit.staged import ParamStage, fit_staged
from diffcloth.fit.ties import Tie, Ties

SETTINGS = FitSettings(method="lm", steps=40, progress=False)


def _residual(p, t, w):
    # block 1 sees only a; block 2 sees a * b and c (tied to b); w weights the blocks
    r1 = (p["a"] - 2.0) * t
    r2 = (p["a"] * p["b"] - 6.0) * t + (p["c"] - 1.5) * t
    return jnp.concatenate([w[0] * r1, w[1] * r2])


T = jnp.linspace(0.5, 2.0, 8)
FIRST = (jnp.asarray([1.0, 0.0]),)
BOTH = (jnp.asarray([1.0, 1.0]),)


def test_stages_hold_the_others_scan_and_tie():
    seen = []
    stages = [
        ParamStage(("a",), stage_args=[FIRST], name="a alone"),
        ParamStage(("b",), scan={"b": [0.25, 0.5, 1.0, 2.0, 4.0]}, stage_args=[BOTH]),
        ParamStage(("a", "b"), stage_args=[BOTH]),
    ]
    out = fit_staged(
        _residual,
        {"a": 0.5, "b": 1.0},
        {"a": "positive", "b": "positive"},
        stages=stages,
        loss_args=(T,),
        ties=Ties((Tie("c", "b", 0.5),)),  # Ties: names outside PARAMETERS
        settings=SETTINGS,
        log=seen.append,
    )
    # stage 1 fits a on block 1 only and leaves b where it was
    assert out.stages[0]["params"]["a"] == pytest.approx(2.0, rel=1e-5)
    assert out.stages[0]["params"]["b"] == 1.0
    # the scan picks the best grid point of b * factor (with c = b / 2 following)
    prof = dict(out.stages[1]["scan"]["profile"])
    assert set(prof) == {0.25, 0.5, 1.0, 2.0, 4.0}
    assert out.stages[1]["scan"]["best"] == min(prof, key=prof.get) == 2.0
    # the optimum: a = 2 (block 1), then a b + c = 7.5 with c = b / 2: b = 3, c = 1.5
    assert float(out.params["a"]) == pytest.approx(2.0, rel=1e-5)
    assert float(out.params["b"]) == pytest.approx(3.0, rel=1e-5)
    assert float(out.params["c"]) == pytest.approx(1.5, rel=1e-5)
    assert out.loss < 1e-8 and out.status == "converged"
    assert [r["name"] for r in seen] == ["a alone", "stage 2", "stage 3"]


def test_stage_errors_name_the_field():
    with pytest.raises(ValueError, match="free must name"):
        ParamStage(())
    with pytest.raises(ValueError, match="not free in this stage"):
        ParamStage(("a",), scan={"b": [0.5, 2.0]})
    with pytest.raises(ValueError, match="positive"):
        ParamStage(("a",), scan={"a": [0.0, 2.0]})
    with pytest.raises(ValueError, match="not in init"):
        fit_staged(_residual, {"a": 1.0}, stages=[ParamStage(("z",))], loss_args=(T,))
    with pytest.raises(ValueError, match="at least one"):
        fit_staged(_residual, {"a": 1.0}, stages=[], loss_args=(T,))


def _product(p, t):
    return (p["a"] * p["b"] - 6.0) * t


def test_held_values_are_arguments_not_constants():
    # the same free set twice with different held values reuses one compiled step and sees them
    out1 = fit_staged(
        _product,
        {"a": 1.0, "b": 2.0},
        stages=[ParamStage(("a",))],
        loss_args=(T,),
        settings=SETTINGS,
    )
    out2 = fit_staged(
        _product,
        {"a": 1.0, "b": 3.0},
        stages=[ParamStage(("a",))],
        loss_args=(T,),
        settings=SETTINGS,
    )
    assert float(out1.params["a"]) == pytest.approx(3.0, rel=1e-5)
    assert float(out2.params["a"]) == pytest.approx(2.0, rel=1e-5)
    assert np.isfinite(out1.loss) and out1.evaluations > 0


def test_schedule_stage_free_and_scan_in_the_config():
    from diffcloth.config import ConfigError
    from diffcloth.config.fit import parse_fit
    from diffcloth.fit.schedule import make_schedule

    stages = [
        {"frames": 0.5, "free": ["drag_normal"]},
        {"min_level": 1, "free": ["bend", "drag_normal"], "scan": {"bend": [0.5, 1.0, 2.0]}},
    ]
    fs = parse_fit(
        {"fit": {"free": ["bend", "drag_normal"], "stages": stages}, "truth": {"bend": 2e-3}}
    )
    sched = make_schedule(fs.engine().stages)
    assert sched.stages[0].free == ("drag_normal",) and sched.stages[0].staged
    assert sched.stages[1].scan == ("bend", (0.5, 1.0, 2.0))
    base = {"free": ["bend", "drag_normal"]}
    for bad, match in (
        ([{"free": ["density"]}], r"stages\[0\].*density"),
        ([{"free": ["bend"], "scan": {"drag_normal": [0.5, 2.0]}}], "not in the stage"),
        ([{"scan": {"bend": [1.0]}}], "positive factors"),
        ([{"frames": 0.5, "fre": ["bend"]}], "keys"),
    ):
        with pytest.raises(ConfigError, match=match):
            parse_fit({"fit": {**base, "stages": bad}, "truth": {"bend": 2e-3}})


@pytest.mark.slow
def test_scene_fit_with_a_staged_schedule():
    # tiny drape (the scene of test_fit_lm): drag alone on the first frames, then a scan of
    # bend from 4x off, then both; the result names every stage
    import diffcloth as dc
    from diffcloth import config as cfg
    from diffcloth import scene
    from tests.test_fit_lm import TINY, TRUTH

    sc = scene.build_scene(cfg.parse_config(TINY), dtype=jnp.float64)
    targets = dc.fit.make_targets(sc, TRUTH)
    res = dc.fit.fit(
        sc,
        targets,
        ["bend", "drag_normal"],
        steps=30,
        init={"bend": 5e-4, "drag_normal": 0.5},
        progress=False,
        method="lm",
        stages=[
            {"frames": 0.5, "free": ["drag_normal"]},
            {"free": ["bend"], "scan": {"bend": [1.0, 2.0, 4.0, 8.0]}},
        ],
    )
    assert res.method == "lm" and len(res.stages) == 3
    assert "free: drag_normal" in res.stages[0]["name"]
    assert "scan bend -> 0.002" in res.stages[1]["name"]  # 4x the start is the truth
    for name, true in TRUTH.items():
        assert float(res.params[name]) == pytest.approx(true, rel=1e-3), res.message
