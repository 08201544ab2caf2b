"""Where a Newton iteration of the mesh cloth's implicit step with self-contact spends its time:
the crumple square of `self_contact_crumple.py` run to a piled frame, then each part of an
iteration timed alone (jitted, float64, median of 7 calls after one warm-up):

  broad phase                the candidate pairs within d_hat + 2 B (`selfcontact_step.candidates`)
  step filter                cap, reach check (a new broad phase where C cannot be kept), CCD
  step pairs, CCD            `within` on C's rows, `step_bound` on the step's pairs
  gradient, HVP              of the energy without self-contact and of the self-contact terms
  line search                8 energies along a step, without (vmap) and with (lax.map) pairs
  Hessian, couplings, LU     the PSD approximation and its sparse factorization

plus whether the candidates at the full reach overflow `--capacity` (and at 2x and 4x it).

    python experiments/self_contact_iteration_parts.py                  # 686 vertices, frame 15
    python experiments/self_contact_iteration_parts.py --frame 20 --capacity 48
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))

import self_contact_crumple as crumple  # noqa: E402
import self_contact_strip_iters as strip  # noqa: E402

from diffcloth.physics.mesh import (  # noqa: E402
    SolverSettings,
    linsolve,
    make_fabric,
    solve,  # noqa: E402
)
from diffcloth.physics.mesh import selfcontact as sc  # noqa: E402
from diffcloth.physics.mesh import selfcontact_energy as sce  # noqa: E402
from diffcloth.physics.mesh import selfcontact_step as scs  # noqa: E402


def bench(name, fn, *args, repeats=7):
    """Print the median wall time (ms) of jit(fn)(*args) after one warm-up call."""
    f = jax.jit(fn)
    jax.block_until_ready(f(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t)
    print(f"{name:44s} {np.median(ts) * 1e3:9.2f} ms", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=float, default=0.25, help="m: the square's side")
    ap.add_argument("--edge", type=float, default=0.0107, help="m: rest edge length")
    ap.add_argument("--frame", type=int, default=15, help="the piled frame to time at")
    ap.add_argument("--capacity", type=int, default=24)
    args = ap.parse_args(argv)
    cloth, x0, floor, _ = crumple.square_scene(args.size, args.edge)
    fabric = make_fabric("wang2011-gray-interlock")
    thickness = min(2e-3, 0.4 * sc.min_rest_height(cloth))
    s = sc.make_self_contact(thickness, cloth=cloth, capacity=args.capacity)
    settings = SolverSettings(max_iters=300, tol=1e-2)
    h = crumple.DT
    with jax.numpy_rank_promotion("allow"):
        step = jax.jit(lambda x, v: strip.step_with_stats(cloth, fabric, x, v, h, floor, s,
                                                          settings))  # fmt: skip
        x, v = jnp.asarray(x0), jnp.zeros(x0.shape)
        for _ in range(args.frame):
            x, v, _, it, _, count = step(x, v)
        print(f"{cloth.num_vertices} vertices, frame {args.frame}: {int(count)} pairs in "
              f"contact, {int(it)} Newton iterations")  # fmt: skip
        theta = strip.implicit_theta(cloth, fabric, x, v, h, floor, s)
        with_sc = solve._Problem("implicit", settings, 0.0, True, True)
        plain = solve._Problem("implicit", settings, 0.0, True, False)
        y = x + h * v  # an iterate inside the next step
        cs = jax.jit(lambda y: scs.start(cloth, s, y))(y)
        pairs = cs.active
        full = float(cs.reach) >= float(sc.step_radius(cloth, s))
        print(f"at the iterate: {int(jnp.sum(pairs.valid))} pairs within d_hat; C found at the "
              f"full reach: {full} (reach {float(cs.reach) * 1e3:.2f} mm; else every step "
              f"filter runs new broad phases)")  # fmt: skip
        for cap in (args.capacity, 2 * args.capacity, 4 * args.capacity):
            s_cap = sc.make_self_contact(thickness, cloth=cloth, capacity=cap)
            c = jax.jit(lambda y, s_cap=s_cap: scs.candidates(cloth, s_cap, y)[0])(y)
            print(f"capacity {cap}: {c.valid.shape[0]} rows, {int(jnp.sum(c.valid))} "
                  f"candidates, overflow {bool(c.overflow)}")  # fmt: skip
        p = 1e-3 * jax.random.normal(jax.random.PRNGKey(0), y.shape)
        bench("broad phase", lambda y: scs.candidates(cloth, s, y), y)
        bench("step filter", lambda y, p: scs.filter_step(cloth, s, cs, y, p)[0], y, p)
        bench(
            "step pairs (within on C)", lambda y, p: sce.within(y, cs.pairs, s.thickness, p), y, p
        )
        step_pairs = jax.jit(lambda y, p: sce.within(y, cs.pairs, s.thickness, p))(y, p)
        bench(f"CCD on the step's {int(jnp.sum(step_pairs.valid))} pairs",
              lambda y, p: sce.step_bound(y, p, step_pairs), y, p)  # fmt: skip
        grad_plain = jax.grad(lambda z: solve._energy(plain, z, theta))
        grad_sc = lambda z: scs.grad(theta, z, pairs, solve._FRICTION_EPS)
        bench("gradient without self-contact", grad_plain, y)
        bench("gradient of the self-contact terms", grad_sc, y)
        bench("HVP without self-contact", lambda y, p: jax.jvp(grad_plain, (y,), (p,))[1], y, p)
        bench("HVP of the self-contact terms", lambda y, p: jax.jvp(grad_sc, (y,), (p,))[1], y, p)
        alphas = jnp.asarray(0.5 ** np.arange(8))
        bench("line search, 8 energies, without",
              lambda y, p: jax.vmap(lambda a: solve._energy(plain, y + a * p, theta))(alphas),
              y, p)  # fmt: skip
        bench("line search, 8 energies, with",
              lambda y, p: jax.lax.map(lambda a: solve._energy(with_sc, y + a * p, theta, pairs),
                                       alphas), y, p)  # fmt: skip
        bench("Hessian without self-contact", lambda y: solve._hessian(plain, y, theta), y)
        bench(
            "Hessian with (diagonal blocks)", lambda y: solve._hessian(with_sc, y, theta, pairs), y
        )
        bench("couplings", lambda y: solve._couplings(with_sc, y, theta, pairs), y)
        hmat = jax.jit(lambda y: solve._hessian(plain, y, theta))(y)
        couplings = jax.jit(lambda y: solve._couplings(with_sc, y, theta, pairs))(y)
        for name, cpl in (
            ("LU without couplings", None),
            ("LU with the pairs' couplings", couplings),
        ):
            ts = []
            for _ in range(3):
                t = time.perf_counter()
                jax.block_until_ready(linsolve.factor(hmat, cloth.neighbors, ~cloth.pinned, cpl))
                ts.append(time.perf_counter() - t)
            print(f"{name:44s} {np.median(ts) * 1e3:9.2f} ms", flush=True)


if __name__ == "__main__":
    main()
