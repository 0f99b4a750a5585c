"""io.scene.scene_cameras: the scene's image size reaches every stage that loads cameras (issue 24 item 1).

EasyMocap's ``write_intri`` and OpenCV write ``intri.yml`` without ``H_<cam>`` / ``W_<cam>``;
a tiny skirt scene with such a file goes through the stages that load cameras (cues, fit,
field train / render, evaluate), which must run to the end.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from anidress_core.io import easymocap, files
from anidress_core.io.scene import scene_cameras, scene_image_size

torch.set_num_threads(1)

H, W = 48, 40  # not square: height and width cannot be swapped unnoticed


def _strip_image_size(seq_dir) -> None:
    """Rewrite ``intri.yml`` as EasyMocap's write_intri does: no H_/W_."""
    raw = easymocap.read_intri(seq_dir / "intri.yml")
    easymocap.write_intri(seq_dir / "intri.yml", {c: {"K": v["K"], "dist": v["dist"]} for c, v in raw.items()})
    assert "H_" not in (seq_dir / "intri.yml").read_text()


def build_tiny_skirt(root):
    """(data, results) of a synthetic 4-camera (3 train), 3-frame skirt scene at H x W whose intri.yml has no
    H_/W_, with results/template.npz and a 4-bone results/rig.npz (shared with tests/test_undistort_stage.py)."""
    from anidress_core.config import default_schema_path, validate_config
    from anidress_core.io.scene import load_body, read_scene
    from anidress_core.stages.synth import run_synth
    from anidress_core.stages.template import run_template
    from tests.fit.conftest import write_gt_rig

    sc = {"kind": "skirt", "image_size": [H, W], "cameras": {"count": 4, "train": 3}, "body": {"vertices": 1500},
          "sequences": [{"name": "walk", "motion": "walk", "frames": 3}],
          "garment": {"vertices": 300, "cloth": {"settle_frames": 3}},
          "render": {"texture_size": 64, "noise_std": 0.0, "supersample": 1}}
    cfg = validate_config({"run_scenes": ["s"], "scenes": {"s": sc}}, yaml.safe_load(default_schema_path().read_text()))
    data = run_synth(cfg["scenes"]["s"], "s", root / "data" / "s", threads=1, progress=False)
    _strip_image_size(data / "walk")
    info = read_scene(data)
    res = root / "results"
    tpl = run_template(data / "garment" / "template.obj", "skirt", load_body(data, info), 300, res / "template.ply",
                       res / "template.npz")
    write_gt_rig(data, tpl, res / "rig.npz", num_bones=4, iters=3)  # stands in for rule rig
    return data, res


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return build_tiny_skirt(tmp_path_factory.mktemp("nosize"))


def test_scene_cameras_take_the_size_from_scene_yaml_or_the_images(scene, tmp_path):
    from anidress_core.camera import load_cameras

    data, _ = scene
    seq = data / "walk"
    with pytest.raises(ValueError, match="no 'H_<cam>' image size"):  # the bare loader cannot know
        load_cameras(seq / "intri.yml", seq / "extri.yml")
    cams = scene_cameras(data, "walk", ["02", "01"])
    assert cams.names == ["02", "01"] and (cams.height, cams.width) == (H, W) and cams.dtype == torch.float64
    # scene.yaml without image_size: the size of the sequence's first image
    info = dict(yaml.safe_load((data / "scene.yaml").read_text()))
    del info["image_size"]
    assert scene_image_size(data, "walk", info) == (H, W)
    assert (scene_cameras(data, "walk", None, info).height, scene_cameras(data, "walk", None, info).width) == (H, W)
    # neither: the error names scene.yaml and the images folder
    (tmp_path / "walk").mkdir()
    with pytest.raises(files.ArtifactError, match=r"scene.yaml: no image_size and no images under .*walk"):
        scene_image_size(tmp_path, "walk", info)
    # a scene.yaml size that contradicts the file's H_/W_ is an error naming intri.yml
    other = tmp_path / "other"
    (other / "walk").mkdir(parents=True)
    raw = easymocap.read_camera(seq / "intri.yml", seq / "extri.yml")
    easymocap.write_camera(other / "walk" / "intri.yml", other / "walk" / "extri.yml",
                           {c: dict(v, H=H + 2, W=W) for c, v in raw.items()})
    with pytest.raises(ValueError, match=r"intri.yml: 'H_<cam>' is 50 but height=48"):
        scene_cameras(other, "walk", None, {"image_size": [H, W]})


def test_stages_that_load_cameras_run_without_H_W_in_intri(scene, tmp_path):
    pytest.importorskip("warp")  # the fit's L_collision
    from anidress_core.io.garment_poses import read_garment_poses
    from anidress_core.stages import cues as sc
    from anidress_core.stages.evaluate import read_metrics_csv, run_evaluate
    from anidress_core.stages.field import run_render, run_train
    from anidress_core.stages.fit import run_fit

    data, res = scene
    seq = data / "walk"
    tpl, rig = res / "template.npz", res / "rig.npz"
    # 1. cues: masks and flows of the training cameras
    ms = sc.run_masks(data, "walk", tmp_path / "masks", {}, tpl, cameras=["01"], threads=1, progress=False)
    assert ms["cameras"] == 1 and ms["frames"] == 3
    assert files.read_mask(tmp_path / "masks" / "01" / "000002.png").shape == (H, W)
    # 2. fit (on the shipped ground-truth cues): every frame fitted in H x W views
    meta = run_fit(data, "walk", rig, tpl, seq / "gt" / "masks", seq / "gt" / "flows", seq / "normals",
                   {"views": 2, "max_iters": 2, "max_iters_first": 2, "prior_reference": "sim"},  # no ensemble here
                   tmp_path / "garment_poses.npz", progress=False)
    gp = read_garment_poses(tmp_path / "garment_poses.npz", frames=3, bones=4)
    assert len(meta["cameras"]) == 2 and np.isfinite(gp.verts).all()
    # 3. field: train a few steps, render a test camera, evaluate it
    params = {"model": {"hash_levels": 2, "hash_log2_size": 10, "hash_max_resolution": 32, "width": 16, "volume_res": 8},
              "priors": {}, "sampler": {"occupancy_res": 16, "step_m": 0.03},
              "train": {"steps": 2, "rays_per_step": 64, "images_per_step": 1, "checkpoint_every": 100},
              "render": {"background": [0.0, 0.0, 0.0]}}
    out = tmp_path / "field.pt"
    tm = run_train(data, "walk", "full", seq / "gt" / "masks", out, params, template_npz=tpl, rig_npz=rig,
                   garment_poses_npz=tmp_path / "garment_poses.npz", progress=False)
    assert out.is_file() and tm["steps"] == 2
    rr = run_render(out, data, tmp_path / "nv", params, seq="walk", cameras=["04"], template_npz=tpl, rig_npz=rig,
                    garment_poses_npz=tmp_path / "garment_poses.npz", progress=False)
    assert rr["images"] == 3 and files.read_image(tmp_path / "nv" / "rgb" / "04" / "000000.png").shape[:2] == (H, W)
    run_evaluate(data, [("novel_view", "walk", tmp_path / "nv")], tmp_path / "metrics.csv", tmp_path / "summary.json",
                 {}, progress=False)
    rows = read_metrics_csv(tmp_path / "metrics.csv")
    assert len(rows) == 3 and all(np.isfinite(r["psnr_db"]) for r in rows)
