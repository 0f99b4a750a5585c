"""Tests of anidress_core.io.motion (file readers/writers for body models and motions)."""
import json
import pickle

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from anidress_core.body.model import smpl_model
from anidress_core.io.motion import (
    read_amass_npz,
    read_easymocap_smpl_dir,
    read_easymocap_smpl_file,
    read_smpl_model_file,
    write_easymocap_smpl,
    write_easymocap_smpl_dir,
)

from anidress_core.io.zju import read_zju_params

from .conftest import make_tiny_smpl


# ------------------------------------------------------------------ SMPL model
def test_smpl_npz_round_trip(tmp_path):
    arrays = make_tiny_smpl()
    path = tmp_path / "model.npz"
    np.savez(path, **arrays)
    got = read_smpl_model_file(path)
    for k, v in arrays.items():
        np.testing.assert_array_equal(got[k], v)
    assert got["f"].dtype == np.int64 and got["kintree_table"].dtype == np.int64
    model = smpl_model(got)
    assert model.parents[0] == -1 and model.v_template.shape == (40, 3)


@pytest.mark.parametrize("protocol", [2, 4])
def test_smpl_pkl_with_sparse_regressor(tmp_path, protocol):
    arrays = make_tiny_smpl()
    data = dict(arrays, J_regressor=sp.csc_matrix(arrays["J_regressor"]), bs_style="lbs", bs_type="lrotmin")
    path = tmp_path / "model.pkl"
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=protocol)
    got = read_smpl_model_file(path)
    np.testing.assert_allclose(got["J_regressor"], arrays["J_regressor"])
    assert str(got["bs_style"]) == "lbs"
    v1 = smpl_model(got).pose(torch.zeros(1, 72)).vertices
    v2 = smpl_model(arrays).pose(torch.zeros(1, 72)).vertices
    torch.testing.assert_close(v1, v2)


def test_chumpy_pickle_gives_clear_error(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    # A protocol-2 pickle that instantiates chumpy.ch.Ch (the official SMPL files).
    path.write_bytes(b"\x80\x02cchumpy.ch\nCh\nq\x00)\x81q\x01.")
    with pytest.raises(ValueError, match=r"SMPL_NEUTRAL\.pkl.*chumpy.*npz"):
        read_smpl_model_file(path)


def test_malicious_pickle_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned",))

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": Evil()}))
    with pytest.raises(ValueError, match="refusing to unpickle"):
        read_smpl_model_file(path)


def test_smpl_file_errors(tmp_path):
    arrays = make_tiny_smpl()
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        read_smpl_model_file(tmp_path / "missing.npz")
    bad = {k: v for k, v in arrays.items() if k != "weights"}
    np.savez(tmp_path / "noweights.npz", **bad)
    with pytest.raises(ValueError, match=r"noweights\.npz.*'weights'"):
        read_smpl_model_file(tmp_path / "noweights.npz")
    nan = dict(arrays)
    nan["v_template"] = arrays["v_template"].copy()
    nan["v_template"][3, 1] = np.nan
    np.savez(tmp_path / "nan.npz", **nan)
    with pytest.raises(ValueError, match=r"nan\.npz.*v_template.*NaN"):
        read_smpl_model_file(tmp_path / "nan.npz")
    np.savez(tmp_path / "shape.npz", **dict(arrays, v_template=arrays["v_template"][:, :2]))
    with pytest.raises(ValueError, match=r"shape\.npz.*\(V, 3\)"):
        read_smpl_model_file(tmp_path / "shape.npz")
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match="unsupported"):
        read_smpl_model_file(tmp_path / "model.obj")
    (tmp_path / "trunc.npz").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(ValueError, match="trunc.npz"):
        read_smpl_model_file(tmp_path / "trunc.npz")


