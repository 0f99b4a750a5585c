"""ZJU-MoCap annots.npy and masks (issue 24 item 8). Sample: tests/data/zju/ (written by
tests/data/make_samples.py with np.save of a dict, as annots.npy is stored)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from anidress_core.io.files import read_mask
from anidress_core.io.zju import read_annots, zju_mask_labels
from anidress_core.synth import LABEL_BACKGROUND, LABEL_BODY, LABEL_GARMENT

DATA = Path(__file__).resolve().parents[1] / "data" / "zju"


def _raw():
    return np.load(DATA / "annots.npy", allow_pickle=True).item()  # the reference reading (neuralbody's)


def test_annots_cameras_in_metres_and_image_lists():
    raw = _raw()
    got = read_annots(DATA / "annots.npy", height=1024, width=1024)
    cams = got["cameras"]
    assert cams.names == ["Camera_B1", "Camera_B2"] and (cams.height, cams.width) == (1024, 1024)
    assert cams.dtype == torch.float64
    np.testing.assert_array_equal(cams.K.numpy(), np.stack(raw["cams"]["K"]))
    np.testing.assert_array_equal(cams.dist.numpy(), np.stack(raw["cams"]["D"])[..., 0])
    np.testing.assert_array_equal(cams.R.numpy(), np.stack(raw["cams"]["R"]))
    np.testing.assert_allclose(cams.T.numpy(), np.stack(raw["cams"]["T"])[..., 0] / 1000.0, rtol=0, atol=1e-15)
    assert cams.T[0, 2].item() == 3.0  # 3000 mm
    assert got["ims"] == [list(e["ims"]) for e in raw["ims"]] and len(got["ims"]) == 3


def test_annots_image_size_from_the_first_image(tmp_path):
    import cv2

    (tmp_path / "Camera_B1").mkdir()
    np.save(tmp_path / "annots.npy", _raw(), allow_pickle=True)
    with pytest.raises(ValueError, match=r"annots\.npy: no image size .*Camera_B1/000000\.jpg.*pass height"):
        read_annots(tmp_path / "annots.npy")
    cv2.imwrite(str(tmp_path / "Camera_B1" / "000000.jpg"), np.zeros((6, 8, 3), np.uint8))
    cams = read_annots(tmp_path / "annots.npy", names=["a", "b"])["cameras"]
    assert (cams.height, cams.width) == (6, 8) and cams.names == ["a", "b"]


def test_malformed_annots_name_file_and_field(tmp_path):
    path = tmp_path / "annots.npy"
    raw = _raw()
    raw["cams"]["T"][1] = np.array([[1.0], [2.0]])
    np.save(path, raw, allow_pickle=True)
    with pytest.raises(ValueError, match=r"annots\.npy: 'cams/T\[1\]' must hold 3 numbers"):
        read_annots(path, 1024, 1024)
    raw = _raw()
    raw["ims"][2] = {"ims": ["Camera_B1/000002.jpg"]}
    np.save(path, raw, allow_pickle=True)
    with pytest.raises(ValueError, match=r"annots\.npy: 'ims\[2\]' lists 1 images for 2 cameras"):
        read_annots(path, 1024, 1024)
    raw = _raw()
    del raw["cams"]["D"]
    np.save(path, raw, allow_pickle=True)
    with pytest.raises(ValueError, match=r"annots\.npy: 'cams' has no 'D'"):
        read_annots(path, 1024, 1024)


def test_annots_pickle_is_restricted(tmp_path):
    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned",))

    np.save(tmp_path / "annots.npy", {"cams": Evil(), "ims": []}, allow_pickle=True)
    with pytest.raises(ValueError, match="refusing to unpickle"):
        read_annots(tmp_path / "annots.npy", 1024, 1024)


def test_mask_labels_from_mask_and_cihp():
    mask = read_mask(DATA / "mask" / "Camera_B1" / "000000.png")
    cihp = read_mask(DATA / "mask_cihp" / "Camera_B1" / "000000.png")
    assert set(np.unique(mask)) == {0, 255}
    lab = zju_mask_labels(mask, cihp)
    assert lab.dtype == np.uint8 and lab.shape == (6, 4)
    # rows 1-4 cols 1-2: face, upper clothes (body), dress, skirt (garment); (5, 0): a shoe only in mask_cihp
    expect = np.zeros((6, 4), np.uint8)
    expect[1:3, 1:3] = LABEL_BODY
    expect[3:5, 1:3] = LABEL_GARMENT
    expect[5, 0] = LABEL_BODY
    np.testing.assert_array_equal(lab, expect)
    assert (zju_mask_labels(mask) == np.where(mask > 0, LABEL_BODY, LABEL_BACKGROUND)).all()
    only_skirt = zju_mask_labels(mask, cihp, garment_labels=(12,))
    assert (only_skirt[3, 1:3] == LABEL_BODY).all() and (only_skirt[4, 1:3] == LABEL_GARMENT).all()
    with pytest.raises(ValueError, match="CIHP labels 0..19"):
        zju_mask_labels(cihp=np.full((2, 2), 25, np.uint8))
    with pytest.raises(ValueError, match="give mask"):
        zju_mask_labels()
