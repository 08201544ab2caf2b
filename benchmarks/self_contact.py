"""Self-contact of the mesh cloth (issue 34): the cost of one implicit step with self-contact
against the same step without.

    python benchmarks/self_contact.py                    # 2,500 and 10,000 vertices, float64
    python benchmarks/self_contact.py --edges 0.0107 --out benchmarks/results/self_contact.jsonl

One JSON line per figure after the "meta" line (`_timing.meta`, plus the git commit and the CPU
model); every line carries utc, commit, cpu, cores, load_1min, dtype, n_vertices, max_rss_mb.

Case
  hanging_step  one `implicit_step` (h = 1/60 s, the first from rest) of the hanging square of
                benchmarks/mesh_cloth.py (rectangle(0.5, 0.5, edge) in the xy-plane, top edge
                pinned, "wang2011-gray-interlock"), without and with self-contact
                (make_self_contact(thickness = min(2 mm, 0.4 x the shortest rest height)));
                no pair comes within the thickness, so the ratio is the price of the broad
                phase, the step filter and the barrier terms themselves. Warm medians
                (`off_ms`, `on_ms`, `on_off_ratio`), Newton iterations and first-call times.

Newton's VBD cloth with and without its self-contact, in the same run as diffcloth on the
peer's own scene: benchmarks/peers/newton_self_contact.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # benchmarks/_timing.py, mesh_cloth.py

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _timing import emit, meta, timed  # noqa: E402
from mesh_cloth import GRAVITY, common, cpu_model, git_commit, hanging_scene, max_rss_mb  # noqa: E402

from diffcloth.physics.mesh import implicit_step  # noqa: E402
from diffcloth.physics.mesh.selfcontact import make_self_contact, min_rest_height  # noqa: E402
from diffcloth.physics.mesh.solve import SolverSettings  # noqa: E402
from diffcloth.physics.state import ClothState  # noqa: E402


def bench(edge, repeats, out, dtype=np.float64):
    cloth, fabric = hanging_scene(dtype, edge)
    g = jnp.asarray(GRAVITY, dtype)
    state = ClothState(x=cloth.rest, v=jnp.zeros_like(cloth.rest))
    thickness = min(2e-3, 0.4 * min_rest_height(cloth))
    sc = make_self_contact(thickness, cloth=cloth, dtype=dtype)
    settings = SolverSettings(max_iters=200)
    row = dict(bench="self_contact_hanging_step", **common(str(np.dtype(dtype)), cloth.num_vertices),
               n_faces=cloth.num_faces, thickness_m=thickness, capacity=sc.capacity,
               scene="hanging square 0.5 m, top edge pinned, h=1/60 s, first step")  # fmt: skip
    for name, contact in (("off", None), ("on", sc)):
        step = jax.jit(lambda s, c=contact: implicit_step(cloth, fabric, s, 1.0 / 60.0, gravity=g,
                                                          settings=settings, self_contact=c))  # fmt: skip
        t0 = time.perf_counter()
        s1 = jax.block_until_ready(step(state))
        row[f"{name}_first_call_s"] = round(time.perf_counter() - t0, 2)
        t = timed(step, state, repeats=repeats, warmup=0)
        row[f"{name}_ms"], row[f"{name}_min_ms"] = t.median_ms, t.min_ms
        row[f"{name}_finite"] = bool(jnp.all(jnp.isfinite(s1.x)))
        row[f"{name}_max_drop_m"] = float(jnp.max(state.x[:, 1] - s1.x[:, 1]))
    row["on_off_ratio"] = round(row["on_ms"] / row["off_ms"], 3)
    row["max_rss_mb"] = max_rss_mb()
    emit(row, out)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--edges", default="0.0107,0.0054",
                        help="rest edge lengths, m (0.0107: ~2,500 vertices; 0.0054: ~10,000)")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="append the JSON lines to this file")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    out = open(args.out, "a") if args.out else None  # noqa: SIM115 - closed below
    try:
        emit(meta("self_contact", commit=git_commit(), cpu=cpu_model()), out)
        for edge in (float(e) for e in args.edges.split(",")):
            bench(edge, args.repeats, out)
    finally:
        if out is not None:
            out.close()


if __name__ == "__main__":
    main()
