"""A capture without ground truth through the whole workflow (issue 24 item 4).

`anidress export-capture` writes a tiny synthetic skirt scene as a user's capture: distorted
cameras whose intri.yml has no H_/W_, 4:3 images (re-encoded here as JPEG, one camera's frames without
zero padding), noisy EasyMocap >= 0.2 body files, no gt/, no background plates, no garment texture, and
the cue files of the tools users run (issue 47): for walk, masks in EasyMocap's mask-schp layout (a
silhouette per person and SCHP's CIHP part labels in masks-parsing/; training cameras only), Sapiens .npy
normals (OpenGL axes) and RAFT .flo flows; jump ships the normals and flows but no masks. With the config entry it prints (and
cues/flows/method: files):

1. the default cues/masks/background 'plate' stops at validate_scene with one message naming the
   missing backgrounds/ folder of jump and the setting (before any long stage);
2. with cues/masks/background: temporal_median, `snakemake` (default target: every rule through
   evaluate_field and the report) runs with no failure: walk's masks converted from SCHP's CIHP labels,
   jump's estimated, the normals' axes found to be OpenGL's and converted, the flows remapped through
   the lens; metrics.csv scores the images with a mask
   of the pipeline (mask_source 'pipeline') and leaves the test camera, which neither the shipped masks
   nor rule masks cover (cues/cameras: train), unscored (NaN, 'none'); the report says there is no
   ground truth;
3. a second run has nothing to do;
4. an empty mask of the pipeline leaves its image unscored (run_evaluate on the run's renders).

The scene's frame rate is 3 fps so that the subject moves between its few frames: a temporal
median of 4 frames of a nearly static subject is the subject itself, and the masks come out empty.
"""
from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import torch
import yaml

REPO = Path(__file__).resolve().parents[2]
SCENE = {"kind": "skirt", "image_size": [48, 40], "fps": 3.0, "cameras": {"count": 4, "train": 3},
         "body": {"vertices": 1500},
         "sequences": [{"name": "walk", "motion": "walk", "frames": 4, "role": "train"},
                       {"name": "jump", "motion": "jump", "frames": 3, "role": "novel_pose"}],
         "garment": {"vertices": 300, "cloth": {"settle_frames": 3}},
         "render": {"texture_size": 64, "noise_std": 0.0, "supersample": 1}}
# tiny stage settings (as tests/workflow/tiny.py and tests/test_import_zju_workflow.py)
SETTINGS = {"template": {"vertices": 300},
            "simulate": {"library": ["sway"], "library_frames": 5, "cloth": {"settle_frames": 3},
                         "ensemble_bend_stiffness": [1.0e-4, 1.0e-3], "ensemble_settle_frames": []},
            "rig": {"bones": 4, "iters": 3}, "fit": {"max_iters": 2, "max_iters_first": 3},
            "field": {"train": {"steps": 20, "rays_per_step": 256, "images_per_step": 4, "checkpoint_every": 10},
                      "render": {"frame_stride": 2, "library": ["sway"], "library_frame_stride": 2, "skip_res": 32}}}


def _snakemake(wd: Path, *args: str) -> subprocess.CompletedProcess:
    # two jobs side by side on the 2 cores of `make test` (pytest waits for the run), each on the one thread it
    # has with --cores 1: the jobs of a serial run (the two fields, their renders, the cues of walk and jump)
    cmd = [sys.executable, "-m", "snakemake", *args, "-s", str(REPO / "Snakefile"), "--directory", str(wd),
           "--configfile", str(wd / "cfg.yaml"), "--cores", "2", "--max-threads", "1"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})


def _tail(res: subprocess.CompletedProcess) -> str:
    return res.stdout[-3000:] + res.stderr[-3000:]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """(workdir, config entry) of the exported tiny capture data/cap (truth held back in data/cap.truth)."""
    from anidress_core.config import default_schema_path, validate_config
    from anidress_core.stages.export_capture import run_export_capture
    from anidress_core.stages.synth import run_synth

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("capture_e2e")
    cfg = validate_config({"run_scenes": ["s"], "scenes": {"s": SCENE}},
                          yaml.safe_load(default_schema_path().read_text()))
    src = run_synth(cfg["scenes"]["s"], "s", root / "src" / "s", threads=1, progress=False)
    wd = root / "wd"
    rec = run_export_capture(src, wd / "data" / "cap", masks="parser", flows=True, cue_files="easymocap_sapiens_raft",
                             seed=1, threads=1)
    shutil.rmtree(wd / "data" / "cap" / "jump" / "masks")  # estimated by rule masks
    for d in ("masks", "masks-parsing"):  # shipped masks cover the training cameras
        shutil.rmtree(wd / "data" / "cap" / "walk" / d / "03")
    # as cameras deliver them: JPEG (quality 95), the frames of camera 02 named without zero padding
    for p in sorted((wd / "data" / "cap").glob("*/images/*/*.png")):
        name = f"{int(p.stem)}.JPG" if p.parent.name == "02" else f"{p.stem}.jpg"
        cv2.imwrite(str(p.with_name(name)), cv2.imread(str(p), cv2.IMREAD_COLOR), [cv2.IMWRITE_JPEG_QUALITY, 95])
        p.unlink()
    return wd, rec["config_entry"]


