"""The 256^2 render forward and gradient of two commits, timed turn about in one process.

    python benchmarks/render_ab.py --base HEAD            # this working tree against HEAD
    python benchmarks/render_ab.py --base 43cf32b --rounds 40

The scene, camera, light and loss are benchmarks/peers/mitsuba_render.py's (the draped seed
cloth at level 13, 23,220 triangles, Lambert "phong", 256 x 256; the gradient of
mean((I - I_target)^2) w.r.t. the vertex positions). `--base` is checked out with `git worktree
add --detach` into a temporary folder; a child process imports diffcloth from there, traces the
forward and the gradient and exports them (`jax.export`, serialized); this process compiles those
and its own tree's programs with the same XLA and the same flags, then times them turn about:
per round, for each program, 3 untimed calls and a block of 10 timed ones (`--rounds` rounds).
On a VM whose speed drifts by 10-20 % between minutes, only such a paired ratio compares like
with like. (Compiling two versions by re-tracing one jitted function after patching the code does
not work: `jax.jit` caches the trace per function object, and the "variant" is the old program.)

One JSON line per program (bench "render_ab", program "forward"/"gradient"): base_ms / new_ms
(medians over all timed calls), ratio (median over rounds of the rounds' new / base block
medians; ratio_p10 / ratio_p90), max_abs_diff (new output against base's; for the gradient
relative to its largest entry), base commit. Needs the `bench` extra (mitsuba_render.py imports
Mitsuba for its scene constants; `jax.export` serialization needs flatbuffers).
"""

from __future__ import annotations

import argparse
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _timing import emit, meta

ROOT = Path(__file__).resolve().parent.parent

CHILD = r"""
import pickle, sys
sys.path[:0] = [sys.argv[1], sys.argv[1] + "/benchmarks/peers"]
import dataclasses, jax, jax.numpy as jnp, numpy as np
from jax import export
import mitsuba_render as mr
from diffcloth.render import render
from diffcloth.render.camera import make_camera
from diffcloth.render.lights import make_appearance, make_lights
out = sys.argv[2]
surface = pickle.load(open(out + "/surface.pkl", "rb"))
camera = make_camera(mr.EYE, mr.TARGET, mr.UP, width=mr.WIDTH, height=mr.HEIGHT, fov_y=mr.FOV_Y)
lights = make_lights(ambient=(0.0, 0.0, 0.0), directional=[(mr.LIGHT_DIR, (1.0, 1.0, 1.0), 1.0)])
app = make_appearance(diffuse=mr.ALBEDO, specular=(0.0, 0.0, 0.0), ambient=(0.0, 0.0, 0.0))
def image(p):
    s = dataclasses.replace(surface, positions=p)
    return render(s, camera, lights, "phong", app, background=(0.0, 0.0, 0.0))
pos = jnp.asarray(surface.positions)
fwd = jax.jit(image)
try:  # the first tree exported (the new one) renders the target, the second reuses it
    target = jnp.asarray(np.load(out + "/target.npy"))
except FileNotFoundError:
    target = fwd(pos + jnp.asarray(mr.SHIFT))[..., :3]
    np.save(out + "/target.npy", np.asarray(target))
grad = jax.jit(jax.grad(lambda p: jnp.mean((image(p)[..., :3] - target) ** 2)))
open(out + "/" + sys.argv[3] + ".fwd", "wb").write(export.export(fwd)(pos).serialize())
open(out + "/" + sys.argv[3] + ".grad", "wb").write(export.export(grad)(pos).serialize())
"""


def _export(tree: Path, tmp: str, name: str):
    """Trace and export the two programs with the diffcloth of `tree` (a fresh process)."""
    subprocess.run(
        [sys.executable, "-c", CHILD, str(tree), tmp, name],
        check=True,
        env={**os.environ, "PYTHONPATH": str(tree)},
    )


def _load(tmp: str, name: str, ext: str, pos):
    import jax
    from jax import export

    with open(f"{tmp}/{name}.{ext}", "rb") as f:
        exp = export.deserialize(f.read())
    return jax.jit(exp.call).lower(pos).compile()


def turn_about(programs: dict, arg, rounds: int, block: int = 10, warm: int = 3):
    """Per round, for each program: `warm` untimed calls, then `block` timed ones. Returns
    {name: [block medians]} and {name: [all times]} in s."""
    import jax

    blocks = {k: [] for k in programs}
    times = {k: [] for k in programs}
    for _ in range(rounds):
        for k, f in programs.items():
            for _ in range(warm):
                jax.block_until_ready(f(arg))
            ts = []
            for _ in range(block):
                t = time.perf_counter()
                jax.block_until_ready(f(arg))
                ts.append(time.perf_counter() - t)
            blocks[k].append(statistics.median(ts))
            times[k] += ts
    return blocks, times


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="HEAD", help="commit to compare against")
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--out", help="also write the JSON lines to this file")
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "benchmarks" / "peers"))
    import jax.numpy as jnp
    import mitsuba_render as mr

    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    emit(meta("render_ab"), out)
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", args.base],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    import jax

    surface = jax.tree_util.tree_map(np.asarray, mr.draped_surface())
    pos = jnp.asarray(surface.positions)
    with tempfile.TemporaryDirectory(prefix="diffcloth_ab_") as tmp:
        with open(f"{tmp}/surface.pkl", "wb") as f:
            pickle.dump(surface, f)
        tree = Path(tmp) / "base_tree"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), commit],
            check=True,
            capture_output=True,
        )
        try:
            _export(ROOT, tmp, "new")  # first: it renders the target both gradients use
            _export(tree, tmp, "base")
            progs = {
                (tree_name, kind): _load(tmp, tree_name, kind, pos)
                for tree_name in ("base", "new")
                for kind in ("fwd", "grad")
            }
        finally:
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                check=False,
                capture_output=True,
            )
    for kind, program in (("fwd", "forward"), ("grad", "gradient")):
        b, n = progs[("base", kind)], progs[("new", kind)]
        ob, on = np.asarray(b(pos)), np.asarray(n(pos))
        diff = float(np.max(np.abs(on - ob)))
        if kind == "grad":
            diff /= max(float(np.max(np.abs(ob))), 1e-30)
        blocks, times = turn_about({"base": b, "new": n}, pos, args.rounds)
        r = [x / y for x, y in zip(blocks["new"], blocks["base"], strict=True)]
        emit(
            dict(
                bench="render_ab",
                program=program,
                base=commit,
                rounds=args.rounds,
                base_ms=round(statistics.median(times["base"]) * 1e3, 3),
                new_ms=round(statistics.median(times["new"]) * 1e3, 3),
                ratio=round(statistics.median(r), 3),
                ratio_p10=round(float(np.percentile(r, 10)), 3),
                ratio_p90=round(float(np.percentile(r, 90)), 3),
                max_abs_diff=diff,
            ),
            out,
        )
    if out is not None:
        out.close()


if __name__ == "__main__":
    sys.exit(main())
