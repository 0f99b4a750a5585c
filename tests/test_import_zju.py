"""anidress import-zju (issue 24 item 3): a ZJU-MoCap capture becomes a scene the pipeline runs on.

The sample is made from the tiny synthetic skirt scene (tests/io/test_scene_cameras.build_tiny_skirt)
in ZJU-MoCap's layout as zju3dv/neuralbody reads it: ``annots.npy`` (np.save of a dict: cams K, D
(5, 1), R, T (3, 1) in MILLIMETRES, ims [{"ims": [C paths]}]), images as JPEG in CoreView_313's
``Camera (1)/CoreView_313_Camera_(1)_0001_<time>.jpg`` naming (or CoreView_377's
``Camera_B1/000000.jpg``), ``params/<i>.npy`` (or ``new_params/``) dicts of poses (1, 72), Rh, Th,
shapes (1, 10) keyed by the image's frame number, ``mask/`` (0/255) and ``mask_cihp/`` (CIHP part
labels) PNGs at the image paths. Nothing licensed: the values are the tiny scene's.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from anidress_core.camera import project
from anidress_core.io import easymocap, files
from anidress_core.io.motion import read_easymocap_smpl_dir
from anidress_core.io.scene import scene_cameras
from anidress_core.io.zju import safe_camera_names, zju_frame_number
from anidress_core.stages.import_capture import parse_frames, run_import_zju, split_cameras
from anidress_core.stages.validate import validate_scene

from tests.io.test_scene_cameras import H, W, build_tiny_skirt

torch.set_num_threads(1)

# CIHP values standing in for the body parts (face, upper clothes, torso skin, left leg) and the skirt
CIHP_BODY = (13, 5, 10, 16)
CIHP_SKIRT = 12


def _zju_name(c: int, t: int, naming: str) -> tuple[str, int]:
    """(image path relative to the capture, its frame number i of params/<i>.npy)."""
    if naming == "coreview":  # CoreView_313 / 315: frame numbers from 1, in the fifth '_' field
        return f"Camera ({c + 1})/CoreView_313_Camera_({c + 1})_{t + 1:04d}_2019-08-23_16-08-50.592.jpg", t + 1
    return f"Camera_B{c + 1}/{t:06d}.jpg", t


def write_zju_capture(data: Path, out: Path, naming: str = "coreview", params_dir: str = "params") -> Path:
    """The tiny scene's sequence 'walk' (data) as a ZJU-MoCap capture in ``out``."""
    seq = data / "walk"
    raw = easymocap.read_camera(seq / "intri.yml", seq / "extri.yml")
    body = read_easymocap_smpl_dir(seq / "smpl")
    ims = []
    for t in range(len(body["frames"])):
        entry = []
        for c, cam in enumerate(raw):
            rel, number = _zju_name(c, t, naming)
            entry.append(rel)
            img = cv2.imread(str(seq / "images" / cam / f"{t:06d}.png"), cv2.IMREAD_COLOR)
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out / rel), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
            lab = files.read_mask(seq / "gt" / "masks" / cam / f"{t:06d}.png")
            cihp = np.zeros_like(lab)
            yy, xx = np.mgrid[0:lab.shape[0], 0:lab.shape[1]]
            parts = np.asarray(CIHP_BODY, np.uint8)[(yy + 2 * xx) % len(CIHP_BODY)]
            cihp[lab == 1] = parts[lab == 1]
            cihp[lab == 2] = CIHP_SKIRT
            stem = rel[:-4] + ".png"
            for kind, m in (("mask", np.where(lab > 0, 255, 0)), ("mask_cihp", cihp)):
                (out / kind / stem).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(out / kind / stem), m.astype(np.uint8))
        ims.append({"ims": np.asarray(entry)})
        _, number = _zju_name(0, t, naming)
        (out / params_dir).mkdir(parents=True, exist_ok=True)
        np.save(out / params_dir / f"{number}.npy", {
            "poses": body["poses"][t][None], "Rh": body["Rh"][t][None], "Th": body["Th"][t][None],
            "shapes": body["shapes"][t][None]}, allow_pickle=True)
    cams = {"K": [v["K"] for v in raw.values()], "D": [v["dist"].reshape(5, 1) for v in raw.values()],
            "R": [v["R"] for v in raw.values()], "T": [v["T"].reshape(3, 1) * 1000.0 for v in raw.values()]}
    np.save(out / "annots.npy", {"cams": cams, "ims": ims}, allow_pickle=True)
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("zju")
    data, res = build_tiny_skirt(root)
    cap = write_zju_capture(data, root / "CoreView_313")
    return data, res, cap


