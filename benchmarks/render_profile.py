"""Where the 256^2 render's time goes: XLA CPU thunk time per fusion and per source line.

    python benchmarks/render_profile.py                 # forward and forward + backward
    python benchmarks/render_profile.py --top 20 --repeats 5

The scene and loss are benchmarks/peers/mitsuba_render.py's (the draped seed cloth at level 13,
23,220 triangles, Lambert "phong", 256 x 256; the gradient of mean((I - I_target)^2) w.r.t. the
vertex positions). Each program is compiled, run, then run `--repeats` times under
`jax.profiler`; every executed XLA thunk (fusion, scatter, copy, ...; loop and conditional
wrappers excluded, their bodies counted) is attributed to the diffcloth source line that most
of its operations come from (the innermost HLO stack frame) and to the forward or backward
pass (backward: its operations come from a transpose). JSON lines:
  bench "render_profile_thunk": program ("forward"/"grad"), thunk (HLO name), shape, line,
    direction, thunk_ms (per call), launches (per call); the `--top` largest
  bench "render_profile_line": program, line, direction, thunk_ms, launches; the `--top` largest
  bench "render_profile_total": program, wall_ms (per profiled call), thunk_ms, launches
Thunk times on both CPU threads add up; under load they include time spent descheduled.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import jax
from _hlo_profile import attribute, hlo_tables, thunk_times
from _timing import emit, meta

sys.path.insert(0, str(Path(__file__).resolve().parent / "peers"))


def _line_of(where):
    """Stack frame id -> 'file:line(function)' (path from the package root), None if unknown."""

    def key(i):
        if i not in where:
            return None
        path, ln, fn = where[i]
        return f"{path.split('diffcloth/')[-1]}:{ln}({fn})"

    return key


def profile(program: str, fn, arg, repeats: int, top: int, out=None):
    compiled = fn.lower(arg).compile()
    ns, launches, wall = thunk_times(compiled, arg, repeats=repeats)
    inst, bodies, where = hlo_tables(compiled.as_text())
    by_line, n_line = collections.Counter(), collections.Counter()
    rows = []
    for name, v in ns.items():
        loc, direction, shape = attribute(name, inst, bodies, _line_of(where))
        by_line[(loc, direction)] += v
        n_line[(loc, direction)] += launches[name]
        rows.append((v, name, shape, loc, direction))
    per = lambda v: round(v / repeats / 1e6, 3)
    for v, name, shape, loc, direction in sorted(rows, reverse=True)[:top]:
        emit(
            dict(
                bench="render_profile_thunk",
                program=program,
                thunk=name,
                shape=shape,
                line=loc,
                direction=direction,
                thunk_ms=per(v),
                launches=round(launches[name] / repeats, 1),
            ),
            out,
        )
    for (loc, direction), v in by_line.most_common(top):
        emit(
            dict(
                bench="render_profile_line",
                program=program,
                line=loc,
                direction=direction,
                thunk_ms=per(v),
                launches=round(n_line[(loc, direction)] / repeats, 1),
            ),
            out,
        )
    emit(
        dict(
            bench="render_profile_total",
            program=program,
            wall_ms=round(wall * 1e3, 2),
            thunk_ms=round(sum(ns.values()) / repeats / 1e6, 2),
            launches=round(sum(launches.values()) / repeats),
        ),
        out,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10, help="profiled calls per program")
    parser.add_argument("--top", type=int, default=30, help="thunks and lines listed")
    parser.add_argument("--out", help="also write the JSON lines to this file")
    args = parser.parse_args()
    import dataclasses

    import jax.numpy as jnp
    import mitsuba_render as mr  # the scene, camera, light and loss of the peers benchmark

    from diffcloth.render import render
    from diffcloth.render.camera import make_camera
    from diffcloth.render.lights import make_appearance, make_lights

    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    emit(meta("render_profile"), out)
    surface = mr.draped_surface()
    camera = make_camera(mr.EYE, mr.TARGET, mr.UP, width=mr.WIDTH, height=mr.HEIGHT, fov_y=mr.FOV_Y)
    lights = make_lights(
        ambient=(0.0, 0.0, 0.0), directional=[(mr.LIGHT_DIR, (1.0, 1.0, 1.0), 1.0)]
    )
    app = make_appearance(diffuse=mr.ALBEDO, specular=(0.0, 0.0, 0.0), ambient=(0.0, 0.0, 0.0))

    def image(pos):
        s = dataclasses.replace(surface, positions=pos)
        return render(s, camera, lights, "phong", app, background=(0.0, 0.0, 0.0))

    pos = surface.positions
    fwd = jax.jit(image)
    target = jax.block_until_ready(fwd(pos + jnp.asarray(mr.SHIFT)))[..., :3]
    grad = jax.jit(jax.grad(lambda p: jnp.mean((image(p)[..., :3] - target) ** 2)))
    profile("forward", fwd, pos, args.repeats, args.top, out)
    profile("grad", grad, pos, max(1, args.repeats // 2), args.top, out)
    if out is not None:
        out.close()


if __name__ == "__main__":
    sys.exit(main())
