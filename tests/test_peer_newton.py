"""Independent reference for the mesh cloth (issue 31): NVIDIA Newton (`newton` on PyPI, CPU
through Warp), same mesh, equal parameters, static end states compared.

Parameter mapping (Newton 1.x `ModelBuilder.add_cloth_mesh`, solver `SolverVBD`):

- Membrane. Newton's VBD triangle is a stable neo-Hookean membrane (Smith et al. 2018, per rest
  area) with Lame parameters mu = tri_ke, lambda = tri_ka: psi = mu/2 (I_C - 2) +
  (lambda + mu)/2 (J - 1 - mu/(lambda + mu))^2. Linearised it is mu tr(E^2) + lambda/2 tr(E)^2,
  diffcloth's orthotropic StVK with C11 = C22 = 2 mu + lambda, C12 = lambda, G = mu: so
  tri_ke = shear, tri_ka = poisson * stretch, and the fabric must be isotropic with
  stretch = 2 shear + poisson * stretch. The models part at large strain (neo-Hookean against
  StVK); the cases below stay below 2 % strain.
- Bending. Newton's hinge energy is edge_ke |e| (theta - theta_0)^2 / 2 per interior edge (|e|
  the rest edge length); diffcloth's is the curvature-tensor energy B/2 |k|^2 per area. edge_ke
  is the value at which the mesh rolled into a cylinder (curvature along 0, 45, 90 and 135
  degrees, averaged) stores the same energy in both (`hinge_stiffness`); on these nearly
  equilateral meshes edge_ke = 1.16 B / a (a the edge length, 2 / sqrt(3) B / a). The two
  differ on doubly curved shapes and at the boundary (Newton has no hinge there; diffcloth a
  free-edge condition).
- Mass: both lump density * area / 3 per face corner. Gravity equal. Pins: Newton particles
  with mass 0 and ACTIVE cleared.
- Contact (sphere case): diffcloth's penalty k_c A_i max(0, thickness - phi)^2 / 2 in a 1 mm
  layer; Newton's particle-shape soft contact at the particle radius (1 mm) with its AVBD
  penalty. Both hold vertices within about a millimetre of the surface; frictionless in both
  (the equilibrium solve has none), the cloth's centre vertex pinned on the sphere's top so
  that the static state is unique.

Method: diffcloth's `equilibrium` (static, converged to 1e-3 of each vertex's weight, float64)
against Newton's VBD run as dynamics (float32, small steps, velocities scaled down each step as
an artificial damping that leaves the static state unchanged) until it has settled. Trajectories
are not compared: VBD takes a fixed number of Gauss-Seidel sweeps per step (its step is not a
converged backward-Euler step), so its transient depends on the sweep count while its settled
state does not.
"""

from __future__ import annotations

import numpy as np
import pytest

newton = pytest.importorskip(
    "newton", reason="NVIDIA Newton is not installed (pip install newton; the `bench` extra)"
)
wp = pytest.importorskip("warp")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from diffcloth.physics import mesh as pm  # noqa: E402
from diffcloth.physics.mesh import energy  # noqa: E402

pytestmark = pytest.mark.slow

GRAVITY = (0.0, -9.81, 0.0)


def hinge_stiffness(cloth, fabric, curvature=None) -> float:
    """Newton edge_ke giving diffcloth's bending energy on the cylinder-rolled mesh (module doc)."""
    uv = np.asarray(cloth.uv, np.float64)
    rest = np.asarray(cloth.rest, np.float64)
    k = curvature or 1.0 / (20.0 * float(np.ptp(uv, axis=0).max()))
    hinges = np.asarray(cloth.hinges)
    length = np.linalg.norm(rest[hinges[:, 1]] - rest[hinges[:, 0]], axis=1)
    ratios = []
    for deg in (0.0, 45.0, 90.0, 135.0):
        d = np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])
        s, t = uv @ d, uv @ np.array([-d[1], d[0]])
        x = jnp.asarray(np.stack([np.sin(k * s) / k, (1.0 - np.cos(k * s)) / k, t], axis=1),
                        cloth.rest.dtype)  # fmt: skip
        theta = np.asarray(energy.dihedral_angles(cloth, x), np.float64)
        ratios.append(float(energy.bending_energy(cloth, fabric, x))
                      / (0.5 * np.sum(length * theta**2)))  # fmt: skip
    return float(np.mean(ratios))


