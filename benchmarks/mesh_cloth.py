"""Mesh cloth (issue 31): the drape test's equilibrium and its fabric gradient, and one implicit
step of a 10,000-vertex mesh.

    python benchmarks/mesh_cloth.py                       # float64 and float32, all cases
    python benchmarks/mesh_cloth.py --dtype float64 --quick
    python benchmarks/mesh_cloth.py --out benchmarks/results/mesh_cloth.jsonl   # appends

One JSON line per figure after the "meta" line (`_timing.meta`, plus the git commit and the CPU
model). Every line carries utc, commit, cpu, cores, load_1min (at that figure), dtype,
n_vertices and max_rss_mb (the process's peak resident memory when the line was written).

Cases
  drape          a Cusick drape test: disc(0.15, 0.0055, rings_at=(0.09,)) (about 2,700
                 vertices), pinned within r <= 0.09 m, resting on a capped-cylinder pedestal
                 (radius 0.09 m, top 1 mm below the sheet: the contact layer), fabric preset
                 "wang2011-gray-interlock", equilibrium from a flat sheet with a seeded 6-lobe
                 fold perturbation (amplitude 2 mm at the rim); `equilibrium_s` warm (median),
                 Newton iterations, converged, residual, drape coefficient. Aim: < 2 s.
  drape_grad     jax.value_and_grad of the mean rim height of that equilibrium with respect to
                 every Fabric field (the Fabric pytree): forward solve + implicit-function-theorem
                 adjoint, warm (median), `grad_s`. Aim: < 2 s.
  (--starts K)   with the drape case: the equilibrium from K seeded fold starts (lobes and
                 phase of STARTS), each timed once, and their median ("mesh_drape_starts").
  implicit_step  one `implicit_step` (h = 1/60 s) of a 10,000-vertex hanging square
                 (rectangle(0.5, 0.5, h) hung in the xy-plane, top edge pinned; the first step
                 from rest), warm (median), `step_ms`, and Newton iterations.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # benchmarks/_timing.py

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _timing import emit, timed  # noqa: E402
from _timing import meta as _meta_line  # noqa: E402

from diffcloth.physics import mesh as pm  # noqa: E402
from diffcloth.physics.mesh import linsolve  # noqa: E402
from diffcloth.physics.state import ClothState  # noqa: E402

GRAVITY = (0.0, -9.81, 0.0)
R, PEDESTAL, EDGE = 0.15, 0.09, 0.0055
PRESET = "wang2011-gray-interlock"
THICKNESS = 1e-3  # m, contact layer


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, text=True,
                             capture_output=True, check=True)  # fmt: skip
        # (the results files this script appends to do not count as a change of the code)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--",
                                ".", ":!results"],
                               cwd=HERE, text=True, capture_output=True).stdout.strip()  # fmt: skip
        return out.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def max_rss_mb() -> float | None:
    """The process's peak resident memory so far, MB (None where `resource` is missing)."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)


def common(dtype: str, n: int) -> dict:
    return dict(
        utc=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        commit=git_commit(),
        cpu=cpu_model(),
        cores=os.cpu_count(),
        load_1min=round(os.getloadavg()[0], 2),
        dtype=dtype,
        n_vertices=n,
        sparse_solver=linsolve.backend(),
    )


# ------------------------------------------------------------------------------------ scenes


#: the seeded fold starts of `--starts K`: (lobes, phase in rad); the first is the default start
STARTS = ((6, 0.3), (5, 1.1), (7, 2.0), (4, 0.7), (8, 2.6))


def drape_scene(dtype, edge=EDGE, start=STARTS[0]):
    """(cloth, fabric, x_start, colliders, r) of the Cusick drape benchmark (edge: target edge
    length of the disc, m; start: the seeded fold's (lobes, phase))."""
    mesh = pm.disc(R, edge, rings_at=(PEDESTAL,))
    r = np.hypot(mesh.vertices[:, 0], mesh.vertices[:, 2])
    cloth = pm.make_cloth(mesh, pinned=r <= PEDESTAL + 1e-9, dtype=dtype)
    fabric = pm.make_fabric(PRESET, dtype=dtype)
    # seeded fold: 6 lobes (by default), 2 mm at the rim, growing quadratically from the
    # pedestal edge
    phi = np.arctan2(mesh.vertices[:, 2], mesh.vertices[:, 0])
    s = np.clip((r - PEDESTAL) / (R - PEDESTAL), 0.0, None)
    x0 = mesh.vertices.copy()
    lobes, phase = start
    x0[:, 1] += 2e-3 * s**2 * np.cos(lobes * phi + phase)
    cols = pm.make_mesh_colliders(
        cylinders=[((0.0, -THICKNESS, 0.0), PEDESTAL, 0.3)], thickness=THICKNESS, dtype=dtype
    )
    return cloth, fabric, jnp.asarray(x0, dtype), cols, r


