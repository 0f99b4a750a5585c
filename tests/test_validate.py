"""Scene validation (issue 8, bad input): one clear error per malformed scene, nothing written.

A tiny valid skirt scene is synthesised once per module; each test copies it, breaks
ONE thing and checks the error type, that the message names the file and the
problem, and that no results file was written.
"""
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from anidress_core.cli import main as cli_main
from anidress_core.config import default_schema_path, validate_config
from anidress_core.io import easymocap, files
from anidress_core.io.files import SceneError
from anidress_core.io.mesh import read_mesh, write_obj
from anidress_core.stages.validate import SELF_INTERSECTION_TOLERANCE, run_validate, unit_guess, validate_scene

REPO = Path(__file__).resolve().parents[1]
TINY = {
    "kind": "skirt", "image_size": [32, 32], "cameras": {"count": 4, "train": 3}, "body": {"vertices": 1500},
    "sequences": [{"name": "walk", "motion": "walk", "frames": 3}],
    "garment": {"vertices": 300, "cloth": {"settle_frames": 2}},
    "render": {"texture_size": 64, "supersample": 1},
}


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from anidress_core.stages.synth import run_synth

    torch.set_num_threads(1)
    cfg = validate_config({"run_scenes": ["t"], "scenes": {"t": TINY}},
                          yaml.safe_load(default_schema_path().read_text()))["scenes"]["t"]
    return run_synth(cfg, "t", tmp_path_factory.mktemp("valid") / "data" / "t", threads=1, progress=False)


@pytest.fixture
def scene(tiny_scene, tmp_path):
    """A fresh copy of the valid scene: tmp/data/t (break one thing in it)."""
    dst = tmp_path / "data" / "t"
    shutil.copytree(tiny_scene, dst)
    return dst


def _fails(scene: Path, path: Path, *words: str) -> str:
    """Validate, expect one SceneError naming ``path`` and ``words``; no results written."""
    out = scene.parent.parent / "results" / "t" / "scene_check.json"
    with pytest.raises(SceneError) as e:
        run_validate(scene, out)
    msg = str(e.value)
    assert "\n" not in msg
    assert str(path) in msg, msg
    for w in words:
        assert w in msg, msg
    assert not (scene.parent.parent / "results").exists()
    return msg


# --------------------------------------------------------------------------- the valid scene


def test_valid_scene_passes_and_writes_the_summary(scene, tmp_path):
    out = tmp_path / "results" / "t" / "scene_check.json"
    s = run_validate(scene, out)
    assert json.loads(out.read_text()) == s
    assert s["sequences"]["walk"]["frames"] == 3 and s["sequences"]["walk"]["cameras"] == 4
    assert s["sequences"]["walk"]["images_decoded"] == 8  # first and last frame of 4 cameras
    assert s["garment"] and s["garment_template"]["self_intersecting_faces"] == 0
    assert s["image_size"] == [32, 32] and s["cameras"]["train"] and s["cameras"]["test"]
    assert "garment self-intersections" in s["checks"] and "cameras see the body (same world frame and units)" in s["checks"]
    assert validate_scene(scene, images="all")["sequences"]["walk"]["images_decoded"] == 12


def test_cli_prints_the_summary_or_the_error(scene, capsys):
    assert cli_main(["validate", str(scene)]) == 0
    assert f"{scene}: OK" in capsys.readouterr().out
    (scene / "walk" / "intri.yml").unlink()
    assert cli_main(["validate", str(scene)]) == 2
    assert f"{scene / 'walk' / 'intri.yml'}: camera file missing" in capsys.readouterr().err


# --------------------------------------------------------------------------- cameras


@pytest.mark.parametrize("name", ["intri.yml", "extri.yml"])
def test_missing_camera_file(scene, name):
    (scene / "walk" / name).unlink()
    _fails(scene, scene / "walk" / name, "camera file missing")


