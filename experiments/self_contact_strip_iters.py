"""Newton iterations per implicit step of the strip pile of tests/test_mesh_selfcontact_slow.py
(a 0.2 x 0.6 m strip released 4 mm above a floor piles onto itself; self-contact on, float64,
dt = 1/60 s, tol 1e-2, max_iters 300): one line per frame with the iterations, the residual,
the contact pairs at the end of the step and the wall time.

    python experiments/self_contact_strip_iters.py [--frames 20] [--out results/....jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from diffcloth.physics.mesh import (  # noqa: E402  # noqa: E402
    SolverSettings,
    dynamics,
    energy,
    make_cloth,
    make_fabric,
    make_mesh_colliders,
    rectangle,
    solve,
)
from diffcloth.physics.mesh import colliders as mc  # noqa: E402
from diffcloth.physics.mesh import selfcontact as sc  # noqa: E402
from diffcloth.physics.mesh import selfcontact_step as scs  # noqa: E402
from diffcloth.physics.mesh.solve import _newton, _Problem  # noqa: E402

G = jnp.array([0.0, -9.81, 0.0])


def implicit_theta(cloth, fabric, x_n, v_n, h, colliders, s):
    """The parameters `solve._newton` takes for dynamics.implicit_step's solve from (x_n, v_n)
    (s None: without self-contact)."""
    theta = {
        "cloth": cloth,
        "fabric": fabric,
        "colliders": colliders,
        "gravity": G,
        "x_pins": x_n,
        "free": ~cloth.pinned,
        "h": jnp.asarray(h),
        "x_n": x_n,
        "v_n": v_n,
        "wind": jnp.zeros(3),
        "el_prev": energy.elastic_energy(cloth, fabric, x_n),
        "g_prev": jax.grad(lambda y: energy.elastic_energy(cloth, fabric, y))(x_n),
    }
    if s is not None:
        theta["self_contact"] = s
        theta["sc_pairs"] = scs.candidates(cloth, s, x_n)  # as dynamics.implicit_step
        theta["sc_frame"] = scs.frame(cloth, s, x_n, theta["sc_pairs"][0])
    return theta


def step_with_stats(cloth, fabric, x_n, v_n, h, colliders, s, settings):
    """dynamics.implicit_step's solve, returning its Newton statistics too (s None: without
    self-contact, pairs within the thickness then 0)."""
    theta = implicit_theta(cloth, fabric, x_n, v_n, h, colliders, s)
    problem = _Problem("implicit", settings, 0.0, mc.has_colliders(colliders), s is not None)
    res = _newton(problem, theta, x_n)
    free = ~cloth.pinned
    v = jnp.where(free[:, None], (res.x - x_n) / h, v_n)
    x, v = dynamics._project_out(colliders, res.x, v)
    count = 0 if s is None else sc.find_pairs(cloth, s, x, s.thickness).count
    return x, v, res.converged, res.iterations, res.residual, count


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--max-iters", type=int, default=300)
    ap.add_argument("--out", default=None)
    ap.add_argument("--capacity", type=int, default=8, help="SelfContact.capacity")
    ap.add_argument(
        "--no-couplings",
        action="store_true",
        help="precondition without the pairs' couplings (diagonal blocks only)",
    )
    ap.add_argument("--dump", default=None, help="save the failing step's start (npz)")
    args = ap.parse_args(argv)
    cloth = make_cloth(rectangle(0.2, 0.6, 0.03))
    r = np.asarray(cloth.rest)
    x = jnp.asarray(np.stack([r[:, 0], r[:, 2] + 0.304, 0.01 * np.sin(7 * r[:, 2])], 1))
    v = jnp.zeros(x.shape)
    fabric = make_fabric("wang2011-gray-interlock")
    floor = make_mesh_colliders(planes=[((0, 1, 0), 0.0)])
    s = sc.make_self_contact(2e-3, cloth=cloth, capacity=args.capacity)
    if args.no_couplings:
        solve._couplings = lambda *a, **k: None
    settings = SolverSettings(max_iters=args.max_iters, tol=1e-2)
    with jax.numpy_rank_promotion("allow"):
        step = jax.jit(
            lambda x, v: step_with_stats(cloth, fabric, x, v, 1 / 60, floor, s, settings)
        )
        total = 0
        out = open(args.out, "a") if args.out else None  # noqa: SIM115
        for k in range(args.frames):
            x_prev, v_prev = x, v
            t0 = time.perf_counter()
            x, v, conv, it, res, cnt = jax.block_until_ready(step(x, v))
            row = dict(
                frame=k,
                converged=bool(conv),
                iterations=int(it),
                residual=float(res),
                pairs=int(cnt),
                seconds=round(time.perf_counter() - t0, 2),
            )
            total += int(it)
            print(json.dumps(row), flush=True)
            if out:
                out.write(json.dumps(row) + "\n")
            if not bool(conv):
                if args.dump:
                    np.savez(args.dump, x=np.asarray(x_prev), v=np.asarray(v_prev))
                print("not converged; stopping", file=sys.stderr)
                break
        print(json.dumps(dict(total_iterations=total, max_y=float(jnp.max(x[:, 1])))))


if __name__ == "__main__":
    main()
