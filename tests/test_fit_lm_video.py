"""`diffcloth.fit.lm_video`: the video from the LM step equals `simulate_and_render`'s, and an LM
fit of the same scene then compiles no new step."""

import logging

import jax
import numpy as np
import pytest
from tiny_scenes import TINY_SCENE

from diffcloth import config as cfg
from diffcloth import pipeline, scene
from diffcloth.config.fit import FitSettings
from diffcloth.fit.lm_video import lm_video, lm_video_ok

TOML = (
    TINY_SCENE
    + """[[cameras]]
eye = [1.9, 0.9, 0.4]
target = [0.0, 0.5, 0.0]
"""
)


def test_lm_video_ok_only_for_a_single_start_lm_fit_without_ties_or_staged_free_sets():
    base = FitSettings(free=("bend",))
    assert lm_video_ok(base, "lm", ["bend"])
    assert not lm_video_ok(base, "adam", ["bend"])
    assert not lm_video_ok(FitSettings(free=("bend",), multistart=2), "lm", ["bend"])
    assert not lm_video_ok(base, "lm", [])


class _Compiles(logging.Handler):
    def __init__(self):
        super().__init__()
        self.names = []

    def emit(self, record):
        msg = record.getMessage()
        if msg.startswith("Finished XLA compilation of "):
            self.names.append(msg.split(" of ")[1].split(" in ")[0])


@pytest.mark.slow  # compiles the LM step and simulate_and_render of a tiny two-camera scene
def test_lm_video_matches_simulate_and_render_and_the_fit_reuses_its_step(tmp_path):
    from diffcloth import fit as dcfit

    path = tmp_path / "scene.toml"
    path.write_text(TOML)
    sc = scene.build_scene(cfg.load_config(path))
    truth = {"bend": 2e-3, "drag_normal": 1.0}
    video = lm_video(sc, truth, loss="pyramid")
    ref = np.asarray(jax.jit(pipeline.simulate_and_render)(sc, truth))
    assert video.shape == ref.shape == sc.video_shape and video.dtype == ref.dtype
    assert ref.max() > 0.1  # the cloth is in view
    # rounding (raw-space round trip, autodiff forces, the residual scale) grown by the dynamics
    np.testing.assert_allclose(video, ref, atol=2e-4)
    handler = _Compiles()
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    prev = jax.config.jax_log_compiles
    jax.config.update("jax_log_compiles", True)
    try:
        result = dcfit.fit(
            sc, video, ["bend", "drag_normal"], 1, init={"bend": 1e-3, "drag_normal": 0.5},
            loss="pyramid", progress=False, method="lm",
        )  # fmt: skip
    finally:
        jax.config.update("jax_log_compiles", prev)
        logger.removeHandler(handler)
    assert result.method == "lm" and np.isfinite(result.loss)
    assert "jit(step)" not in handler.names and "jit(init)" not in handler.names, handler.names
