"""EasyMocap intri.yml / extri.yml: layout, exact round trips, EasyMocap-written files, errors."""
import os

import cv2
import numpy as np
import pytest

from anidress_core.io import easymocap as em


def _rot(rvec):
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def _cameras(names=("b2", "01", "a-c"), seed=0, hw=True):
    rng = np.random.default_rng(seed)
    cams = {}
    for n in names:
        K = np.array([[rng.uniform(500, 1500), 0.0, rng.uniform(300, 700)],
                      [0.0, rng.uniform(500, 1500), rng.uniform(200, 500)],
                      [0.0, 0.0, 1.0]])
        cams[n] = {
            "K": K,
            # awkward doubles: tiny, negative zero, long mantissas
            "dist": np.array([rng.normal() * 0.1, 1e-17 * rng.normal(), -0.0, rng.normal() * 1e-3, 1 / 3]),
            "R": _rot(rng.normal(size=3)),
            "T": rng.normal(size=3) * 3,
        }
        if hw:
            cams[n].update(H=1024, W=1224)
    return cams


def test_round_trip_is_exact_and_keeps_order(tmp_path):
    cams = _cameras()
    em.write_camera(tmp_path / "intri.yml", tmp_path / "extri.yml", cams)
    back = em.read_camera(tmp_path / "intri.yml", tmp_path / "extri.yml")
    assert list(back) == ["b2", "01", "a-c"]
    for n, cam in cams.items():
        for k in ("K", "dist", "R", "T"):
            assert back[n][k].dtype == np.float64
            assert back[n][k].shape == np.shape(cam[k])
            # bit for bit, including the sign of -0.0
            assert back[n][k].tobytes() == np.asarray(cam[k], dtype=np.float64).tobytes(), (n, k)
        assert back[n]["H"] == 1024 and back[n]["W"] == 1224
    # subset, in the order asked for
    sub = em.read_camera(tmp_path / "intri.yml", tmp_path / "extri.yml", names=["a-c", "b2"])
    assert list(sub) == ["a-c", "b2"]


def test_files_are_opencv_yaml_with_easymocap_nodes(tmp_path):
    cams = _cameras(names=("01", "02"))
    em.write_camera(tmp_path / "intri.yml", tmp_path / "extri.yml", cams)
    raw = (tmp_path / "intri.yml").read_bytes()
    assert raw.startswith(b"%YAML:1.0\r\n---\r\nnames:\r\n  - \"01\"\r\n  - \"02\"\r\n")
    assert b"\n" not in raw.replace(b"\r\n", b"")
    fs = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_READ)
    assert fs.root().keys() == ("names", "K_01", "dist_01", "H_01", "W_01", "K_02", "dist_02", "H_02", "W_02")
    assert fs.getNode("K_01").mat().shape == (3, 3)
    assert fs.getNode("dist_01").mat().shape == (1, 5)
    assert fs.getNode("H_02").isInt() and int(fs.getNode("W_02").real()) == 1224
    names = fs.getNode("names")
    assert [names.at(i).string() for i in range(names.size())] == ["01", "02"]
    fs.release()
    fs = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_READ)
    assert fs.root().keys() == ("names", "R_01", "Rot_01", "T_01", "R_02", "Rot_02", "T_02")
    assert fs.getNode("R_01").mat().shape == (3, 1)
    assert fs.getNode("Rot_01").mat().shape == (3, 3)
    assert fs.getNode("T_01").mat().shape == (3, 1)
    np.testing.assert_allclose(cv2.Rodrigues(fs.getNode("R_02").mat())[0], cams["02"]["R"], atol=1e-12)
    fs.release()


