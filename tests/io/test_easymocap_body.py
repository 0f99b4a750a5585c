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
    read_easymocap_smpl_dir,
    read_easymocap_smpl_file,
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
