"""An independent Provot mass-spring cloth in NVIDIA Warp kernels (no diffcloth code inside).

The reference engine of the harness: it generates target footage for the cross-engine benchmark
and checks diffcloth's `physics.massspring` model. Only numpy and warp are imported.

    from benchmarks.peers.warp_massspring import simulate
    xs = simulate(8, 8, (0.5, 0.5), {"k_struct": 400.0, "height": 0.6},
                  sphere=((0.0, 0.3, 0.0), 0.15), dt=1 / 2400, substeps=40, frames=60)
    xs.shape   # (61, 8, 8, 3): the initial state, then the end of every frame

    python benchmarks/peers/warp_massspring.py            # a drape demo, prints one JSON line

Model (every choice is discussed in docs/physics.md, beside diffcloth's own models):
- A flat rows x cols grid of point masses, columns along +x, rows along +z (plane "xz", horizontal)
  or rows downwards along -y (plane "xy", vertical, row 0 on top), centred at
  (0, height, 0) + center (as diffcloth's `grid_net`). Node (i, j) sits at
  x = -w/2 + j w/(cols-1), z (or -y) = -h/2 + i h/(rows-1).
- Masses: "uniform" (every node density * w * h / (rows cols)) or "area" (each cell gives a quarter
  of its area to each corner; node mass = density * that area).
- Springs, each with its own stiffness k (N/m) and dashpot d (N s/m) per class:
  structural (i, j)-(i, j+1), (i, j)-(i+1, j); shear (i, j)-(i+1, j+1), (i, j+1)-(i+1, j);
  flexion (i, j)-(i, j+2), (i, j)-(i+2, j). Rest length = rest distance. The force on node a of
  spring (a, b), with e = x_b - x_a, L = |e|, n = e / L, is (k (L - L0) + d (v_b - v_a).n) n;
  b gets the opposite. A spring of zero length gives no force. Border springs are not scaled.
- Air: f = -air_damping (v - wind) on every node (N s/m per node). Gravity m g.
- Substep (semi-implicit Euler, dt = one substep): f(x, v) -> v += dt f / m -> x += dt v (free
  nodes) -> pinned nodes back to their rest position with v = 0 -> contacts, spheres first (in
  order) then planes. Contact with sphere (c, r): if |x - c| < r + thickness, x is projected to
  c + (r + thickness) n, n = (x - c)/|x - c| (+y at the centre); plane (n, o): if
  x.n - o - thickness < 0, x moves along n onto it. Velocity ("coulomb" rule): if v.n < 0 the
  normal part is removed and the tangential part v_t shrinks by friction * |v.n|, to zero at
  most (Coulomb, velocity level). The "displacement" rule first sets v = (x_projected - x_prev)/dt
  (x_prev: position before the drift), then applies the same rule.

Parameters (`params` dict; all optional, defaults in DEFAULTS). The model's names and defaults
are those of diffcloth's `[material] model = "provot"` and `[sim]` keys (docs/config.md), so a
config's values can be passed through unchanged:
  k_struct, k_shear, k_flex    spring stiffness, N/m
  d_struct, d_shear, d_flex    dashpot along each spring, N s/m
  air_damping                  linear air damping per node, N s/m
  density                      areal density, kg/m^2 (total mass = density * w * h)
  mass_lumping                 "uniform" | "area"
  friction                     Coulomb coefficient against spheres and planes
  friction_rule                "coulomb" | "displacement"
  contact_thickness            m, added to every sphere radius and plane offset
  gravity, wind                (3,) m/s^2 and m/s
  height                       y of the net's centre, m
  center                       (3,) extra offset of the net's centre, m
  plane                        "xz" (horizontal) | "xy" (vertical, hanging)
  pins                         None | "none" | "top_row" | "top_corners" | "all" | (row, col) pairs
  velocity                     (3,) initial velocity of every free node, m/s
  planes                       list of ((nx, ny, nz), offset) half-spaces x.n >= offset
"""

import json
import math
import sys
import time

import numpy as np
import warp as wp

