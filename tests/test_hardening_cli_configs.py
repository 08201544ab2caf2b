"""Issue 35, class 7: every material model and every shipped config runs through the real CLI.

The CLI fit of a Provot config ended in "internal error (AttributeError: 'MassSpring' object has
no attribute 'stretch')": the LM stages read the run's dtype from a continuum-only field. Here
`diffcloth simulate`, `render` and `fit --smoke` run in-process through `diffcloth.cli.main` for

- each material model (`config.physics.MATERIAL_MODELS`) on the tiny scene of test_hardening.py:
  the default run (one parametrized test, the smallest variant per model);
- every shipped config in configs/ and configs/experiments/ (slow): shrunk only through the CLI's
  own documented overrides: `simulate --frames`, `render --frames --size` (override [sim]
  num_frames and [render] width/height) and `fit --smoke` (tiny sizes, 2 steps: what CI runs).

configs/cross_engine_drape.toml is the cross-engine recipe as a config (staged LM, ties, scan,
LM tolerances, x64); its [fit] keys are checked here without running it.
"""

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from test_hardening import FIT, TINY, TRUTH, run, write

from diffcloth.config import load_config
from diffcloth.config.physics import MATERIAL_MODELS

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "configs").glob("*.toml")) + sorted(
    (ROOT / "configs" / "experiments").glob("*.toml")
)

#: the tiny scene in each material model. The provot case fits a stiffness with Levenberg-Marquardt
#: (the path that crashed); the continuum case, whose material fits run in many other tests, fits
#: an albedo with Adam (the other engine, and a cheaper program: the default run's budget)
MODELS = {
    "continuum": TINY
    + FIT.replace('["bend"]', '["diffuse"]')
    + 'method = "adam"\n'
    + "[truth]\ndiffuse = [0.5, 0.4, 0.3]\n",
    "provot": TINY.replace(
        "[material]\nstretch = 20.0\nshear = 5.0\nbend = 1e-3",
        '[material]\nmodel = "provot"\nk_struct = 40.0\nk_flex = 2.0',
    )
    + FIT.replace('["bend"]', '["k_struct"]')
    + "[truth]\nk_struct = 55.0\n",
}


def test_every_material_model_has_a_case():
    assert set(MODELS) == set(MATERIAL_MODELS)


def _cli_all(tmp_path, capsys, cfg, *, frames=None, size=None, fit=True):
    """simulate, render and fit --smoke of one config; returns the fit's result.json (or None)."""
    sim = ["simulate", cfg, "--out", str(tmp_path / "sim")]
    ren = ["render", cfg, "--out", str(tmp_path / "ren"), "--format", "gif"]
    if frames is not None:
        sim += ["--frames", str(frames)]
        ren += ["--frames", str(frames)]
    if size is not None:
        ren += ["--size", str(size)]
    code, out, err = run(sim, capsys)
    assert code == 0, err
    x = np.load(tmp_path / "sim" / "trajectory.npz")["x"]
    assert np.all(np.isfinite(x)) and x.shape[0] == (frames or load_config(cfg).sim.num_frames)
    code, out, err = run(ren, capsys)
    assert code == 0, err
    assert (tmp_path / "ren" / "video.gif").is_file() and (tmp_path / "ren" / "last.png").is_file()
    if not fit:
        return None
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "fit"), "--smoke"], capsys)
    assert code == 0, err
    assert "internal error" not in err and "Traceback" not in err
    result = json.loads((tmp_path / "fit" / "result.json").read_text())
    assert result["status"] in ("converged", "stalled", "max_steps"), result["status"]
    return result


@pytest.mark.parametrize("model", sorted(MODELS))
def test_cli_simulate_render_fit_for_every_material_model(tmp_path, capsys, model):
    cfg = write(tmp_path, MODELS[model])
    assert load_config(cfg).material.model == model
    result = _cli_all(tmp_path, capsys, cfg)
    free = next(iter(result["params"]))
    assert np.all(np.isfinite(np.asarray(result["params"][free]["fitted"], float)))


def test_the_cross_engine_recipe_is_a_config():
    config = load_config(ROOT / "configs" / "cross_engine_drape.toml")
    fit = config.fit
    assert config.material.model == "provot" and fit.x64 and fit.method == "lm"
    assert (fit.lm_xtol, fit.lm_ftol, fit.lm_tau, fit.lm_polish) == (1e-3, 1e-5, 1.0, 0)
    assert set(fit.ties) == {"k_shear", "k_flex"} and fit.free == ("k_struct", "air_damping")
    loop = fit.engine()  # the loop settings receive the LM keys
    assert (loop.lm_xtol, loop.lm_ftol, loop.lm_tau, loop.lm_polish) == (1e-3, 1e-5, 1.0, 0)
    assert [st.get("free") for st in fit.stages] == [["air_damping"], None]


@pytest.mark.parametrize(
    "extra, needle",
    [
        ("lm_xtol = 0.0", "[fit] lm_xtol = 0.0 is out of range"),
        ("lm_tau = -1.0", "[fit] lm_tau"),
        ("lm_polish = 1.5", "[fit] lm_polish"),
        ('x64 = "yes"', "[fit] x64"),
    ],
)
def test_new_fit_keys_are_validated(tmp_path, capsys, extra, needle):
    cfg = write(tmp_path, TINY + FIT + extra + "\n" + TRUTH)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and needle in err, err


def test_fit_x64_key_needs_float64_in_the_library(tmp_path):
    import jax

    from diffcloth.config import ConfigError
    from diffcloth.experiment import run_fit_config

    cfg = write(tmp_path, TINY + FIT + "x64 = true\n" + TRUTH)
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(ConfigError, match=r"\[fit\] x64 = true needs"):
            run_fit_config(cfg, tmp_path / "o")
    finally:
        jax.config.update("jax_enable_x64", True)


def test_render_frames_override(tmp_path, capsys):
    cfg = write(tmp_path, TINY.replace("level = 2", "level = 2\nframe_stride = 2"))
    code, out, err = run(["render", cfg, "--out", str(tmp_path / "o"), "--frames", "1"], capsys)
    assert code == 2 and "--frames 1 is below [render] frame_stride = 2" in err, err


@pytest.mark.slow  # every shipped config: minutes
@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_cli_simulate_render_fit_for_every_shipped_config(tmp_path, capsys, path):
    data = tomllib.loads(path.read_text())
    stride = data.get("render", {}).get("frame_stride", 1)
    # a fit of footage files (configs/footage_example.toml) needs the footage at its own size:
    # tests/test_footage_config.py runs that path on a small footage file
    fit = "fit" in data and "targets" not in data["fit"]
    _cli_all(tmp_path, capsys, str(path), frames=max(2, stride), size=16, fit=fit)
