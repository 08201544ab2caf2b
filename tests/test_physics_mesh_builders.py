"""Mesh cloth builders: disc, rectangle (holes), grid square, OBJ reading and mesh checks."""

import math

import numpy as np
import pytest

from diffcloth.io.mesh import write_obj
from diffcloth.physics.mesh.builders import (
    MeshData,
    MeshError,
    check_mesh,
    disc,
    grid_square,
    mesh_quality,
    read_cloth_obj,
    rectangle,
)
from diffcloth.physics.net import grid_net

R = 0.15  # m, the drape-test specimen
PEDESTAL = 0.09  # m


def _normals(m: MeshData) -> np.ndarray:
    p = m.vertices[m.faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def _uv_area(m: MeshData) -> np.ndarray:
    p = m.uv[m.faces]
    a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


def _boundary_edges(faces: np.ndarray) -> np.ndarray:
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    key, count = np.unique(np.sort(half, axis=1), axis=0, return_counts=True)
    return key[count == 1]


def _edge_set(faces: np.ndarray) -> set:
    half = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    return {tuple(e) for e in np.sort(half, axis=1).tolist()}


# ------------------------------------------------------------------------------------------------
# disc


@pytest.mark.parametrize("h", [0.0108, 0.0055, 0.00285])
def test_disc_quality_area_and_boundary(h):
    m = disc(R, h, rings_at=(PEDESTAL,))
    q = mesh_quality(m)
    assert m.vertices.dtype == np.float64 and m.uv.dtype == np.float64
    assert m.faces.dtype == np.int32 and m.faces.shape[1] == 3
    assert q["min_angle"] >= 30.0
    assert 0.5 * h <= q["min_edge"] and q["max_edge"] <= 1.6 * h
    check_mesh(m.vertices, m.faces, m.source)
    # The boundary is a closed polygon with every vertex exactly on the circle.
    rim = np.unique(_boundary_edges(m.faces))
    assert np.allclose(np.linalg.norm(m.vertices[rim][:, [0, 2]], axis=1), R, rtol=0, atol=1e-14)
    # The triangulated area is the inscribed polygon's area, close to pi R^2.
    k = rim.size
    assert q["area"] == pytest.approx(0.5 * k * R**2 * math.sin(2 * math.pi / k), rel=1e-12)
    assert q["area"] == pytest.approx(math.pi * R**2, rel=2e-3)


def test_disc_vertex_counts_span_700_to_10000():
    counts = [disc(R, h).vertices.shape[0] for h in (0.0108, 0.00285)]
    assert 700 <= counts[0] < 800
    assert 9_000 < counts[1] <= 10_500


def test_disc_rings_at_resolves_the_pedestal_edge():
    h = 0.008
    m = disc(R, h, rings_at=(PEDESTAL, 0.04), center=(0.2, 0.5, -0.1))
    d = m.vertices - (0.2, 0.5, -0.1)
    r = np.linalg.norm(d[:, [0, 2]], axis=1)
    edges = _edge_set(m.faces)
    for radius in (PEDESTAL, 0.04):
        on = np.flatnonzero(np.abs(r - radius) < 1e-13)
        assert on.size >= round(2 * math.pi * radius / h) - 1
        # Neighbours in angle along the ring are joined by mesh edges: the circle is resolved.
        ring = on[np.argsort(np.arctan2(d[on, 2], d[on, 0]))]
        for a, b in zip(ring, np.roll(ring, -1), strict=True):
            assert (min(a, b), max(a, b)) in edges


def test_disc_orientation_and_uv_convention():
    c = (0.3, 0.7, -0.2)
    m = disc(R, 0.01, center=c)
    n = _normals(m)
    assert np.all(n[:, 1] > 0) and np.allclose(n[:, [0, 2]], 0)
    assert np.allclose(m.vertices[:, 1], 0.7)
    assert np.allclose(m.uv, np.stack([m.vertices[:, 0] - c[0], -(m.vertices[:, 2] - c[2])], 1))
    assert np.all(_uv_area(m) > 0)  # u x v along the normal


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(radius=0.15, edge_length=0.1), "edge_length"),
        (dict(radius=-1.0, edge_length=0.01), "radius"),
        (dict(radius=0.15, edge_length=0.01, rings_at=(0.2,)), r"rings_at\[0\]"),
        (dict(radius=0.15, edge_length=0.01, rings_at=(0.09, 0.092)), "apart"),
    ],
)
def test_disc_bad_input(kwargs, match):
    with pytest.raises(MeshError, match=match):
        disc(**kwargs)