DEFAULTS = {
    "k_struct": 400.0,
    "k_shear": 100.0,
    "k_flex": 20.0,
    "d_struct": 0.05,
    "d_shear": 0.02,
    "d_flex": 0.005,
    "air_damping": 0.002,
    "density": 0.2,
    "mass_lumping": "uniform",
    "friction": 0.3,
    "friction_rule": "coulomb",
    "contact_thickness": 0.005,
    "gravity": (0.0, -9.81, 0.0),
    "wind": (0.0, 0.0, 0.0),
    "height": 0.0,
    "center": (0.0, 0.0, 0.0),
    "plane": "xz",
    "pins": None,
    "velocity": (0.0, 0.0, 0.0),
    "planes": (),
}

# neighbour offsets (di, dj) and spring class (0 structural, 1 shear, 2 flexion); both directions
# of every spring are listed so each node gathers its own force (no atomics: deterministic sums)
_OFFSETS = (
    (0, 1, 0), (0, -1, 0), (1, 0, 0), (-1, 0, 0),
    (1, 1, 1), (-1, -1, 1), (1, -1, 1), (-1, 1, 1),
    (0, 2, 2), (0, -2, 2), (2, 0, 2), (-2, 0, 2),
)  # fmt: skip

_KERNELS: dict = {}


