"""anidress import-easymocap (issue 24 item 3): an EasyMocap capture folder becomes a scene.

An EasyMocap capture is not a scene as it is (no scene.yaml; EasyMocap >= 0.2's body files lie in
``output-smpl-3d/smpl/``, not ``<seq>/smpl``), so it is converted. The sample is the tiny skirt
scene's sequence in EasyMocap's layout (zju3dv/EasyMocap doc/dataset.md, doc/02_output.md):
``intri.yml`` as ``write_intri`` writes it (no H_/W_) with unquoted camera names, ``extri.yml``,
``images/<cam>/<frame:06d>.jpg``, ``output-smpl-3d/smpl/<frame:06d>.json`` as ``{"annots": [...]}``
with poses of 69 (root in Rh) and two people per file (the order changing between frames).
"""
from __future__ import annotations

import json
import logging
import re
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
from anidress_core.stages.import_capture import run_import_easymocap
from anidress_core.stages.validate import validate_scene

from tests.io.test_scene_cameras import H, W, build_tiny_skirt

torch.set_num_threads(1)


def write_easymocap_capture(data: Path, out: Path, masks: bool = True) -> Path:
    seq = data / "walk"
    raw = easymocap.read_camera(seq / "intri.yml", seq / "extri.yml")
    easymocap.write_intri(out / "intri.yml", {c: {"K": v["K"], "dist": v["dist"]} for c, v in raw.items()})
    easymocap.write_extri(out / "extri.yml", raw)
    for name in ("intri.yml", "extri.yml"):  # hand-edited: unquoted names, as issue 24 item 8 found them
        p = out / name
        p.write_bytes(p.read_bytes().replace(b'- "01"', b"- 01"))
    body = read_easymocap_smpl_dir(seq / "smpl")
    for t in range(len(body["frames"])):
        for cam in raw:
            (out / "images" / cam).mkdir(parents=True, exist_ok=True)
            img = cv2.imread(str(seq / "images" / cam / f"{t:06d}.png"), cv2.IMREAD_COLOR)
            cv2.imwrite(str(out / "images" / cam / f"{t:06d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
            if masks:
                lab = files.read_mask(seq / "gt" / "masks" / cam / f"{t:06d}.png")
                (out / "mask" / cam).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(out / "mask" / cam / f"{t:06d}.png"), lab)
        person = {"id": 3, "Rh": [body["Rh"][t].tolist()], "Th": [body["Th"][t].tolist()],
                  "poses": [body["poses"][t][3:].tolist()], "shapes": [body["shapes"][t].tolist()]}
        other = {"id": 0, "Rh": [[0.0, 0.0, 0.0]], "Th": [[5.0, 5.0, 0.0]], "poses": [[0.0] * 69],
                 "shapes": [[0.0] * 10]}
        people = [person, other] if t % 2 else [other, person]
        (out / "output-smpl-3d" / "smpl").mkdir(parents=True, exist_ok=True)
        (out / "output-smpl-3d" / "smpl" / f"{t:06d}.json").write_text(json.dumps({"annots": people}))
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("easymocap")
    data, res = build_tiny_skirt(root)
    return data, res, write_easymocap_capture(data, root / "capture")


def _import(cap, dst, data, **kw):
    kw.setdefault("garment", data / "garment" / "template.obj")
    kw.setdefault("garment_kind", "skirt")
    kw.setdefault("body_model", data / "body_model.npz")
    kw.setdefault("train", "01,02,04")
    kw.setdefault("person_id", 3)
    return run_import_easymocap(cap, dst, **kw)


def test_a_capture_folder_is_not_a_scene(tiny):
    """Why the conversion exists: the pipeline's reader needs scene.yaml and <seq>/smpl."""
    _, _, cap = tiny
    with pytest.raises(ValueError, match="scene.yaml: scene description not found"):
        validate_scene(cap)


def test_import_easymocap_validates_and_round_trips(tiny, tmp_path):
    data, _, cap = tiny
    dst = tmp_path / "s"
    rec = _import(cap, dst, data, sequence="walk", masks="mask", mask_format="labels")
    info = yaml.safe_load((dst / "scene.yaml").read_text())
    assert info["synthetic"] is False and info["image_size"] == [H, W] and info["kind"] == "skirt"
    assert info["cameras"] == {"train": ["01", "02", "04"], "test": ["03"]}
    assert rec["cameras"]["01"] == "01" and rec["smpl"].endswith("output-smpl-3d/smpl")
    s = validate_scene(dst)
    assert s["sequences"]["walk"]["frames"] == 3 and s["sequences"]["walk"]["masks"]
    pts = torch.as_tensor(np.random.default_rng(0).normal([0.0, 0.0, 1.0], 0.4, (200, 3)))
    err = (project(pts, scene_cameras(dst, "walk")).uv - project(pts, scene_cameras(data, "walk")).uv).abs().max()
    assert err.item() < 1e-3
    # the person of id 3 in every frame, wherever EasyMocap listed it; poses 69 -> 72 with the root zero
    a, b = read_easymocap_smpl_dir(dst / "walk" / "smpl"), read_easymocap_smpl_dir(data / "walk" / "smpl")
    for k in ("poses", "Rh", "Th", "shapes"):
        np.testing.assert_array_equal(a[k], b[k])
    for cam in ("01", "03"):
        np.testing.assert_array_equal(files.read_mask(dst / "walk" / "masks" / cam / "000002.png"),
                                      files.read_mask(data / "walk" / "gt" / "masks" / cam / "000002.png"))
    # frames by index, renumbered from 0; a second sequence of the same scene
    rec = _import(cap, dst, data, sequence="late", frames="1:", role="novel_pose", garment=None, garment_kind=None,
                  body_model=None, train=None)
    assert [f["source_frame"] for f in rec["frames"]] == [1, 2]
    np.testing.assert_array_equal(read_easymocap_smpl_dir(dst / "late" / "smpl")["Th"], b["Th"][1:])
    assert validate_scene(dst)["sequences"]["late"]["frames"] == 2


def _broken(cap: Path, tmp: Path, edit) -> Path:
    out = tmp / "broken"
    shutil.copytree(cap, out)
    edit(out)
    return out


MALFORMED = {
    "several people, no person id": (lambda d: None, {"person_id": None},
                                     r"000000\.json: holds 2 people \(ids \[0, 3\]\); choose one with person_id"),
    "camera without images": (lambda d: shutil.rmtree(d / "images" / "03"), {},
                              r"images/03: image folder of camera '03' \(listed in .*intri\.yml\) not found"),
    "frame count": (lambda d: (d / "images" / "02" / "000001.jpg").unlink(), {},
                    r"images/02: camera '02' has 2 frames, camera '01' 3 \(frames \[1\]"),
    "missing body file": (lambda d: (d / "output-smpl-3d" / "smpl" / "000002.json").unlink(), {},
                          r"smpl/000002\.json: missing: no body parameters for image frame 2"),
    "missing extrinsics of a camera asked for": (
        lambda d: (d / "extri.yml").write_text((d / "extri.yml").read_text().replace("T_02", "X_02")),
        {"cameras": "01,02,03,04"},
        r"extri\.yml: cameras \['02'\] \(asked for by cameras\) have intrinsics in intri\.yml but no pose here"),
    "no camera with extrinsics": (lambda d: (d / "extri.yml").write_text(
        re.sub(r"\b(T)_0(\d):", r"X_0\2:", (d / "extri.yml").read_text())), {},
        r"extri\.yml: none of the cameras of .*intri\.yml \(\['01', '02', '03', '04'\]\) has a pose"),
    "image size": (lambda d: cv2.imwrite(str(d / "images" / "04" / "000001.jpg"), np.zeros((10, 12, 3), np.uint8)), {},
                   r"images/04/000001\.jpg: image is 12x10 \(WxH\)"),
    "mask labels": (lambda d: cv2.imwrite(str(d / "mask" / "01" / "000000.png"), np.full((H, W), 7, np.uint8)),
                    {"masks": "mask", "mask_format": "labels"}, r"mask/01/000000\.png: labels must be 0 .* found 7"),
    "missing mask": (lambda d: (d / "mask" / "02" / "000002.png").unlink(), {"masks": "mask"},
                     r"mask/02/000002\.png: missing: the mask of this image frame"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_capture_names_file_and_field(tiny, tmp_path, case):
    data, _, cap = tiny
    edit, kw, msg = MALFORMED[case]
    bad = _broken(cap, tmp_path, edit)
    with pytest.raises(ValueError, match=msg):
        _import(bad, tmp_path / "out", data, **kw)
    assert not (tmp_path / "out" / "scene.yaml").exists()


def test_cameras_without_extrinsics_are_skipped_and_named(tiny, tmp_path, caplog):
    """intri.yml listing more cameras than extri.yml poses (as trackmesh_gui writes them): those are left out."""
    data, _, cap = tiny
    src = _broken(cap, tmp_path, lambda d: (d / "extri.yml").write_text(
        re.sub(r"\b(Rot|R|T)_03:", r"Unused\1_03:", (d / "extri.yml").read_text())))
    with caplog.at_level(logging.WARNING, logger="anidress.import"):
        _import(src, tmp_path / "s", data, sequence="walk", train="01,02")
    info = yaml.safe_load((tmp_path / "s" / "scene.yaml").read_text())
    assert info["cameras"] == {"train": ["01", "02"], "test": ["04"]}
    assert any("1 of 4 cameras have intrinsics but no pose in extri.yml, skipped: 03" in r.getMessage()
               for r in caplog.records)
    assert validate_scene(tmp_path / "s")["sequences"]["walk"]["frames"] == 3


def test_cli_import_easymocap(tiny, tmp_path, capsys):
    from anidress_core.cli import main

    data, _, cap = tiny
    rc = main(["import-easymocap", str(cap), str(tmp_path / "c"), "--person-id", "3", "--masks", "mask",
               "--mask-format", "labels", "--body-model", str(data / "body_model.npz"), "--cameras", "01,02,03"])
    assert rc == 0 and "capture: 3 cameras x 3 frames" in capsys.readouterr().out
    info = yaml.safe_load((tmp_path / "c" / "scene.yaml").read_text())
    assert info["kind"] == "tight" and info["cameras"] == {"train": ["01", "02"], "test": ["03"]}
    m = files.read_mask(tmp_path / "c" / "capture" / "masks" / "01" / "000000.png")
    assert set(np.unique(m)) <= {0, 1}  # a tight scene: the garment label is body
    validate_scene(tmp_path / "c")
    assert main(["import-easymocap", str(cap), str(tmp_path / "d")]) == 2  # two people, no --person-id


def test_easymocap_mask_schp_silhouettes_and_parsing_become_labels(tiny, tmp_path):
    """--mask-format schp: EasyMocap's mask-schp (a 0 / 255 silhouette per person, written as its SCHP fork does)
    with the CIHP part labels in mask-schp-parsing/: the person's pixels, dress / skirt as the garment."""
    import shutil

    from anidress_core.io import cue_files

    data, _, cap0 = tiny
    cap = tmp_path / "cap"
    shutil.copytree(cap0, cap)
    for p in sorted((cap / "mask").rglob("*.png")):
        lab = files.read_mask(p)
        cam, t = p.parent.name, p.stem
        (cap / "mask-schp" / cam).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(cap / "mask-schp" / cam / f"{t}_0.png"), ((lab > 0) * 255).astype(np.uint8))
        parsing = np.choose(lab, [0, 13, 12]).astype(np.uint8)  # body: CIHP face, garment: skirt
        parsing[:2] = 2  # hair of someone else above the person: outside the silhouette, not theirs
        cue_files.write_schp_png(cap / "mask-schp-parsing" / cam / f"{t}.png", parsing)
    dst = tmp_path / "s"
    _import(cap, dst, data, sequence="walk", masks="mask-schp", mask_format="schp")
    for cam in ("01", "03"):
        want = files.read_mask(data / "walk" / "gt" / "masks" / cam / "000002.png")
        want[:2] = np.where(want[:2] > 0, 1, 0)  # the hair label is body where the silhouette has the person
        np.testing.assert_array_equal(files.read_mask(dst / "walk" / "masks" / cam / "000002.png"), want)
    shutil.rmtree(cap / "mask-schp-parsing")
    with pytest.raises(ValueError, match="without part labels"):
        _import(cap, tmp_path / "s2", data, sequence="walk", masks="mask-schp", mask_format="schp")
