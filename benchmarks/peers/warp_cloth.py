"""diffcloth vs NVIDIA Warp: the same mass-spring cloth, side by side in one process (CPU).

    python benchmarks/peers/warp_cloth.py                 # nets 13x10, 32x32, 64x64, 128x128
    python benchmarks/peers/warp_cloth.py --quick         # 13x10 and 32x32, fewer repeats
    python benchmarks/peers/warp_cloth.py --out benchmarks/results/warp_cloth.jsonl

One JSON line per net (cols x rows). The Warp kernels below re-implement diffcloth's force model
(`diffcloth.physics.forces`) term by term on diffcloth's own spring lists (`net.spring_list`,
`net.bend_triplets`): structural + shear springs k = stiffness * weight with stiffness-
proportional damping c = damping * k along the spring, linear skip-one bending
g = bend * w * (s + damping * s_v),
lumped masses density * area, gravity, symplectic Euler v += h f / m, x += h v, pinned nodes held.
Drag is set to zero (diffcloth's per-cell drag is not re-implemented) and there are no colliders.

Keys: net, nodes, springs, bends, steps (substeps in the rollout), dtype,
  diffcloth_step_us / warp_step_us   forward time per substep (median), us
  diffcloth_grad_ms / warp_grad_ms   forward + backward of sum |x_100 - target|^2 w.r.t. the
                                     five material parameters (stretch, shear, bend, damping,
                                     density), ms
  max_abs_dx_m                       max |x_diffcloth - x_warp| after `steps` substeps, m
  max_rel_dgrad                      max over the five parameters of |g_dc - g_wp| / |g_dc|
  step_ratio, grad_ratio             diffcloth / Warp (below 1: diffcloth faster)
A last line, bench "peers_physics_agreement", compares the 13x10 net after 1 s (1200 substeps,
metre-scale swing) forward only.
Warp runs its CPU kernels single-threaded and pays a Python launch per kernel (3 per substep).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # benchmarks/_timing.py
from _timing import meta as _meta_line  # noqa: E402
from _timing import timed  # noqa: E402

from diffcloth import physics
from diffcloth.physics.net import bend_triplets, spring_list

PARAMS = ("stretch", "shear", "bend", "damping", "density")
H = 1.0 / 1200.0  # substep, s (the physics benchmark's 1/30 s frame with 40 substeps)
FRAMES, SUBSTEPS = 10, 10  # 100 substeps per rollout
GRAVITY = (0.0, -9.81, 0.0)

# --------------------------------------------------------------------------------- Warp model


@wp.kernel
def _springs(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    i0: wp.array(dtype=int),
    i1: wp.array(dtype=int),
    kind: wp.array(dtype=int),
    rest: wp.array(dtype=float),
    weight: wp.array(dtype=float),
    p: wp.array(dtype=float),
    f: wp.array(dtype=wp.vec3),
):
    t = wp.tid()
    a = i0[t]
    b = i1[t]
    d = x[b] - x[a]
    dv = v[b] - v[a]
    k = p[kind[t]] * weight[t]  # p[0] stretch (structural), p[1] shear
    sq = wp.dot(d, d)
    length = float(0.0)  # noqa: UP018 (Warp: a mutable float variable)
    n = wp.vec3(0.0, 1.0, 0.0)  # diffcloth's +y fallback for a zero-length spring
    if sq > 1.0e-12:
        length = wp.sqrt(sq)
        n = d / length
    mag = k * (length - rest[t]) + (p[3] * k) * wp.dot(dv, n)
    fs = mag * n
    wp.atomic_add(f, a, fs)
    wp.atomic_sub(f, b, fs)


@wp.kernel
def _bends(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    ta: wp.array(dtype=int),
    tb: wp.array(dtype=int),
    tc: wp.array(dtype=int),
    bweight: wp.array(dtype=float),
    p: wp.array(dtype=float),
    f: wp.array(dtype=wp.vec3),
):
    t = wp.tid()
    a = ta[t]
    b = tb[t]
    c = tc[t]
    s = x[a] - 2.0 * x[b] + x[c]
    sv = v[a] - 2.0 * v[b] + v[c]
    g = (p[2] * bweight[t]) * (s + p[3] * sv)
    wp.atomic_sub(f, a, g)
    wp.atomic_add(f, b, 2.0 * g)
    wp.atomic_sub(f, c, g)


@wp.kernel
def _integrate(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    area: wp.array(dtype=float),
    free: wp.array(dtype=int),
    p: wp.array(dtype=float),
    gravity: wp.vec3,
    h: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    if free[i] == 1:
        m = p[4] * area[i]
        v1 = v[i] + (h * (f[i] + m * gravity)) / m
        x_out[i] = x[i] + h * v1
        v_out[i] = v1
    else:
        x_out[i] = x[i]
        v_out[i] = wp.vec3(0.0, 0.0, 0.0)


@wp.kernel
def _loss(x: wp.array(dtype=wp.vec3), target: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    i = wp.tid()
    d = x[i] - target[i]
    wp.atomic_add(out, 0, wp.dot(d, d))


class WarpCloth:
    """The diffcloth net and material as Warp arrays; forward and taped rollouts."""

    def __init__(self, net, material, steps: int, device: str = "cpu"):
        self.device = device
        self.n = net.rows * net.cols
        self.steps = steps
        pairs, kind, rest, weight = spring_list(net)
        trip, bweight = bend_triplets(net)
        arr = lambda a, dt: wp.array(np.ascontiguousarray(a), dtype=dt, device=device)
        self.i0, self.i1 = (
            arr(pairs[:, 0].astype(np.int32), int),
            arr(pairs[:, 1].astype(np.int32), int),
        )
        self.kind = arr(kind.astype(np.int32), int)
        self.rest = arr(np.asarray(rest, np.float32), float)
        self.weight = arr(np.asarray(weight, np.float32), float)
        self.ta, self.tb, self.tc = (arr(trip[:, j].astype(np.int32), int) for j in range(3))
        self.bweight = arr(np.asarray(bweight, np.float32), float)
        self.area = arr(np.asarray(net.area, np.float32).ravel(), float)
        self.free = arr((~np.asarray(net.pinned)).ravel().astype(np.int32), int)
        self.num_springs, self.num_bends = len(pairs), len(trip)
        p = np.array([float(getattr(material, k)) for k in PARAMS], np.float32)
        self.p = wp.array(p, dtype=float, device=device, requires_grad=True)
        x0 = np.asarray(net.rest, np.float32).reshape(-1, 3)
        self.x0 = x0
        # one state per substep and one force buffer per substep, so the tape can replay backward
        z = np.zeros_like(x0)
        self.xs = [wp.array(x0, dtype=wp.vec3, device=device, requires_grad=True)]
        self.vs = [wp.array(z, dtype=wp.vec3, device=device, requires_grad=True)]
        for _ in range(steps):
            self.xs.append(wp.zeros(self.n, dtype=wp.vec3, device=device, requires_grad=True))
            self.vs.append(wp.zeros(self.n, dtype=wp.vec3, device=device, requires_grad=True))
        self.fs = [
            wp.zeros(self.n, dtype=wp.vec3, device=device, requires_grad=True) for _ in range(steps)
        ]
        self.loss = wp.zeros(1, dtype=float, device=device, requires_grad=True)
        self.gravity = wp.vec3(*GRAVITY)

    def _substep(self, x, v, f, x_out, v_out):
        dev = self.device
        wp.launch(
            _springs,
            self.num_springs,
            inputs=[x, v, self.i0, self.i1, self.kind, self.rest, self.weight, self.p, f],
            device=dev,
        )
        wp.launch(
            _bends,
            self.num_bends,
            inputs=[x, v, self.ta, self.tb, self.tc, self.bweight, self.p, f],
            device=dev,
        )
        wp.launch(
            _integrate,
            self.n,
            inputs=[x, v, f, self.area, self.free, self.p, self.gravity, H, x_out, v_out],
            device=dev,
        )

    def forward(self) -> np.ndarray:
        """`steps` substeps from rest; returns the final positions (n, 3)."""
        for s in range(self.steps):
            self.fs[s].zero_()
            self._substep(self.xs[s], self.vs[s], self.fs[s], self.xs[s + 1], self.vs[s + 1])
        wp.synchronize_device(self.device)
        return self.xs[-1].numpy()

    def grad(self, target: wp.array) -> np.ndarray:
        """d/dp of sum |x_steps - target|^2 (forward recorded on a tape, then backward)."""
        for f in self.fs:
            f.zero_()
        self.loss.zero_()
        tape = wp.Tape()
        with tape:
            for s in range(self.steps):
                self._substep(self.xs[s], self.vs[s], self.fs[s], self.xs[s + 1], self.vs[s + 1])
            wp.launch(_loss, self.n, inputs=[self.xs[-1], target, self.loss], device=self.device)
        tape.backward(loss=self.loss)
        g = self.p.grad.numpy().copy()
        tape.zero()
        wp.synchronize_device(self.device)
        return g


# --------------------------------------------------------------------------------- harness


def _median(fn, repeats):
    return timed(fn, repeats=repeats).median


def scene(rows, cols):
    """The physics benchmark's scene: 0.1 m spacing, top row pinned, hanging from horizontal."""
    net = physics.grid_net(rows, cols, (0.1 * (cols - 1), 0.1 * (rows - 1)), pinned="top_row")
    mat = physics.make_material(drag_normal=0.0, drag_tangent=0.0)
    sim = physics.make_sim(H * SUBSTEPS, num_substeps=SUBSTEPS, integrator="symplectic")
    return net, mat, sim


