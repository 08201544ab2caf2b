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
import glob
import re
import sys
import tempfile
import time
from pathlib import Path

import jax
from _timing import emit, meta

sys.path.insert(0, str(Path(__file__).resolve().parent / "peers"))
SKIP = ("ThunkExecutor", "ThreadpoolListener", "while", "end:", "conditional", "cond")


def _tables(text: str):
    """(instruction line by name, fused computation body by name, 'file:line(function)' by
    stack frame id) from the compiled HLO text."""
    files, funcs, locs, frames = {}, {}, {}, {}
    section = None
    for line in text.splitlines():
        s = line.strip()
        if s in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = s
            continue
        m = re.match(r"^(\d+) (.*)$", s)
        if section and m:
            i, rest = int(m.group(1)), m.group(2)
            if section == "FileNames":
                files[i] = rest.strip('"').split("diffcloth/")[-1]
            elif section == "FunctionNames":
                funcs[i] = rest.strip('"')
            elif section == "FileLocations":
                get = lambda k, rest=rest: int(re.search(rf"\b{k}=(\d+)", rest).group(1))
                locs[i] = (get("file_name_id"), get("function_name_id"), get("line"))
            elif section == "StackFrames":
                frames[i] = int(re.search(r"file_location_id=(\d+)", rest).group(1))
        elif section and s:
            section = None
    where = {}
    for k, v in frames.items():
        f, fn, ln = locs[v]
        where[k] = f"{files.get(f, '?')}:{ln}({funcs.get(fn, '')})"
    bodies, inst, cur = {}, {}, None
    for line in text.splitlines():
        m = re.match(r"^%?([\w.-]+) .*\{$", line)
        if m and not line.startswith(" "):
            cur = m.group(1)
            bodies[cur] = []
            continue
        if cur is not None:
            bodies[cur].append(line)
        m = re.search(r"%([\w.-]+) = ", line)
        if m:
            inst[m.group(1)] = line
    return inst, bodies, where


def _attribute(name, inst, bodies, where):
    line = inst.get(name, "")
    called = re.search(r"calls=%([\w.-]+)", line)
    body = bodies.get(called.group(1), []) if called else [line]
    lines = collections.Counter()
    backward = False
    for b in body:
        m = re.search(r"stack_frame_id=(\d+)", b)
        if m and int(m.group(1)) in where:
            lines[where[int(m.group(1))]] += 1
        backward = backward or "transpose(" in b
    shape = re.search(r"= (\S+) ", line)
    return (
        lines.most_common(1)[0][0] if lines else "other",
        "backward" if backward else "forward",
        shape.group(1) if shape else "",
    )


def profile(program: str, fn, arg, repeats: int, top: int, out=None):
    from jax._src.profiler import ProfileData

    compiled = fn.lower(arg).compile()
    for _ in range(2):
        jax.block_until_ready(compiled(arg))
    with tempfile.TemporaryDirectory(prefix="diffcloth_prof_") as tmp:
        jax.profiler.start_trace(tmp)
        t = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(compiled(arg))
        wall = (time.perf_counter() - t) / repeats
        jax.profiler.stop_trace()
        data = ProfileData.from_file(glob.glob(tmp + "/**/*.xplane.pb", recursive=True)[0])
        ns, launches = collections.Counter(), collections.Counter()
        for plane in data.planes:
            for line in plane.lines:
                if not line.name.startswith("tf_XLAEigen"):
                    continue
                for ev in line.events:
                    if not ev.name.startswith(SKIP):
                        ns[ev.name] += ev.duration_ns
                        launches[ev.name] += 1
    inst, bodies, where = _tables(compiled.as_text())
    by_line, n_line = collections.Counter(), collections.Counter()
    rows = []
    for name, v in ns.items():
        loc, direction, shape = _attribute(name, inst, bodies, where)
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
