"""Mesh files: OBJ/PLY round trips, per-corner UVs, errors naming the file."""
import numpy as np
import pytest
import trimesh

from anidress_core.io.files import ArtifactError
from anidress_core.io.mesh import read_mesh, write_obj, write_ply


def _mesh():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]], dtype=np.float64) * 0.3
    f = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]], dtype=np.int64)
    uv = np.random.default_rng(0).random((4, 3, 2))
    uv[0, 2] = (0.1, 0.9)
    uv[1, 2] = (0.7, 0.2)  # vertex 4 has different UVs in different faces (a seam)
    return v, f, uv


def test_obj_round_trip_with_corner_uvs(tmp_path):
    v, f, uv = _mesh()
    p = tmp_path / "g.obj"
    write_obj(p, v, f, uv)
    v2, f2, uv2 = read_mesh(p)
    np.testing.assert_allclose(v2, v, atol=1e-9)
    np.testing.assert_array_equal(f2, f)
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    assert v2.dtype == np.float64 and f2.dtype == np.int64
    assert not list(tmp_path.glob(".*"))  # no temporary left behind


def test_obj_without_uv_and_polygons(tmp_path):
    p = tmp_path / "q.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\n")
    v, f, uv = read_mesh(p)
    assert uv is None and f.shape == (2, 3) and len(v) == 4
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nf -3/-3 -2/-2 -1/-1\n")
    v, f, uv = read_mesh(p)
    np.testing.assert_array_equal(f, [[0, 1, 2]])
    np.testing.assert_allclose(uv[0], [[0, 0], [1, 0], [1, 1]])


def test_ply_round_trip_with_attributes(tmp_path):
    v, f, _ = _mesh()
    band = np.array([True, False, True, False, False])
    w = np.random.default_rng(1).random((5, 3)).astype(np.float32)
    p = tmp_path / "t.ply"
    write_ply(p, v, f, {"band": band, "w": w})
    v2, f2, uv2 = read_mesh(p)
    np.testing.assert_allclose(v2, v, atol=1e-6)
    np.testing.assert_array_equal(f2, f)
    assert uv2 is None
    raw = trimesh.load(p, process=False).metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(raw["band"].astype(bool), band)
    np.testing.assert_allclose(np.stack([raw[f"w_{k}"] for k in range(3)], 1), w)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.obj"):
        read_mesh(tmp_path / "missing.obj")
    p = tmp_path / "nofaces.obj"
    p.write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(ArtifactError, match="nofaces.obj.*no triangle faces"):
        read_mesh(p)
    p = tmp_path / "nan.obj"
    p.write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ArtifactError, match="nan.obj.*non-finite"):
        read_mesh(p)
    p = tmp_path / "garbage.obj"
    p.write_text("v 0 zero 0\n")
    with pytest.raises(ArtifactError, match="garbage.obj"):
        read_mesh(p)
    p = tmp_path / "binary.obj"
    p.write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(ArtifactError, match="binary.obj"):
        read_mesh(p)
    p = tmp_path / "bad.ply"
    p.write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(ArtifactError, match="bad.ply"):
        read_mesh(p)
    p = tmp_path / "range.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nf 1 2 9\n")
    with pytest.raises(ArtifactError, match="range.obj"):
        read_mesh(p)
