"""The front door `dc.fit.fit(..., method=...)`: dispatch, deprecated engine names, the "auto"
rules (x64 under contact, the far-start scan) and the stall hints. Cheap: the engines are
replaced by recorders where only the routing is checked, and the scan rule runs on an analytic
residual; one slow test fits a tiny drape end to end."""

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import diffcloth as dc
from diffcloth import config as cfg
from diffcloth.fit import auto, engines
from diffcloth.fit.constraints import Bounded, Positive
from diffcloth.fit.results import FitResult, History

MICRO = {
    "net": {"rows": 4, "cols": 4, "width": 0.6, "height": 0.6, "center": [0.0, 0.8, 0.0],
            "plane": "xz"},
    "sim": {"dt": 1.0 / 30.0, "num_frames": 3, "num_substeps": 8},
    "spheres": [{"center": [0.0, 0.2, 0.0], "radius": 0.2}],
    "render": {"width": 8, "height": 8, "level": 2},
    "camera": {"eye": [0.0, 1.0, 1.6], "target": [0.0, 0.6, 0.0]},
}  # fmt: skip


def _scene(**changes):
    data = {**MICRO, **changes}
    config = cfg.parse_config({k: v for k, v in data.items() if v is not None})
    return dc.build_scene(config, dtype=jnp.float32)  # as users get it (the tests run in x64)


def _result(params, initial, status="converged", method="lm", iterations=3):
    hist = History(
        loss=np.array([1.0, 0.5]),
        params={k: np.array([initial[k], v]) for k, v in params.items()},
        grad_norm={k: np.zeros(2) for k in params},
        wall_s=np.zeros(2),
    )
    p = {k: np.asarray(v) for k, v in params.items()}
    return FitResult(params=p, raw=p, loss=0.5, initial={k: np.asarray(v) for k, v in
                     initial.items()}, history=hist, iterations=iterations, wall_s=0.1,
                     status=status, message="", best_step=1, last_finite=p, method=method)  # fmt: skip


@pytest.fixture
def engines_recorded(monkeypatch):
    """Replace the engines the front door calls by recorders returning a converged result."""
    from diffcloth.fit import lm, loop, scene_fit

    calls = []

    def record(name):
        def engine(fn, init, cons, *args, **kwargs):
            if name == "staged_schedule":  # (res_fn, init, cons, sched, args, names, la, s)
                kwargs = {"sched": args[0], "settings": args[-1]}
            calls.append((name, dict(init), kwargs))
            start = init[0] if isinstance(init, list) else init
            return _result(dict(start), dict(start), method="adam" if "adam" in name else "lm")

        return engine

    monkeypatch.setattr(lm, "fit_lm", record("lm"))
    monkeypatch.setattr(loop, "fit_params", record("adam"))
    monkeypatch.setattr(scene_fit, "_fit_staged_schedule", record("staged_schedule"))
    return calls


def test_method_dispatch(engines_recorded):
    sc = _scene()
    video = np.zeros(sc.video_shape, np.float32)
    kw = dict(init={"stretch": 50.0}, progress=False, scan=False)
    r = dc.fit.fit(sc, video, ["stretch"], method="lm", **kw)
    assert engines_recorded[-1][0] == "lm" and r.method == "lm" and r.auto["x64"] is False
    r = dc.fit.fit(sc, video, ["stretch"], method="adam", **kw)
    assert engines_recorded[-1][0] == "adam" and r.method == "adam"
    r = dc.fit.fit(sc, video, ["stretch"], loss="l1", **kw)  # auto: not least squares -> Adam
    assert engines_recorded[-1][0] == "adam" and r.auto["engine"] == "adam"
    r = dc.fit.fit(sc, video, ["stretch"], **kw)  # auto: LM, float64 (the sphere is contact)
    name, init, kwargs = engines_recorded[-1]
    assert name == "lm" and r.auto == {"method": "auto", "engine": "lm", "x64": True}
    assert init["stretch"].dtype == np.float64
    assert kwargs["loss_args"][1].material.density.dtype == jnp.float64
    assert r.params["stretch"].dtype == np.float32  # handed back in the scene's dtype
    r = dc.fit.fit(sc, video, ["stretch", "bend"], method="staged", **kw)
    name, _, kwargs = engines_recorded[-1]
    assert name == "staged_schedule" and r.method == "staged"
    stages = kwargs["sched"].stages  # the recipe: a scan of the stiffest on the first half
    assert stages[-1].scan[0] == "stretch" and stages[-1].frames == 0.5
    s = kwargs["settings"]
    assert (s.lm_tau, s.lm_xtol, s.lm_polish) == (1.0, 1e-3, 0)  # the recipe's LM settings
    r = dc.fit.fit(sc, video, ["stretch", "bend"], method="staged", lm_tau=0.1, **kw)
    assert engines_recorded[-1][2]["settings"].lm_tau == 0.1  # a given setting wins
    with pytest.raises(ValueError, match="method 'staged' fits least-squares"):
        dc.fit.fit(sc, video, ["stretch"], method="staged", loss="l1", **kw)
    with pytest.raises(ValueError, match="method="):
        dc.fit.fit(sc, video, ["stretch"], method="newton", **kw)