# What EasyMocap's write_camera produces (six decimals, CRLF), for one camera.
EASYMOCAP_INTRI = (
    "%YAML:1.0\r\n---\r\nnames:\r\n  - \"01\"\r\n"
    "K_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 3\r\n  dt: d\r\n"
    "  data: [1000.000000, 0.000000, 511.500000, 0.000000, 1001.250000, 383.500000, 0.000000, 0.000000, 1.000000]\r\n"
    "dist_01: !!opencv-matrix\r\n  rows: 1\r\n  cols: 5\r\n  dt: d\r\n"
    "  data: [-0.100000, 0.020000, 0.001000, -0.002000, 0.000000]\r\n"
    "H_01: 768\r\nW_01: 1024\r\n"
)
EASYMOCAP_EXTRI = (
    "%YAML:1.0\r\n---\r\nnames:\r\n  - \"01\"\r\n"
    "R_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 1\r\n  dt: d\r\n"
    "  data: [0.000000, 0.000000, 0.000000]\r\n"
    "Rot_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 3\r\n  dt: d\r\n"
    "  data: [1.000000, 0.000000, 0.000000, 0.000000, 1.000000, 0.000000, 0.000000, 0.000000, 1.000000]\r\n"
    "T_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 1\r\n  dt: d\r\n"
    "  data: [0.100000, -0.200000, 3.000000]\r\n"
)


def _easymocap_camera():
    return {"01": {
        "K": np.array([[1000.0, 0, 511.5], [0, 1001.25, 383.5], [0, 0, 1]]),
        "dist": np.array([-0.1, 0.02, 0.001, -0.002, 0.0]),
        "R": np.eye(3), "T": np.array([0.1, -0.2, 3.0]), "H": 768, "W": 1024,
    }}


def test_easymocap_written_files_parse(tmp_path):
    (tmp_path / "intri.yml").write_bytes(EASYMOCAP_INTRI.encode())
    (tmp_path / "extri.yml").write_bytes(EASYMOCAP_EXTRI.encode())
    back = em.read_camera(tmp_path / "intri.yml", tmp_path / "extri.yml")
    want = _easymocap_camera()["01"]
    assert list(back) == ["01"]
    for k in ("K", "dist", "R", "T"):
        np.testing.assert_array_equal(back["01"][k], want[k])
    assert (back["01"]["H"], back["01"]["W"]) == (768, 1024)


def test_six_decimals_reproduce_easymocap_bytes(tmp_path):
    em.write_camera(tmp_path / "intri.yml", tmp_path / "extri.yml", _easymocap_camera(), decimals=6)
    assert (tmp_path / "intri.yml").read_bytes() == EASYMOCAP_INTRI.encode()
    assert (tmp_path / "extri.yml").read_bytes() == EASYMOCAP_EXTRI.encode()


def test_rodrigues_fallback_numeric_names_and_optional_keys(tmp_path):
    rvec = [0.1, -0.2, 0.3]
    intri = (
        "%YAML:1.0\n---\nnames:\n  - 1\n  - none\n  - \"cam2\"\n"
        "K_1: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [2., 0., 1., 0., 2., 1., 0., 0., 1.]\n"
        # ZJU-MoCap style 'D_' and four coefficients
        "D_1: !!opencv-matrix\n  rows: 4\n  cols: 1\n  dt: d\n  data: [0.1, 0.2, 0.3, 0.4]\n"
        "K_cam2: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: f\n  data: [2., 0., 1., 0., 2., 1., 0., 0., 1.]\n"
        "dist_cam2: !!opencv-matrix\n  rows: 5\n  cols: 1\n  dt: d\n  data: [0., 0., 0., 0., 0.]\n"
    )
    extri = (
        "%YAML:1.0\n---\nnames:\n  - 1\n  - \"cam2\"\n"
        f"R_1: !!opencv-matrix\n  rows: 3\n  cols: 1\n  dt: d\n  data: {rvec}\n"
        "T_1: !!opencv-matrix\n  rows: 1\n  cols: 3\n  dt: d\n  data: [1., 2., 3.]\n"
        f"R_cam2: !!opencv-matrix\n  rows: 3\n  cols: 1\n  dt: d\n  data: {rvec}\n"
        "T_cam2: !!opencv-matrix\n  rows: 3\n  cols: 1\n  dt: d\n  data: [1., 2., 3.]\n"
    )
    (tmp_path / "intri.yml").write_text(intri)
    (tmp_path / "extri.yml").write_text(extri)
    back = em.read_camera(tmp_path / "intri.yml", tmp_path / "extri.yml")
    assert list(back) == ["1", "cam2"]
    np.testing.assert_array_equal(back["1"]["dist"], [0.1, 0.2, 0.3, 0.4, 0.0])
    np.testing.assert_array_equal(back["1"]["R"], _rot(rvec))
    np.testing.assert_array_equal(back["1"]["T"], [1.0, 2.0, 3.0])
    assert back["cam2"]["K"].dtype == np.float64 and back["cam2"]["K"][0, 0] == 2.0
    assert "H" not in back["1"] and "W" not in back["1"]