# ------------------------------------------------------------------------------------------------
# rectangle


def test_rectangle_plain():
    h = 0.02
    m = rectangle(0.6, 0.4, h, center=(0.0, 1.0, 0.0))
    q = mesh_quality(m)
    assert q["area"] == pytest.approx(0.24, rel=1e-12)
    assert q["min_angle"] >= 30.0
    assert 0.45 * h <= q["min_edge"] and q["max_edge"] <= 1.6 * h
    assert np.all(_normals(m)[:, 1] > 0) and np.all(_uv_area(m) > 0)
    assert np.allclose(m.uv, m.vertices[:, [0, 2]] * (1, -1))
    x, z = m.vertices[:, 0], m.vertices[:, 2]
    for value, coord in ((-0.3, x), (0.3, x), (-0.2, z), (0.2, z)):  # corners and border exact
        assert np.sum(np.abs(coord - value) < 1e-15) >= 10


def test_rectangle_with_holes():
    h = 0.01
    holes = [(0.1, 0.05, 0.06), (-0.15, -0.05, 0.045)]
    c = np.array([0.5, 0.2, 0.1])
    m = rectangle(0.6, 0.4, h, holes=holes, center=c)
    q = mesh_quality(m)
    check_mesh(m.vertices, m.faces, m.source)
    hole_area = sum(math.pi * r**2 for *_, r in holes)
    # Inscribed polygons: a little less than the circles removed.
    assert 0.24 - hole_area <= q["area"] <= 0.24 - 0.97 * hole_area
    assert q["min_angle"] >= 25.0
    assert 0.4 * h <= q["min_edge"] and q["max_edge"] <= 1.7 * h
    assert np.all(_normals(m)[:, 1] > 0) and np.all(_uv_area(m) > 0)
    local = m.vertices[:, [0, 2]] - c[[0, 2]]
    assert np.allclose(m.uv, local * (1, -1))
    # Every boundary vertex is on the outer border or exactly on one hole's circle.
    rim = np.unique(_boundary_edges(m.faces))
    on_border = np.isclose(np.abs(local[rim, 0]), 0.3) | np.isclose(np.abs(local[rim, 1]), 0.2)
    on_hole = np.zeros(rim.size, bool)
    for hx, hz, r in holes:
        d = np.linalg.norm(local - (hx, hz), axis=1)
        assert np.all(d >= r - 1e-12)  # nothing inside a hole
        on = np.abs(d[rim] - r) < 1e-12
        assert on.sum() >= 2 * math.pi * r / h * 0.8
        on_hole |= on
    assert np.all(on_border | on_hole)


def test_rectangle_hole_errors_name_the_hole():
    with pytest.raises(MeshError, match=r"hole 0 .*border"):
        rectangle(0.6, 0.4, 0.02, holes=[(0.25, 0.0, 0.1)])
    with pytest.raises(MeshError, match=r"hole 1 .*overlaps .*hole 0"):
        rectangle(0.6, 0.4, 0.02, holes=[(0.0, 0.0, 0.08), (0.12, 0.0, 0.05)])
    with pytest.raises(MeshError, match=r"hole 0 .*radius"):
        rectangle(0.6, 0.4, 0.02, holes=[(0.0, 0.0, 0.01)])


# ------------------------------------------------------------------------------------------------
# grid square