def _import(cap: Path, dst: Path, data: Path, **kw) -> dict:
    kw.setdefault("garment", data / "garment" / "template.obj")
    kw.setdefault("garment_kind", "skirt")
    kw.setdefault("body_model", data / "body_model.npz")
    kw.setdefault("train", "0,1,3")  # as the tiny scene: 01, 02, 04 train, 03 test
    kw.setdefault("fps", 50.0)
    return run_import_zju(cap, dst, **kw)


# =========================================================================== pure helpers
def test_helpers():
    assert zju_frame_number("Camera (1)/CoreView_313_Camera_(1)_0001_2019-08-23_16-08-50.592.jpg") == 1
    assert zju_frame_number("Camera_B23/000654.jpg") == 654
    with pytest.raises(ValueError, match="no frame number"):
        zju_frame_number("Camera_B1/frame.jpg")
    assert safe_camera_names(["Camera (1)", "Camera (12)"]) == ["Camera_1", "Camera_12"]
    assert safe_camera_names(["Camera_B1", "01"]) == ["Camera_B1", "01"]
    assert safe_camera_names(["a b", "a_b", "c"]) == ["01", "02", "03"]  # collision: indices
    assert safe_camera_names(["(1)", "none"]) == ["01", "02"]  # empty / 'none': indices
    assert parse_frames(None, 4) == [0, 1, 2, 3] and parse_frames("1:", 4) == [1, 2, 3]
    assert parse_frames("::2", 5) == [0, 2, 4] and parse_frames("3,0", 4) == [3, 0]
    for bad, msg in (("9:", "selects no frame"), ("0,7", "outside"), ("a:b", "START:STOP"), ("1,1", "repeated")):
        with pytest.raises(ValueError, match=msg):
            parse_frames(bad, 4)
    names = [f"Camera_B{i + 1}" for i in range(23)]
    tr, te = split_cameras(names)
    assert tr == ["Camera_B1", "Camera_B7", "Camera_B13", "Camera_B19"] and len(te) == 19  # Neural Body's views
    assert split_cameras(["a", "b", "c"]) == (["a", "b"], ["c"])
    assert split_cameras(["a", "b", "c"], ["A", "B", "C"], train="A,2") == (["a", "c"], ["b"])
    assert split_cameras(["a", "b", "c"], test="b") == (["a", "c"], ["b"])
    with pytest.raises(ValueError, match="both train and test"):
        split_cameras(["a", "b"], train="a", test="a")
    with pytest.raises(ValueError, match="'x' is not a camera name"):
        split_cameras(["a", "b"], train="x")