def _write_pair(tmp_path, intri=None, extri=None):
    em.write_camera(tmp_path / "intri.yml", tmp_path / "extri.yml", _cameras(names=("01",)))
    for name, repl in (("intri.yml", intri), ("extri.yml", extri)):
        if repl is not None:
            p = tmp_path / name
            p.write_bytes(repl(p.read_bytes().decode()).encode())
    return tmp_path / "intri.yml", tmp_path / "extri.yml"


def test_errors_name_file_and_key(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.yml"):
        em.read_intri(tmp_path / "nope.yml")

    i, e = _write_pair(tmp_path, intri=lambda s: s.replace("K_01", "Kx_01"))
    with pytest.raises(ValueError, match=r"intri\.yml.*'01'.*'K_01'"):
        em.read_camera(i, e)

    i, e = _write_pair(tmp_path, extri=lambda s: s.replace("T_01", "Tx_01"))
    with pytest.raises(ValueError, match=r"extri\.yml.*'01'.*'T_01'"):
        em.read_camera(i, e)

    i, e = _write_pair(tmp_path, intri=lambda s: s.replace("dist_01", "dd_01"))
    with pytest.raises(ValueError, match=r"intri\.yml.*'dist_01'.*'D_01'"):
        em.read_camera(i, e)

    # rows * cols != number of data
    i, e = _write_pair(tmp_path, intri=lambda s: s.replace("rows: 3\r\n  cols: 3", "rows: 3\r\n  cols: 4", 1))
    with pytest.raises(ValueError, match=r"intri\.yml.*'K_01'.*malformed"):
        em.read_camera(i, e)

    # a plain list instead of an !!opencv-matrix
    i, e = _write_pair(tmp_path, extri=lambda s: s.split("T_01")[0] + "T_01: [1, 2, 3]\r\n")
    with pytest.raises(ValueError, match=r"extri\.yml.*'T_01'"):
        em.read_camera(i, e)

    # wrong size
    i, e = _write_pair(tmp_path, extri=lambda s: s.split("T_01")[0]
                       + "T_01: !!opencv-matrix\r\n  rows: 2\r\n  cols: 1\r\n  dt: d\r\n  data: [1., 2.]\r\n")
    with pytest.raises(ValueError, match=r"extri\.yml.*'T_01' has 2 elements"):
        em.read_camera(i, e)

    i, e = _write_pair(tmp_path, intri=lambda s: s.replace("names:", "cams:"))
    with pytest.raises(ValueError, match=r"intri\.yml.*'names'"):
        em.read_camera(i, e)

    i, e = _write_pair(tmp_path)
    with pytest.raises(ValueError, match=r"intri\.yml.*\['zz'\]"):
        em.read_camera(i, e, names=["zz"])

    (tmp_path / "garbage.yml").write_text("K_01: [1, 2\n  : :")
    with pytest.raises(ValueError, match="garbage.yml"):
        em.read_intri(tmp_path / "garbage.yml")


def test_rot_and_rvec_must_agree(tmp_path):
    cams = _cameras(names=("01",))
    em.write_camera(tmp_path / "intri.yml", tmp_path / "extri.yml", cams)
    text = (tmp_path / "extri.yml").read_bytes().decode()
    head, rest = text.split("R_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 1\r\n  dt: d\r\n  data: [")
    bad = head + "R_01: !!opencv-matrix\r\n  rows: 3\r\n  cols: 1\r\n  dt: d\r\n  data: [0.5, 0.5, 0.5" \
        + rest[rest.index("]"):]
    (tmp_path / "extri.yml").write_bytes(bad.encode())
    with pytest.raises(ValueError, match=r"extri\.yml.*'Rot_01'.*'R_01'.*disagree"):
        em.read_extri(tmp_path / "extri.yml")


def test_writer_validates_and_is_atomic(tmp_path, monkeypatch):
    cams = _cameras(names=("01",))
    with pytest.raises(ValueError, match="'a.b'"):
        em.write_intri(tmp_path / "intri.yml", {"a.b": cams["01"]})
    with pytest.raises(ValueError, match=r"'01'.*'K_01' needs 9 values"):
        em.write_intri(tmp_path / "intri.yml", {"01": {**cams["01"], "K": np.eye(2)}})
    with pytest.raises(ValueError, match=r"extri.yml.*'01'.*'T_01'.*non-finite"):
        em.write_extri(tmp_path / "extri.yml", {"01": {**cams["01"], "T": np.array([0, np.nan, 0])}})
    assert list(tmp_path.iterdir()) == []

    # a failure while renaming leaves the old file and no temporary behind
    em.write_intri(tmp_path / "intri.yml", cams)
    before = (tmp_path / "intri.yml").read_bytes()

    def boom(*a, **k):
        raise OSError("disk gone")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        em.write_intri(tmp_path / "intri.yml", _cameras(names=("01",), seed=5))
    monkeypatch.undo()
    assert (tmp_path / "intri.yml").read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["intri.yml"]


# ---------------------------------------------- issue 24 item 8: unquoted names, used cameras
SAMPLE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "data", "easymocap_cams")