def _write_cfg(wd: Path, entry: dict, **extra) -> None:
    (wd / "cfg.yaml").write_text(yaml.safe_dump({"run_scenes": ["cap"], "scenes": {"cap": entry}, **SETTINGS,
                                                 **extra}))


@pytest.fixture(scope="module")
def plates_run(capture):
    """`snakemake` with the default cues/masks/background 'plate' on the capture: (result, validate_scene's log,
    whether scene_check.json / template.npz were written). Run first in the capture's workdir: the manifests
    of rule scene_files (2 s each) serve the run of ``ran`` too."""
    wd, entry = capture
    _write_cfg(wd, entry)
    res = _snakemake(wd)
    log = wd / "logs" / "cap" / "validate_scene.log"
    out = wd / "results" / "cap"
    return res, log.read_text() if log.is_file() else "", (out / "scene_check.json").exists(), \
        (out / "template.npz").exists()


def test_missing_plates_are_named_by_validate_scene(plates_run):
    """The default 'plate' on a capture without plates: validate_scene names the missing backgrounds/ folder
    and the setting, and nothing after it runs."""
    res, log, checked, template = plates_run
    assert res.returncode != 0
    assert "cues/masks/background is 'plate'" in log and "temporal_median" in log, log + _tail(res)
    assert str(Path("jump") / "backgrounds") in log and str(Path("walk") / "backgrounds") not in log, log
    assert not checked and not template  # stopped before any long stage


@pytest.fixture(scope="module")
def ran(capture, plates_run):
    """The capture's workdir after `snakemake` (default target) with temporal-median plates."""
    wd, entry = capture
    _write_cfg(wd, entry, cues={"masks": {"background": "temporal_median"}, "flows": {"method": "files"}},
               refine_body={"enabled": True})
    res = _snakemake(wd)
    assert res.returncode == 0, _tail(res)
    return wd