@pytest.mark.parametrize("plane", ["xz", "xy"])
def test_grid_square_matches_grid_net(plane):
    rows, cols, size, c = 5, 7, (0.6, 0.4), (0.1, 0.8, -0.3)
    m = grid_square(rows, cols, size, center=c, plane=plane)
    net = grid_net(rows, cols, size, center=c, plane=plane)
    np.testing.assert_array_equal(m.vertices, np.asarray(net.rest, np.float64).reshape(-1, 3))
    assert m.faces.shape == (2 * (rows - 1) * (cols - 1), 3)
    check_mesh(m.vertices, m.faces, m.source)
    n = _normals(m)
    axis = 1 if plane == "xz" else 2
    assert np.all(n[:, axis] > 0) and np.all(_uv_area(m) > 0)
    assert mesh_quality(m)["area"] == pytest.approx(0.24, rel=1e-12)
    # u along the columns (+x), v = -z or +y.
    assert np.allclose(m.uv[:, 0], m.vertices[:, 0] - c[0])


def test_grid_square_default_layout_and_diagonals():
    net = grid_net(10, 13)
    for diagonal in ("d1", "d2", "alternate"):
        m = grid_square(10, 13, diagonal=diagonal)
        assert np.allclose(m.vertices, np.asarray(net.rest).reshape(-1, 3), rtol=0, atol=0)
        assert np.all(_normals(m)[:, 1] > 0)
    sq = grid_square(4, 4, 0.3)
    assert np.ptp(sq.vertices[:, 0]) == pytest.approx(0.3)
    assert np.ptp(sq.vertices[:, 2]) == pytest.approx(0.3)


# ------------------------------------------------------------------------------------------------
# OBJ


def test_obj_round_trip_with_vt(tmp_path):
    m = disc(R, 0.02)
    path = write_obj(tmp_path / "disc.obj", positions=m.vertices, faces=m.faces, uv=m.uv * 7.0)
    back = read_cloth_obj(path)
    assert back.source == str(path)
    np.testing.assert_array_equal(back.faces, m.faces)
    np.testing.assert_allclose(back.vertices, m.vertices, atol=1e-6)
    np.testing.assert_allclose(back.uv, m.uv, atol=1e-5)  # vt rescaled to m


def test_obj_flat_without_vt_uses_the_plane(tmp_path):
    m = rectangle(0.3, 0.2, 0.02)
    path = write_obj(tmp_path / "rect.obj", positions=m.vertices * 100, faces=m.faces)
    back = read_cloth_obj(path, scale=0.01)
    np.testing.assert_allclose(back.vertices, m.vertices, atol=1e-8)
    # Default warp: world x in the plane; normal +y, so v = y x x = -z: the builders' convention.
    np.testing.assert_allclose(back.uv - back.uv.mean(0), m.uv - m.uv.mean(0), atol=1e-8)
    # A warp along z turns the material frame: u = z offset, v = y x z = +x.
    turned = read_cloth_obj(path, warp=(0.0, 0.0, 1.0), scale=0.01)
    local = m.vertices - m.vertices.mean(0)
    np.testing.assert_allclose(turned.uv, local[:, [2, 0]], atol=1e-8)
    assert np.all(_uv_area(back) > 0) and np.all(_uv_area(turned) > 0)


