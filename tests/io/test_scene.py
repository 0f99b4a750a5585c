"""Reading a scene folder (anidress_core.io.scene): scene.yaml errors, body model, image paths."""
import numpy as np
import pytest
import yaml

from anidress_core.body.kinematic import SMPL_PARENTS
from anidress_core.io import files
from anidress_core.io.scene import garment_texture_path, image_path, load_body, read_scene


def test_read_scene_names_file_and_key(tmp_path):
    with pytest.raises(FileNotFoundError, match="scene.yaml"):
        read_scene(tmp_path)
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump({"fps": 30, "sequences": []}))
    with pytest.raises(files.ArtifactError, match=r"scene\.yaml: missing key 'body_model'"):
        read_scene(tmp_path)
    (tmp_path / "scene.yaml").write_text("fps: [30\n")
    with pytest.raises(files.ArtifactError, match=r"scene\.yaml: not valid YAML"):
        read_scene(tmp_path)


def test_load_body_mannequin_and_bad_type(tmp_path):
    rng = np.random.default_rng(0)
    w = rng.random((8, 24)).astype(np.float32)
    a = {"v_template": rng.normal(size=(8, 3)).astype(np.float32), "faces": np.array([[0, 1, 2], [2, 3, 4]]),
         "weights": w / w.sum(1, keepdims=True), "joints_rest": rng.normal(size=(24, 3)).astype(np.float32),
         "parents": np.asarray(SMPL_PARENTS, np.int64)}
    files.save_npz(tmp_path / "body.npz", a)
    info = {"fps": 30, "sequences": [], "body_model": {"type": "mannequin", "file": "body.npz"}}
    body = load_body(tmp_path, info)
    np.testing.assert_allclose(body.v_template.numpy(), a["v_template"], rtol=0, atol=0)
    with pytest.raises(files.ArtifactError, match=r"scene\.yaml: body_model/type must be mannequin or smpl"):
        load_body(tmp_path, {**info, "body_model": {"type": "other", "file": "body.npz"}})


def test_image_path_and_texture_path(tmp_path):
    d = tmp_path / "walk" / "images" / "01"
    d.mkdir(parents=True)
    assert image_path(tmp_path / "walk", "01", 3) == d / "000003.png"  # none there: .png
    (d / "000003.jpg").write_bytes(b"")
    assert image_path(tmp_path / "walk", "01", 3) == d / "000003.jpg"
    assert garment_texture_path(tmp_path, {}) == tmp_path / "garment" / "texture.png"
    assert garment_texture_path(tmp_path, {"garment_texture": "t.png"}) == tmp_path / "t.png"