def test_unquoted_names_take_the_zero_padded_spelling_of_the_keys():
    intri, extri = os.path.join(SAMPLE, "intri.yml"), os.path.join(SAMPLE, "extri.yml")
    assert "  - 01\r\n" in open(intri, newline="").read()  # the sample really is unquoted
    assert em.read_names(intri) == em.read_names(extri) == ["01", "02", "03"]
    cams = em.read_camera(intri, extri)
    assert list(cams) == ["01", "02", "03"]
    assert cams["02"]["K"][0, 0] == 501.0
    np.testing.assert_allclose(cams["02"]["R"], _rot([0.0, 2 * np.pi / 3, 0.0]), atol=1e-6)
    np.testing.assert_array_equal(cams["03"]["T"], [0.0, 0.0, 3.0])


def test_numeric_name_without_one_spelling_says_to_quote(tmp_path):
    k = "  rows: 3\n  cols: 3\n  dt: d\n  data: [2., 0., 1., 0., 2., 1., 0., 0., 1.]\n"
    d = "  rows: 1\n  cols: 5\n  dt: d\n  data: [0., 0., 0., 0., 0.]\n"
    # 7 is spelled two ways (07, 007): ambiguous, the name stays "7"
    (tmp_path / "intri.yml").write_text("%YAML:1.0\n---\nnames:\n  - 7\n"
                                        f"K_07: !!opencv-matrix\n{k}dist_07: !!opencv-matrix\n{d}"
                                        f"K_007: !!opencv-matrix\n{k}dist_007: !!opencv-matrix\n{d}")
    with pytest.raises(ValueError, match=r"intri\.yml: camera '7': missing key 'K_7' \(camera names must be "
                                         r"strings: quote them \('01'\)"):
        em.read_intri(tmp_path / "intri.yml")


def test_camera_names_asked_as_numbers_say_to_quote():
    intri, extri = os.path.join(SAMPLE, "intri.yml"), os.path.join(SAMPLE, "extri.yml")
    with pytest.raises(ValueError, match=r"intri\.yml: cameras \[1\] asked for are not strings: .*quote them"):
        em.read_camera(intri, extri, names=[1, "02"])
    with pytest.raises(ValueError, match=r"extri\.yml: cameras \[2\] asked for are not strings"):
        em.read_extri(extri, names=[2])
