"""Physics benchmark: one JSON line per case.

    python benchmarks/physics.py            # nets 13x10, 32x32, 64x64, 128x128; both integrators
    python benchmarks/physics.py --quick    # 13x10 and 32x32 only, fewer repeats
    python benchmarks/physics.py --integrators symplectic --no-extras   # the gradient cases only

Keys: bench, net ("cols x rows" as "RxC" -> e.g. "13x10"), integrator, step_us (forward, per substep,
median, of one call rolling out one frame: 40 substeps symplectic, 100 implicit), symplectic only:
step_rollout_us (per substep inside one call of 2000 substeps: the substep's own cost) and
step_call_us (one jitted call of a single substep: mostly JAX dispatch overhead), grad100_ms
(forward + backward of a loss after 100 substeps w.r.t. the material, median),
peak_mb (XLA's compiled memory analysis of that gradient: arguments + outputs + temporaries).
Extra cases: "forces_layout" (shifted slices vs gather/scatter-add) and "grad_memory" (gradient
through 60 vs 600 frames).
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from _timing import emit, meta, timed

from diffcloth import physics
from diffcloth.physics.forces import make_gather_forces


def _median_time(fn, *args, repeats):
    return timed(fn, *args, repeats=repeats).median


def _peak_mb(jitted, *args) -> float:
    compiled = jitted.lower(*args).compile()
    m = compiled.memory_analysis()
    if m is None:
        return float("nan")
    total = m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
    return total / 2**20


def _scene(rows, cols, integrator, substeps):
    # 0.1 m spacing, so the default material is stable with the explicit integrator at 40 substeps
    net = physics.grid_net(rows, cols, (0.1 * (cols - 1), 0.1 * (rows - 1)), pinned="top_row")
    mat = physics.make_material()
    sim = physics.make_sim(1 / 30, num_substeps=substeps, integrator=integrator)
    return net, mat, sim, physics.rest_state(net)


def bench_case(rows, cols, integrator, repeats):
    sub = 40 if integrator == "symplectic" else 4
    net, mat, sim, s0 = _scene(rows, cols, integrator, sub)
    frames = max(1, 100 // sub) if integrator == "implicit" else 1
    step = jax.jit(lambda m, s: physics.rollout(net, sim, m, s, num_frames=frames).x[-1])
    t = _median_time(step, mat, s0, repeats=2 if integrator == "implicit" else repeats)
    step_us = t / (frames * sub) * 1e6
    extra = {}
    if integrator == "symplectic":
        # per substep inside a long rollout (50 frames x 40 substeps in one call: the call's
        # dispatch amortized away) and one jitted call of a single substep (dispatch-dominated)
        long = jax.jit(lambda m, s: physics.rollout(net, sim, m, s, num_frames=50).x[-1])
        extra["step_rollout_us"] = round(
            _median_time(long, mat, s0, repeats=repeats) / 2000 * 1e6, 2
        )
        sim1 = physics.make_sim(1 / 30 / sub, num_substeps=1, integrator=integrator)
        one = jax.jit(lambda m, s: physics.rollout(net, sim1, m, s, num_frames=1).x[-1])
        extra["step_call_us"] = round(_median_time(one, mat, s0, repeats=repeats * 10) * 1e6, 2)

    # gradient through 100 substeps: 10 frames x 10 substeps (explicit) / 25 x 4 (implicit)
    gsub = 10 if integrator == "symplectic" else 4
    gframes = 100 // gsub
    gsim = physics.make_sim(
        1 / 30 / (40 // gsub) if integrator == "symplectic" else 1 / 30,
        num_substeps=gsub,
        integrator=integrator,
    )
    target = net.rest + 0.01

    def loss(m):
        traj = physics.rollout(net, gsim, m, s0, num_frames=gframes)
        return jnp.sum((traj.x[-1] - target) ** 2)

    grad = jax.jit(jax.grad(loss))
    tg = _median_time(grad, mat, repeats=1 if integrator == "implicit" else max(1, repeats // 2))
    return dict(
        bench="physics",
        net=f"{cols}x{rows}",
        integrator=integrator,
        step_us=round(step_us, 2),
        grad100_ms=round(tg * 1e3, 2),
        peak_mb=round(_peak_mb(grad, mat), 2),
        substeps_per_frame=sub,
        **extra,
    )


def bench_layout(rows, cols, repeats):
    net, mat, _, s0 = _scene(rows, cols, "symplectic", 40)
    rng = np.random.default_rng(0)
    x = net.rest + 0.01 * jnp.asarray(rng.normal(size=net.rest.shape), net.rest.dtype)
    v = jnp.zeros_like(x)
    sl = jax.jit(lambda m, x, v: physics.internal_forces(net, m, x, v))
    ga = jax.jit(make_gather_forces(net))
    return dict(
        bench="forces_layout",
        net=f"{cols}x{rows}",
        slices_us=round(_median_time(sl, mat, x, v, repeats=repeats * 10) * 1e6, 2),
        gather_scatter_us=round(_median_time(ga, mat, x, v, repeats=repeats * 10) * 1e6, 2),
    )


def bench_memory(rows, cols):
    net, mat, sim, s0 = _scene(rows, cols, "symplectic", 40)
    out = dict(bench="grad_memory", net=f"{cols}x{rows}", integrator="symplectic")
    for frames in (60, 600):

        def loss(m, frames=frames):
            return jnp.sum(physics.rollout(net, sim, m, s0, num_frames=frames).x[-1] ** 2)

        out[f"peak_mb_{frames}"] = round(_peak_mb(jax.jit(jax.grad(loss)), mat), 3)
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--integrators", default="symplectic,implicit", help="comma-separated, in this order"
    )
    parser.add_argument("--no-extras", action="store_true", help="skip the layout and memory cases")
    args = parser.parse_args()
    sizes = [(10, 13), (32, 32)] if args.quick else [(10, 13), (32, 32), (64, 64), (128, 128)]
    repeats = 3 if args.quick else 7
    emit(meta("physics"))
    for rows, cols in sizes:
        for integrator in args.integrators.split(","):
            print(json.dumps(bench_case(rows, cols, integrator, repeats)), flush=True)
        if not args.no_extras:
            print(json.dumps(bench_layout(rows, cols, repeats)), flush=True)
    if not args.no_extras:
        print(json.dumps(bench_memory(10, 13)), flush=True)


if __name__ == "__main__":
    main()
