"""Rigid-body timings: one JSON line per case (median of several runs after a compile call).

python benchmarks/rigid.py [--quick]
"""

import sys

import jax
import jax.numpy as jnp
from _timing import emit, meta, timed

from diffcloth import physics
from diffcloth.physics import coupled, rigid
from diffcloth.shapes import make_plane


def _time(fn, *args, repeats=5):
    return timed(fn, *args, repeats=repeats).median


def _bodies(n):
    out = []
    for i in range(n):
        shape = "box" if i % 2 else "sphere"
        kw = {"half_extents": (0.1, 0.1, 0.1)} if shape == "box" else {"radius": 0.1}
        out.append(rigid.make_body(shape, mass=1.0, position=(0.3 * i, 0.5 + 0.1 * i, 0.0), **kw))
    return tuple(out)


def _emit(row):
    emit({"bench": "rigid", **row})


def main(quick=False):
    emit(meta("rigid"))
    frames = 30 if quick else 120
    ground = make_plane((0.0, 1.0, 0.0), 0.0)
    sim = rigid.make_settings(dt=1 / 60, num_substeps=8)
    for n in (1, 2, 4) if quick else (1, 2, 4, 8):
        bodies = _bodies(n)
        fwd = jax.jit(lambda b: rigid.rigid_rollout(sim, b, num_frames=frames, planes=ground))
        sec = _time(fwd, bodies)
        row = {"case": "rigid_rollout", "bodies": n, "frames": frames, "substeps": 8}
        _emit({**row, "seconds": sec, "ms_per_frame": 1e3 * sec / frames})

        def loss(m, bodies=bodies):
            b0 = bodies[0].__class__(**{**bodies[0].__dict__, "mass": m})
            traj = rigid.rigid_rollout(sim, (b0,) + bodies[1:], num_frames=frames, planes=ground)
            return jnp.sum(traj[0].position[-1])

        sec = _time(jax.jit(jax.grad(loss)), jnp.asarray(1.0))
        _emit({"case": "rigid_rollout_grad_mass", "bodies": n, "frames": frames,
                          "seconds": sec})  # fmt: skip

    rows = 10
    net = physics.grid_net(rows, rows, (1.0, 1.0), plane="xy", pinned="top_row")
    csim = physics.make_sim(1 / 60, num_substeps=16)
    mat = physics.make_material()
    ball = rigid.make_body("sphere", mass=0.15, radius=0.1, position=(0, -0.1, 0.6),
                           velocity=(0, 1.0, -4.0))  # fmt: skip
    state = physics.rest_state(net)
    for two_way in (False, True):
        fn = jax.jit(lambda b, tw=two_way: coupled.coupled_rollout(
            net, csim, mat, state, b, num_frames=frames, two_way=tw))  # fmt: skip
        sec = _time(fn, (ball,))
        _emit({"case": "coupled_rollout", "net": f"{rows}x{rows}", "two_way": two_way,
                          "frames": frames, "substeps": 16, "seconds": sec,
                          "ms_per_frame": 1e3 * sec / frames})  # fmt: skip
    plain = jax.jit(lambda s: physics.rollout(net, csim, mat, s, num_frames=frames))
    sec = _time(plain, state)
    row = {"case": "cloth_rollout_reference", "net": f"{rows}x{rows}", "frames": frames}
    _emit({**row, "seconds": sec, "ms_per_frame": 1e3 * sec / frames})


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