# =========================================================================== the converted scene
def test_import_validates_projects_and_round_trips(tiny, tmp_path):
    data, _, cap = tiny
    dst = tmp_path / "zju"
    rec = _import(cap, dst, data)
    info = yaml.safe_load((dst / "scene.yaml").read_text())
    names = ["Camera_1", "Camera_2", "Camera_3", "Camera_4"]
    assert info["synthetic"] is False and info["kind"] == "skirt" and info["image_size"] == [H, W]
    assert info["cameras"] == {"train": ["Camera_1", "Camera_2", "Camera_4"], "test": ["Camera_3"]}
    assert info["sequences"] == [{"name": "CoreView_313", "role": "train", "frames": 3}]
    assert "motion" not in info["sequences"][0] and info["body_model"]["type"] == "mannequin"
    assert rec["cameras"] == dict(zip(names, [f"Camera ({i})" for i in range(1, 5)]))
    assert [f["params"] for f in rec["frames"]] == ["1.npy", "2.npy", "3.npy"]
    s = validate_scene(dst)
    q = s["sequences"]["CoreView_313"]
    assert q["frames"] == 3 and q["cameras"] == 4 and q["masks"] and q["distorted_cameras"] == []
    # 1. cameras: the converted files project like the originals (the tiny scene's, metres)
    seq = dst / "CoreView_313"
    new = scene_cameras(dst, "CoreView_313")
    old = scene_cameras(data, "walk")
    assert new.names == names and (new.height, new.width) == (H, W)
    pts = torch.as_tensor(np.random.default_rng(0).normal([0.0, 0.0, 1.0], 0.4, (200, 3)))
    err = (project(pts, new).uv - project(pts, old).uv).abs().max().item()
    assert err < 1e-3, err
    # 2. body parameters round trip (EasyMocap files of the converted scene = the originals)
    a, b = read_easymocap_smpl_dir(seq / "smpl"), read_easymocap_smpl_dir(data / "walk" / "smpl")
    for k in ("poses", "Rh", "Th", "shapes"):
        np.testing.assert_array_equal(a[k], b[k])
    # 3. masks: mask_cihp (dress/skirt garment, other parts body) and mask union = the scene's labels
    for c, (n, old_cam) in enumerate(zip(names, ["01", "02", "03", "04"])):
        for t in range(3):
            np.testing.assert_array_equal(files.read_mask(seq / "masks" / n / f"{t:06d}.png"),
                                          files.read_mask(data / "walk" / "gt" / "masks" / old_cam / f"{t:06d}.png"))
            img = seq / "images" / n / f"{t:06d}.jpg"
            assert img.is_symlink() and img.resolve() == (cap / _zju_name(c, t, "coreview")[0]).resolve()
    assert files.read_json(seq / "import.json")["frames"][2]["images"][0] == _zju_name(0, 2, "coreview")[0]


def test_distortion_and_unsafe_names_project_like_opencv(tiny, tmp_path):
    """Non-zero D in annots.npy: the scene's cameras (dist_<cam>, T / 1000) project as cv2.projectPoints
    does with the file's values as neuralbody reads them; camera folders need no quoting."""
    data, _, cap = tiny
    cap2 = tmp_path / "cap"
    shutil.copytree(cap, cap2)
    raw = np.load(cap2 / "annots.npy", allow_pickle=True).item()
    raw["cams"]["D"][0] = np.array([[-0.3], [0.1], [4e-4], [-3e-4], [0.01]])
    raw["cams"]["D"][2] = np.array([[0.2], [0.0], [0.0], [5e-4], [0.0]])
    np.save(cap2 / "annots.npy", raw, allow_pickle=True)
    dst = tmp_path / "d"
    _import(cap2, dst, data, garment=None, garment_kind=None, body_model=None, sequence="walk", masks="mask")
    cams = scene_cameras(dst, "walk")
    pts = np.random.default_rng(1).normal([0.0, 0.0, 1.0], 0.3, (100, 3))
    uv = project(torch.as_tensor(pts), cams).uv.numpy()
    for c in range(4):
        ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(raw["cams"]["R"][c])[0], raw["cams"]["T"][c] / 1000.0,
                                   raw["cams"]["K"][c], raw["cams"]["D"][c])
        assert np.abs(uv[c] - ref[:, 0]).max() < 1e-3
    info = yaml.safe_load((dst / "scene.yaml").read_text())
    assert info["kind"] == "tight" and "garment_template" not in info
    assert info["body_model"] == {"type": "mannequin", "file": "body_model.npz", "height_m": 1.7}  # the bundled one
    s = validate_scene(dst)
    assert s["sequences"]["walk"]["distorted_cameras"] == ["Camera_1", "Camera_3"]
    # no garment template: every person pixel is body (mask/ alone has no part labels anyway)
    m = files.read_mask(dst / "walk" / "masks" / "Camera_2" / "000001.png")
    assert set(np.unique(m)) == {0, 1}


