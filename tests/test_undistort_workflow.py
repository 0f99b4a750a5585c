"""Rule undistort in the workflow: a captured scene with lens distortion (issue 24 item 2).

The DAG gets one undistort job per distorted sequence, which the cue rules depend on; they read
the undistorted images, cameras and shipped masks / normals. A pinhole scene has no undistort job.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.test_undistort_stage import build_distorted_capture
from tests.workflow.tiny import job_counts

REPO = Path(__file__).resolve().parents[1]
CFG = {"run_scenes": ["cap"],
       # a user capture: no procedural motion name needed (its motion is smpl/)
       "scenes": {"cap": {"synthetic": False, "kind": "skirt", "sequences": [{"name": "walk", "frames": 3}]}}}


def _snakemake(wd: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(wd), "--configfile",
           str(wd / "cfg.yaml"), "--cores", "2", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def wd(tmp_path_factory):
    root = tmp_path_factory.mktemp("undistort_wf")
    data, res, _ = build_distorted_capture(root / "build")
    wd = root / "wd"
    shutil.copytree(data, wd / "data" / "cap")
    (wd / "results" / "cap").mkdir(parents=True)
    for ext in ("npz", "ply"):  # the template (rule template is not under test), newer than the data
        shutil.copy(res / f"template.{ext}", wd / "results" / "cap" / f"template.{ext}")
    meta = yaml.safe_load((wd / "data" / "cap" / "scene.yaml").read_text())
    meta.update(name="cap", synthetic=False)
    (wd / "data" / "cap" / "scene.yaml").write_text(yaml.safe_dump(meta))
    (wd / "cfg.yaml").write_text(yaml.safe_dump(CFG))
    return wd


def test_the_dag_undistorts_once_and_the_cue_rules_read_it(wd):
    from anidress_core.io.files import read_exr, read_json

    # 1. the plan up to the fit: one undistort job; shipped masks, so no masks job
    plan = job_counts(_snakemake(wd, "results/cap/walk/garment_poses.npz", "-n", "--quiet", "rules"))
    assert plan.get("undistort") == 1 and "masks" not in plan and plan.get("flows") == 1 and plan.get("fit") == 1
    # 2. run the cues: undistort, then flows on the undistorted shipped masks, normals checked on the copy
    res = _snakemake(wd, "results/cap/walk/flows", "results/cap/walk/normals.json")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    und = wd / "results" / "cap" / "walk" / "undistorted"
    rec = read_json(und / "undistort.json")
    assert rec["distorted"] == ["01", "02"] and "normals" in rec["undistorted"]
    rec = read_json(wd / "results" / "cap" / "walk" / "normals.json")  # checked on the copy, written for the fit
    assert rec["dir"] == "results/cap/walk/normals" and rec["convention_axes"] == "x, y, z" and rec["format"] == "exr"
    assert (wd / "results" / "cap" / "walk" / "normals" / "01" / "000001.exr").is_file()
    assert read_exr(wd / "results" / "cap" / "walk" / "flows" / "01" / "000001.exr").shape[-1] == 3
    # 3. nothing left to do; a stage's setting does not rerun the undistortion
    assert job_counts(_snakemake(wd, "results/cap/walk/flows", "results/cap/walk/normals.json", "-n", "--quiet",
                            "rules")) == {}
    cfg = dict(CFG, cues={"flows": {"margin_px": 6}})
    (wd / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    try:
        plan = job_counts(_snakemake(wd, "results/cap/walk/flows", "-n", "--quiet", "rules"))
    finally:
        (wd / "cfg.yaml").write_text(yaml.safe_dump(CFG))
    assert plan == {"flows": 1}


def test_a_pinhole_capture_has_no_undistort_job(wd, tmp_path):
    from anidress_core.io import easymocap

    pin = tmp_path / "pin"
    shutil.copytree(wd, pin, ignore=shutil.ignore_patterns("undistorted", "flows", "normals.json", ".snakemake"))
    intri = pin / "data" / "cap" / "walk" / "intri.yml"
    raw = easymocap.read_intri(intri)
    easymocap.write_intri(intri, {c: dict(v, dist=v["dist"] * 0) for c, v in raw.items()})
    plan = job_counts(_snakemake(pin, "results/cap/walk/garment_poses.npz", "-n", "--quiet", "rules"))
    assert "undistort" not in plan and plan.get("flows") == 1 and plan.get("fit") == 1
