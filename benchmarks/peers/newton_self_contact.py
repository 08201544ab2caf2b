"""The price of self-contact in one implicit step, diffcloth against NVIDIA Newton's VBD cloth
solver, in the same run: each engine's step with its self-contact handling on and off.

    python benchmarks/peers/newton_self_contact.py                 # 2,667 vertices, float64
    python benchmarks/peers/newton_self_contact.py --edge 0.0054   # 10,206 vertices
    python benchmarks/peers/newton_self_contact.py --out benchmarks/results/newton_self_contact.jsonl

The scene of benchmarks/peers/newton_cloth.py (a 0.5 m square of a 500 N/m membrane hanging
from its top edge, one step of 1/60 s from rest, equal parameters): no pair of the sheet comes
within the contact thickness, so each ratio is what the engine pays for looking. diffcloth:
`implicit_step(..., self_contact=make_self_contact(thickness))` (broad phase, barrier, CCD step
filter, thickness min(2 mm, 0.4 x the shortest rest triangle height)); Newton:
`SolverVBD(particle_enable_self_contact=True, particle_self_contact_margin=thickness,
particle_self_contact_gap=thickness)` (interaction distance: the thickness; query radius: twice
it) at `--iterations` Gauss-Seidel sweeps (default 10,
Newton's examples). Calls alternate between the four programs for `--rounds` rounds (after one
untimed call each); medians. One JSON line "peers_newton_self_contact".
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # benchmarks/_timing.py, benchmarks/mesh_cloth.py
sys.path.insert(0, str(HERE))  # newton_cloth.py

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mesh_cloth  # noqa: E402
import newton_cloth as nc  # noqa: E402
import numpy as np  # noqa: E402
from _timing import emit  # noqa: E402

from diffcloth.physics import mesh as pm  # noqa: E402
from diffcloth.physics.mesh.selfcontact import make_self_contact, min_rest_height  # noqa: E402
from diffcloth.physics.state import ClothState  # noqa: E402


class VBD:
    """One VBD step from rest into a fresh output state, self-contact on or off."""

    def __init__(self, model, iterations: int, thickness: float | None):
        import newton

        kw = {}
        if thickness is not None:
            kw = dict(particle_enable_self_contact=True, particle_self_contact_margin=thickness,
                      particle_self_contact_gap=thickness)  # fmt: skip
        self.solver = newton.solvers.SolverVBD(model, iterations=iterations, **kw)
        self.s0, self.s1, self.control = model.state(), model.state(), model.control()

    def __call__(self):
        import warp as wp

        self.s0.clear_forces()
        self.solver.step(self.s0, self.s1, self.control, None, nc.H)
        wp.synchronize()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--edge", type=float, default=0.011, help="target edge length, m")
    ap.add_argument("--iterations", type=int, default=10, help="VBD sweeps")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    ap.add_argument("--out", help="append the JSON lines to this file")
    args = ap.parse_args(argv)
    out = nc.start_session("newton_self_contact", args.out)
    dtype = jnp.dtype(args.dtype)
    cloth, _ = mesh_cloth.hanging_scene(dtype, args.edge)
    fabric = pm.make_fabric(mesh_cloth.PRESET, stretch=500.0, shear=250.0, poisson=0.0,
                            damping=0.0, friction=0.0, dtype=dtype)  # fmt: skip
    thickness = min(2e-3, 0.4 * min_rest_height(cloth))
    sc = make_self_contact(thickness, cloth=cloth, dtype=dtype)
    g = jnp.asarray(nc.GRAVITY, dtype)
    state = ClothState(x=cloth.rest, v=jnp.zeros_like(cloth.rest))
    dc = {
        on: jax.jit(lambda s, on=on: pm.implicit_step(cloth, fabric, s, nc.H, gravity=g,
                                                      self_contact=sc if on else None).x)
        for on in (False, True)
    }  # fmt: skip
    model = nc.newton_model(np.asarray(cloth.rest), np.asarray(cloth.faces),
                            np.asarray(cloth.pinned), nc.newton_params(cloth, fabric))  # fmt: skip
    vbd = {on: VBD(model, args.iterations, thickness if on else None) for on in (False, True)}
    progs = {("diffcloth", on): (lambda on=on: jax.block_until_ready(dc[on](state)))
             for on in (False, True)}  # fmt: skip
    progs.update({("newton", on): vbd[on] for on in (False, True)})
    for fn in progs.values():  # compile / load kernels
        fn()
    load0 = os.getloadavg()[0]
    times = {k: [] for k in progs}
    for r in range(args.rounds):
        keys = list(progs) if r % 2 == 0 else list(progs)[::-1]
        for k in keys:
            t = time.perf_counter()
            progs[k]()
            times[k].append(time.perf_counter() - t)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    emit(dict(bench="peers_newton_self_contact", **mesh_cloth.common(args.dtype, cloth.num_vertices),
              n_faces=cloth.num_faces, load_1min_start=round(load0, 2), thickness_m=thickness,
              scene="hanging square 0.5 m, top edge pinned, one step h=1/60 s from rest, no pair "
              "within the thickness", rounds=args.rounds, newton_iterations=args.iterations,
              diffcloth_off_ms=round(med["diffcloth", False], 2),
              diffcloth_on_ms=round(med["diffcloth", True], 2),
              diffcloth_ratio=round(med["diffcloth", True] / med["diffcloth", False], 3),
              newton_off_ms=round(med["newton", False], 2),
              newton_on_ms=round(med["newton", True], 2),
              newton_ratio=round(med["newton", True] / med["newton", False], 3),
              on_ratio=round(med["diffcloth", True] / med["newton", True], 3)), out)  # fmt: skip
    if out:
        out.close()


if __name__ == "__main__":
    main()