def test_second_sequence_frames_and_new_params(tiny, tmp_path):
    """CoreView_377's naming (Camera_B1/000000.jpg) with new_params/; a frame range added as a
    novel-pose sequence of the same scene."""
    data, _, _ = tiny
    cap = write_zju_capture(data, tmp_path / "CoreView_377", naming="b", params_dir="new_params")
    dst = tmp_path / "s"
    _import(cap, dst, data, sequence="train", frames="0:2", link="copy")
    rec = _import(cap, dst, data, sequence="novel", frames="2,1", role="novel_pose", garment=None,
                  garment_kind=None, body_model=None, train=None)
    info = yaml.safe_load((dst / "scene.yaml").read_text())
    assert [(s["name"], s["role"], s["frames"]) for s in info["sequences"]] == [("train", "train", 2),
                                                                                 ("novel", "novel_pose", 2)]
    assert info["cameras"]["train"] == ["Camera_B1", "Camera_B2", "Camera_B4"]
    assert [f["ims_index"] for f in rec["frames"]] == [2, 1] and rec["params"].endswith("new_params")
    assert not (dst / "train" / "images" / "Camera_B1" / "000000.jpg").is_symlink()
    b = read_easymocap_smpl_dir(data / "walk" / "smpl")
    n = read_easymocap_smpl_dir(dst / "novel" / "smpl")
    np.testing.assert_array_equal(n["poses"], b["poses"][[2, 1]])
    np.testing.assert_array_equal(n["Th"], b["Th"][[2, 1]])
    assert validate_scene(dst)["sequences"]["novel"]["frames"] == 2
    with pytest.raises(ValueError, match="no --garment / --body-model when adding"):
        _import(cap, dst, data, sequence="x")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match=r"other: exists, is not empty and has no scene.yaml"):
        _import(cap, tmp_path / "other", data)


# =========================================================================== malformed captures
def _broken(cap: Path, tmp: Path, edit) -> Path:
    out = tmp / "broken"
    shutil.copytree(cap, out)
    edit(out)
    return out


def _edit_annots(fn):
    def edit(d):
        raw = np.load(d / "annots.npy", allow_pickle=True).item()
        fn(raw)
        np.save(d / "annots.npy", raw, allow_pickle=True)
    return edit


def _edit_params(i, fn):
    def edit(d):
        p = d / "params" / f"{i}.npy"
        obj = np.load(p, allow_pickle=True).item()
        fn(obj)
        np.save(p, obj, allow_pickle=True)
    return edit


