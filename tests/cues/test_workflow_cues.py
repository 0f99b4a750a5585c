"""Rules masks / flows / normals end to end on a tiny scene, and the input functions at DAG time."""
from __future__ import annotations

import copy
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.workflow.tiny import job_counts

from .conftest import TINY_SKIRT

REPO = Path(__file__).resolve().parents[2]

CFG = {
    "run_scenes": ["tinyskirt"],
    "scenes": {
        # the session's tiny scene (tests/cues/conftest.py), copied in: the rules under test
        # are the cue rules, not synth/template (tests/workflow covers those)
        "tinyskirt": {"synthetic": True, **TINY_SKIRT},
        # a user capture (not synthetic): ships masks, no normals
        "cap": {"synthetic": False, "kind": "skirt", "sequences": [{"name": "walk", "motion": "walk", "frames": 3}]},
    },
    "template": {"vertices": 600},
}
TARGETS = ["results/tinyskirt/walk/masks", "results/tinyskirt/walk/flows", "results/tinyskirt/walk/normals.json",
           "results/cap/walk/normals.json"]


def _snakemake(wd: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(wd), "--configfile",
           str(wd / "cfg.yaml"), "--cores", "2", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _jobs(wd: Path, cfg: dict, *targets: str) -> dict:
    (wd / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    try:
        res = _snakemake(wd, *targets, "-n", "--quiet", "rules")
    finally:
        (wd / "cfg.yaml").write_text(yaml.safe_dump(CFG))
    return job_counts(res)


@pytest.fixture(scope="module")
def run(tmp_path_factory, tiny_scene):
    wd = tmp_path_factory.mktemp("cues_wf")
    (wd / "cfg.yaml").write_text(yaml.safe_dump(CFG))
    shutil.copytree(tiny_scene[0], wd / "data" / "tinyskirt")
    (wd / "results" / "tinyskirt").mkdir(parents=True)
    for ext in ("npz", "ply"):
        shutil.copy(tiny_scene[1].with_suffix("." + ext), wd / "results" / "tinyskirt" / f"template.{ext}")
    # the capture: the tiny scene's images, cameras, body and garment, with masks shipped
    # (its ground truth's), no normal maps and no ground truth -- a valid scene (rule
    # validate_scene runs before every cue rule)
    cap = wd / "data" / "cap"
    shutil.copytree(tiny_scene[0], cap)
    shutil.move(cap / "walk" / "gt" / "masks", cap / "walk" / "masks")
    for d in ("normals", "gt"):
        shutil.rmtree(cap / "walk" / d)
    meta = yaml.safe_load((cap / "scene.yaml").read_text())
    meta.update(name="cap", synthetic=False)
    (cap / "scene.yaml").write_text(yaml.safe_dump(meta))
    res = _snakemake(wd, *TARGETS)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return wd


def test_rules_write_the_contract_layout(run):
    from anidress_core.io.files import read_exr, read_json, read_mask

    scene = yaml.safe_load((run / "data" / "tinyskirt" / "scene.yaml").read_text())
    res = run / "results" / "tinyskirt" / "walk"
    for cam in scene["cameras"]["train"]:
        assert sorted(p.name for p in (res / "masks" / cam).iterdir()) == [f"{i:06d}.png" for i in range(4)]
        assert sorted(p.name for p in (res / "flows" / cam).iterdir()) == [f"{i:06d}.exr" for i in range(1, 4)]
        assert set(np.unique(read_mask(res / "masks" / cam / "000002.png"))) <= {0, 1, 2}
        assert read_exr(res / "flows" / cam / "000002.exr").shape == (64, 64, 3)
    # (Snakemake puts a hidden .snakemake_timestamp into directory outputs)
    assert sorted(p.name for p in (res / "masks").iterdir() if not p.name.startswith(".")) == \
        sorted(scene["cameras"]["train"])
    rec = read_json(res / "normals.json")
    assert rec["skipped"] is False and rec["dir"] == "data/tinyskirt/walk/normals"
    skip = read_json(run / "results" / "cap" / "walk" / "normals.json")
    assert skip["skipped"] is True and skip["normal_weight"] == 0.0 and "ships no normal maps" in skip["reason"]
    for name in ("masks", "flows", "normals"):
        assert (run / "logs" / "tinyskirt" / "walk" / f"{name}.log").is_file()
    assert not [p for p in res.iterdir() if p.name.startswith(".")]  # no partial folders


def test_rerun_nothing_to_do_and_param_changes_rerun_only_downstream(run):
    res = _snakemake(run, "-n", *TARGETS)
    assert res.returncode == 0 and "Nothing to be done" in res.stdout + res.stderr
    cfg = copy.deepcopy(CFG)
    cfg["cues"] = {"flows": {"method": "dis_fast"}}
    assert _jobs(run, cfg, *TARGETS) == {"flows": 1}
    # the capture ships masks: its flows read them and no masks job is planned for it (its
    # garment template, the flow prior, is made first)
    jobs = _jobs(run, cfg, *TARGETS, "results/cap/walk/flows")
    assert jobs["flows"] == 2 and "masks" not in jobs and jobs.get("template") == 1
    cfg["cues"] = {"masks": {"fg_threshold": 0.1}}
    assert _jobs(run, cfg, *TARGETS) == {"masks": 1, "flows": 1}
