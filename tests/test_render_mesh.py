"""Smooth vertex normals by area-weighted face averaging (Delannoy slide 18), for any mesh."""

import jax.numpy as jnp
import numpy as np

from diffcloth.io.mesh import read_obj, write_obj
from diffcloth.render.mesh import mesh_surface, vertex_normals


def _uv_sphere(n_lat, n_lon, radius=0.7):
    """Closed latitude-longitude sphere: vertices, counter-clockwise (outward) faces."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    t, p = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]]) * radius
    faces = []
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)
    for j in range(n_lon):
        faces.append([0, idx(0, j + 1), idx(0, j)])
        faces.append([len(verts) - 1, idx(n_lat - 2, j), idx(n_lat - 2, j + 1)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j + 1), idx(i + 1, j)
            faces += [[a, b, c], [a, c, d]]
    return verts, np.asarray(faces)


def test_sphere_normals_approach_the_analytic_normals():
    errors = []
    for n in (8, 16, 32):
        verts, faces = _uv_sphere(n, 2 * n)
        fv = verts[faces]
        assert np.all(
            np.sum(np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0]) * fv.mean(1), -1) > 0
        )
        nrm = np.asarray(vertex_normals(jnp.asarray(verts), jnp.asarray(faces)))
        np.testing.assert_allclose(np.linalg.norm(nrm, axis=-1), 1.0, atol=1e-12)
        exact = verts / np.linalg.norm(verts, axis=-1, keepdims=True)
        errors.append(np.max(np.arccos(np.clip(np.sum(nrm * exact, -1), -1, 1))))
    assert errors[-1] < 0.02  # radians (largest error: the pole fans)
    assert errors[0] > errors[1] > errors[2]  # converges as the tessellation refines


def test_flat_mesh_normals_equal_the_face_normal():
    rng = np.random.default_rng(0)
    uv = rng.uniform(-1, 1, (30, 2))
    from scipy.spatial import Delaunay

    faces = Delaunay(uv).simplices
    # a tilted plane; orient faces counter-clockwise in uv, i.e. along +normal
    e1, e2 = np.array([1.0, 0.2, 0.3]), np.array([-0.1, 1.0, 0.5])
    verts = 2.0 + uv[:, :1] * e1 + uv[:, 1:] * e2
    p = uv[faces]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    ccw = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0
    faces = np.where(ccw[:, None], faces, faces[:, ::-1])
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n)
    nrm = np.asarray(vertex_normals(jnp.asarray(verts), jnp.asarray(faces)))
    np.testing.assert_allclose(nrm, np.broadcast_to(n, nrm.shape), atol=1e-12)


def test_area_weighting_and_obj_reader_smooth_option(tmp_path):
    # two triangles at a right angle sharing an edge, areas 1 : 4 -> normal weighted 1 : 4
    verts = np.array([[0.0, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, -4]])
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    nrm = np.asarray(vertex_normals(jnp.asarray(verts), jnp.asarray(faces)))
    want = np.array([0.0, 4.0, 1.0]) / np.sqrt(17.0)  # 1 * (+z, area 1) + 4 * (+y, area 4)
    np.testing.assert_allclose(nrm[0], want, atol=1e-12)
    np.testing.assert_allclose(nrm[2], [0, 0, 1], atol=1e-12)
    path = tmp_path / "m.obj"
    write_obj(path, positions=verts, faces=faces)
    got = read_obj(path, smooth=True)
    np.testing.assert_allclose(got["vertex_normals"], nrm, atol=1e-6)
    assert "vertex_normals" not in read_obj(path)
    surf = mesh_surface(got["positions"], got["faces"], normals=got["vertex_normals"])
    t, b, n = (np.asarray(a) for a in (surf.tangents, surf.bitangents, surf.normals))
    np.testing.assert_allclose(np.sum(t * n, -1), 0, atol=1e-6)
    np.testing.assert_allclose(np.cross(n, t), b, atol=1e-6)