def test_camera_missing_from_extri(scene):
    p = scene / "walk" / "extri.yml"
    cams = easymocap.read_extri(p)
    del cams["03"]
    easymocap.write_extri(p, cams)
    _fails(scene, p, "camera '03' listed in intri.yml has no extrinsics")


def test_scene_camera_missing_from_both_files(scene):
    for name, rd, wr in (("intri.yml", easymocap.read_intri, easymocap.write_intri),
                         ("extri.yml", easymocap.read_extri, easymocap.write_extri)):
        cams = rd(scene / "walk" / name)
        del cams["02"]
        wr(scene / "walk" / name, cams)
    _fails(scene, scene / "walk" / "intri.yml", "camera '02' of scene.yaml cameras/", "is not listed")


def test_extrinsics_in_millimetres(scene):
    p = scene / "walk" / "extri.yml"
    cams = easymocap.read_extri(p)
    easymocap.write_extri(p, {c: {"R": v["R"], "T": 1000.0 * v["T"]} for c, v in cams.items()})
    _fails(scene, p, "looks like millimetres")


def _calibrate_at(scene: Path, factor: float, sizes: bool) -> dict:
    """Rewrite walk/intri.yml as made for images ``factor`` times the size of the scene's (with or without
    H_/W_); returns the original intrinsics."""
    from anidress_core.camera import scale_intrinsics

    p = scene / "walk" / "intri.yml"
    orig = easymocap.read_intri(p)
    new = {}
    for c, v in orig.items():
        new[c] = {"K": scale_intrinsics(v["K"], factor), "dist": v["dist"]}
        if sizes:
            new[c].update(H=int(v["H"] * factor), W=int(v["W"] * factor))
    easymocap.write_intri(p, new)
    return orig


def _scene_yaml(scene: Path, **cameras) -> None:
    p = scene / "scene.yaml"
    info = yaml.safe_load(p.read_text())
    info["cameras"].update(cameras)
    p.write_text(yaml.safe_dump(info))


@pytest.mark.parametrize("sizes", [False, True], ids=["no H_W_", "with H_W_"])
def test_a_calibration_of_twice_the_image_size_names_the_factor(scene, sizes):
    from anidress_core.io.scene import scene_cameras

    orig = _calibrate_at(scene, 2.0, sizes)
    if not sizes:  # EasyMocap's files: only the principal point tells
        _fails(scene, scene / "walk" / "intri.yml", "camera '01': principal point", "of the 32x32 images",
               "looks made for images 2x this size", "cameras/scale: 0.5")
    else:
        p = scene / "scene.yaml"
        info = yaml.safe_load(p.read_text())
        del info["image_size"]  # the size then comes from H_/W_, the images disagree
        p.write_text(yaml.safe_dump(info))
        _fails(scene, scene / "walk" / "images", "image is 32x32 (WxH), expected 64x64",
               "the images are 0.5x the calibration's size", "cameras/scale: 0.5")
    _scene_yaml(scene, scale=0.5)
    assert validate_scene(scene)["sequences"]["walk"]["frames"] == 3
    cams = scene_cameras(scene, "walk")
    K0 = torch.as_tensor(np.stack([orig[c]["K"] for c in cams.names]))
    assert torch.allclose(cams.K, K0, atol=1e-9) and (cams.height, cams.width) == (32, 32)


def test_an_off_centre_principal_point_passes_only_when_declared(scene):
    p = scene / "walk" / "intri.yml"
    cams = easymocap.read_intri(p)
    cams["02"]["K"][0, 2] = 28.0  # near the right edge of the 32 pixels
    easymocap.write_intri(p, cams)
    msg = _fails(scene, p, "camera '02': principal point (28.0, ", "cameras/off_centre: true")
    assert "cameras/scale" not in msg  # no factor brings it near the centre on both axes
    _scene_yaml(scene, off_centre=True)
    assert "principal points not checked" in " ".join(validate_scene(scene)["checks"])