def test_no_contact_no_x64(engines_recorded):
    sc = _scene(spheres=None)
    assert not auto.has_contact(sc) and auto.has_contact(_scene())
    r = dc.fit.fit(sc, np.zeros(sc.video_shape), ["stretch"], scan=False, progress=False)
    assert r.auto["x64"] is False
    r = dc.fit.fit(sc, np.zeros(sc.video_shape), ["stretch"], scan=False, x64=True,
                   progress=False)  # fmt: skip
    assert r.auto["x64"] is True


def test_deprecated_engine_names_warn_and_still_work():
    for old, new in engines.RENAMED.items():
        with pytest.warns(DeprecationWarning, match=rf"diffcloth.fit.{old} is deprecated.*"
                          rf"engines.{new}"):  # fmt: skip
            fn = getattr(dc.fit, old)
        assert fn is getattr(engines, new)
    with pytest.warns(DeprecationWarning, match="fit_lm is deprecated"):
        from diffcloth.fit import fit_lm  # noqa: F401
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from diffcloth.fit.engines import lm  # noqa: F401  (the new names do not warn)
        from diffcloth.fit.lm import fit_lm as direct  # noqa: F401  (nor the modules')
    assert "fit_lm" not in dc.fit.__all__ and "engines" in dc.fit.__all__
    with pytest.raises(AttributeError):
        dc.fit.no_such_name  # noqa: B018


def _decay(p, t, y):  # bounded residuals, as an image loss's
    return jnp.exp(-p["k"] * t) - y


def test_auto_scan_rule_far_moves_near_stays():
    t = jnp.linspace(0.0, 3.0, 40)
    y = jnp.exp(-2.0 * t)
    far, rec = auto.scan_start(_decay, {"k": np.asarray(30.0)}, ["k"], (t, y), ())
    assert rec["far"] and rec["scans"][0]["moved"]
    assert float(far["k"]) == pytest.approx(30.0 / 16)  # the grid point nearest the truth
    hi = max(v for _, v in rec["scans"][0]["profile"] if np.isfinite(v))
    assert rec["initial_loss"] - rec["loss"] > auto.SCAN_RISE * (hi - rec["loss"])
    near, rec = auto.scan_start(_decay, {"k": np.asarray(2.3)}, ["k"], (t, y), ())
    assert not rec["far"] and float(near["k"]) == 2.3  # the start is the best grid point: stay
    for k0 in (2.9, 3.5, 5.0, 7.0):  # the rule: move iff the start is in the upper half
        got, rec = auto.scan_start(_decay, {"k": np.asarray(k0)}, ["k"], (t, y), ())
        prof = [v for _, v in rec["scans"][0]["profile"] if np.isfinite(v)]
        low, hi, l0 = min(prof), max(prof + [rec["initial_loss"]]), rec["initial_loss"]
        assert rec["far"] == (l0 - low > auto.SCAN_RISE * (hi - low)), (k0, rec)
        assert float(got["k"]) == (rec["scans"][0]["best"] if rec["far"] else k0)
    # explicit factors (rise None) always move to the best grid point
    got, rec = auto.scan_start(_decay, {"k": np.asarray(2.3)}, {"k": [0.5, 0.87, 1.0]}, (t, y),
                               (), rise=None)  # fmt: skip
    assert float(got["k"]) == pytest.approx(2.3 * 0.87) and rec["scans"][0]["moved"]


def test_scan_candidates_order_and_limit():
    init = {n: np.asarray(1.0) for n in ("bend", "light_intensity", "stretch", "air_damping",
                                          "density", "shear")}  # fmt: skip
    cons = {n: Positive() for n in init}
    assert auto.scan_candidates(init, cons) == ["air_damping", "stretch", "shear"]
    cons["air_damping"] = Bounded(0.0, 1.0)  # not log-space: not scanned
    init["wind"] = np.zeros(3)
    assert auto.scan_candidates(init, cons) == ["stretch", "shear", "bend"]