# ------------------------------------------------------------------- EasyMocap
def test_easymocap_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    T = 5
    poses, Rh, Th, shapes = rng.normal(size=(T, 72)), rng.normal(size=(T, 3)), rng.normal(size=(T, 3)), rng.normal(size=10)
    paths = write_easymocap_smpl_dir(tmp_path / "smpl", torch.from_numpy(poses), Rh, Th, shapes, start_frame=3)
    assert [p.name for p in paths] == [f"{i:06d}.json" for i in range(3, 8)]
    got = read_easymocap_smpl_dir(tmp_path / "smpl")
    np.testing.assert_array_equal(got["poses"], poses)  # exact: full float64 precision
    np.testing.assert_array_equal(got["Rh"], Rh)
    np.testing.assert_array_equal(got["Th"], Th)
    np.testing.assert_array_equal(got["shapes"], np.broadcast_to(shapes, (T, 10)))
    assert got["frames"] == [3, 4, 5, 6, 7]
    # The file follows EasyMocap's layout: a list of people with [[...]] arrays.
    data = json.loads(paths[0].read_text())
    assert isinstance(data, list) and data[0]["id"] == 0
    assert np.shape(data[0]["Rh"]) == (1, 3) and np.shape(data[0]["poses"]) == (1, 72)
    assert not list((tmp_path / "smpl").glob("*.tmp"))


def test_easymocap_variants(tmp_path):
    people = [
        {"id": 3, "Rh": [[0.1, 0.2, 0.3]], "Th": [[1, 2, 3]], "poses": [[0.0] * 72], "shapes": [[0.5] * 10]},
        {"id": 7, "Rh": [[0, 0, 0]], "Th": [[4, 5, 6]], "poses": [list(np.arange(78) / 100)], "shapes": [[0.0] * 10]},
    ]
    (tmp_path / "000010.json").write_text(json.dumps({"annots": people}))
    with pytest.raises(ValueError, match=r"000010\.json: holds 2 people \(ids \[3, 7\]\)"):
        read_easymocap_smpl_file(tmp_path / "000010.json")  # no id chosen: no silent "first entry"
    first = read_easymocap_smpl_file(tmp_path / "000010.json", person_id=3)
    assert int(first["id"]) == 3 and first["Th"].tolist() == [1, 2, 3]
    smplh = read_easymocap_smpl_file(tmp_path / "000010.json", person_id=7)
    assert smplh["poses"].shape == (72,)
    np.testing.assert_array_equal(smplh["poses"][:66], np.arange(66) / 100)
    assert (smplh["poses"][66:] == 0).all()  # SMPL-H hand PCA is not copied into SMPL hands
    with pytest.raises(ValueError, match=r"000010\.json.*no person with id 5"):
        read_easymocap_smpl_file(tmp_path / "000010.json", person_id=5)


def test_easymocap_errors(tmp_path):
    d = tmp_path / "smpl"
    d.mkdir()
    good = {"id": 0, "Rh": [[0, 0, 0]], "Th": [[0, 0, 0]], "poses": [[0.0] * 72], "shapes": [[0.0] * 10]}
    (d / "000000.json").write_text(json.dumps([dict(good, poses=[[0.0] * 70])]))
    with pytest.raises(ValueError, match=r"000000\.json.*'poses'.*72"):
        read_easymocap_smpl_dir(d)
    (d / "000000.json").write_text(json.dumps([dict(good, Th=[[0, float("nan"), 0]])]))
    with pytest.raises(ValueError, match=r"000000\.json.*'Th'.*NaN"):
        read_easymocap_smpl_dir(d)
    (d / "000000.json").write_text("[{not json")
    with pytest.raises(ValueError, match=r"000000\.json.*invalid JSON"):
        read_easymocap_smpl_dir(d)
    (d / "000000.json").write_text(json.dumps([{"id": 0, "poses": [[0.0] * 72]}]))
    with pytest.raises(ValueError, match=r"000000\.json.*missing.*Rh"):
        read_easymocap_smpl_dir(d)
    (d / "000000.json").write_text(json.dumps([good]))
    (d / "notes.json").write_text("[]")
    with pytest.raises(ValueError, match="frame numbers"):
        read_easymocap_smpl_dir(d)
    with pytest.raises(FileNotFoundError):
        read_easymocap_smpl_dir(tmp_path / "nope")
    with pytest.raises(ValueError, match="'poses' must hold 72"):
        write_easymocap_smpl(tmp_path / "x.json", np.zeros(69), np.zeros(3), np.zeros(3), np.zeros(10))
    with pytest.raises(ValueError, match="'Rh'.*NaN"):
        write_easymocap_smpl(tmp_path / "x.json", np.zeros(72), [0, np.inf, 0], np.zeros(3), np.zeros(10))
    assert not (tmp_path / "x.json").exists()