def test_scaled_intrinsics_keep_the_pixel_centre_convention():
    from anidress_core.camera import scale_intrinsics, scaled_size

    K = np.array([[100.0, 0.0, 63.5], [0.0, 90.0, 31.5], [0.0, 0.0, 1.0]])  # the centre of 128x64 pixels
    K2 = scale_intrinsics(K, 0.5)
    assert np.allclose(K2, [[50.0, 0.0, 31.5], [0.0, 45.0, 15.5], [0.0, 0.0, 1.0]])  # the centre of 64x32
    x = np.array([0.3, -0.2, 1.7])
    u, u2 = (K @ x)[:2] / x[2], (K2 @ x)[:2] / x[2]
    assert np.allclose(u2, 0.5 * (u + 0.5) - 0.5)  # the same point of the picture, resized
    with pytest.raises(ValueError, match="H_01 = 33 times cameras/scale 0.5 is 16.5, not a whole number"):
        scaled_size(33, 0.5, "H_01")


def _use_cameras(scene: Path, train: list[str], test: list[str]) -> None:
    p = scene / "scene.yaml"
    info = yaml.safe_load(p.read_text())
    info["cameras"] = {"train": train, "test": test}
    p.write_text(yaml.safe_dump(info))


def test_extrinsics_needed_only_for_the_cameras_scene_yaml_uses(scene):
    seq = scene / "walk"
    cams = easymocap.read_extri(seq / "extri.yml")
    easymocap.write_extri(seq / "extri.yml", {c: cams[c] for c in ("01", "02")})  # intri.yml keeps 01 .. 04
    _use_cameras(scene, ["01"], ["02"])
    s = validate_scene(scene)
    assert s["cameras"] == {"train": ["01"], "test": ["02"]} and s["sequences"]["walk"]["cameras"] == 2
    _use_cameras(scene, ["01", "03"], ["02"])
    _fails(scene, seq / "extri.yml", "camera '03' listed in intri.yml has no extrinsics")
    # unquoted names in both camera files (as some exporters write them): the same cameras, no
    # "no intrinsics" error for 01 read as the number 1
    easymocap.write_extri(seq / "extri.yml", cams)
    for name in ("intri.yml", "extri.yml"):
        p = seq / name
        text, n = re.subn(r'^  - "(\d+)"$', r"  - \1", p.read_text(), flags=re.M)
        assert n == 4 and "\n  - 01\n" in text
        p.write_text(text)
    s = validate_scene(scene)
    assert s["sequences"]["walk"]["cameras"] == 3


# --------------------------------------------------------------------------- frames and images


def test_frame_counts_differ_between_cameras(scene):
    (scene / "walk" / "images" / "02" / "000001.png").unlink()
    _fails(scene, scene / "walk" / "images" / "02", "camera '02' has 2 frames but camera '01' has 3",
           "missing 000001.png")


def test_image_with_garbage_bytes(scene):
    p = scene / "walk" / "images" / "03" / "000001.png"  # a middle frame: caught by the header check
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 500, dtype=np.uint8).tobytes())
    _fails(scene, p, "unreadable image", "not a PNG or JPEG")


def test_truncated_image(scene):
    p = scene / "walk" / "images" / "04" / "000001.png"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    _fails(scene, p, "truncated")


def test_image_of_the_wrong_size(scene):
    p = scene / "walk" / "images" / "01" / "000002.png"
    files.write_png(p, np.zeros((32, 40, 3)))
    _fails(scene, p, "image is 40x32 (WxH), expected 32x32")


def test_scene_yaml_frames_disagree_with_the_images(scene):
    p = scene / "scene.yaml"
    info = yaml.safe_load(p.read_text())
    info["sequences"][0]["frames"] = 4
    p.write_text(yaml.safe_dump(info))
    _fails(scene, p, "sequence 'walk' has frames: 4", "holds 3 per camera")


def test_shipped_normals_miss_a_frame(scene):
    (scene / "walk" / "normals" / "01" / "000002.exr").unlink()
    _fails(scene, scene / "walk" / "normals" / "01", "2 normals (exr) for 3 image frames", "missing 000002.exr")