def newton_params(cloth, fabric) -> dict:
    stretch = float(fabric.stretch_warp)
    assert float(fabric.stretch_weft) == stretch, "Newton's membrane is isotropic"
    mu, lam = float(fabric.shear), float(fabric.poisson) * stretch
    assert abs(2 * mu + lam - stretch) <= 1e-9 * stretch, "needs stretch = 2 shear + C12"
    return dict(tri_ke=mu, tri_ka=lam, edge_ke=hinge_stiffness(cloth, fabric),
                density=float(fabric.density))  # fmt: skip


def newton_settle(cloth, params, x_start, *, sphere=None, dt=1.0 / 1500.0, iterations=10,
                  steps=1500, keep=0.995, radius=1e-3):  # fmt: skip
    """Newton VBD from x_start until settled; returns (n, 3) float64 positions."""
    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=GRAVITY)
    rest = np.asarray(cloth.rest, np.float64)
    builder.add_cloth_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=[wp.vec3(*map(float, v)) for v in rest],
        indices=np.asarray(cloth.faces, np.int64).reshape(-1).tolist(),
        density=params["density"], tri_ke=params["tri_ke"], tri_ka=params["tri_ka"],
        tri_kd=0.0, edge_ke=params["edge_ke"], edge_kd=0.0, particle_radius=radius,
    )  # fmt: skip
    for i in np.flatnonzero(np.asarray(cloth.pinned)):
        builder.particle_mass[i] = 0.0
        builder.particle_flags[i] = builder.particle_flags[i] & ~newton.ParticleFlags.ACTIVE
    if sphere is not None:
        center, r = sphere
        cfg = newton.ModelBuilder.ShapeConfig(mu=0.0)
        builder.add_shape_sphere(body=-1, xform=wp.transform(wp.vec3(*center), wp.quat_identity()),
                                 radius=r, cfg=cfg)  # fmt: skip
    builder.color(include_bending=True)
    model = builder.finalize(device="cpu")
    model.soft_contact_mu = 0.0
    solver = newton.solvers.SolverVBD(model, iterations=iterations)
    s0, s1, control = model.state(), model.state(), model.control()
    s0.particle_q.assign(np.asarray(x_start, np.float32))
    pipeline = contacts = None
    if sphere is not None:
        pipeline = newton.CollisionPipeline(model)
        contacts = pipeline.contacts()
    for _ in range(steps):
        s0.clear_forces()
        if pipeline is not None:
            pipeline.collide(s0, contacts)
        solver.step(s0, s1, control, contacts, dt)
        s0, s1 = s1, s0
        s0.particle_qd.assign(s0.particle_qd.numpy() * keep)
    return s0.particle_q.numpy().astype(np.float64)


def hanging_square(size, edge):
    """A square in the xy-plane (hanging), its two top corners pinned."""
    mesh = pm.rectangle(size, size, edge)
    v = mesh.vertices
    v = np.stack([v[:, 0], -v[:, 2], np.zeros(len(v))], axis=1)
    mesh = pm.MeshData(v, mesh.faces, mesh.uv, mesh.source)
    top = v[:, 1] >= v[:, 1].max() - 1e-9
    pins = np.zeros(len(v), bool)
    pins[np.argmin(np.where(top, v[:, 0], np.inf))] = True
    pins[np.argmax(np.where(top, v[:, 0], -np.inf))] = True
    return pm.make_cloth(mesh, pinned=pins, dtype=jnp.float64)


def rms_over_size(a, b, size) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))) / size)


@pytest.fixture(autouse=True)
def _x64():
    # rank promotion allowed: solve._newton adds (n, 1, 1) * (3, 3) (solve.py, `mu * mass` times
    # the identity; hessian.py's was fixed in 46f1bdc); remove once that is explicit too
    with jax.enable_x64(True), jax.numpy_rank_promotion("allow"):
        yield


