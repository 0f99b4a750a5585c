"""EasyMocap body files as EasyMocap >= 0.2 writes them (issue 24 items 3 and 5).

Samples: tests/data/easymocap/ (made by tests/data/make_samples.py in EasyMocap's
``write_smpl`` layout).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from anidress_core.io.motion import (
    EmptyFrameError,
    read_easymocap_smpl_dir,
    read_easymocap_smpl_file,
    smpl_selection,
)

DATA = Path(__file__).resolve().parents[1] / "data" / "easymocap"


def _raw(path: Path, idx: int = 0) -> dict:
    return {k: np.asarray(v, float).reshape(-1) if k != "id" else v for k, v in json.loads(path.read_text())[idx].items()}


# ------------------------------------------------------------------ item 3: pose lengths
def test_smpl_69_without_root_reads_root_from_rh():
    got = read_easymocap_smpl_dir(DATA / "smpl_v02")
    raw = [_raw(DATA / "smpl_v02" / f"{f:06d}.json") for f in (0, 1)]
    assert got["poses"].shape == (2, 72) and got["frames"] == [0, 1]
    np.testing.assert_array_equal(got["poses"][:, :3], 0.0)  # the root is Rh, applied after skinning
    np.testing.assert_array_equal(got["poses"][:, 3:], np.stack([r["poses"] for r in raw]))  # joints 1..23
    np.testing.assert_array_equal(got["Rh"], np.stack([r["Rh"] for r in raw]))
    np.testing.assert_array_equal(got["Th"], np.stack([r["Th"] for r in raw]))


@pytest.mark.parametrize("name", ["smplh_v02", "smplx_v02"])
def test_smplh_smplx_63_body_joints_hands_zero(name):
    path = DATA / name / "000000.json"
    raw = _raw(path)
    assert raw["poses"].size == 63 and "handl" in raw  # the sample is what SMPLHModel writes
    got = read_easymocap_smpl_file(path)
    assert got["poses"].shape == (72,)
    np.testing.assert_array_equal(got["poses"][:3], 0.0)
    np.testing.assert_array_equal(got["poses"][3:66], raw["poses"])  # joints 1..21
    np.testing.assert_array_equal(got["poses"][66:], 0.0)  # SMPL hand joints 22, 23: MANO pose is not SMPL's
    np.testing.assert_array_equal(got["Rh"], raw["Rh"])
    np.testing.assert_array_equal(got["shapes"], raw["shapes"])
    assert set(got) == {"poses", "Rh", "Th", "shapes", "id"}


def test_bad_pose_length_names_file_field_and_accepted_lengths():
    with pytest.raises(ValueError) as info:
        read_easymocap_smpl_dir(DATA / "bad_poses")
    msg = str(info.value)
    assert "bad_poses/000000.json" in msg and "'poses' holds 70 numbers" in msg
    for n in ("72", "69", "63"):
        assert n in msg


def test_hand_entries_are_checked(tmp_path):
    d = tmp_path / "smpl"
    shutil.copytree(DATA / "smplh_v02", d)
    data = json.loads((d / "000000.json").read_text())
    data[0]["handl"] = [[0.0, float("nan")]]
    (d / "000000.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"000000\.json: 'handl' contains NaN"):
        read_easymocap_smpl_dir(d)


# ------------------------------------------------------------- item 5: several people
def test_several_people_without_id_is_an_error_naming_file_and_ids():
    with pytest.raises(ValueError, match=r"two_people/000000\.json: holds 2 people \(ids \[0, 1\]\).*person_id"):
        read_easymocap_smpl_dir(DATA / "two_people")


def test_person_id_follows_the_person_when_the_order_changes():
    # frame 1 lists id 1 first: taking "the first entry" would jump 5 m
    for pid, x0 in ((0, 0.0), (1, 5.0)):
        got = read_easymocap_smpl_dir(DATA / "two_people", person_id=pid, max_gap=1)
        np.testing.assert_allclose(got["Th"][:, 0], x0 + np.array([0.0, 0.2, 0.4, 0.6]), atol=1e-12)
        assert np.abs(np.diff(got["Th"][:, 0])).max() < 0.25
        raw1 = [p for p in json.loads((DATA / "two_people" / "000001.json").read_text()) if p["id"] == pid][0]
        np.testing.assert_array_equal(got["poses"][1, 3:], np.asarray(raw1["poses"]).reshape(-1))


def test_empty_frame_is_an_error_naming_the_file_by_default():
    with pytest.raises(EmptyFrameError, match=r"two_people/000002\.json: no person.*max_gap"):
        read_easymocap_smpl_dir(DATA / "two_people", person_id=0)
    with pytest.raises(EmptyFrameError, match=r"000002\.json: no person"):
        read_easymocap_smpl_file(DATA / "two_people" / "000002.json")
    with pytest.raises(EmptyFrameError, match=r"000000\.json: no person with id 4 .*ids: \[0, 1\]"):
        read_easymocap_smpl_file(DATA / "two_people" / "000000.json", person_id=4)


def test_empty_frame_interpolated_from_neighbours_when_allowed():
    from scipy.spatial.transform import Rotation, Slerp

    got = read_easymocap_smpl_dir(DATA / "two_people", person_id=0, max_gap=1)
    assert got["interpolated"] == [2] and got["frames"] == [0, 1, 2, 3]
    # Th linear between frames 1 and 3; rotations by slerp half way
    np.testing.assert_allclose(got["Th"][2], 0.5 * (got["Th"][1] + got["Th"][3]), atol=1e-12)
    for key, n in (("Rh", 1), ("poses", 24)):
        a = Rotation.from_rotvec(got[key][1].reshape(n, 3))
        b = Rotation.from_rotvec(got[key][3].reshape(n, 3))
        mid = Rotation.from_rotvec(got[key][2].reshape(n, 3))
        for m in range(n):
            ref = Slerp([0, 1], Rotation.concatenate([a[m], b[m]]))(0.5)
            assert (ref.inv() * mid[m]).magnitude() < 1e-9
    assert np.isfinite(got["poses"]).all()


def test_gap_longer_than_allowed_or_at_the_ends_is_an_error(tmp_path):
    d = tmp_path / "smpl"
    shutil.copytree(DATA / "two_people", d)
    (d / "000001.json").write_text("[\n]\n")
    with pytest.raises(EmptyFrameError, match=r"000001\.json: the person is missing in 2 consecutive files"):
        read_easymocap_smpl_dir(d, person_id=1, max_gap=1)
    assert read_easymocap_smpl_dir(d, person_id=1, max_gap=2)["interpolated"] == [1, 2]
    (d / "000003.json").write_text("[\n]\n")
    with pytest.raises(EmptyFrameError, match=r"000001\.json: .*last frames of the sequence"):
        read_easymocap_smpl_dir(d, person_id=1, max_gap=5)
    with pytest.raises(ValueError, match="max_gap must be a non-negative int"):
        read_easymocap_smpl_dir(d, person_id=1, max_gap=-1)


def test_single_person_files_need_no_id():
    got = read_easymocap_smpl_file(DATA / "smpl_v02" / "000000.json")
    assert int(got["id"]) == 0


def test_scene_yaml_selection_keys():
    info = {"person_id": 1, "sequences": [{"name": "walk"}, {"name": "dance", "person_id": 0, "max_missing_frames": 2}]}
    assert smpl_selection(info, "walk") == {"person_id": 1}
    assert smpl_selection(info, "dance") == {"person_id": 0, "max_gap": 2}
    assert smpl_selection({"sequences": [{"name": "walk"}]}, "walk") == {}
    got = read_easymocap_smpl_dir(DATA / "two_people", **smpl_selection(info, "dance"))
    assert got["interpolated"] == [2] and got["Th"][0, 0] == 0.0
    with pytest.raises(ValueError, match=r"x/scene\.yaml: 'person_id' must be an integer"):
        smpl_selection({"person_id": "01"}, "walk", "x/scene.yaml")
    with pytest.raises(ValueError, match=r"scene\.yaml: 'max_missing_frames' must be a non-negative integer"):
        smpl_selection({"sequences": [{"name": "walk", "max_missing_frames": -1}]}, "walk")


def test_scene_readers_take_the_person_of_scene_yaml(tmp_path):
    """io.scene's motion reader follows scene.yaml's person_id / max_missing_frames (validate_scene does too:
    tests/test_validate.py::test_body_params_of_the_person_scene_yaml_selects)."""
    import yaml

    from anidress_core.io.scene import load_sequence_motion

    shutil.copytree(DATA / "two_people", tmp_path / "walk" / "smpl")
    info = {"fps": 30, "body_model": {"type": "mannequin", "file": "body.npz"}, "sequences": [{"name": "walk"}]}
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(info))
    with pytest.raises(ValueError, match=r"walk/smpl/000000\.json: holds 2 people \(ids \[0, 1\]\)"):
        load_sequence_motion(tmp_path, "walk", 30.0)
    info["sequences"][0].update(person_id=1, max_missing_frames=1)
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(info))
    motion = load_sequence_motion(tmp_path, "walk", 30.0)
    np.testing.assert_allclose(motion.Th[:, 0].numpy(), [5.0, 5.2, 5.4, 5.6], atol=1e-6)