def bench_case(rows, cols, repeats):
    net, mat, sim = scene(rows, cols)
    s0 = physics.rest_state(net)
    steps = FRAMES * SUBSTEPS
    target = net.rest + 0.01

    # diffcloth
    fwd = jax.jit(lambda m, s: physics.rollout(net, sim, m, s, num_frames=FRAMES).x[-1])

    def loss(m):
        return jnp.sum((physics.rollout(net, sim, m, s0, num_frames=FRAMES).x[-1] - target) ** 2)

    grad = jax.jit(jax.grad(loss))
    x_dc = np.asarray(jax.block_until_ready(fwd(mat, s0))).reshape(-1, 3)
    t_dc = _median(lambda: jax.block_until_ready(fwd(mat, s0)), repeats)
    g_dc_tree = jax.block_until_ready(grad(mat))
    g_dc = np.array([float(getattr(g_dc_tree, k)) for k in PARAMS])
    tg_dc = _median(lambda: jax.block_until_ready(grad(mat)), max(1, repeats // 2))

    # Warp
    wc = WarpCloth(net, mat, steps)
    x_wp = wc.forward()
    t_wp = _median(wc.forward, repeats)
    tgt = wp.array(np.asarray(target, np.float32).reshape(-1, 3), dtype=wp.vec3, device=wc.device)
    g_wp = wc.grad(tgt)
    tg_wp = _median(lambda: wc.grad(tgt), max(1, repeats // 2))

    rel = np.abs(g_dc - g_wp) / np.maximum(np.abs(g_dc), 1e-30)
    return dict(
        bench="peers_physics",
        net=f"{cols}x{rows}",
        nodes=rows * cols,
        springs=wc.num_springs,
        bends=wc.num_bends,
        steps=steps,
        dtype=str(x_dc.dtype),
        diffcloth_step_us=round(t_dc / steps * 1e6, 2),
        warp_step_us=round(t_wp / steps * 1e6, 2),
        diffcloth_grad_ms=round(tg_dc * 1e3, 2),
        warp_grad_ms=round(tg_wp * 1e3, 2),
        step_ratio=round(t_dc / t_wp, 3),
        grad_ratio=round(tg_dc / tg_wp, 3),
        max_abs_dx_m=float(np.max(np.abs(x_dc - x_wp))),
        max_displacement_m=float(np.max(np.abs(x_dc - wc.x0))),
        max_rel_dgrad=float(rel.max()),
        grad_diffcloth=[float(g) for g in g_dc],
        grad_warp=[float(g) for g in g_wp],
    )


def agreement_case(rows, cols, seconds):
    """Forward-only agreement over a longer swing (large motion), no timing."""
    net, mat, _ = scene(rows, cols)
    frames = int(round(seconds / (H * SUBSTEPS)))
    sim = physics.make_sim(H * SUBSTEPS, num_substeps=SUBSTEPS, integrator="symplectic")
    traj = jax.jit(
        lambda m: physics.rollout(net, sim, m, physics.rest_state(net), num_frames=frames)
    )(mat)
    x_dc = np.asarray(traj.x[-1]).reshape(-1, 3)
    wc = WarpCloth(net, mat, frames * SUBSTEPS)
    x_wp = wc.forward()
    return dict(
        bench="peers_physics_agreement",
        net=f"{cols}x{rows}",
        steps=frames * SUBSTEPS,
        seconds=seconds,
        dtype=str(x_dc.dtype),
        max_abs_dx_m=float(np.max(np.abs(x_dc - x_wp))),
        max_displacement_m=float(np.max(np.abs(x_dc - wc.x0))),
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="13x10 and 32x32 only, fewer repeats")
    parser.add_argument("--out", help="also write the JSON lines to this file")
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    sizes = [(10, 13), (32, 32)] if args.quick else [(10, 13), (32, 32), (64, 64), (128, 128)]
    repeats = args.repeats or (3 if args.quick else 5)
    meta = _meta_line("warp_cloth", warp=wp.__version__, params=list(PARAMS), substep_s=H)
    lines = [meta]
    print(json.dumps(meta), flush=True)
    for rows, cols in sizes:
        row = bench_case(rows, cols, repeats)
        lines.append(row)
        print(json.dumps(row), flush=True)
    row = agreement_case(10, 13, 1.0)
    lines.append(row)
    print(json.dumps(row), flush=True)
    if args.out:
        with open(args.out, "w") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in lines)


if __name__ == "__main__":
    main()