def drape_coefficient(x, r_flat) -> float:
    """Projected-area drape coefficient from the vertex positions' outer radius per angle
    (a polar-binned estimate: 72 bins of the largest horizontal radius)."""
    x = np.asarray(x, np.float64)
    rho = np.hypot(x[:, 0], x[:, 2])
    ang = np.arctan2(x[:, 2], x[:, 0])
    bins = np.floor((ang + np.pi) / (2 * np.pi) * 72).astype(int) % 72
    outer = np.zeros(72)
    np.maximum.at(outer, bins, rho)
    area = 0.5 * np.sum(outer**2) * (2 * np.pi / 72)
    a_ped, a_disc = np.pi * PEDESTAL**2, np.pi * R**2
    return float((area - a_ped) / (a_disc - a_ped))


def hanging_scene(dtype, edge):
    """A 0.5 m square hanging in the xy-plane (rectangle rotated up), top edge pinned."""
    mesh = pm.rectangle(0.5, 0.5, edge)
    v = mesh.vertices.copy()
    v = np.stack([v[:, 0], -v[:, 2], np.zeros(len(v))], axis=1)  # xz -> xy, +z (uv v) -> +y
    mesh = pm.MeshData(v, mesh.faces, mesh.uv, mesh.source)
    cloth = pm.make_cloth(mesh, pinned="top_edge", dtype=dtype)
    return cloth, pm.make_fabric(PRESET, dtype=dtype)


# ------------------------------------------------------------------------------------- cases


def bench_drape_starts(dtype, starts, out, max_iters=None, edge=EDGE):
    """The equilibrium from `starts` seeded fold starts (STARTS[:starts]), each timed once warm
    (one compiled solve): the Newton step count, and so the time, moves with the start and with
    float32 rounding, so one start's figure is one draw of a spread. One line, "mesh_drape_starts":
    per-start seconds, iterations, drape coefficients, and their median."""
    cloth, fabric, _, cols, r = drape_scene(dtype, edge)
    g = jnp.asarray(GRAVITY, dtype)
    st = pm.SolverSettings() if max_iters is None else pm.SolverSettings(max_iters=max_iters)
    solve = jax.jit(lambda f, x: pm.equilibrium(cloth, f, x, gravity=g, colliders=cols,
                                                settings=st))  # fmt: skip
    xs = [drape_scene(dtype, edge, start)[2] for start in STARTS[:starts]]
    jax.block_until_ready(solve(fabric, xs[0]))
    secs, its, conv, dcs = [], [], [], []
    for x in xs:
        t0 = time.perf_counter()
        res = jax.block_until_ready(solve(fabric, x))
        secs.append(round(time.perf_counter() - t0, 4))
        its.append(int(res.iterations))
        conv.append(bool(res.converged))
        dcs.append(round(drape_coefficient(res.x, r), 4))
    row = dict(bench="mesh_drape_starts", **common(str(np.dtype(dtype)), cloth.num_vertices),
               starts=[list(s) for s in STARTS[:starts]], equilibrium_s=secs,
               median_s=round(float(np.median(secs)), 4), iterations=its, converged=conv,
               drape_coefficient=dcs, max_iters=st.max_iters, max_rss_mb=max_rss_mb(),
               aim_s=2.0, met=all(conv) and float(np.median(secs)) < 2.0)  # fmt: skip
    emit(row, out)