def test_hanging_from_two_corners_matches_newton():
    """A 0.2 m square (332 vertices) hanging from its two top corners settles to the same shape
    in both engines: RMS vertex distance below 0.5 % of the side, the lowest point within 1 mm
    (measured: 0.09 % and 0.13 mm, largest vertex distance 0.5 mm).

    Tolerance: the two models agree to first order in the strain (membrane) and exactly on
    cylindrical bending; what is left is the membrane's nonlinearity near the pinned corners
    (up to ~0.6 % strain there), the boundary hinges Newton does not have, float32 in Newton and
    the residual of VBD's fixed sweep count. That last one dominates unless VBD's step is small:
    with 10 sweeps per step, its settled state over-stretches by an amount that grows with the
    step (RMS 1.1 % of the side at h = 1/600 s, 2.4 % at 1/200 s with 40 sweeps, 0.09 % at
    1/1500 s), so the reference runs at h = 1/1500 s.
    """
    size = 0.2
    cloth = hanging_square(size, 0.0125)
    fabric = pm.make_fabric(density=0.2, stretch=200.0, shear=100.0, poisson=0.0, bend=2e-5,
                            damping=0.0, dtype=jnp.float64)  # fmt: skip
    x0 = np.asarray(cloth.rest).copy()
    # the same small out-of-plane seed in both (the flat hanging sheet is a symmetric state)
    x0[:, 2] += 1e-3 * np.sin(np.pi * (x0[:, 0] + size / 2) / size) * (size / 2 - x0[:, 1]) / size
    res = pm.equilibrium(cloth, fabric, jnp.asarray(x0), gravity=jnp.asarray(GRAVITY),
                         x_pins=cloth.rest)  # fmt: skip
    assert bool(res.converged)
    x_dc = np.asarray(res.x)
    x_nt = newton_settle(cloth, newton_params(cloth, fabric), x0)
    print(
        f"hanging: rms/size {rms_over_size(x_dc, x_nt, size):.4f}, lowest point "
        f"{x_dc[:, 1].min():.5f} vs {x_nt[:, 1].min():.5f} m"
    )
    assert rms_over_size(x_dc, x_nt, size) < 0.005
    assert abs(x_dc[:, 1].min() - x_nt[:, 1].min()) < 1e-3


def test_draping_a_sphere_matches_newton():
    """A 0.3 x 0.05 m strip (about 290 vertices) laid flat over a 0.06 m sphere, its centre
    vertex pinned on the sphere's top, settles to the same drape in both engines: RMS vertex
    distance below 1 % of the length, the ends' height within 2 mm.

    A strip, not a square: a square over a sphere must fold (it cannot wrap a doubly curved
    surface), and where its folds form is a bifurcation each solver resolves its own way (a
    0.2 m square over this sphere settled 6 % of its side apart, RMS, in fold placement, not in
    the drape's overall shape). A strip wraps the sphere along its length without folding, so
    its static state is unique.

    Tolerance: besides the hanging case's differences, the contact models differ (diffcloth's
    penalty layer of 1 mm against Newton's particle radius of 1 mm and its own penalty), which
    moves the vertices on the sphere by up to about a millimetre, and the strip's hanging ends
    depend on where it leaves the sphere, which that offset shifts.
    """
    length, width, radius = 0.3, 0.05, 0.06
    mesh = pm.rectangle(length, width, 0.008, center=(0.0, radius + 1e-3, 0.0))
    v = mesh.vertices
    centre = int(np.argmin(np.hypot(v[:, 0], v[:, 2])))
    mesh = pm.MeshData(v - np.array([v[centre, 0], 0.0, v[centre, 2]]), mesh.faces, mesh.uv,
                       mesh.source)  # fmt: skip
    cloth = pm.make_cloth(mesh, pinned=[centre], dtype=jnp.float64)
    fabric = pm.make_fabric(density=0.2, stretch=200.0, shear=100.0, poisson=0.0, bend=2e-5,
                            damping=0.0, dtype=jnp.float64)  # fmt: skip
    cols = pm.make_mesh_colliders(spheres=[((0.0, 0.0, 0.0), radius)], thickness=1e-3,
                                  dtype=jnp.float64)  # fmt: skip
    x0 = np.asarray(cloth.rest).copy()
    x0[:, 1] -= 1e-3 * (x0[:, 0] / length) ** 2  # a slight downward seed at the ends
    res = pm.equilibrium(cloth, fabric, jnp.asarray(x0), gravity=jnp.asarray(GRAVITY),
                         colliders=cols, x_pins=cloth.rest)  # fmt: skip
    assert bool(res.converged)
    x_dc = np.asarray(res.x)
    x_nt = newton_settle(cloth, newton_params(cloth, fabric), x0, sphere=((0.0, 0.0, 0.0), radius))
    ends = np.abs(x0[:, 0]) >= 0.5 * length - 1e-9
    print(
        f"sphere: rms/length {rms_over_size(x_dc, x_nt, length):.4f}, ends' height "
        f"{x_dc[ends, 1].mean():.5f} vs {x_nt[ends, 1].mean():.5f} m, max distance "
        f"{np.abs(x_dc - x_nt).max():.5f} m, lowest phi "
        f"{(np.linalg.norm(x_dc, axis=1) - radius).min():.5f} vs "
        f"{(np.linalg.norm(x_nt, axis=1) - radius).min():.5f} m"
    )
    assert rms_over_size(x_dc, x_nt, length) < 0.01
    assert abs(x_dc[ends, 1].mean() - x_nt[ends, 1].mean()) < 2e-3
