"""OBJ export: round trip of positions, uv, normals and 1-based faces; sequences; errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.io import mesh as mesh_module
from diffcloth.io import read_obj, write_obj, write_obj_sequence
from diffcloth.surface import tessellate


@pytest.fixture(scope="module")
def nets():
    rng = np.random.default_rng(0)
    x, z = np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 1, 4))
    base = np.stack([x, np.zeros_like(x), z], -1)
    return jnp.asarray(base[None] + 0.05 * rng.normal(size=(3, 4, 5, 3)))


@pytest.fixture(scope="module")
def surfaces(nets):
    return jax.jit(jax.vmap(lambda n: tessellate(n, 2)))(nets)


def one(surfaces, t):
    return jax.tree_util.tree_map(lambda a: a[t], surfaces)


def test_all_lists_public_names():
    assert set(mesh_module.__all__) == {"write_obj", "write_obj_sequence", "read_obj"}


def test_round_trip(tmp_path, surfaces):
    s = one(surfaces, 0)
    path = write_obj(tmp_path / "sub" / "cloth.obj", s)
    text = path.read_text()
    n, m = s.positions.shape[0], s.faces.shape[0]
    assert text.count("\nv ") == n and text.count("\nvt ") == n and text.count("\nvn ") == n
    assert text.count("\nf ") == m
    back = read_obj(path)
    np.testing.assert_allclose(back["positions"], s.positions, atol=1e-6)
    np.testing.assert_allclose(back["uv"], s.uv, atol=1e-6)
    np.testing.assert_allclose(back["normals"], s.normals, atol=1e-6)
    np.testing.assert_array_equal(back["faces"], s.faces)
    np.testing.assert_array_equal(back["face_uv"], s.faces)
    np.testing.assert_array_equal(back["face_normals"], s.faces)
    first_face = next(line for line in text.splitlines() if line.startswith("f "))
    a, b, c = (int(k) for k in first_face.split()[1].split("/"))
    assert a == b == c == int(s.faces[0, 0]) + 1  # 1-based


def test_arrays_without_uv_or_normals(tmp_path):
    p = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    path = write_obj(tmp_path / "tri.obj", positions=p, faces=[[0, 1, 2]])
    assert "f 1 2 3" in path.read_text()
    path = write_obj(tmp_path / "tri_n.obj", positions=p, faces=[[0, 1, 2]], normals=np.eye(3))
    assert "f 1//1 2//2 3//3" in path.read_text()


def test_sequences(tmp_path, surfaces):
    paths = write_obj_sequence(tmp_path / "batched", surfaces)
    assert [p.name for p in paths] == ["frame_0000.obj", "frame_0001.obj", "frame_0002.obj"]
    np.testing.assert_allclose(read_obj(paths[2])["positions"], surfaces.positions[2], atol=1e-6)
    listed = [one(surfaces, t) for t in range(3)]
    paths = write_obj_sequence(tmp_path / "listed", listed, prefix="cloth_", start=5)
    assert paths[0].name == "cloth_0005.obj"
    np.testing.assert_allclose(read_obj(paths[1])["normals"], surfaces.normals[1], atol=1e-6)
    faces = surfaces.faces[0]
    paths = write_obj_sequence(tmp_path / "raw", np.asarray(surfaces.positions), faces=faces)
    back = read_obj(paths[1])
    np.testing.assert_allclose(back["positions"], surfaces.positions[1], atol=1e-6)
    assert "uv" not in back


def test_errors(tmp_path, surfaces):
    p = np.zeros((3, 3))
    with pytest.raises(ValueError, match="faces index range"):
        write_obj(tmp_path / "x.obj", positions=p, faces=[[0, 1, 3]])
    with pytest.raises(ValueError, match="needs positions and faces"):
        write_obj(tmp_path / "x.obj", positions=p)
    with pytest.raises(ValueError, match="non-finite"):
        write_obj(tmp_path / "x.obj", positions=p + np.nan, faces=[[0, 1, 2]])
    with pytest.raises(ValueError, match="normals must have 3 rows"):
        write_obj(tmp_path / "x.obj", positions=p, faces=[[0, 1, 2]], normals=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="needs faces"):
        write_obj_sequence(tmp_path / "y", np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="use write_obj for one frame"):
        write_obj_sequence(tmp_path / "y", one(surfaces, 0))
