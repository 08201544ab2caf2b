"""diffcloth's mesh cloth vs NVIDIA Newton (VBD, CPU through Warp): one implicit step of the same
10,000-vertex triangle mesh, side by side in one process, turn about.

    python benchmarks/peers/newton_cloth.py
    python benchmarks/peers/newton_cloth.py --quick
    python benchmarks/peers/newton_cloth.py --out benchmarks/results/newton_cloth.jsonl   # appends

The scene is `benchmarks/mesh_cloth.py`'s implicit-step case: a 0.5 m square
(`rectangle(0.5, 0.5, 0.0054)`, 10,206 vertices, nearly equilateral) hanging in the xy-plane
with its top edge pinned, one backward-Euler step of h = 1/60 s from rest. Both engines get the
same vertices, faces, pins, areal density and gravity, and equal material parameters
(`newton_params`, derived in docs/performance.md and tests/test_peer_newton.py):

  membrane  Newton's VBD triangle is a stable neo-Hookean membrane with Lame parameters
            mu = tri_ke, lambda = tri_ka (per rest area); linearised it is
            psi = mu tr(E^2) + lambda / 2 tr(E)^2, which is diffcloth's StVK with
            stretch = 2 mu + lambda, shear = mu, poisson = lambda / (2 mu + lambda). The fabric is
            therefore isotropic here: stretch 500 N/m, shear 250 N/m, poisson 0 ->
            tri_ke = 250, tri_ka = 0.
  bending   Newton's hinge energy is edge_ke |e| (theta - theta0)^2 / 2 per interior edge;
            edge_ke is set so that the mesh bent into a cylinder (curvature along 0, 45, 90 and
            135 degrees, averaged) stores diffcloth's bending energy (`hinge_stiffness`).
  damping   none in either (Newton tri_kd = edge_kd = 0; diffcloth damping = 0).

Newton solver: `SolverVBD` (vertex block descent, Chen et al. 2024). It is Newton's cloth solver
that minimises the same backward-Euler incremental potential as diffcloth's `implicit_step`
(the others are explicit: SemiImplicit, XPBD; or a projective-dynamics scheme with its own
anisotropic model: Style3D), so per step it does the same job. It runs a fixed number of
Gauss-Seidel sweeps (`iterations`, default 10, what Newton's cloth examples use) instead of a
convergence test; diffcloth's Newton-Krylov stops at a force residual of 1e-3 of each vertex's
weight. Each line reports, besides the times, how far each engine's step lands from a tightly
converged step of its own model (VBD: 1,000 iterations; diffcloth: tol 1e-7), in m, and how
far VBD's step lands from diffcloth's converged one (the two models agree to first order).

Keys: diffcloth_step_ms, newton_step_ms (medians over alternating rounds, each a blocked call of
one step), step_ratio = diffcloth / Newton (below 1: diffcloth faster), newton_iterations,
diffcloth_err_m / newton_err_m (max vertex distance to the converged step of one step from
rest), newton_to_diffcloth_m (VBD's step to diffcloth's converged one), drop_m / newton_drop_m
(largest displacement in diffcloth's converged / VBD's step, for scale), load_1min before and
after, dtype (diffcloth's; Newton is float32 only). Lines before 2026-11-28T18:45Z measured
newton_err_m after the timed calls, when VBD's input state had moved: too large.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # benchmarks/_timing.py, benchmarks/mesh_cloth.py

import mesh_cloth  # noqa: E402
from _timing import emit  # noqa: E402
from _timing import meta as _meta_line  # noqa: E402

from diffcloth.physics import mesh as pm  # noqa: E402
from diffcloth.physics.mesh import energy  # noqa: E402
from diffcloth.physics.state import ClothState  # noqa: E402

H = 1.0 / 60.0
GRAVITY = (0.0, -9.81, 0.0)


def hinge_stiffness(cloth, fabric, curvature: float | None = None) -> float:
    """Newton's edge_ke (N m / m = N) that stores diffcloth's bending energy when the flat mesh
    is rolled into a cylinder: sum_e edge_ke |e| theta_e^2 / 2 = E_bend(diffcloth), averaged over
    four bending directions (0, 45, 90, 135 degrees in the material plane). Isometric rolling,
    small curvature (1 / (20 size) by default), so only bending energy is stored."""
    uv = np.asarray(cloth.uv, np.float64)
    rest = np.asarray(cloth.rest, np.float64)
    # the flat mesh's in-plane frame: the rest positions are an isometry of uv; build the
    # cylinder in uv coordinates (x, y) with the height along z (rigid motion does not matter)
    size = float(np.ptp(uv, axis=0).max())
    k = curvature or 1.0 / (20.0 * size)
    hinges = np.asarray(cloth.hinges)
    length = np.linalg.norm(rest[hinges[:, 1]] - rest[hinges[:, 0]], axis=1)
    ratios = []
    for deg in (0.0, 45.0, 90.0, 135.0):
        d = np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])
        p = np.array([-d[1], d[0]])
        s, t = uv @ d, uv @ p
        x = np.stack([np.sin(k * s) / k, t, (1.0 - np.cos(k * s)) / k], axis=1)
        x = x[:, [0, 2, 1]]  # any isometry; keep it a 3D embedding
        xj = jnp.asarray(x, cloth.rest.dtype)
        e_dc = float(energy.bending_energy(cloth, fabric, xj))
        theta = np.asarray(energy.dihedral_angles(cloth, xj), np.float64)
        ratios.append(e_dc / (0.5 * np.sum(length * theta**2)))
    return float(np.mean(ratios))


def newton_params(cloth, fabric) -> dict:
    """Newton add_cloth_mesh parameters equal to an isotropic diffcloth fabric (see module doc)."""
    stretch = 0.5 * (float(fabric.stretch_warp) + float(fabric.stretch_weft))
    lam = float(fabric.poisson) * stretch
    mu = float(fabric.shear)
    if abs(2 * mu + lam - stretch) > 1e-6 * stretch:
        raise ValueError(
            f"Newton's membrane is isotropic neo-Hookean: needs stretch = 2 shear + poisson "
            f"stretch, got stretch {stretch}, shear {mu}, poisson {float(fabric.poisson)}"
        )
    return dict(tri_ke=mu, tri_ka=lam, tri_kd=0.0, edge_ke=hinge_stiffness(cloth, fabric),
                edge_kd=0.0, density=float(fabric.density))  # fmt: skip


def newton_model(vertices, faces, pinned, params, *, colliders=(), particle_radius=1e-3,
                 contact_ke=1e4, contact_mu=0.0, gravity=GRAVITY):  # fmt: skip
    """A finalized Newton model (y up) of the cloth; pinned particles get mass 0 and are
    inactive. colliders: ("sphere", center, radius) or ("plane", ...) tuples (static shapes)."""
    import newton
    import warp as wp

    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=tuple(map(float, gravity)))
    builder.add_cloth_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=[wp.vec3(*map(float, v)) for v in vertices],
        indices=np.asarray(faces, np.int64).reshape(-1).tolist(),
        density=params["density"], tri_ke=params["tri_ke"], tri_ka=params["tri_ka"],
        tri_kd=params["tri_kd"], edge_ke=params["edge_ke"], edge_kd=params["edge_kd"],
        particle_radius=particle_radius,
    )  # fmt: skip
    for i in np.flatnonzero(np.asarray(pinned)):
        builder.particle_mass[i] = 0.0
        builder.particle_flags[i] = builder.particle_flags[i] & ~newton.ParticleFlags.ACTIVE
    for kind, *args in colliders:
        cfg = newton.ModelBuilder.ShapeConfig(mu=contact_mu)
        if kind == "sphere":
            center, radius = args
            builder.add_shape_sphere(body=-1, xform=wp.transform(wp.vec3(*center),
                                     wp.quat_identity()), radius=radius, cfg=cfg)  # fmt: skip
        else:
            raise ValueError(kind)
    builder.color(include_bending=True)
    model = builder.finalize(device="cpu")
    model.soft_contact_ke = contact_ke
    model.soft_contact_kd = 0.0
    model.soft_contact_mu = contact_mu
    return model


class NewtonStepper:
    """One VBD step from a fixed start state into a fresh output state (no contacts)."""

    def __init__(self, model, iterations: int):
        import newton

        self.model = model
        self.solver = newton.solvers.SolverVBD(model, iterations=iterations)
        self.s0 = model.state()
        self.s1 = model.state()
        self.control = model.control()

    def __call__(self):
        self.s0.clear_forces()
        self.solver.step(self.s0, self.s1, self.control, None, H)
        import warp as wp

        wp.synchronize()
        return self.s1

    def x(self):
        return self.s1.particle_q.numpy().astype(np.float64)


def start_session(script: str, out_path):
    """x64 on, Warp quiet, the meta line (Newton, Warp, commit, CPU) emitted; returns the
    JSON-lines file opened for appending (None: stdout only)."""
    jax.config.update("jax_enable_x64", True)
    import newton
    import warp as wp

    wp.config.quiet = True
    out = open(out_path, "a") if out_path else None  # noqa: SIM115
    emit(_meta_line(script, newton=newton.__version__, warp=wp.__version__,
                    commit=mesh_cloth.git_commit(), cpu=mesh_cloth.cpu_model(),
                    sparse_solver=mesh_cloth.linsolve.backend()), out)  # fmt: skip
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="5 rounds instead of 9")
    parser.add_argument("--edge", type=float, default=0.0054, help="target edge length, m")
    parser.add_argument("--iterations", default="10", help="VBD iterations, comma-separated")
    parser.add_argument("--dtype", choices=["float32", "float64", "both"], default="both")
    parser.add_argument("--out", help="append the JSON lines to this file")
    args = parser.parse_args(argv)
    out = start_session("newton_cloth", args.out)
    rounds = 5 if args.quick else 9
    dtypes = ["float64", "float32"] if args.dtype == "both" else [args.dtype]

    cloth64, _ = mesh_cloth.hanging_scene(jnp.float64, args.edge)
    fabric64 = pm.make_fabric(mesh_cloth.PRESET, stretch=500.0, shear=250.0, poisson=0.0,
                              damping=0.0, friction=0.0, dtype=jnp.float64)  # fmt: skip
    params = newton_params(cloth64, fabric64)
    model = newton_model(np.asarray(cloth64.rest), np.asarray(cloth64.faces),
                         np.asarray(cloth64.pinned), params)  # fmt: skip
    ref_stepper = NewtonStepper(model, 1000)
    ref_stepper()
    x_newton_ref = ref_stepper.x()
    g64 = jnp.asarray(GRAVITY, jnp.float64)
    s64 = ClothState(x=cloth64.rest, v=jnp.zeros_like(cloth64.rest))
    tight = pm.SolverSettings(max_iters=100, tol=1e-7)
    x_dc_ref = np.asarray(pm.implicit_step(cloth64, fabric64, s64, H, gravity=g64,
                                           settings=tight).x)  # fmt: skip
    x_start = np.asarray(cloth64.rest)
    drop = float(np.max(np.linalg.norm(x_dc_ref - x_start, axis=1)))
    gap = float(np.max(np.linalg.norm(x_dc_ref - x_newton_ref, axis=1)))

    for dt_name in dtypes:
        dtype = jnp.dtype(dt_name)
        cloth, _ = mesh_cloth.hanging_scene(dtype, args.edge)
        fabric = pm.make_fabric(mesh_cloth.PRESET, stretch=500.0, shear=250.0, poisson=0.0,
                                damping=0.0, friction=0.0, dtype=dtype)  # fmt: skip
        step, state = mesh_cloth.implicit_step_fn(cloth, fabric, dtype, H)
        x_dc = np.asarray(jax.block_until_ready(step(fabric, state)).x, np.float64)
        for iters in [int(i) for i in args.iterations.split(",")]:
            stepper = NewtonStepper(model, iters)
            stepper()  # warm-up: Warp kernel compilation / module load
            load0 = os.getloadavg()[0]
            t_dc, t_nt = [], []
            for r in range(rounds):  # turn about, alternating who goes first
                order = ("dc", "nt") if r % 2 == 0 else ("nt", "dc")
                for who in order:
                    t = time.perf_counter()
                    if who == "dc":
                        jax.block_until_ready(step(fabric, state))
                        t_dc.append(time.perf_counter() - t)
                    else:
                        stepper()
                        t_nt.append(time.perf_counter() - t)
            # the error of ONE step from the start: a fresh stepper (VBD's step updates its input
            # state, so the timed stepper's repeated calls do not all start from rest)
            fresh = NewtonStepper(model, iters)
            fresh()
            x_nt = fresh.x()
            dc_ms = statistics.median(t_dc) * 1e3
            nt_ms = statistics.median(t_nt) * 1e3
            emit(dict(bench="peers_newton_step", **mesh_cloth.common(dt_name, cloth.num_vertices),
                      n_faces=cloth.num_faces, load_1min_start=round(load0, 2),
                      scene="hanging square 0.5 m, top edge pinned, one step h=1/60 s from rest",
                      newton_solver="SolverVBD", newton_iterations=iters, rounds=rounds,
                      diffcloth_step_ms=round(dc_ms, 2), newton_step_ms=round(nt_ms, 2),
                      diffcloth_min_ms=round(min(t_dc) * 1e3, 2),
                      newton_min_ms=round(min(t_nt) * 1e3, 2),
                      step_ratio=round(dc_ms / nt_ms, 3),
                      diffcloth_err_m=float(np.max(np.linalg.norm(x_dc - x_dc_ref, axis=1))),
                      newton_err_m=float(np.max(np.linalg.norm(x_nt - x_newton_ref, axis=1))),
                      newton_to_diffcloth_m=float(np.max(np.linalg.norm(x_nt - x_dc_ref, axis=1))),
                      newton_drop_m=float(np.max(np.linalg.norm(x_nt - x_start, axis=1))),
                      converged_gap_m=gap, drop_m=drop, newton_params=params),
                 out)  # fmt: skip
    if out:
        out.close()


if __name__ == "__main__":
    main()
