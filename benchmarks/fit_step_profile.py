"""Where a fit step's time goes: XLA CPU thunk time of one fit step, by package and direction.

    python benchmarks/fit_step_profile.py                       # the two configs of fit_step.py
    python benchmarks/fit_step_profile.py --configs configs/drape_fit.toml --repeats 3

The step is the one `benchmarks/fit_step.py` times (value and gradient of the config's fit loss at
its [fit.initial] values). It is compiled once, then run `--repeats` times under `jax.profiler`;
every executed XLA thunk (a fusion, copy, scatter, ...) is attributed to the diffcloth package
(physics, surface, render, fit, ...) that most of its operations come from (the HLO stack frames)
and to the forward or backward pass (backward: the operations come from a transpose). One JSON
line per (config, package, direction):
  bench "fit_step_profile", config, package, direction ("forward"/"backward"),
  thunk_ms   summed thunk time per step, ms (thunks on both CPU threads add up, so the sum can
             exceed the wall time), share (of all thunk time),
  launches   thunks launched per step (each launch costs about a microsecond on its own)
and one line per config with bench "fit_step_profile_total": wall_ms (per profiled step), thunk_ms,
launches, compile_s.
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
import time
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
from _hlo_profile import attribute, hlo_tables, thunk_times
from _timing import compile_and_run, emit, meta

from diffcloth import pipeline
from diffcloth.fit.scene_fit import make_targets, video_loss
from diffcloth.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ("configs/drape_fit.toml", "configs/experiments/drape_material.toml")


def _step(path: Path):
    raw = tomllib.loads(path.read_text())
    fit = raw.get("fit", {})
    kind = fit.get("loss", "l2")
    scene = load_scene(path)
    dt = scene.material.stretch.dtype
    targets = jnp.asarray(make_targets(scene, raw.get("truth", {})), dt)
    init = fit.get("initial", {})
    params = {
        n: jnp.asarray(init[n] if n in init else pipeline.param_value(scene, n), dt)
        for n in fit["free"]
    }

    def loss(p):
        return video_loss(pipeline.simulate_and_render(scene, p), targets, kind)

    return jax.jit(jax.value_and_grad(loss)), params


def _package_of(where):
    """Stack frame id -> the diffcloth package its file belongs to ("other" outside diffcloth)."""

    def key(i):
        if i not in where:
            return None
        m = re.search(r"diffcloth/(\w+?)(/|\.py)", where[i][0])
        return m.group(1) if m else "other"

    return key


def profile(config: str, repeats: int, out=None):
    step, params = _step(ROOT / config)
    t = time.perf_counter()
    compiled = step.lower(params).compile()
    compile_s = time.perf_counter() - t
    compile_and_run(compiled, params)
    ns, launches, wall = thunk_times(compiled, params, repeats=repeats)
    inst, bodies, where = hlo_tables(compiled.as_text())
    by = collections.Counter()
    nby = collections.Counter()
    for name, v in ns.items():
        key = attribute(name, inst, bodies, _package_of(where))[:2]
        by[key] += v
        nby[key] += launches[name]
    total = sum(by.values())
    for (pkg, direction), v in by.most_common():
        emit(
            dict(
                bench="fit_step_profile",
                config=config,
                package=pkg,
                direction=direction,
                thunk_ms=round(v / repeats / 1e6, 2),
                share=round(v / total, 3),
                launches=round(nby[(pkg, direction)] / repeats),
            ),
            out,
        )
    emit(
        dict(
            bench="fit_step_profile_total",
            config=config,
            wall_ms=round(wall * 1e3, 1),
            thunk_ms=round(total / repeats / 1e6, 1),
            launches=round(sum(nby.values()) / repeats),
            compile_s=round(compile_s, 1),
        ),
        out,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS))
    parser.add_argument("--repeats", type=int, default=3, help="profiled steps per config")
    parser.add_argument("--out", help="also write the JSON lines to this file")
    args = parser.parse_args()
    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    emit(meta("fit_step_profile"), out)
    for config in args.configs:
        profile(config, args.repeats, out)
    if out is not None:
        out.close()


if __name__ == "__main__":
    sys.exit(main())