def test_shipped_tool_cue_files_are_checked_in_their_format(scene):
    """scene.yaml cues names the formats: SCHP masks, Sapiens normals and RAFT flows pass; a flow of another
    size, a missing flow and files of another format than declared are named."""
    from anidress_core.io import cue_files

    info = yaml.safe_load((scene / "scene.yaml").read_text())
    info["cues"] = {"masks": {"format": "schp", "label_set": "lip"}, "normals": {"format": "sapiens"},
                    "flows": {"format": "raft"}}
    (scene / "scene.yaml").write_text(yaml.safe_dump(info))
    walk = scene / "walk"
    for cam in info["cameras"]["train"] + info["cameras"]["test"]:
        for f in range(3):
            lab = files.read_mask(walk / "gt" / "masks" / cam / f"{f:06d}.png")
            cue_files.write_schp_png(walk / "masks" / cam / f"{f:06d}.png", np.choose(lab, [0, 13, 12]).astype(np.uint8))
            n = walk / "normals" / cam / f"{f:06d}.exr"
            cue_files.write_sapiens_normals(n.with_suffix(".npy"), files.read_exr(n)[..., :3])
            n.unlink()
            if f:
                cue_files.write_flo(walk / "flows" / cam / f"{f:06d}.flo",
                                    files.read_exr(walk / "gt" / "flows" / cam / f"{f:06d}.exr")[..., :2])
    summ = validate_scene(scene)
    assert summ["sequences"]["walk"]["flows"] and summ["sequences"]["walk"]["masks"]
    assert any(c.startswith("flows (raft)") for c in summ["checks"])
    cam = info["cameras"]["train"][0]
    bad = walk / "flows" / cam / "000002.flo"
    cue_files.write_flo(bad, np.zeros((40, 40, 2), np.float32))
    _fails(scene, bad, "flow is 40x40", "the images are 32x32")
    bad.unlink()
    _fails(scene, walk / "flows" / cam, "for 2 image frames after the first", "missing 000002.flo")
    info["cues"]["flows"]["format"] = "kitti"
    (scene / "scene.yaml").write_text(yaml.safe_dump(info))
    _fails(scene, walk / "flows" / cam, "0 flows (kitti)", "cues/flows/format is 'kitti'")


# --------------------------------------------------------------------------- body parameters


@pytest.mark.parametrize("key,value", [("Th", math.nan), ("poses", math.inf)])
def test_non_finite_body_params(scene, key, value):
    p = scene / "walk" / "smpl" / "000001.json"
    data = json.loads(p.read_text())
    data[0][key][0][1] = value
    p.write_text(json.dumps(data))  # Python's json writes NaN / Infinity, as numpy-based exporters do
    _fails(scene, p, f"'{key}' contains NaN or inf")


def test_body_params_missing_a_frame(scene):
    (scene / "walk" / "smpl" / "000002.json").unlink()
    _fails(scene, scene / "walk" / "smpl", "2 body parameter files for 3 image frames", "missing 000002.json")


def test_body_translation_in_millimetres(scene):
    for p in (scene / "walk" / "smpl").glob("*.json"):
        data = json.loads(p.read_text())
        data[0]["Th"] = [[1000.0 * x for x in data[0]["Th"][0]]]
        p.write_text(json.dumps(data))
    _fails(scene, scene / "walk" / "smpl" / "000000.json", "'Th'", "looks like millimetres")


