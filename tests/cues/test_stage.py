"""Cue stage runners on a tiny scene on disk: layout, contract, errors naming files, atomicity."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from anidress_core.io import files
from anidress_core.stages import cues as sc
from anidress_core.io.scene import read_scene


@pytest.fixture(scope="module")
def outputs(tiny_scene, cues_config, tmp_path_factory):
    scene_dir, tpl = tiny_scene
    out = tmp_path_factory.mktemp("cues_out")
    ms = sc.run_masks(scene_dir, "walk", out / "masks", cues_config["masks"], tpl, progress=False)
    fs = sc.run_flows(scene_dir, "walk", out / "masks", out / "flows", cues_config["flows"], tpl, progress=False)
    assert cues_config["flows"]["prior"] and fs["prior"]
    return out, ms, fs


def _copy_scene(tiny_scene, tmp_path) -> Path:
    dst = tmp_path / "data" / "t"
    shutil.copytree(tiny_scene[0], dst)
    return dst


def test_masks_and_flows_layout_and_contract(tiny_scene, outputs):
    scene_dir, _ = tiny_scene
    out, mstats, fstats = outputs
    train = read_scene(scene_dir)["cameras"]["train"]
    assert sorted(p.name for p in (out / "masks").iterdir()) == sorted(train)
    for cam in train:
        assert sorted(p.name for p in (out / "masks" / cam).iterdir()) == [f"{i:06d}.png" for i in range(4)]
        assert sorted(p.name for p in (out / "flows" / cam).iterdir()) == [f"{i:06d}.exr" for i in range(1, 4)]
        m = files.read_mask(out / "masks" / cam / "000002.png")
        assert m.shape == (64, 64) and set(np.unique(m)) <= {0, 1, 2} and (m == 2).any() and (m == 1).any()
        f = files.read_exr(out / "flows" / cam / "000002.exr")
        assert f.shape == (64, 64, 3) and set(np.unique(f[..., 2])) <= {0.0, 1.0}
        assert (f[..., :2][f[..., 2] == 0] == 0).all()  # no flow outside the processed region
        # the processed region covers the subject of both frames
        m1 = files.read_mask(out / "masks" / cam / "000001.png")
        assert (f[..., 2][(m > 0) | (m1 > 0)] == 1).all()
    assert mstats["frames"] == 4 and fstats["pairs"] == 3 * len(train)
    # nothing but the outputs is left beside them
    assert sorted(p.name for p in out.iterdir()) == ["flows", "masks"]


def test_lk_refinement_changes_only_the_garment_pixels(tiny_scene, outputs, cues_config, tmp_path):
    scene_dir, tpl = tiny_scene
    out, _, plain = outputs
    assert plain["refine"] == "none" and plain["refined_pixels_per_pair"] == 0
    cfg = dict(cues_config["flows"], refine="lk", refine_window=7)
    fs = sc.run_flows(scene_dir, "walk", out / "masks", tmp_path / "flows", cfg, tpl, progress=False)
    assert fs["refine"] == "lk" and fs["refined_pixels_per_pair"] > 0
    changed = 0
    for cam in read_scene(scene_dir)["cameras"]["train"]:
        for f in range(1, 4):
            a = files.read_exr(out / "flows" / cam / f"{f:06d}.exr")
            b = files.read_exr(tmp_path / "flows" / cam / f"{f:06d}.exr")
            garment = files.read_mask(out / "masks" / cam / f"{f - 1:06d}.png") == 2  # frame t-1's garment
            assert (a[~garment] == b[~garment]).all() and (a[..., 2] == b[..., 2]).all()
            changed += int((a[garment] != b[garment]).any(-1).sum())
    assert changed > 0
    with pytest.raises(ValueError, match="refine"):
        sc.run_flows(scene_dir, "walk", out / "masks", tmp_path / "g", dict(cfg, refine="raft"), tpl, progress=False)
    with pytest.raises(ValueError, match="refine_window must be odd"):
        sc.run_flows(scene_dir, "walk", out / "masks", tmp_path / "g", dict(cfg, refine_window=8), tpl, progress=False)
    assert not (tmp_path / "g").exists()


def test_estimated_cues_against_ground_truth(tiny_scene, outputs):
    scene_dir, _ = tiny_scene
    out, _, _ = outputs
    res = sc.evaluate_cues(scene_dir, "walk", out / "masks", out / "flows", scene_dir / "walk" / "normals")
    print({k: round(v, 4) for k, v in res.items() if isinstance(v, float)})
    assert res["iou_subject"] > 0.85  # 64x64: the silhouette ring is a large share of the subject
    assert res["iou_garment"] > 0.6
    assert res["epe_subject_px"] < 1.0
    assert 0 < res["normal_garment_mean_deg"] < 45


def test_ground_truth_as_estimate_scores_perfectly(tiny_scene):
    scene_dir, _ = tiny_scene
    gt = scene_dir / "walk" / "gt"
    res = sc.evaluate_cues(scene_dir, "walk", gt / "masks", gt / "flows", gt / "normals", cameras="all")
    assert res["iou_subject"] == res["iou_garment"] == res["iou_body"] == 1.0
    assert res["epe_all_px"] == res["epe_garment_px"] == 0.0
    assert res["normal_subject_mean_deg"] < 0.1
    assert res["cameras"] == 6


def test_normals_record_and_skip(tiny_scene, tmp_path):
    scene_dir, tpl = tiny_scene
    rec = sc.run_normals(scene_dir, "walk", scene_dir / "walk" / "normals", tmp_path / "n.json", template_npz=tpl)
    assert json.loads((tmp_path / "n.json").read_text()) == rec
    assert rec["skipped"] is False and rec["dir"] == str(scene_dir / "walk" / "normals")
    assert rec["convention_axes"] == "x, y, z" and rec["agreement"] > 0.8
    rec = sc.run_normals(scene_dir, "walk", None, tmp_path / "skip.json", reason="no normals here")
    assert rec["skipped"] is True and rec["normal_weight"] == 0.0 and rec["reason"] == "no normals here"
    assert json.loads((tmp_path / "skip.json").read_text())["skipped"] is True


def test_corrupt_or_missing_images_name_the_file_and_leave_nothing(tiny_scene, cues_config, tmp_path):
    scene_dir = _copy_scene(tiny_scene, tmp_path)
    tpl = tiny_scene[1]
    cam = read_scene(scene_dir)["cameras"]["train"][1]
    out = tmp_path / "res" / "masks"
    # an earlier, complete output must survive a failed rerun untouched
    (out / "old").mkdir(parents=True)
    (out / "old" / "keep.txt").write_text("previous run")
    bad = scene_dir / "walk" / "images" / cam / "000002.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    with pytest.raises(files.ArtifactError, match=str(bad)):
        sc.run_masks(scene_dir, "walk", out, cues_config["masks"], tpl, progress=False)
    assert (out / "old" / "keep.txt").read_text() == "previous run"
    assert sorted(p.name for p in out.parent.iterdir()) == ["masks"]  # no partial folder left
    bad.unlink()
    with pytest.raises(FileNotFoundError, match=str(bad.parent)):
        sc.run_masks(scene_dir, "walk", out, cues_config["masks"], tpl, progress=False)
    assert sorted(p.name for p in out.parent.iterdir()) == ["masks"]


def test_missing_plate_and_corrupt_mask_and_normals_name_the_file(tiny_scene, cues_config, outputs, tmp_path):
    scene_dir = _copy_scene(tiny_scene, tmp_path)
    cam = read_scene(scene_dir)["cameras"]["train"][0]
    plate = scene_dir / "walk" / "backgrounds" / f"{cam}.png"
    plate.unlink()
    with pytest.raises(FileNotFoundError, match=str(plate)):
        sc.run_masks(scene_dir, "walk", tmp_path / "m", cues_config["masks"], tiny_scene[1], progress=False)
    assert not (tmp_path / "m").exists()
    masks = tmp_path / "masks"
    shutil.copytree(outputs[0] / "masks", masks)
    bad = masks / cam / "000003.png"
    bad.write_bytes(b"garbage")
    with pytest.raises(files.ArtifactError, match=str(bad)):
        sc.run_flows(scene_dir, "walk", masks, tmp_path / "f", cues_config["flows"], progress=False)
    assert not (tmp_path / "f").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    nbad = scene_dir / "walk" / "normals" / cam / "000001.exr"
    nbad.write_bytes(b"not an exr")
    with pytest.raises(files.ArtifactError, match=str(nbad)):
        sc.run_normals(scene_dir, "walk", scene_dir / "walk" / "normals", tmp_path / "n.json")
    assert not (tmp_path / "n.json").exists()


def test_camera_selection_and_bad_config(tiny_scene, cues_config, tmp_path):
    info = read_scene(tiny_scene[0])
    assert sc.select_cameras(info, "all") == info["cameras"]["train"] + info["cameras"]["test"]
    assert sc.select_cameras(info, ["02"]) == ["02"]
    with pytest.raises(ValueError, match="cameras must be"):
        sc.select_cameras(info, "some")
    with pytest.raises(ValueError, match="cues/flows/method"):
        sc.run_flows(tiny_scene[0], "walk", tmp_path, tmp_path / "f", {"method": "raft", "margin_px": 4},
                     progress=False)


def test_tight_scene_masks_have_no_garment_label(tiny_scene, cues_config, tmp_path):
    """Without a garment template the labels are background / body only."""
    scene_dir, _ = tiny_scene
    sc.run_masks(scene_dir, "walk", tmp_path / "m", cues_config["masks"], None, cameras=["01"], progress=False)
    m = np.stack([files.read_mask(p) for p in sorted((tmp_path / "m" / "01").iterdir())])
    assert set(np.unique(m)) == {0, 1}


def test_temporal_median_background_option(tiny_scene, cues_config, tmp_path):
    scene_dir, tpl = tiny_scene
    cfg = {**cues_config["masks"], "background": "temporal_median"}
    st = sc.run_masks(scene_dir, "walk", tmp_path / "m", cfg, tpl, cameras=["01"], progress=False)
    assert st["frames"] == 4 and len(list((tmp_path / "m" / "01").iterdir())) == 4
    with pytest.raises(ValueError, match="background"):
        sc.run_masks(scene_dir, "walk", tmp_path / "m2", {**cfg, "background": "green"}, tpl, progress=False)
    assert not (tmp_path / "m2").exists()


def test_masks_that_are_mostly_empty_fail_the_stage(tiny_scene, cues_config, tmp_path):
    """A subject that does not move is its own temporal-median plate: every mask comes out empty. The
    stage fails naming the setting (nothing written), unless max_empty_fraction allows it; then
    the count is in the stats."""
    scene_dir = _copy_scene(tiny_scene, tmp_path)
    tpl = tiny_scene[1]
    images = scene_dir / "walk" / "images"
    for cam_dir in images.iterdir():
        first, *rest = sorted(cam_dir.iterdir())
        for p in rest:
            shutil.copyfile(first, p)
    cfg = {**cues_config["masks"], "background": "temporal_median"}
    out = tmp_path / "m"
    with pytest.raises(ValueError, match="max_empty_fraction"):
        sc.run_masks(scene_dir, "walk", out, cfg, tpl, cameras=["01", "02"], progress=False)
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".m")]
    st = sc.run_masks(scene_dir, "walk", out, {**cfg, "max_empty_fraction": 1.0}, tpl, cameras=["01", "02"],
                      progress=False)
    assert st["empty_masks"] == 2 * st["frames"]


def _set_cues(scene_dir: Path, cues: dict) -> None:
    import yaml

    info = yaml.safe_load((scene_dir / "scene.yaml").read_text())
    info["cues"] = cues
    (scene_dir / "scene.yaml").write_text(yaml.safe_dump(info))


def test_shipped_tool_files_are_converted_to_the_pipelines_cues(tiny_scene, tmp_path):
    """SCHP LIP masks, Sapiens normals in OpenGL axes and RAFT flows, written from the scene's own cues: the
    converted masks equal the labels, the flows the flows; the normals' axes are found and undone."""
    from anidress_core.io import cue_files

    scene_dir = _copy_scene(tiny_scene, tmp_path)
    walk = scene_dir / "walk"
    train = read_scene(scene_dir)["cameras"]["train"]
    gl = np.diag([1.0, -1.0, -1.0]).astype(np.float32)
    truth_n = {}
    for cam in train:
        for f in range(4):
            lab = files.read_mask(walk / "gt" / "masks" / cam / f"{f:06d}.png")
            cue_files.write_schp_png(walk / "masks" / cam / f"{f:06d}.png", np.choose(lab, [0, 13, 12]).astype(np.uint8))
            n = files.read_exr(walk / "normals" / cam / f"{f:06d}.exr")[..., :3]
            truth_n[cam, f] = n
            cue_files.write_sapiens_normals(walk / "normals" / cam / f"{f:06d}.npy", n @ gl.T)
            (walk / "normals" / cam / f"{f:06d}.exr").unlink()
            if f:
                g = files.read_exr(walk / "gt" / "flows" / cam / f"{f:06d}.exr")
                cue_files.write_flo(walk / "flows" / cam / f"{f:06d}.flo", g[..., :2])
    _set_cues(scene_dir, {"masks": {"format": "schp", "label_set": "lip"}, "normals": {"format": "sapiens"},
                          "flows": {"format": "raft"}})
    m = sc.run_convert_masks(scene_dir, "walk", tmp_path / "masks", progress=False)
    assert m["cameras"] == len(train) and 0 < m["garment_fraction"] < 1
    for cam in train:
        assert np.array_equal(files.read_mask(tmp_path / "masks" / cam / "000002.png"),
                              files.read_mask(walk / "gt" / "masks" / cam / "000002.png"))
    fl = sc.run_flows(scene_dir, "walk", tmp_path / "masks", tmp_path / "flows", {"method": "files"}, progress=False)
    assert fl["format"] == "raft" and fl["pairs"] == 3 * len(train)
    got = files.read_exr(tmp_path / "flows" / train[0] / "000003.exr")
    g = files.read_exr(walk / "gt" / "flows" / train[0] / "000003.exr")
    assert np.allclose(got[..., :2], g[..., :2]) and got[..., 2].all()
    assert not (tmp_path / "flows" / train[0] / "000000.exr").exists()
    rec = sc.run_normals(scene_dir, "walk", walk / "normals", tmp_path / "n.json", template_npz=tiny_scene[1],
                         out_dir=tmp_path / "normals")
    assert rec["convention_axes"] == "x, -y, -z" and rec["format"] == "sapiens" and rec["consistency"] >= 0.9
    assert rec["dir"] == str(tmp_path / "normals")
    assert np.allclose(files.read_exr(tmp_path / "normals" / train[1] / "000001.exr"), truth_n[train[1], 1], atol=2e-3)
    # read in place (a synthetic scene's own maps) only in the pipeline's format and axes
    with pytest.raises(ValueError, match="must be the pipeline's"):
        sc.run_normals(scene_dir, "walk", walk / "normals", tmp_path / "n2.json", template_npz=tiny_scene[1])
    # normals of nothing in particular: no convention agrees
    rng = np.random.default_rng(0)
    for cam in train:
        for f in range(4):
            cue_files.write_sapiens_normals(walk / "normals" / cam / f"{f:06d}.npy",
                                            rng.standard_normal((64, 64, 3)).astype(np.float32))
    with pytest.raises(ValueError, match="no axis convention"):
        sc.run_normals(scene_dir, "walk", walk / "normals", tmp_path / "n3.json", template_npz=tiny_scene[1],
                       out_dir=tmp_path / "normals3")
    assert not (tmp_path / "normals3").exists() or not any((tmp_path / "normals3").iterdir())
    # a missing flow is named with its folder
    (walk / "flows" / train[1] / "000002.flo").unlink()
    with pytest.raises(FileNotFoundError, match=rf"{train[1]}: no raft flow for frames \[2\]"):
        sc.run_convert_flows(scene_dir, "walk", tmp_path / "flows2", progress=False)
    assert not (tmp_path / "flows2").exists()
