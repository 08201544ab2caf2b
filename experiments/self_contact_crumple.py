"""The crumple scenes of issue 34's acceptance (self-contact of the mesh cloth), run frame by
frame with every frame checked by the independent numpy triangle-triangle intersection test
(tests/tri_intersections.py):

  square  a square sheet hanging by one corner (flat, its diagonal vertical, slightly waved),
          lowest corner 4 mm above a floor, released: it falls and piles onto itself;
  disc    a horizontal disc with its rim pinned, the pins moved inward to half the radius over
          the first 2/3 of the run (then held): gravity and the shrinking rim push it into folds.

float64, implicit Euler at dt = 1/60 s (a frame whose step does not converge is rerun from its
start as 2, then 4 steps of dt / 2, dt / 4), "wang2011-gray-interlock", thickness min(2 mm,
0.4 x the shortest rest triangle height), tol 1e-2 (--tol), max_iters 300. Writes
results/self_contact_crumple/<scene>.json (per frame: converged, Newton iterations, residual,
pairs in contact, intersecting triangle pairs, seconds; substeps where more than one) and
<scene>.png (six frames). Stops at the first frame that does not converge in 4 steps.

    python experiments/self_contact_crumple.py square --size 0.5 --edge 0.0107 --seconds 3
    python experiments/self_contact_crumple.py disc --size 0.15 --edge 0.0057 --seconds 3
    python experiments/self_contact_crumple.py square --size 0.25 --seconds 0.5 --tol 0.05
    python experiments/self_contact_crumple.py square --max-wall 3600 --resume   # in parts
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from self_contact_strip_iters import step_with_stats  # noqa: E402
from tri_intersections import intersecting_pairs  # noqa: E402

from diffcloth.physics.mesh import (  # noqa: E402
    SolverSettings,
    disc,
    make_cloth,
    make_fabric,
    make_mesh_colliders,
    rectangle,
)
from diffcloth.physics.mesh import selfcontact as sc  # noqa: E402

DT = 1 / 60


def square_scene(size, edge):
    """(cloth, x0, floor, pin_path=None)."""
    cloth = make_cloth(rectangle(size, size, edge))
    r = np.asarray(cloth.rest)
    u, v = r[:, 0] - r[:, 0].mean(), r[:, 2] - r[:, 2].mean()
    a, b = (u + v) / np.sqrt(2), (u - v) / np.sqrt(2)  # a: along the vertical diagonal
    x = np.stack([b, a - a.min() + 0.004, 0.01 * size * np.sin(14 * a / size)], 1)
    floor = make_mesh_colliders(planes=[((0, 1, 0), 0.0)])
    return cloth, x, floor, None


def disc_scene(radius, edge, seconds):
    mesh = disc(radius, edge)
    r = np.asarray(mesh.vertices)
    rad = np.hypot(r[:, 0], r[:, 2])
    rim = rad >= radius * (1 - 1e-6)
    cloth = make_cloth(mesh, pinned=rim)
    x = np.asarray(cloth.rest).copy()
    x[:, 1] = 0.3
    t_in = 2.0 * seconds / 3.0

    def pins(t):  # rim radius scale at time t
        return 1.0 - 0.5 * min(t / t_in, 1.0)

    return cloth, x, None, pins


def _first_substeps(rows, settle=10):
    """The steps a frame is tried with first: as many as the last frame needed (a failed try
    costs max_iters iterations), half as many once the last `settle` frames all needed that."""
    prev = [r.get("substeps", 1) for r in rows[-settle:]]
    if not prev:
        return 1
    if len(prev) == settle and len(set(prev)) == 1:
        return max(prev[-1] // 2, 1)
    return prev[-1]


def crumple(
    scene,
    size,
    edge,
    seconds,
    capacity=24,
    log=print,
    every=1,
    max_wall=None,
    tol=1e-2,
    self_contact=True,
    step_fraction=0.5,
    state=None,
    substeps=(1, 2, 4),
):
    """Run a scene; returns (cloth, frames (list of (n, 3) arrays, every `every` frames and the
    last), rows (per-frame dicts), info); stops at the first frame that does not converge, or
    after the frame that ends past max_wall seconds of wall time. self_contact False: the same
    solve without it (the baseline of its Newton iterations). state: an .npz path written after
    every frame (positions, velocities, the rows and kept frames so far) and, where it exists,
    resumed from (a long run spread over several calls; the steps are deterministic). substeps:
    the implicit steps a frame is tried with, in turn, until one converges (a frame whose one
    step of dt does not converge is rerun from its start as 2, then 4 steps)."""
    if scene == "square":
        cloth, x0, colliders, pins = square_scene(size, edge)
    else:
        cloth, x0, colliders, pins = disc_scene(size, edge, seconds)
    fabric = make_fabric("wang2011-gray-interlock")
    thickness = min(2e-3, 0.4 * sc.min_rest_height(cloth))
    s = None
    if self_contact:
        s = sc.make_self_contact(
            thickness, cloth=cloth, capacity=capacity, step_fraction=step_fraction
        )
    settings = SolverSettings(max_iters=300, tol=tol)
    pinned = np.asarray(cloth.pinned)
    rest = np.asarray(cloth.rest)
    with jax.numpy_rank_promotion("allow"):
        step = jax.jit(lambda x, v, h: step_with_stats(cloth, fabric, x, v, h, colliders, s,
                                                       settings))  # fmt: skip
        x, v = jnp.asarray(x0), jnp.zeros(x0.shape)
        faces = np.asarray(cloth.faces)
        frames, rows, ids = [np.asarray(x)], [], [0]
        nframes = int(round(seconds / DT))
        if state is not None and Path(state).exists():
            saved = np.load(state)
            x, v = jnp.asarray(saved["x"]), jnp.asarray(saved["v"])
            frames, ids = list(saved["frames"]), [int(i) for i in saved["ids"]]
            rows = json.loads(str(saved["rows"]))
            log(f"resumed from {state} after frame {len(rows)}")
        start = time.perf_counter()

        def advance(x, v, k, n):
            """Frame k as n implicit steps of DT / n: (x, v, converged, Newton iterations,
            residual, pairs, intersecting pairs at the substeps' ends before the last)."""
            its, between = 0, 0
            for j in range(n):
                if pins is not None:  # the rim pins' next positions (kept by the step)
                    t1 = (k + (j + 1) / n) * DT
                    xn = np.asarray(x).copy()
                    xn[pinned, 0] = rest[pinned, 0] * pins(t1)
                    xn[pinned, 2] = rest[pinned, 2] * pins(t1)
                    x = jnp.asarray(xn)
                x, v, conv, it, res, cnt = jax.block_until_ready(step(x, v, DT / n))
                its += int(it)
                if not bool(conv):
                    break
                if j < n - 1:
                    between = max(between, len(intersecting_pairs(np.asarray(x), faces)))
            return x, v, conv, its, res, cnt, between

        for k in range(len(rows), nframes):
            t0 = time.perf_counter()
            failed = []  # a frame whose step does not converge is rerun as 2, then 4 steps
            first = _first_substeps(rows)
            for n in [m for m in substeps if m >= first] or substeps[-1:]:
                xs, vs, conv, it, res, cnt, between = advance(x, v, k, n)
                if bool(conv):
                    break
                failed.append(dict(substeps=n, iterations=it, residual=float(res)))
            x, v = xs, vs
            sec = time.perf_counter() - t0
            xa = np.asarray(x)
            finite = bool(np.all(np.isfinite(xa)))
            bad = intersecting_pairs(xa, faces) if finite else np.zeros((0, 2))
            row = dict(frame=k + 1, t=round((k + 1) * DT, 4), converged=bool(conv),
                       iterations=int(it), residual=float(res), pairs=int(cnt),
                       intersecting=int(len(bad)), seconds=round(sec, 2))  # fmt: skip
            if n > 1:
                row.update(substeps=n, intersecting_substeps=between, failed=failed)
            rows.append(row)
            log(json.dumps(row))
            if (k + 1) % every == 0 or k + 1 == nframes or not bool(conv):
                frames.append(xa)
                ids.append(k + 1)
            if state is not None and bool(conv) and finite:
                keep = frames if ids[-1] == k + 1 else [*frames, xa]
                np.savez(state, x=xa, v=np.asarray(v), frames=np.stack(keep),
                         ids=np.asarray(ids if ids[-1] == k + 1 else [*ids, k + 1]),
                         rows=json.dumps(rows))  # fmt: skip
            if not bool(conv) or not finite:
                break
            if max_wall is not None and time.perf_counter() - start > max_wall:
                if (k + 1) % every:
                    frames.append(xa)
                    ids.append(k + 1)
                log(f"stopped after frame {k + 1}: past --max-wall {max_wall} s")
                break
    return cloth, frames, rows, dict(frame_ids=ids, thickness_m=thickness, capacity=capacity,
                                     n_vertices=int(cloth.num_vertices),
                                     n_faces=int(cloth.num_faces))  # fmt: skip


def _png(path, cloth, frames, ids, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    faces = np.asarray(cloth.faces)
    pick = np.unique(np.linspace(0, len(frames) - 1, 6).round().astype(int))
    allx = np.concatenate([frames[i] for i in pick])
    lo, hi = allx.min(axis=0), allx.max(axis=0)
    fig = plt.figure(figsize=(3.2 * len(pick), 3.4))
    for j, i in enumerate(pick):
        ax = fig.add_subplot(1, len(pick), j + 1, projection="3d")
        tri = frames[i][faces][:, :, [0, 2, 1]]  # y up
        ax.add_collection3d(Poly3DCollection(tri, facecolor="#8fb3d9", edgecolor="#20406080",
                                             linewidth=0.1))  # fmt: skip
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[2], hi[2])
        ax.set_zlim(lo[1], hi[1])
        ax.set_box_aspect(np.maximum(hi - lo, 1e-3)[[0, 2, 1]])
        ax.set_title(f"{title} t = {ids[i] * DT:.2f} s", fontsize=8)
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", choices=["square", "disc"])
    ap.add_argument("--size", type=float, default=None, help="m: square side / disc radius")
    ap.add_argument("--edge", type=float, default=None, help="m: rest edge length")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--capacity", type=int, default=24)
    ap.add_argument("--every", type=int, default=1, help="keep every this many frames for the png")
    ap.add_argument(
        "--max-wall",
        type=float,
        default=None,
        help="s: stop after the frame that ends past this wall time (outputs kept)",
    )
    ap.add_argument(
        "--tol",
        type=float,
        default=1e-2,
        help="Newton tolerance: the largest free-vertex force residual over its weight",
    )
    ap.add_argument(
        "--step-fraction",
        type=float,
        default=0.5,
        help="SelfContact.step_fraction: a Newton step's cap, in mean rest edges",
    )
    ap.add_argument(
        "--no-self-contact",
        action="store_true",
        help="the same scene and solve without self-contact (its Newton iterations' baseline)",
    )
    ap.add_argument(
        "--resume",
        action="store_true",
        help="continue from <out>/<scene tag>.state.npz (written after every converged frame) "
        "where it exists, appending to the log: a long run over several calls",
    )
    ap.add_argument("--out", default=str(ROOT / "results" / "self_contact_crumple"))
    args = ap.parse_args(argv)
    size = args.size or (0.5 if args.scene == "square" else 0.15)
    edge = args.edge or (0.0107 if args.scene == "square" else 0.0057)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = f"{args.scene}_{int(round(size * 1000))}mm_e{edge * 1000:.1f}mm_{args.seconds:g}s"
    if args.tol != 1e-2:
        tag += f"_tol{args.tol:g}"
    if args.no_self_contact:
        tag += "_no_self_contact"
    if args.step_fraction != 0.5:
        tag += f"_sf{args.step_fraction:g}"
    state = out / f"{tag}.state.npz"
    if not args.resume:
        state.unlink(missing_ok=True)
    log_file = open(out / f"{tag}.log", "a" if args.resume else "w")  # noqa: SIM115

    def log(line):
        print(line, flush=True)
        log_file.write(line + "\n")
        log_file.flush()

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    t0 = time.perf_counter()
    cloth, frames, rows, info = crumple(
        args.scene,
        size,
        edge,
        args.seconds,
        args.capacity,
        log,
        args.every,
        args.max_wall,
        args.tol,
        not args.no_self_contact,
        args.step_fraction,
        state,
    )
    ids = info.pop("frame_ids")
    summary = dict(scene=args.scene, size_m=size, edge_m=edge, seconds=args.seconds,
                   frames_run=len(rows), frames_planned=int(round(args.seconds / DT)),
                   all_converged=all(r["converged"] for r in rows),
                   intersecting_frames=sum(r["intersecting"] > 0 for r in rows),
                   max_iterations=max(r["iterations"] for r in rows),
                   mean_iterations=float(np.mean([r["iterations"] for r in rows])),
                   max_pairs=max(r["pairs"] for r in rows), wall_s=round(time.perf_counter() - t0),
                   step_seconds=round(sum(r["seconds"] for r in rows), 1),
                   commit=commit, load_1min=os.getloadavg()[0], **info)  # fmt: skip
    log(json.dumps(summary))
    (out / f"{tag}.json").write_text(json.dumps(dict(summary=summary, frames=rows), indent=1))
    _png(out / f"{tag}.png", cloth, frames, ids, args.scene)


if __name__ == "__main__":
    main()