def test_body_params_of_the_person_scene_yaml_selects(scene):
    smpl = scene / "walk" / "smpl"
    for p in sorted(smpl.glob("*.json")):  # a second person (id 1) in every frame, 2 cm to the side
        people = json.loads(p.read_text())
        people.append({**people[0], "id": 1, "Th": [[people[0]["Th"][0][0] + 0.02, *people[0]["Th"][0][1:]]]})
        p.write_text(json.dumps(people))
    _fails(scene, smpl / "000000.json", "holds 2 people (ids [0, 1])")
    p = scene / "scene.yaml"
    info = yaml.safe_load(p.read_text())
    info["sequences"][0]["person_id"] = 1
    p.write_text(yaml.safe_dump(info))
    assert validate_scene(scene)["sequences"]["walk"]["frames"] == 3
    people = json.loads((smpl / "000001.json").read_text())
    (smpl / "000001.json").write_text(json.dumps(people[:1]))  # person 1 missing in the middle frame
    _fails(scene, smpl / "000001.json", "no person with id 1 in this frame", "'max_missing_frames'")
    info["sequences"][0]["max_missing_frames"] = 1  # ... which scene.yaml allows to interpolate
    p.write_text(yaml.safe_dump(info))
    assert validate_scene(scene)["sequences"]["walk"]["frames"] == 3


# --------------------------------------------------------------------------- body model units


@pytest.mark.parametrize("factor,unit", [(1000.0, "millimetres"), (0.001, "kilometres")])
def test_body_model_in_wrong_units(scene, factor, unit):
    p = scene / "body_model.npz"
    arrays, header = files.load_npz(p)
    arrays["v_template"] = arrays["v_template"] * factor
    arrays["joints_rest"] = arrays["joints_rest"] * factor
    files.save_npz(p, arrays, meta=header.get("meta"))
    _fails(scene, p, "'v_template' spans", f"looks like {unit}", "metres")


def test_body_joints_alone_in_wrong_units(scene):
    p = scene / "body_model.npz"
    arrays, header = files.load_npz(p)
    arrays["joints_rest"] = arrays["joints_rest"] * 1000.0
    files.save_npz(p, arrays, meta=header.get("meta"))
    _fails(scene, p, "'joints_rest' spans", "looks like millimetres")


# --------------------------------------------------------------------------- garment template


def _template(scene):
    p = scene / "garment" / "template.obj"
    v, f, uv = read_mesh(p)
    return p, v, f, uv


@pytest.mark.parametrize("factor,unit", [(1000.0, "millimetres"), (0.001, "kilometres")])
def test_template_in_wrong_units(scene, factor, unit):
    p, v, f, uv = _template(scene)
    write_obj(p, v * factor, f, uv)
    _fails(scene, p, "wrong units", f"looks like {unit}")


def test_non_manifold_template(scene):
    p, v, f, _ = _template(scene)
    # a new face on an interior edge (already shared by two faces): three faces share it
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    edges, cnt = np.unique(e, axis=0, return_counts=True)
    a, b = edges[cnt == 2][0]
    tip = 0.5 * (v[a] + v[b]) + np.array([0.0, 0.0, 0.02])
    write_obj(p, np.vstack([v, tip]), np.vstack([f, [[a, b, len(v)]]]))
    _fails(scene, p, "non-manifold", "shared by more than two faces", f"between vertices {a + 1} and {b + 1}")


def test_self_intersecting_template(scene):
    p, v, f, _ = _template(scene)
    # a sheet through the skirt's axis: it cuts the surface in front and behind
    y = float(v[:, 1].mean())
    tri = np.array([[0.0, y - 0.08, -0.6], [0.0, y - 0.08, 0.6], [0.0, y + 0.08, 0.0]])
    n = len(v)
    write_obj(p, np.vstack([v, tri]), np.vstack([f, [[n, n + 1, n + 2]]]))
    msg = _fails(scene, p, "self-intersecting", "passes through itself")
    assert int(msg.split("self-intersecting: ")[1].split(" ")[0]) > SELF_INTERSECTION_TOLERANCE


def test_template_with_a_few_duplicate_faces_passes_with_a_warning(scene, tmp_path):
    p, v, f, _ = _template(scene)
    write_obj(p, v, np.vstack([f, f[:3]]))  # cleaning removes duplicates: repairable
    s = run_validate(scene, tmp_path / "results" / "t" / "scene_check.json")
    assert s["garment_template"]["duplicate_faces"] == 3
    assert any("3 duplicate faces" in w for w in s["warnings"])


