"""AMASS SMPL-X stage-II files (issue 24 item 4): a pickled object array beside the
keys we need is neither refused nor unpickled. Sample: tests/data/amass/stageii_smplx.npz
(tests/data/make_samples.py, the key set of a MoSh++ stage-II file, made-up values)."""
from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest

from anidress_core.io.motion import read_amass_npz

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "amass" / "stageii_smplx.npz"


def test_stageii_smplx_with_pickled_markers_latent_vids_is_read():
    with np.load(SAMPLE, allow_pickle=False) as z:  # the sample really holds an object array
        assert "markers_latent_vids" in z.files
        with pytest.raises(ValueError, match="Object arrays cannot be loaded"):
            z["markers_latent_vids"]
        poses, trans, betas = z["poses"], z["trans"], z["betas"]
    got = read_amass_npz(SAMPLE)
    assert poses.shape == (4, 165) and got["poses"].shape == (4, 72)
    np.testing.assert_array_equal(got["poses"][:, :66], poses[:, :66])  # root + 21 body joints
    np.testing.assert_array_equal(got["poses"][:, 66:], 0.0)
    np.testing.assert_array_equal(got["trans"], trans)
    np.testing.assert_array_equal(got["betas"], betas)
    assert got["fps"] == 120.0 and got["gender"] == "female"


def test_object_arrays_are_never_unpickled(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("unpickled")

    monkeypatch.setattr(pickle, "load", boom)
    monkeypatch.setattr(pickle, "loads", boom)
    assert read_amass_npz(SAMPLE)["poses"].shape == (4, 72)


def test_a_needed_key_stored_as_object_array_names_file_and_key(tmp_path):
    path = tmp_path / "objtrans.npz"
    with np.load(SAMPLE, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "markers_latent_vids"}
    trans = np.empty(4, dtype=object)
    trans[:] = [list(r) for r in arrays["trans"]]
    np.savez(path, **dict(arrays, trans=trans))
    with pytest.raises(ValueError, match=r"objtrans\.npz: key 'trans' is a pickled object array"):
        read_amass_npz(path)


def test_truncated_file_names_the_file(tmp_path):
    path = tmp_path / "cut.npz"
    path.write_bytes(SAMPLE.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"cut\.npz: not a readable AMASS \.npz"):
        read_amass_npz(path)
    assert not zipfile.is_zipfile(path)
