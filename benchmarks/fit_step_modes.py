"""Same-process A/B of one fit step by [sim] gradient mode (forward sensitivities vs reverse).

    python benchmarks/fit_step_modes.py                        # the two configs of fit_step.py
    python benchmarks/fit_step_modes.py --configs configs/drape_fit.toml --rounds 5

The step is the one `benchmarks/fit_step.py` times (`value_and_grad` of the config's fit loss at
its [fit.initial] values), compiled once per mode; the modes alternate for every round, so both
see the same machine load. JSON lines: bench "fit_step_modes", config, gradient, compile_s, and
step_ms (the fastest of `--repeats` calls per round, then the median over rounds), plus the
physics alone (`physics_grad_ms`: gradient of a random projection of the cloth trajectory).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
from _timing import emit, meta

from diffcloth import pipeline
from diffcloth.fit.scene_fit import make_targets, video_loss
from diffcloth.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ("configs/drape_fit.toml", "configs/experiments/drape_material.toml")
MODES = ("reverse", "forward")


def _fns(path: Path):
    raw = tomllib.loads(path.read_text())
    fit = raw["fit"]
    scene = load_scene(path)
    dt = scene.material.stretch.dtype
    targets = jnp.asarray(make_targets(scene, raw.get("truth", {})), dt)
    init = fit.get("initial", {})
    params = {
        n: jnp.asarray(init[n] if n in init else pipeline.param_value(scene, n), dt)
        for n in fit["free"]
    }
    w = jax.random.normal(jax.random.PRNGKey(0), (scene.num_frames,) + scene.state.x.shape, dt)
    fns = {}
    for mode in MODES:
        sc = dataclasses.replace(scene, sim=dataclasses.replace(scene.sim, gradient=mode))
        loss = lambda p, sc=sc: video_loss(
            pipeline.simulate_and_render(sc, p), targets, fit.get("loss", "l2")
        )
        phys = lambda p, sc=sc: jnp.sum(pipeline.simulate(sc, p).x * w)
        fns[mode] = (jax.jit(jax.value_and_grad(loss)), jax.jit(jax.grad(phys)))
    return fns, params


def _best(fn, params, repeats):
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(params))
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    emit(meta("fit_step_modes"))
    for config in args.configs:
        fns, params = _fns(ROOT / config)
        compile_s = {}
        for mode, (step, phys) in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(step(params))
            compile_s[mode] = round(time.perf_counter() - t, 2)
            jax.block_until_ready(phys(params))
        times = {m: ([], []) for m in fns}
        for _ in range(args.rounds):
            for mode, (step, phys) in fns.items():
                times[mode][0].append(_best(step, params, args.repeats))
                times[mode][1].append(_best(phys, params, args.repeats))
        for mode, (steps, physs) in times.items():
            emit(
                dict(
                    bench="fit_step_modes",
                    config=config,
                    gradient=mode,
                    compile_s=compile_s[mode],
                    step_ms=round(statistics.median(steps), 1),
                    physics_grad_ms=round(statistics.median(physs), 1),
                )
            )


if __name__ == "__main__":
    main()