def _kernels(scalar):
    """Force and update kernels for one scalar type (wp.float32 or wp.float64), cached."""
    if scalar in _KERNELS:
        return _KERNELS[scalar]
    vec3 = wp.types.vector(3, scalar)

    @wp.kernel(module="unique")
    def forces(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        x0: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        offsets: wp.array(dtype=wp.vec3i),
        k: wp.array(dtype=scalar),
        d: wp.array(dtype=scalar),
        air: scalar,
        gravity: vec3,
        wind: vec3,
        rows: int,
        cols: int,
        f: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        r = i // cols
        c = i - r * cols
        xi = x[i]
        vi = v[i]
        acc = mass[i] * gravity - air * (vi - wind)
        for s in range(12):
            o = offsets[s]
            rr = r + o[0]
            cc = c + o[1]
            if rr >= 0 and rr < rows and cc >= 0 and cc < cols:
                j = rr * cols + cc
                e = x[j] - xi
                sq = wp.dot(e, e)
                if sq > scalar(0.0):
                    length = wp.sqrt(sq)
                    n = e / length
                    rest = wp.length(x0[j] - x0[i])
                    cls = o[2]
                    mag = k[cls] * (length - rest) + d[cls] * wp.dot(v[j] - vi, n)
                    acc = acc + mag * n
        f[i] = acc

    @wp.kernel(module="unique")
    def update(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        f: wp.array(dtype=vec3),
        x0: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        free: wp.array(dtype=int),
        centers: wp.array(dtype=vec3),
        radii: wp.array(dtype=scalar),
        normals: wp.array(dtype=vec3),
        offsets: wp.array(dtype=scalar),
        h: scalar,
        mu: scalar,
        thickness: scalar,
        displacement_rule: int,
        x_out: wp.array(dtype=vec3),
        v_out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        if free[i] == 0:
            x_out[i] = x0[i]
            v_out[i] = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
            return
        xp = x[i]
        v1 = v[i] + h * f[i] / mass[i]
        x1 = xp + h * v1
        for s in range(centers.shape[0]):
            e = x1 - centers[s]
            dist = wp.length(e)
            rad = radii[s] + thickness
            if dist < rad:
                n = vec3(scalar(0.0), scalar(1.0), scalar(0.0))
                if dist > scalar(0.0):
                    n = e / dist
                x1 = centers[s] + rad * n
                if displacement_rule == 1:
                    v1 = (x1 - xp) / h
                un = wp.dot(v1, n)
                if un < scalar(0.0):
                    vt = v1 - un * n
                    lt = wp.length(vt)
                    scale = scalar(0.0)
                    if lt > scalar(0.0):
                        scale = wp.max(scalar(1.0) - mu * (-un) / lt, scalar(0.0))
                    v1 = vt * scale
        for s in range(normals.shape[0]):
            n = normals[s]
            sd = wp.dot(x1, n) - offsets[s] - thickness
            if sd < scalar(0.0):
                x1 = x1 - sd * n
                if displacement_rule == 1:
                    v1 = (x1 - xp) / h
                un = wp.dot(v1, n)
                if un < scalar(0.0):
                    vt = v1 - un * n
                    lt = wp.length(vt)
                    scale = scalar(0.0)
                    if lt > scalar(0.0):
                        scale = wp.max(scalar(1.0) - mu * (-un) / lt, scalar(0.0))
                    v1 = vt * scale
        x_out[i] = x1
        v_out[i] = v1

    _KERNELS[scalar] = (forces, update, vec3)
    return _KERNELS[scalar]


def rest_grid(rows, cols, size, *, height=0.0, center=(0.0, 0.0, 0.0), plane="xz"):
    """(rows, cols, 3) float64 rest positions of the flat net (see the module docstring)."""
    width, depth = (float(s) for s in size)
    u = np.linspace(-width / 2, width / 2, cols)
    w = np.linspace(-depth / 2, depth / 2, rows)
    uu, ww = np.meshgrid(u, w)
    zero = np.zeros_like(uu)
    if plane == "xz":
        g = np.stack([uu, zero, ww], -1)
    elif plane == "xy":
        g = np.stack([uu, -ww, zero], -1)
    else:
        raise ValueError(f"plane: must be 'xz' or 'xy', got {plane!r}")
    return g + np.asarray(center, np.float64) + np.array([0.0, float(height), 0.0])


def pin_mask(pins, rows, cols):
    """(rows, cols) bool mask from None, a preset name or (row, col) pairs."""
    m = np.zeros((rows, cols), bool)
    if pins is None or (isinstance(pins, str) and pins == "none"):
        return m
    if isinstance(pins, str):
        presets = {"top_row": (0, slice(None)), "all": (slice(None), slice(None))}
        if pins == "top_corners":
            m[0, 0] = m[0, -1] = True
        elif pins in presets:
            m[presets[pins]] = True
        else:
            raise ValueError(f"pins: unknown preset {pins!r}")
        return m
    for r, c in pins:
        m[int(r), int(c)] = True
    return m


def node_masses(rows, cols, size, density, lumping):
    """(rows, cols) node masses in kg for a regular grid."""
    width, depth = (float(s) for s in size)
    if lumping == "uniform":
        return np.full((rows, cols), density * width * depth / (rows * cols))
    if lumping != "area":
        raise ValueError(f"mass_lumping: must be 'uniform' or 'area', got {lumping!r}")
    cell = density * width / (cols - 1) * depth / (rows - 1) / 4.0
    m = np.zeros((rows, cols))
    m[:-1, :-1] += cell
    m[1:, :-1] += cell
    m[:-1, 1:] += cell
    m[1:, 1:] += cell
    return m


def _spheres(sphere):
    if sphere is None:
        return np.zeros((0, 3)), np.zeros(0)
    if len(sphere) == 2 and np.ndim(sphere[1]) == 0:
        sphere = [sphere]
    centers = np.array([np.asarray(s[0], np.float64) for s in sphere]).reshape(-1, 3)
    radii = np.array([float(s[1]) for s in sphere])
    return centers, radii


def simulate(
    rows: int,
    cols: int,
    size=(1.0, 1.0),
    params: dict | None = None,
    sphere=None,
    dt: float = 1.0 / 2400.0,
    substeps: int = 40,
    frames: int = 60,
    dtype=np.float64,
    device: str = "cpu",
) -> np.ndarray:
    """Simulate the Provot cloth; return positions (frames + 1, rows, cols, 3) as numpy.

    Args:
      rows, cols: grid nodes (>= 2 each; flexion springs exist where 3 nodes fit).
      size: (width along the columns, depth along the rows) in m.
      params: see the module docstring (unknown keys raise).
      sphere: None, ((cx, cy, cz), radius) or a list of them (static spheres), m.
      dt: substep length in s (1/2400 default).
      substeps: substeps per recorded frame.
      frames: recorded frames; entry 0 is the initial state, entry k the end of frame k.
      dtype: np.float64 or np.float32 (all kernel arithmetic in that precision).
      device: Warp device ("cpu" or "cuda:0").
    """
    p = dict(DEFAULTS)
    unknown = set(params or {}) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"params: unknown key(s) {sorted(unknown)}; allowed: {sorted(DEFAULTS)}")
    p.update(params or {})
    if p["friction_rule"] not in ("coulomb", "displacement"):
        raise ValueError(
            f"friction_rule: must be 'coulomb' or 'displacement', got {p['friction_rule']!r}"
        )
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt: must be > 0, got {dt}")
    scalar = {np.dtype(np.float64): wp.float64, np.dtype(np.float32): wp.float32}[np.dtype(dtype)]
    np_dt = np.dtype(dtype)
    wp.config.quiet = True
    wp.init()
    forces, update, vec3 = _kernels(scalar)
    n = rows * cols

    x0 = rest_grid(
        rows, cols, size, height=p["height"], center=p["center"], plane=p["plane"]
    ).reshape(n, 3)
    mass = node_masses(rows, cols, size, p["density"], p["mass_lumping"]).ravel()
    free = (~pin_mask(p["pins"], rows, cols)).ravel().astype(np.int32)
    v0 = np.where(free[:, None] == 1, np.asarray(p["velocity"], np.float64)[None], 0.0)
    centers, radii = _spheres(sphere)
    planes = list(p["planes"])
    normals = np.array([np.asarray(q[0], np.float64) for q in planes]).reshape(-1, 3)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    poffs = np.array([float(q[1]) for q in planes])

    def arr(a, t):
        return wp.array(np.ascontiguousarray(np.asarray(a, np_dt)), dtype=t, device=device)

    xs = [arr(x0, vec3), wp.zeros(n, dtype=vec3, device=device)]
    vs = [arr(v0, vec3), wp.zeros(n, dtype=vec3, device=device)]
    f = wp.zeros(n, dtype=vec3, device=device)
    rest = arr(x0, vec3)
    m = arr(mass, scalar)
    fr = wp.array(free, dtype=int, device=device)
    offs = wp.array(np.array(_OFFSETS, np.int32), dtype=wp.vec3i, device=device)
    k = arr([p["k_struct"], p["k_shear"], p["k_flex"]], scalar)
    d = arr([p["d_struct"], p["d_shear"], p["d_flex"]], scalar)
    cen, rad = arr(centers, vec3), arr(radii, scalar)
    nrm, off = arr(normals, vec3), arr(poffs, scalar)
    s = lambda val: scalar(float(val))
    v3 = lambda val: vec3(*[scalar(float(c)) for c in val])
    rule = 1 if p["friction_rule"] == "displacement" else 0

    # two recorded launch pairs (state buffers 0 -> 1 and 1 -> 0): no argument packing per substep
    cmds = []
    for a in (0, 1):
        b = 1 - a
        cmds.append(
            (
                wp.launch(
                    forces,
                    n,
                    inputs=[xs[a], vs[a], rest, m, offs, k, d, s(p["air_damping"]),
                            v3(p["gravity"]), v3(p["wind"]), rows, cols, f],
                    device=device,
                    record_cmd=True,
                ),
                wp.launch(
                    update,
                    n,
                    inputs=[xs[a], vs[a], f, rest, m, fr, cen, rad, nrm, off, s(dt),
                            s(p["friction"]), s(p["contact_thickness"]), rule, xs[b], vs[b]],
                    device=device,
                    record_cmd=True,
                ),
            )
        )  # fmt: skip
    out = np.empty((frames + 1, n, 3), np_dt)
    out[0] = x0
    cur = 0
    for frame in range(frames):
        for _ in range(substeps):
            for cmd in cmds[cur]:
                cmd.launch()
            cur = 1 - cur
        out[frame + 1] = xs[cur].numpy()
    return out.reshape(frames + 1, rows, cols, 3)


def main(argv=None):
    """A drape demo: 16 x 16 net, 0.6 m, dropped from 0.45 m onto a 0.2 m sphere, 1 s."""
    t = time.perf_counter()
    xs = simulate(
        16,
        16,
        (0.6, 0.6),
        {"height": 0.45},
        sphere=((0.0, 0.2, 0.0), 0.2),
        substeps=40,
        frames=60,
    )
    print(
        json.dumps(
            dict(
                bench="warp_massspring_demo",
                net="16x16",
                frames=60,
                seconds=round(time.perf_counter() - t, 3),
                lowest_y=float(xs[-1][..., 1].min()),
                finite=bool(np.isfinite(xs).all()),
            )
        )
    )


if __name__ == "__main__":
    main(sys.argv[1:])