def test_front_door_scans_a_far_start(engines_recorded, monkeypatch):
    sc = _scene()
    seen = {}

    def fake_scan(res_fn, init, names, loss_args, stage_args, rise):
        seen.update(names=list(names), rise=rise)
        return {**init, "stretch": init["stretch"] / 4}, dict(
            initial_loss=1.0, loss=0.1, far=True,
            scans=[dict(name="stretch", profile=[], best=12.5, moved=True, edge=False)])  # fmt: skip

    monkeypatch.setattr(auto, "scan_start", fake_scan)
    r = dc.fit.fit(sc, np.zeros(sc.video_shape), ["stretch", "wind"], init={"stretch": 50.0},
                   progress=False)  # fmt: skip
    name, init, kwargs = engines_recorded[-1]
    assert seen == {"names": ["stretch"], "rise": auto.SCAN_RISE}
    # far: the staged recipe from the caller's start (damped LM, the recipe's stages)
    assert name == "staged_schedule" and float(init["stretch"]) == 50.0
    assert kwargs["settings"].lm_tau == 1.0 and kwargs["sched"].stages[-1].scan[0] == "stretch"
    assert r.auto["far"] and r.auto["engine"] == "staged" and r.method == "staged"
    assert float(r.initial["stretch"]) == 50.0
    dc.fit.fit(sc, np.zeros(sc.video_shape), ["stretch"], init={"stretch": 50.0}, stages="none",
               progress=False)  # fmt: skip
    name, init, kwargs = engines_recorded[-1]  # own stages: LM from the scanned start, undamped
    assert name == "lm" and float(init["stretch"]) == 12.5 and kwargs["settings"].lm_tau == 1e-3
    seen.clear()
    dc.fit.fit(sc, np.zeros(sc.video_shape), ["stretch"], method="lm", progress=False)
    assert not seen  # method "lm": no scan
    seen.clear()
    dc.fit.fit(sc, np.zeros(sc.video_shape), ["stretch"], init={"stretch": 50.0},
               scan={"stretch": [0.5, 2.0]}, method="lm", progress=False)  # fmt: skip
    assert seen == {"names": ["stretch"], "rise": None}  # explicit factors: always the best


def test_hints_name_the_knob():
    start = {"k": 1.0, "a": 0.5}
    cons = {"k": Positive(), "a": Bounded(0.0, 1.0)}
    quiet = auto.hints(_result({"k": 2.0, "a": 0.4}, start), cons=cons, auto=None, x64=True,
                       contact=True)  # fmt: skip
    assert quiet == []
    stalled = _result({"k": 1.01, "a": 0.5}, start, status="stalled")
    h = auto.hints(stalled, cons=cons, auto=None, x64=False, contact=True)
    assert any(s.startswith("float32 noise") and "x64=True" in s for s in h), h
    assert any(s.startswith("start far") and "scan=" in s for s in h), h
    bound = _result({"k": 500.0, "a": 0.99999}, start, status="max_steps", iterations=7)
    h = auto.hints(bound, cons=cons, auto={"scans": []}, x64=True, contact=False)
    assert any(s.startswith("parameter at a bound: a") for s in h), h
    assert any(s.startswith("parameter ran off: k") for s in h), h
    assert any("ran all 7 steps" in s for s in h), h
    scans = {"scans": [dict(name="k", profile=[], best=16.0, moved=True, edge=True)]}
    h = auto.hints(bound, cons=cons, auto=scans, x64=True, contact=False)
    assert any(s.startswith("scan edge: k") for s in h), h
    assert not auto.hints(
        _result({"k": 16.0, "a": 0.4}, start), cons=cons, auto=scans, x64=True, contact=False
    )  # converged: the LM went past the grid's end
    wrong = _result({"k": 2.0, "a": 0.4}, start)  # converged, loss 0.5: RMS 0.71 > 0.05
    assert auto.hints(wrong, cons=cons, auto=None, x64=True, contact=True) == []
    h = auto.hints(wrong, cons=cons, auto=None, x64=True, contact=True, loss="l2")
    assert len(h) == 1 and h[0].startswith("large residual: pixel error 0.71"), h
    ident = type("I", (), {"confounded": [("k", "a", 0.99)]})()
    h = auto.hints(stalled, cons=cons, auto=None, x64=True, contact=False, ident=ident)
    assert any(s.startswith("confounded pair: k and a") and "tie or fix" in s for s in h), h
    stalled.hints = h
    assert "\n  hint: confounded pair" in stalled.summary()


@pytest.mark.slow  # compiles a tiny drape's scan and LM step (~1-2 min on a loaded 2-core box)
def test_auto_scans_a_far_start_and_fits():
    from tests.test_fit_lm import TINY, TRUTH

    sc = dc.build_scene(cfg.parse_config(TINY))
    targets = dc.fit.make_targets(sc, TRUTH)
    init = {"bend": TRUTH["bend"] * 12, "drag_normal": TRUTH["drag_normal"]}
    res = dc.fit.fit(sc, targets, ["bend", "drag_normal"], steps=30, init=init, loss="pyramid",
                     progress=False)  # fmt: skip
    assert res.auto["x64"] and res.auto["far"], res.auto
    for k, v in TRUTH.items():
        assert float(res.params[k]) == pytest.approx(v, rel=0.02), res.summary()
    assert dataclasses.asdict(res)["hints"] == []
