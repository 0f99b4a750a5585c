"""scene.yaml's cue formats and the shipped cue files read in the pipeline's form (anidress_core.io.shipped_cues)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from anidress_core.io import cue_files, files, shipped_cues
from anidress_core.io.scene_info import cue_formats

DATA = Path(__file__).resolve().parents[1] / "data" / "cue_files"


def test_cue_formats_defaults_and_errors(tmp_path):
    f = cue_formats({})
    assert f == {"masks": {"format": "labels", "label_set": "lip", "garment_labels": None, "person": None},
                 "normals": {"format": "exr"}, "flows": {"format": "exr"}}
    f = cue_formats({"cues": {"masks": {"format": "schp", "label_set": "atr", "garment_labels": [5], "person": 1},
                              "normals": {"format": "sapiens"}, "flows": {"format": "raft"}}})
    assert f["masks"] == {"format": "schp", "label_set": "atr", "garment_labels": [5], "person": 1}
    assert shipped_cues.garment_labels(f["masks"]) == (5,)
    assert shipped_cues.garment_labels(cue_formats({"cues": {"masks": {"format": "schp"}}})["masks"]) == (6, 12)
    for bad, match in [({"flows": {"format": "flo"}}, "cues/flows/format must be one of"),
                       ({"masks": {"format": "schp", "label_set": "pascal"}}, "label_set"),
                       ({"masks": {"format": "schp", "garment_labels": 6}}, "garment_labels"),
                       ({"masks": {"label_set": "lip"}}, "apply to format schp"),
                       ({"normal": {}}, "unknown key"), ({"normals": {"fmt": "png"}}, "cues/normals/fmt")]:
        with pytest.raises(files.ArtifactError, match=match):
            cue_formats({"cues": bad}, tmp_path)


def test_schp_masks_of_both_layouts_become_labels(tmp_path):
    cfg = cue_formats({"cues": {"masks": {"format": "schp", "label_set": "lip"}}})["masks"]
    lab = shipped_cues.read_mask_labels(DATA / "schp" / "lip", "01", 1, cfg, (12, 20))
    idx = cue_files.read_label_indices(DATA / "schp" / "lip" / "01" / "000001.png")
    assert np.array_equal(lab == 2, idx == 12) and np.array_equal(lab == 0, idx == 0)
    # EasyMocap: a silhouette per person, CIHP parsing beside (<masks>-parsing); the person picked in scene.yaml
    root = tmp_path / "masks"
    shutil.copytree(DATA / "easymocap" / "mask-schp", root)
    shutil.copytree(DATA / "easymocap" / "mask-schp-parsing", tmp_path / "masks-parsing")
    cfg = cue_formats({"cues": {"masks": {"format": "schp", "label_set": "cihp", "person": 1}}})["masks"]
    lab = shipped_cues.read_mask_labels(root, "01", 0, cfg, (12, 20))
    sil = cue_files.read_label_indices(root / "01" / "000000_1.png")
    assert np.array_equal(lab > 0, sil > 0) and (lab == 2).any()
    with pytest.raises(files.ArtifactError, match="choose one with the person setting"):
        shipped_cues.read_mask_labels(root, "01", 0, dict(cfg, person=None), (12, 20))
    assert sorted(shipped_cues.cue_frames(root / "01", "masks", "schp")) == [0, 1]
    with pytest.raises(files.ArtifactError, match="the images are 30x12"):
        shipped_cues.read_mask_labels(root, "01", 0, cfg, (12, 30))
    shutil.rmtree(tmp_path / "masks-parsing")
    with pytest.raises(files.ArtifactError, match="without part labels"):
        shipped_cues.read_mask_labels(root, "01", 0, cfg, (12, 20))


def test_label_masks_with_parser_values_name_the_setting(tmp_path):
    files.write_mask(tmp_path / "01" / "000000.png", np.full((4, 5), 12, np.uint8))
    with pytest.raises(files.ArtifactError, match="cues/masks/format: schp"):
        shipped_cues.read_mask_labels(tmp_path, "01", 0, cue_formats({})["masks"])


def test_normals_of_every_format_read_in_their_own_axes(tmp_path):
    sap = shipped_cues.read_normals(DATA / "sapiens", "01", 1, "sapiens", (12, 20))
    png = shipped_cues.read_normals(DATA / "normals_png", "01", 1, "png", (12, 20))
    both = (np.linalg.norm(png, axis=-1) > 0) & (np.linalg.norm(sap, axis=-1) > 0)
    assert both.any() and np.abs(sap - png)[both].max() < 0.02  # 8-bit quantisation
    crops = cue_files.read_crops(DATA / "icon" / shipped_cues.CROPS_FILE)
    icon = shipped_cues.read_normals(DATA / "icon", "01", 1, "icon", (12, 20), crops)
    assert icon.shape == (12, 20, 3) and (np.linalg.norm(icon, axis=-1) > 0).any()
    with pytest.raises(files.ArtifactError, match="no crop box for 01/000000"):
        shipped_cues.read_normals(DATA / "icon", "01", 0, "icon", (12, 20), {})
    with pytest.raises(files.ArtifactError, match="the images are 21x12"):
        shipped_cues.read_normals(DATA / "sapiens", "01", 0, "sapiens", (12, 21))
    bad = tmp_path / "01" / "000000.npy"
    bad.parent.mkdir()
    np.save(bad, np.full((12, 20, 3), np.nan, np.float32))
    with pytest.raises(files.ArtifactError, match=str(bad)):
        shipped_cues.read_normals(tmp_path, "01", 0, "sapiens", (12, 20))


def test_flows_of_every_format(tmp_path):
    raft, ok = shipped_cues.read_flow(DATA / "raft", "01", 1, "raft", (12, 20))
    kitti, ok2 = shipped_cues.read_flow(DATA / "kitti", "01", 1, "kitti", (12, 20))
    assert ok.all() and ok2.all() and np.abs(raft - kitti).max() <= 1 / 64 + 1e-6
    _, ok3 = shipped_cues.read_flow(DATA / "kitti", "01", 2, "kitti", (12, 20))
    assert not ok3[:, :4].any() and ok3[:, 4:].all()
    with pytest.raises(files.ArtifactError, match="unpad"):
        shipped_cues.read_flow(DATA / "raft_padded", "01", 1, "raft", (12, 20))
    exr = np.concatenate([raft, np.ones((12, 20, 1), np.float32)], -1)
    exr[0, 0, 2] = 0
    files.write_exr(tmp_path / "01" / "000001.exr", exr, ("X", "Y", "valid"))
    f, v = shipped_cues.read_flow(tmp_path, "01", 1, "exr", (12, 20))
    assert np.array_equal(f, raft) and not v[0, 0] and v.sum() == 239
    assert sorted(shipped_cues.cue_frames(DATA / "raft" / "01", "flows", "raft")) == [1, 2]
    assert shipped_cues.source_format(tmp_path, "flows", "raft") == "raft"
    (tmp_path / "undistort.json").write_text(json.dumps({}))
    assert shipped_cues.source_format(tmp_path, "flows", "raft") == "exr"
    assert shipped_cues.source_format(tmp_path, "masks", "schp") == "schp"
