"""Gradient memory of long rollouts: one JSON line per (substeps, strategy).

    python benchmarks/memory.py            # 32x32 net, 100 / 1,000 / 10,000 substeps
    python benchmarks/memory.py --net 13x10

A loss on the final cloth state after N substeps (10 substeps per frame, N / 10 frames), its
gradient w.r.t. the material, in float32. Three strategies:
  - "advance": `physics.advance` (frames checkpointed in ceil(sqrt(frames)) blocks, substeps
    checkpointed, no trajectory kept): what diffcloth does for a final-state loss;
  - "rollout": `physics.rollout(...)[-1]`: the same checkpointing, but the whole trajectory is
    returned (one state per frame, the output a video loss needs);
  - "per_frame": baseline, a plain `lax.scan` over `jax.checkpoint(physics.step)`: one stored
    state per frame, i.e. linear growth.
Keys: temp_mb (XLA's compiled buffer plan: temporaries of the gradient program), total_mb
(temporaries + arguments + outputs), peak_rss_mb (peak resident memory of a fresh process that
compiles and runs the gradient once; includes the JAX runtime, about the same for every case),
grad_s (one gradient, after compilation). Sublinear growth: temp_mb at 10,000 substeps stays
far below 100 x temp_mb at 100.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys

from _timing import timed

SUBSTEPS_PER_FRAME = 10


def case(net: str, substeps: int, strategy: str) -> dict:
    import jax
    import jax.numpy as jnp

    from diffcloth import physics

    cols, rows = (int(v) for v in net.split("x"))
    cloth = physics.grid_net(rows, cols, (0.1 * (cols - 1), 0.1 * (rows - 1)), pinned="top_row")
    sim = physics.make_sim(SUBSTEPS_PER_FRAME / 600.0, num_substeps=SUBSTEPS_PER_FRAME)
    s0 = physics.rest_state(cloth)
    frames = substeps // SUBSTEPS_PER_FRAME

    def loss(m):
        if strategy == "advance":
            final = physics.advance(cloth, sim, m, s0, num_frames=frames)
        elif strategy == "per_frame":
            body = jax.checkpoint(lambda s, _: (physics.step(cloth, sim, m, s), None))
            final, _ = jax.lax.scan(body, s0, None, length=frames)
        else:
            final = jax.tree_util.tree_map(
                lambda a: a[-1], physics.rollout(cloth, sim, m, s0, num_frames=frames)
            )
        return jnp.sum(final.x**2)

    mat = physics.make_material()
    compiled = jax.jit(jax.grad(loss)).lower(mat).compile()
    mem = compiled.memory_analysis()
    grad_s = timed(compiled, mat, repeats=1).median
    g = compiled(mat)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(g))
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # Linux: KiB
    return dict(
        bench="grad_memory",
        net=net,
        substeps=substeps,
        frames=frames,
        strategy=strategy,
        temp_mb=round(mem.temp_size_in_bytes / 2**20, 3),
        total_mb=round(
            (mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes)
            / 2**20,
            3,
        ),
        peak_rss_mb=round(rss_kb / 1024, 1),
        grad_s=round(grad_s, 4),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--net", default="32x32", help="cols x rows")
    ap.add_argument("--substeps", default="100,1000,10000")
    ap.add_argument("--case", nargs=2, metavar=("SUBSTEPS", "STRATEGY"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:  # child process: one case, fresh peak RSS
        print(json.dumps(case(args.net, int(args.case[0]), args.case[1])), flush=True)
        return
    import jax

    print(
        json.dumps(
            dict(
                bench="meta",
                machine=platform.processor() or platform.machine(),
                jax=jax.__version__,
                backend=jax.default_backend(),
            )
        ),
        flush=True,
    )
    for n in (int(v) for v in args.substeps.split(",")):
        for strategy in ("advance", "rollout", "per_frame"):
            cmd = [sys.executable, __file__, "--net", args.net, "--case", str(n), strategy]
            out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
            print(out.strip().splitlines()[-1], flush=True)


if __name__ == "__main__":
    main()