def test_template_mostly_degenerate_is_refused(scene):
    p, v, f, _ = _template(scene)
    bad = np.repeat(f[:, :1], 3, axis=1)[: len(f) // 5]  # faces (a, a, a): 20% degenerate
    write_obj(p, v, np.vstack([f, bad]))
    _fails(scene, p, "degenerate", "not a usable garment surface")


def test_garment_texture_checked(scene, tmp_path):
    s = run_validate(scene, tmp_path / "ok" / "scene_check.json")
    assert s["garment_template"]["texture"]["size"] == [64, 64] and "garment texture readable" in s["checks"]
    tex = scene / "garment" / "texture.png"
    data = tex.read_bytes()
    tex.write_bytes(data[: len(data) // 2])  # truncated
    _fails(scene, tex, "truncated or corrupt PNG")
    tex.write_bytes(data)
    p, v, f, _ = _template(scene)
    write_obj(p, v, f)  # no UVs: the texture cannot be used, a warning
    s = run_validate(scene, tmp_path / "ok" / "scene_check.json")
    assert any(str(tex) in w and "no UVs" in w for w in s["warnings"])


def test_declared_garment_texture_missing(scene):
    y = scene / "scene.yaml"
    y.write_text(y.read_text() + "garment_texture: garment/fabric.png\n")
    _fails(scene, scene / "garment" / "fabric.png", "garment texture not found", "garment_texture")


# --------------------------------------------------------------------------- scene.yaml


def test_scene_yaml_in_millimetres(scene):
    p = scene / "scene.yaml"
    info = yaml.safe_load(p.read_text())
    info["units"] = "millimetres"
    p.write_text(yaml.safe_dump(info))
    _fails(scene, p, "'units' is 'millimetres'")


def test_scene_yaml_unquoted_camera_names(scene):
    p = scene / "scene.yaml"
    p.write_text(p.read_text().replace("- '01'", "- 01"))
    _fails(scene, p, "is not a string", "quote camera names")


# --------------------------------------------------------------------------- pieces


def test_unit_guess():
    assert unit_guess(1000.0) == "millimetres" and unit_guess(0.001) == "kilometres"
    assert unit_guess(95.0) == "centimetres"


# --------------------------------------------------------------------------- the rule


def test_snakemake_stops_at_validate_scene(scene):
    wd = scene.parent.parent
    p = scene / "walk" / "extri.yml"
    cams = easymocap.read_extri(p)
    del cams["03"]
    easymocap.write_extri(p, cams)
    cfg = {"run_scenes": ["t"], "scenes": {"t": {"synthetic": False, "kind": "skirt",
                                                  "sequences": [{"name": "walk", "motion": "walk", "frames": 3}]}}}
    (wd / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    # two jobs side by side on the 2 cores of `make test`, each on one thread as with --cores 1: the scene_files
    # listings (one job per part of the scene) before validate_scene
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(wd),
           "--configfile", str(wd / "cfg.yaml"), "--cores", "2", "--max-threads", "1", "results/t/scene_check.json"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert res.returncode != 0, res.stdout[-2000:] + res.stderr[-2000:]
    assert "validate_scene" in res.stdout + res.stderr
    log_text = (wd / "logs" / "t" / "validate_scene.log").read_text()
    # the rule runs in the work directory: the message names the scene's relative path
    assert "data/t/walk/extri.yml: camera '03' listed in intri.yml has no extrinsics" in log_text, log_text
    # nothing written but rule scene_files' listings of the scene's files (results/t/inputs/, read by validate_scene)
    left = [q for q in (wd / "results").rglob("*") if q.is_file()] if (wd / "results").exists() else []
    assert [q for q in left if q.relative_to(wd / "results").parts[:2] != ("t", "inputs")] == [] and left