CIHP_STEM = "Camera (2)/CoreView_313_Camera_(2)_0002_2019-08-23_16-08-50.592"
MALFORMED = {
    "annots missing key": (_edit_annots(lambda r: r.pop("ims")), r"annots\.npy: missing key 'ims'"),
    "cams missing field": (_edit_annots(lambda r: r["cams"].pop("R")), r"annots\.npy: 'cams' has no 'R'"),
    "camera count": (_edit_annots(lambda r: r["cams"]["T"].pop()),
                     r"annots\.npy: 'cams/T' has 3 cameras, 'cams/K' has 4"),
    "image list count": (_edit_annots(lambda r: r["ims"][1].update(ims=r["ims"][1]["ims"][:3])),
                         r"annots\.npy: 'ims\[1\]' lists 3 images for 4 cameras"),
    "T shape": (_edit_annots(lambda r: r["cams"]["T"].__setitem__(2, np.zeros((2, 1)))),
                r"annots\.npy: 'cams/T\[2\]' must hold 3 numbers"),
    "frame numbers disagree": (_edit_annots(lambda r: r["ims"][0]["ims"].__setitem__(
        1, "Camera (2)/CoreView_313_Camera_(2)_0007_2019-08-23_16-08-50.592.jpg")),
        r"annots\.npy: 'ims\[0\]' images have different frame numbers \[1, 7\]"),
    "missing image": (lambda d: (d / f"{CIHP_STEM}.jpg").unlink(),
                      r"annots\.npy: 'ims\[1\]' image 1 \(Camera \(2\)/.*_0002_.*\.jpg\) is missing"),
    "image size": (lambda d: cv2.imwrite(str(d / f"{CIHP_STEM}.jpg"), np.zeros((20, 20, 3), np.uint8)),
                   r"_0002_.*\.jpg: image is 20x20 \(WxH\), the capture's first image is 40x48"),
    "missing params file": (lambda d: (d / "params" / "3.npy").unlink(),
                            r"params/3\.npy: missing: no body parameters for frame number 3"),
    "params missing Th": (_edit_params(2, lambda o: o.pop("Th")), r"params/2\.npy: missing key\(s\) \['Th'\]"),
    "params poses size": (_edit_params(1, lambda o: o.update(poses=np.zeros((1, 10)))),
                          r"params/1\.npy: 'poses' holds 10 numbers"),
    "missing mask": (lambda d: (d / "mask_cihp" / f"{CIHP_STEM}.png").unlink(),
                     r"mask_cihp/Camera \(2\)/.*_0002_.*\.png: missing: the mask_cihp/ file of image"),
    "mask size": (lambda d: cv2.imwrite(str(d / "mask" / f"{CIHP_STEM}.png"), np.zeros((8, 8), np.uint8)),
                  r"mask/Camera \(2\)/.*\.png: mask is 8x8 \(WxH\), the image .* is 40x48"),
    "cihp labels": (lambda d: cv2.imwrite(str(d / "mask_cihp" / f"{CIHP_STEM}.png"), np.full((H, W), 30, np.uint8)),
                    r"mask_cihp/Camera \(2\)/.*\.png: .*CIHP labels 0\.\.19, got 30\.\.30"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_capture_names_file_and_field(tiny, tmp_path, case):
    data, _, cap = tiny
    edit, msg = MALFORMED[case]
    bad = _broken(cap, tmp_path, edit)
    with pytest.raises(ValueError, match=msg):
        _import(bad, tmp_path / "out", data)
    assert not (tmp_path / "out" / "scene.yaml").exists()  # nothing half-written


def test_cli_import_zju(tiny, tmp_path, capsys):
    from anidress_core.cli import main

    data, _, cap = tiny
    dst = tmp_path / "cli"
    rc = main(["import-zju", str(cap), str(dst), "--sequence", "walk", "--frames", "0:2", "--garment",
               str(data / "garment" / "template.obj"), "--garment-kind", "skirt", "--body-model",
               str(data / "body_model.npz"), "--train", "Camera (1),Camera (2),Camera (4)", "--fps", "50"])
    out = capsys.readouterr().out
    assert rc == 0 and "walk: 4 cameras x 2 frames" in out and ": OK (3 train + 1 test cameras" in out  # validated
    assert yaml.safe_load(out[out.index("scenes:"):])["scenes"]["cli"]["sequences"] == [
        {"name": "walk", "frames": 2, "role": "train"}]  # the config entry, ready to paste
    assert yaml.safe_load((dst / "scene.yaml").read_text())["cameras"]["test"] == ["Camera_3"]
    bad = _broken(cap, tmp_path, lambda d: (d / "params" / "2.npy").unlink())
    assert main(["import-zju", str(bad), str(tmp_path / "x"), "--fps", "50"]) == 2
    with pytest.raises(ValueError, match=r"annots\.npy: ZJU-MoCap's files do not store the frame rate: give"):
        run_import_zju(cap, tmp_path / "nofps")


# =========================================================================== through the pipeline
def test_converted_scene_runs_validate_masks_fit(tiny, tmp_path):
    """validate -> template -> masks (estimated, no background plates) -> fit on the converted masks;
    the fit equals the fit of the scene the capture was made from (same cues, cameras in mm and back)."""
    pytest.importorskip("warp")  # the fit's L_collision
    from anidress_core.io.garment_poses import read_garment_poses
    from anidress_core.io.scene import read_scene
    from anidress_core.stages.cues import ShapePrior, run_masks
    from anidress_core.stages.fit import run_fit
    from anidress_core.stages.template import run_template
    from anidress_core.io.scene import load_body

    data, res, cap = tiny
    dst = tmp_path / "zju"
    _import(cap, dst, data, sequence="walk")
    validate_scene(dst)
    # template of the converted scene = the original's (same garment file and body model)
    tpl = run_template(dst / "garment" / "template.obj", "skirt", load_body(dst), 300, tmp_path / "template.ply",
                       tmp_path / "template.npz")
    ref = files.load_npz(res / "template.npz")[0]
    np.testing.assert_array_equal(tpl.verts, ref["verts"])
    np.testing.assert_array_equal(tpl.faces, ref["faces"])
    # masks estimated without plates (a capture has none): the stage runs on the converted scene, and its
    # shape prior (posed body + skinned garment, from the converted cameras and body parameters) is the
    # original scene's and lands on the subject
    # (3 frames of a slow walk: their median plate is mostly the subject, so most masks come out empty; the
    # stage would refuse that (tests/cues/test_stage.py), allowed here: only the run and the prior are tested)
    ms = run_masks(dst, "walk", tmp_path / "est", {"background": "temporal_median", "median_frames": 3,
                                                     "max_empty_fraction": 1.0},
                   tmp_path / "template.npz", cameras=["Camera_1"], threads=1, progress=False)
    assert ms["frames"] == 3 and 0 <= ms["empty_masks"] <= 3 and files.read_mask(tmp_path / "est" / "Camera_1" / "000002.png").shape == (H, W)
    info_new, info_old = read_scene(dst), read_scene(data)
    new = ShapePrior(dst, "walk", info_new, tmp_path / "template.npz",
                     scene_cameras(dst, "walk", None, info_new, torch.float32), [0, 1, 2]).labels(1)
    old = ShapePrior(data, "walk", info_old, res / "template.npz",
                     scene_cameras(data, "walk", None, info_old, torch.float32), [0, 1, 2]).labels(1)
    assert (new != old).mean() < 1e-3, (new != old).mean()
    truth = np.stack([files.read_mask(dst / "walk" / "masks" / c / "000001.png") for c in info_new["cameras"]["train"]
                      + info_new["cameras"]["test"]])
    truth = truth[[0, 1, 3, 2]]  # scene.yaml order (train 1, 2, 4; test 3) back to the file order
    iou = ((new > 0) & (truth > 0)).sum() / ((new > 0) | (truth > 0)).sum()
    assert iou > 0.7, iou
    params = {"views": 2, "max_iters": 2, "max_iters_first": 3, "weights": {"anchor": 0.0}, "threads": 1,
              "prior_reference": "sim"}  # the rig's own simulation: no stiffness ensemble in this test
    run_fit(dst, "walk", res / "rig.npz", tmp_path / "template.npz", dst / "walk" / "masks", None, None, params,
            tmp_path / "zju_poses.npz", progress=False)
    run_fit(data, "walk", res / "rig.npz", res / "template.npz", data / "walk" / "gt" / "masks", None, None, params,
            tmp_path / "ref_poses.npz", progress=False)
    a = read_garment_poses(tmp_path / "zju_poses.npz", frames=3, bones=4)
    b = read_garment_poses(tmp_path / "ref_poses.npz", frames=3, bones=4)
    assert np.isfinite(a.verts).all()
    assert np.abs(a.verts - b.verts).max() < 1e-4, np.abs(a.verts - b.verts).max()