def bench_drape(dtype, repeats, out, max_iters=None, edge=EDGE):
    cloth, fabric, x0, cols, r = drape_scene(dtype, edge)
    g = jnp.asarray(GRAVITY, dtype)
    st = pm.SolverSettings() if max_iters is None else pm.SolverSettings(max_iters=max_iters)
    solve = jax.jit(lambda f: pm.equilibrium(cloth, f, x0, gravity=g, colliders=cols,
                                             settings=st))  # fmt: skip
    t0 = time.perf_counter()
    res = jax.block_until_ready(solve(fabric))
    first = time.perf_counter() - t0
    t = timed(solve, fabric, repeats=repeats, warmup=0)
    row = dict(bench="mesh_drape", **common(str(np.dtype(dtype)), cloth.num_vertices),
               n_faces=cloth.num_faces, preset=PRESET, equilibrium_s=round(t.median, 4),
               equilibrium_min_s=round(t.min, 4), first_call_s=round(first, 2),
               iterations=int(res.iterations), max_iters=st.max_iters,
               krylov_iters=st.krylov_iters, line_search=getattr(st, "line_search", 1),
               mu_update=getattr(st, "mu_update", "fixed"),
               refactor_every=getattr(st, "refactor_every", 1), max_rss_mb=max_rss_mb(),
               per_iteration_ms=round(t.median / max(int(res.iterations), 1) * 1e3, 1),
               converged=bool(res.converged),
               residual=float(res.residual), drape_coefficient=round(drape_coefficient(res.x, r), 4),
               aim_s=2.0, met=bool(res.converged) and t.median < 2.0)  # fmt: skip
    emit(row, out)

    rim = jnp.asarray(r > R - 1e-6)

    def loss(f):
        x = pm.equilibrium(cloth, f, x0, gravity=g, colliders=cols, settings=st).x
        return jnp.sum(jnp.where(rim, x[:, 1], 0.0)) / jnp.sum(rim)

    vg = jax.jit(jax.value_and_grad(loss))
    t0 = time.perf_counter()
    val, grad = jax.block_until_ready(vg(fabric))
    first = time.perf_counter() - t0
    t = timed(vg, fabric, repeats=repeats, warmup=0)
    finite = all(bool(jnp.isfinite(v)) for v in jax.tree_util.tree_leaves(grad))
    row = dict(bench="mesh_drape_grad", **common(str(np.dtype(dtype)), cloth.num_vertices),
               loss="mean rim height (m)", loss_value=float(val), fields=len(pm.FABRIC_FIELDS),
               grad_s=round(t.median, 4), grad_min_s=round(t.min, 4),
               forward_s=row["equilibrium_s"], converged=row["converged"],
               iterations=row["iterations"], first_call_s=round(first, 2), finite=finite,
               grad={k: float(getattr(grad, k)) for k in pm.FABRIC_FIELDS},
               max_rss_mb=max_rss_mb(),
               aim_s=2.0, met=finite and row["converged"] and t.median < 2.0)  # fmt: skip
    emit(row, out)


def implicit_step_fn(cloth, fabric, dtype, h=1.0 / 60.0):
    g = jnp.asarray(GRAVITY, dtype)
    state = ClothState(x=cloth.rest, v=jnp.zeros_like(cloth.rest))
    step = jax.jit(lambda f, s: pm.implicit_step(cloth, f, s, h, gravity=g))
    return step, state


def bench_step(dtype, repeats, out, edge=0.0054):
    cloth, fabric = hanging_scene(dtype, edge)
    step, state = implicit_step_fn(cloth, fabric, dtype)
    t0 = time.perf_counter()
    s1 = jax.block_until_ready(step(fabric, state))
    first = time.perf_counter() - t0
    t = timed(step, fabric, state, repeats=repeats, warmup=0)
    sag = float(jnp.max(state.x[:, 1] - s1.x[:, 1]))
    row = dict(bench="mesh_implicit_step", **common(str(np.dtype(dtype)), cloth.num_vertices),
               n_faces=cloth.num_faces, scene="hanging square 0.5 m, top edge pinned, h=1/60 s",
               step_ms=t.median_ms, step_min_ms=t.min_ms, first_call_s=round(first, 2),
               finite=bool(jnp.all(jnp.isfinite(s1.x))), max_drop_m=sag,
               max_rss_mb=max_rss_mb())  # fmt: skip
    emit(row, out)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dtype", choices=["float32", "float64", "both"], default="both")
    parser.add_argument("--cases", default="drape,step")
    parser.add_argument("--quick", action="store_true", help="3 repeats instead of 5")
    parser.add_argument("--repeats", type=int, help="timed calls per figure (after one untimed)")
    parser.add_argument(
        "--max-iters",
        type=int,
        help="cap the drape's Newton iterations (default:"
        " SolverSettings' 200); a capped solve reports converged false",
    )
    parser.add_argument("--edge", type=float, default=EDGE,
                        help=f"the drape disc's edge length, m (default {EDGE}: about 2,800 vertices; "
                        "0.011: about 700)")  # fmt: skip
    parser.add_argument("--starts", type=int, default=0,
                        help=f"also time the drape from this many seeded fold starts (at most "
                        f"{len(STARTS)}), one line with their spread")  # fmt: skip
    parser.add_argument("--out", help="append the JSON lines to this file")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    out = open(args.out, "a") if args.out else None  # noqa: SIM115
    emit(_meta_line("mesh_cloth", commit=git_commit(), cpu=cpu_model()), out)
    repeats = args.repeats or (3 if args.quick else 5)
    dtypes = ["float64", "float32"] if args.dtype == "both" else [args.dtype]
    cases = args.cases.split(",")
    for dt in dtypes:
        dtype = jnp.dtype(dt)
        if "drape" in cases:
            bench_drape(dtype, repeats, out, args.max_iters, args.edge)
            if args.starts:
                bench_drape_starts(dtype, min(args.starts, len(STARTS)), out, args.max_iters,
                                   args.edge)  # fmt: skip
        if "step" in cases:
            bench_step(dtype, repeats, out)
    if out:
        out.close()


if __name__ == "__main__":
    main()
