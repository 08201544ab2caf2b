"""render_frames: a small video rendered as one vmapped batch equals the frame-by-frame
checkpointed map (values and gradients), the path longer videos take (pipeline.VMAP_PIXELS)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import pipeline, scene

TINY = {
    "net": {"rows": 4, "cols": 4, "width": 0.8, "height": 0.8, "center": [0.0, 0.75, 0.0]},
    "sim": {"dt": 1.0 / 30.0, "num_frames": 2, "num_substeps": 8},
    "spheres": [{"center": [0.05, 0.4, 0.0], "radius": 0.25}],
    "render": {"width": 16, "height": 16, "level": 2, "frame_stride": 1},
    "camera": {"eye": [0.0, 1.2, 1.6], "target": [0.0, 0.45, 0.0]},
}


@pytest.mark.slow  # two render gradient compiles (~40 s of CPU)
def test_batched_render_equals_checkpointed_map(monkeypatch):
    sc = scene.build_scene(cfg.parse_config(TINY))
    xs, spheres = pipeline.rendered_states(sc, pipeline.simulate(sc))
    w = jnp.asarray(np.random.default_rng(0).normal(size=(1, 2, 16, 16, 3)), xs.dtype)

    def loss(x):
        return jnp.sum(pipeline.render_frames(sc, x, spheres) * w)

    assert 2 * 16 * 16 <= pipeline.VMAP_PIXELS  # this video takes the batched path
    batched = jax.jit(jax.value_and_grad(loss))(xs)
    monkeypatch.setattr(pipeline, "VMAP_PIXELS", 0)
    mapped = jax.jit(jax.value_and_grad(loss))(xs)  # traced anew: VMAP_PIXELS = 0
    assert float(jnp.abs(batched[1]).max()) > 0
    np.testing.assert_allclose(batched[0], mapped[0], rtol=1e-5)
    np.testing.assert_allclose(batched[1], mapped[1], rtol=1e-4, atol=1e-6)