def test_capture_runs_end_to_end_without_ground_truth(ran):
    wd = ran
    data = wd / "data" / "cap"
    assert "H_" not in (data / "walk" / "intri.yml").read_text()
    assert not list(data.rglob("gt")) and not list(data.rglob("backgrounds"))
    assert (data / "walk" / "masks" / "01" / "000000_0.png").is_file() and not (data / "jump" / "masks").exists()
    assert (data / "walk" / "masks-parsing" / "01" / "000000.png").is_file()
    assert (data / "walk" / "normals" / "01" / "000000.npy").is_file()
    assert (data / "walk" / "flows" / "01" / "000001.flo").is_file()
    assert (data / "walk" / "images" / "02" / "1.JPG").is_file() and not list(data.rglob("images/*/*.png"))
    out = wd / "results" / "cap"
    for v in ("full", "body_only"):
        with open(out / "walk" / v / "metrics.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert {r["kind"] for r in rows} == {"novel_view", "novel_pose"}
        scored = [r for r in rows if r["mask_source"] == "pipeline"]
        unscored = [r for r in rows if r["mask_source"] == "none"]
        assert len(scored) + len(unscored) == len(rows) and scored and unscored
        # the test camera 03 has no mask (rule masks covers the training cameras): not scored
        assert {r["camera"] for r in unscored} == {"03"} and all(r["camera"] != "03" for r in scored)
        assert all(math.isnan(float(r[k])) for r in unscored for k in ("psnr_db", "ssim", "iou"))
        assert all(math.isfinite(float(r["psnr_db"])) and 0 <= float(r["iou"]) <= 1 for r in scored)
        summ = json.loads((out / "walk" / v / "metrics_summary.json").read_text())
        assert summ["ground_truth"] is False
        assert summ["sources"]["jump"]["masks"] == "results/cap/jump/masks"  # rule masks', working cameras
        assert summ["sources"]["jump"]["images"] == "results/cap/jump/undistorted/images"
        nv = next(m for m in summ["metrics"] if m["kind"] == "novel_view")
        assert nv["scored"] == 0 and math.isnan(nv["psnr_db"])  # no figure without a mask
    assert not (out / "walk" / "fit_metrics.csv").exists()  # the fit is not scored: no true meshes
    # the cue files: SCHP labels converted (the garment is CIHP's skirt), normals in OpenGL axes found and converted,
    # flows remapped by rule undistort and converted
    from anidress_core.io import files

    labels = files.read_mask(out / "walk" / "masks" / "01" / "000001.png")
    assert set(labels.ravel().tolist()) <= {0, 1, 2} and (labels == 2).any() and (labels == 1).any()
    assert sorted(p.name for p in (out / "walk" / "masks").iterdir() if p.is_dir()) == ["01", "02", "04"]
    rec = json.loads((out / "walk" / "normals.json").read_text())
    assert rec["convention_axes"] == "x, -y, -z" and rec["agreement"] > 0.5
    assert rec["dir"] == "results/cap/walk/normals" and (out / "walk" / "normals" / "01" / "000000.exr").is_file()
    flow = files.read_exr(out / "walk" / "flows" / "01" / "000001.exr")
    assert flow.shape[-1] == 3 and flow[..., 2].any() and not (out / "walk" / "flows" / "01" / "000000.exr").exists()
    from anidress_core.io.garment_poses import read_garment_poses

    meta = read_garment_poses(out / "walk" / "garment_poses.npz").header["meta"]
    assert meta["normals_dir"] == "results/cap/walk/normals" and meta["masks_dir"] == "results/cap/walk/masks"
    assert meta["flows_dir"] == "results/cap/walk/flows"
    html = (wd / "results" / "report.html").read_text()
    assert 'data-ground-truth="none"' in html and "No ground truth" in html
    assert "fit metrics (walk)" in html and "captured image, pipeline&#39;s mask" in html
    assert "converted to labels (SCHP cihp)" in html and "axes x, -y, -z" in html  # what the cue files became
    # 3. nothing left to do
    res = _snakemake(wd, "-n")
    assert res.returncode == 0 and "Nothing to be done" in res.stdout + res.stderr, _tail(res)


def test_refined_body_poses_are_what_the_stages_pose(ran):
    """refine_body on: each sequence's poses refined against rule masks' masks (training cameras), and the
    stages that pose the body read those: the simulated motion of walk is the refined one, not data/'s."""
    import numpy as np

    from anidress_core.io.motion import read_easymocap_smpl_dir
    from anidress_core.io.scene_info import read_scene

    wd = ran
    out, data = wd / "results" / "cap", wd / "data" / "cap"
    train = read_scene(data)["cameras"]["train"]
    for seq in ("walk", "jump"):
        rec = json.loads((out / seq / "body" / "refine_body.json").read_text())
        assert rec["cameras"] == train and rec["masks_dir"] == f"results/cap/{seq}/masks"
        assert 0 < rec["body_iou_after"] <= 1
    refined = read_easymocap_smpl_dir(out / "walk" / "body" / "smpl")
    given = read_easymocap_smpl_dir(data / "walk" / "smpl")
    assert refined["frames"] == given["frames"] and not np.allclose(refined["Th"], given["Th"])
    with np.load(out / "motions" / "seq-walk.npz") as m:
        assert np.allclose(m["Th"], refined["Th"], atol=1e-5) and np.allclose(m["Rh"], refined["Rh"], atol=1e-5)


def test_empty_pipeline_masks_are_not_scored(ran, tmp_path):
    """run_evaluate on the run's jump renders with the pipeline's masks, one of them emptied: that image is not
    scored (mask_source 'empty', NaN), not an IoU of 1 for an empty render; the others score as in the run."""
    from anidress_core.io import files
    from anidress_core.stages.evaluate import read_metrics_csv, run_evaluate

    wd = ran
    out = wd / "results" / "cap"
    masks = tmp_path / "masks"
    for p in (out / "jump" / "masks").rglob("*.png"):
        (masks / p.parent.name).mkdir(parents=True, exist_ok=True)
        (masks / p.parent.name / p.name).write_bytes(p.read_bytes())
    empty = masks / "01" / "000000.png"
    files.write_mask(empty, files.read_mask(empty) * 0)
    renders = [("novel_pose", "jump", out / "walk" / "full" / "renders" / "novel_pose" / "jump")]
    cwd = os.getcwd()
    os.chdir(wd)  # the scene and the undistorted folders as the rule passes them
    try:
        summ = run_evaluate("data/cap", renders, tmp_path / "m.csv", tmp_path / "s.json", {"box_pad_m": 0.05},
                            undistorted={"jump": "results/cap/jump/undistorted"}, masks={"jump": str(masks)},
                            bodies={"jump": "results/cap/jump/body"}, progress=False)
    finally:
        os.chdir(cwd)
    rows = {(r["camera"], r["frame"]): r for r in read_metrics_csv(tmp_path / "m.csv")}
    run = {(r["camera"], r["frame"]): r for r in read_metrics_csv(out / "walk" / "full" / "metrics.csv")
           if r["kind"] == "novel_pose"}
    assert rows[("01", 0)]["mask_source"] == "empty" and math.isnan(rows[("01", 0)]["iou"])
    for key, r in rows.items():
        if key != ("01", 0):
            assert r["mask_source"] == run[key]["mask_source"]
            assert r["psnr_db"] == pytest.approx(run[key]["psnr_db"], abs=1e-3, nan_ok=True)
    assert summ["metrics"][0]["scored"] == sum(r["mask_source"] == "pipeline" for r in run.values()) - 1
