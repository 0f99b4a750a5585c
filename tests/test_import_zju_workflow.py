"""An imported ZJU-MoCap capture in the Snakemake workflow (issue 24 item 3).

`anidress import-zju` writes data/<scene> and prints the config entry; with that entry the real
Snakefile plans the whole pipeline for the scene (undistort for the camera with lens distortion,
the shipped masks used as they are: no masks job) and runs it up to the fitted garment poses:
validate_scene, undistort, template, motion, simulate, rig, flows, fit.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from anidress_core.io.garment_poses import read_garment_poses
from anidress_core.stages.import_capture import run_import_zju

from tests.io.test_scene_cameras import build_tiny_skirt
from tests.test_import_zju import write_zju_capture
from tests.workflow.tiny import job_counts

REPO = Path(__file__).resolve().parents[1]
SETTINGS = {"template": {"vertices": 300}, "simulate": {"library": [], "cloth": {"settle_frames": 3}, "ensemble_bend_stiffness": [1.0e-4, 1.0e-3], "ensemble_settle_frames": []},
            "rig": {"bones": 4, "iters": 3}, "field": {"render": {"library": []}},
            "fit": {"max_iters": 2, "max_iters_first": 3, "views": 2}}


def _snakemake(wd: Path, *args: str) -> subprocess.CompletedProcess:
    # two jobs side by side on the 2 cores of `make test` (pytest waits for the run), each on the one thread it
    # has with --cores 1 (the scene_files listings, undistort beside template, normals beside motions)
    cmd = [sys.executable, "-m", "snakemake", *args, "-s", str(REPO / "Snakefile"), "--directory", str(wd),
           "--configfile", str(wd / "cfg.yaml"), "--cores", "2", "--max-threads", "1"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def wd(tmp_path_factory):
    root = tmp_path_factory.mktemp("zju_wf")
    data, _ = build_tiny_skirt(root / "build")
    cap = write_zju_capture(data, root / "CoreView_313")
    raw = np.load(cap / "annots.npy", allow_pickle=True).item()
    raw["cams"]["D"][1] = np.array([[-0.2], [0.05], [0.0], [0.0], [0.0]])  # one camera with lens distortion
    np.save(cap / "annots.npy", raw, allow_pickle=True)
    wd = root / "wd"
    rec = run_import_zju(cap, wd / "data" / "zju", garment=data / "garment" / "template.obj", garment_kind="skirt",
                         body_model=data / "body_model.npz", train="0,1,3", link="copy", fps=50.0)
    (wd / "cfg.yaml").write_text(yaml.safe_dump({"run_scenes": ["zju"], "scenes": {"zju": rec["config_entry"]},
                                                 **SETTINGS}))
    return wd


def test_config_entry_is_valid():
    from anidress_core.config import default_schema_path, validate_config
    from anidress_core.io.scene_info import scene_config_entry

    info = {"kind": "skirt", "fps": 50.0, "image_size": [48, 40], "sequences": [{"name": "a", "frames": 3},
                                                                                 {"name": "b", "frames": 2,
                                                                                  "role": "novel_pose"}]}
    entry = scene_config_entry(info)
    assert "fit" not in entry  # tight: nothing to fit
    assert "fit" not in scene_config_entry({**info, "garment_template": "g.obj"})  # the default fit needs no texture
    cfg = validate_config({"run_scenes": ["z"], "scenes": {"z": entry}},
                          yaml.safe_load(default_schema_path().read_text()))
    assert cfg["scenes"]["z"]["synthetic"] is False and cfg["scenes"]["z"]["sequences"][1]["role"] == "novel_pose"


def test_imported_scene_plans_and_runs_in_the_workflow(wd):
    seq = "CoreView_313"
    # 1. the plan up to the fit: one undistort job (Camera_2 is distorted), the shipped masks (no masks job)
    plan = job_counts(_snakemake(wd, f"results/zju/{seq}/garment_poses.npz", "-n", "--quiet", "rules"))
    assert plan.get("undistort") == 1 and "masks" not in plan and "synth" not in plan
    assert plan.get("fit") == 1 and plan.get("flows") == 1 and plan.get("simulate", 0) >= 1
    # 2. the first rules run: the scene check, the undistortion, the template and the flows
    res = _snakemake(wd, "results/zju/scene_check.json", f"results/zju/{seq}/flows")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    check = yaml.safe_load((wd / "results" / "zju" / "scene_check.json").read_text())
    assert check["sequences"][seq]["distorted_cameras"] == ["Camera_2"]
    und = wd / "results" / "zju" / seq / "undistorted"
    assert (und / "images" / "Camera_2" / "000002.png").is_file() and (und / "masks" / "Camera_2").is_dir()
    assert (wd / "results" / "zju" / seq / "flows" / "Camera_1" / "000002.exr").is_file()
    # 3. on to the fitted garment poses: motion, simulate, rig, fit on the undistorted sequence
    res = _snakemake(wd, f"results/zju/{seq}/garment_poses.npz")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    gp = read_garment_poses(wd / "results" / "zju" / seq / "garment_poses.npz", frames=3, bones=4)
    assert np.isfinite(gp.verts).all() and gp.header["meta"]["cameras"] == ["Camera_1", "Camera_4"]
    assert job_counts(_snakemake(wd, f"results/zju/{seq}/garment_poses.npz", "-n", "--quiet", "rules")) == {}
