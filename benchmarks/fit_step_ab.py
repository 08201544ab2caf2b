"""Same-process A/B of one fit step: stencil forces with the hand-written VJP vs JAX autodiff.

    python benchmarks/fit_step_ab.py   # drape_material.toml, 3 alternating rounds

Prints {"hand_vjp", "round", "step_ms"} lines (value_and_grad of the fit loss, median of 3).
"""

import json
import sys
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import jax
import jax.numpy as jnp
from _timing import timed

from diffcloth import pipeline
from diffcloth.fit.scene_fit import make_targets, video_loss
from diffcloth.physics import forces as F
from diffcloth.scene import load_scene

path = Path(__file__).resolve().parent.parent / "configs/experiments/drape_material.toml"
raw = tomllib.loads(path.read_text())
fit = raw["fit"]
scene = load_scene(path)
dt = scene.material.stretch.dtype
targets = jnp.asarray(make_targets(scene, raw["truth"]), dt)
params = {n: jnp.asarray(fit["initial"][n], dt) for n in fit["free"]}


def loss(p):
    return video_loss(pipeline.simulate_and_render(scene, p), targets, fit.get("loss", "l2"))


steps = {}
for mode in (True, False):
    F._HAND_VJP[0] = mode
    steps[mode] = jax.jit(jax.value_and_grad(loss))
    jax.block_until_ready(steps[mode](params))
F._HAND_VJP[0] = True
for rnd in range(3):
    for mode in (True, False):
        print(
            json.dumps(
                dict(
                    hand_vjp=mode,
                    round=rnd,
                    step_ms=timed(steps[mode], params, repeats=3).median_ms,
                )
            ),
            flush=True,
        )
