import numpy as np
import pytest

from anidress_core.io import files as io


def test_exr_round_trip_keeps_channel_order(tmp_path):
    flow = np.random.default_rng(0).normal(size=(7, 9, 2)).astype(np.float32)
    io.write_exr(tmp_path / "f.exr", flow)
    assert np.array_equal(io.read_exr(tmp_path / "f.exr"), flow)
    normals = np.random.default_rng(1).normal(size=(5, 4, 3)).astype(np.float32)
    io.write_exr(tmp_path / "n.exr", normals)
    assert np.array_equal(io.read_exr(tmp_path / "n.exr"), normals)
    named = np.random.default_rng(2).normal(size=(3, 3, 3)).astype(np.float32)
    io.write_exr(tmp_path / "z.exr", named, channels=("z", "a", "m"))
    assert np.array_equal(io.read_exr(tmp_path / "z.exr"), named)


def test_png_mask_and_image_round_trip(tmp_path):
    lab = np.random.default_rng(0).integers(0, 3, size=(6, 8)).astype(np.uint8)
    io.write_mask(tmp_path / "m.png", lab)
    assert np.array_equal(io.read_mask(tmp_path / "m.png"), lab)
    img = np.random.default_rng(0).random((6, 8, 3)).astype(np.float32)
    io.write_png(tmp_path / "i.png", img)
    back = io.read_image(tmp_path / "i.png")
    assert back.shape == img.shape and np.abs(back - img).max() <= 0.5 / 255 + 1e-6
    # colour order: a pure red image stays red
    red = np.zeros((2, 2, 3)); red[..., 0] = 1
    io.write_png(tmp_path / "r.png", red)
    assert io.read_image(tmp_path / "r.png")[0, 0].tolist() == [1.0, 0.0, 0.0]


def test_errors_name_the_file(tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(io.ArtifactError, match="broken.png"):
        io.read_image(bad)
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        io.read_exr(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"\x76\x2f\x31\x01garbage")
    with pytest.raises(io.ArtifactError, match="bad.exr"):
        io.read_exr(tmp_path / "bad.exr")


def test_npz_header_and_required(tmp_path):
    p = tmp_path / "a.npz"
    io.save_npz(p, {"x": np.arange(3)}, config={"k": 1}, meta={"fps": 30})
    arrays, header = io.load_npz(p, required=("x",))
    assert arrays["x"].tolist() == [0, 1, 2]
    assert header["config_hash"] == io.config_hash({"k": 1}) and header["meta"]["fps"] == 30
    assert header["code_version"]
    with pytest.raises(io.ArtifactError, match="missing arrays"):
        io.load_npz(p, required=("y",))


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.npz"
    with pytest.raises(RuntimeError):
        with io.atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