# ------------------------------------------------------------------- ZJU-MoCap
def test_zju_params_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    recs = []
    for i in (0, 1, 2, 10):  # numeric, not lexicographic, order
        rec = {"poses": rng.normal(size=(1, 72)), "Rh": rng.normal(size=(1, 3)),
               "Th": rng.normal(size=(1, 3)), "shapes": rng.normal(size=(1, 10))}
        np.save(tmp_path / f"{i}.npy", rec)
        recs.append(rec)
    got = read_zju_params(tmp_path)
    assert got["frames"] == [0, 1, 2, 10]
    for k in ("poses", "Rh", "Th", "shapes"):
        np.testing.assert_array_equal(got[k], np.concatenate([r[k] for r in recs]))


def test_zju_params_errors(tmp_path):
    np.save(tmp_path / "0.npy", {"poses": np.zeros((1, 72)), "Th": np.zeros((1, 3)), "shapes": np.zeros((1, 10))})
    with pytest.raises(ValueError, match=r"0\.npy.*missing.*Rh"):
        read_zju_params(tmp_path)
    np.save(tmp_path / "0.npy", np.zeros(3))
    with pytest.raises(ValueError, match=r"0\.npy.*expected a pickled dict"):
        read_zju_params(tmp_path)

    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned",))

    np.save(tmp_path / "0.npy", np.array(Evil(), dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="refusing to unpickle"):
        read_zju_params(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no <i>.npy"):
        read_zju_params(empty)


# ------------------------------------------------------------------------ AMASS
@pytest.mark.parametrize("width,fps_key", [(156, "mocap_framerate"), (165, "mocap_frame_rate"), (72, "mocap_framerate")])
def test_amass(tmp_path, width, fps_key):
    rng = np.random.default_rng(2)
    T = 7
    poses = rng.normal(size=(T, width))
    trans = rng.normal(size=(T, 3))
    path = tmp_path / "clip_poses.npz"
    np.savez(path, poses=poses, trans=trans, betas=rng.normal(size=16), gender=np.array("female"),
             dmpls=np.zeros((T, 8)), **{fps_key: np.array(120.0)})
    got = read_amass_npz(path)
    assert got["poses"].shape == (T, 72) and got["trans"].shape == (T, 3)
    np.testing.assert_array_equal(got["poses"][:, :66], poses[:, :66])
    if width != 72:
        assert (got["poses"][:, 66:] == 0).all()
    assert got["fps"] == 120.0 and got["betas"].shape == (16,) and got["gender"] == "female"


def test_amass_errors(tmp_path):
    T = 4
    base = {"poses": np.zeros((T, 156)), "trans": np.zeros((T, 3)), "mocap_framerate": np.array(60.0)}
    cases = {
        "nofps": ({k: v for k, v in base.items() if k != "mocap_framerate"}, "frame rate"),
        "notrans": ({k: v for k, v in base.items() if k != "trans"}, "'trans'"),
        "badtrans": (dict(base, trans=np.zeros((T + 1, 3))), r"'trans' must be \(4, 3\)"),
        "narrow": (dict(base, poses=np.zeros((T, 30))), "'poses' must be"),
        "nan": (dict(base, poses=np.full((T, 156), np.nan)), "'poses' contains NaN"),
        "zerofps": (dict(base, mocap_framerate=np.array(0.0)), "positive"),
    }
    for name, (arrays, msg) in cases.items():
        path = tmp_path / f"{name}.npz"
        np.savez(path, **arrays)
        with pytest.raises(ValueError, match=msg) as info:
            read_amass_npz(path)
        assert f"{name}.npz" in str(info.value)