def test_obj_polygons_slashes_and_curved_with_vt(tmp_path):
    # Two quads of a bent strip, with a/b/c and negative indices; vt one per vertex.
    positions = "v 0 0 0\nv 1 0 0\nv 2 0.5 0\nv 0 0 -1\nv 1 0 -1\nv 2 0.5 -1\n"
    texcoords = "vt 0 0\nvt 1 0\nvt 2.118 0\nvt 0 1\nvt 1 1\nvt 2.118 1\nvn 0 1 0\n"
    path = tmp_path / "strip.obj"
    path.write_text(
        "# bent strip\n"
        + positions
        + texcoords
        + "f 1/1/1 2/2/1 5/5/1 4/4/1\nf -5/-5 -4/-4 -1/-1 -2/-2\n"
    )
    m = read_cloth_obj(path)
    assert m.faces.shape == (4, 3) and m.vertices.shape == (6, 3)
    assert np.all(_uv_area(m) > 0)
    assert np.all(_normals(m)[:, 1] > 0)
    np.testing.assert_allclose(m.uv[1] - m.uv[0], [1.0, 0.0], rtol=0.02)  # vt scaled to m
    # Without vt the curved strip is refused: it has no material coordinates.
    path.write_text(positions + "f 1 2 5 4\nf 2 3 6 5\n")
    with pytest.raises(MeshError, match=rf"{path.name}.*not flat.*vt"):
        read_cloth_obj(path)


# ------------------------------------------------------------------------------------------------
# check_mesh: one case per refusal, each named by file and face or vertex

SQUARE = np.array([[0, 0, 0], [1, 0, 0], [1, 0, -1], [0, 0, -1.0]])


def _obj(tmp_path, vertices, faces, name="bad.obj"):
    lines = ["v " + " ".join(repr(float(x)) for x in v) for v in np.asarray(vertices)]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "vertices, faces, match",
    [
        (np.r_[SQUARE[:3], [[np.nan, 0, 0]]], [[0, 1, 2], [0, 2, 3]], r"vertex 3 .*non-finite"),
        (SQUARE, [[0, 1, 2], [0, 2, 9]], r"face 1 .*outside"),
        (SQUARE, [[0, 1, 2], [0, 2, 2]], r"face 1 .*repeats"),
        (np.r_[SQUARE, [[0.5, 0, -0.5]]], [[0, 1, 2], [0, 2, 3], [0, 4, 2]], r"face 2 .*zero area"),
        (SQUARE, [[0, 1, 2]], r"vertex 3 .*not used .*1 unreferenced"),
        (
            np.r_[SQUARE, [[0.5, 1, -0.5]]],
            [[0, 1, 2], [0, 2, 3], [2, 0, 4]],
            r"edge \(0, 2\) .*3 faces \[0, 1, 2\]",
        ),
        (SQUARE, [[0, 1, 2], [0, 3, 2]], r"faces 0 and 1 .*same direction"),
        (
            np.r_[SQUARE[:3], [[-1, 0, 0], [-1, 0, 1]]],
            [[0, 1, 2], [0, 3, 4]],
            r"vertex 0 joins 2 separate fans",
        ),
    ],
    ids=["nan", "range", "repeat", "area", "unused", "nonmanifold", "orient", "fans"],
)
def test_check_mesh_errors_name_file_and_element(tmp_path, vertices, faces, match):
    path = _obj(tmp_path, vertices, faces)
    with pytest.raises(MeshError, match=match) as info:
        read_cloth_obj(path)
    assert str(info.value).startswith(str(path))
    with pytest.raises(MeshError, match=match):
        check_mesh(vertices, faces, "here")


def test_check_mesh_empty_and_shapes(tmp_path):
    path = tmp_path / "empty.obj"
    path.write_text("# nothing\n")
    with pytest.raises(MeshError, match=r"empty\.obj: empty mesh"):
        read_cloth_obj(path)
    with pytest.raises(MeshError, match="shape"):
        check_mesh(np.zeros((3, 2)), [[0, 1, 2]], "x")
    assert issubclass(MeshError, ValueError)
    check_mesh(SQUARE, [[0, 1, 2], [0, 2, 3]], "ok")


def test_obj_flipped_vt_is_refused(tmp_path):
    m = grid_square(3, 3, 0.2)
    path = write_obj(tmp_path / "flip.obj", positions=m.vertices, faces=m.faces, uv=-m.uv[:, ::-1])
    with pytest.raises(MeshError, match=r"flip\.obj: face 0 is flipped"):
        read_cloth_obj(path)
