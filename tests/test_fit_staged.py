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
