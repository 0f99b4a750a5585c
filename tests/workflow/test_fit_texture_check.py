"""rule validate_scene reports a fit's missing garment texture before any long stage (issue 24).

With fit/anchor_reference 'texture' L_anchor samples the garment texture; a captured scene
without one used to pass validate_scene and stop rule fit after template, simulate, rig, masks and
flows had run. The workflow passes rule validate_scene what the scene's effective fit section needs
(helpers/fit.smk fit_texture_check: only when a fit needs a texture the scene lacks), and
anidress_core.stages.validate fails naming the texture file and the setting.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from anidress_core.io.files import SceneError
from anidress_core.stages.validate import validate_scene
from tests.io.test_scene_cameras import build_tiny_skirt

REPO = Path(__file__).resolve().parents[2]
CFG = {"run_scenes": ["cap"], "fit": {"anchor_reference": "texture"},
       "scenes": {"cap": {"synthetic": False, "kind": "skirt", "sequences": [{"name": "walk", "frames": 3}]}}}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A captured skirt scene (the tiny synthetic one, marked captured) without a garment texture."""
    root = tmp_path_factory.mktemp("fit_texture")
    data, _ = build_tiny_skirt(root / "build")
    wd = root / "wd"
    shutil.copytree(data, wd / "data" / "cap")
    meta = yaml.safe_load((wd / "data" / "cap" / "scene.yaml").read_text())
    meta.update(name="cap", synthetic=False)
    meta.pop("garment_texture", None)
    (wd / "data" / "cap" / "scene.yaml").write_text(yaml.safe_dump(meta))
    (wd / "data" / "cap" / "garment" / "texture.png").unlink()
    return wd


def test_validate_names_the_missing_texture_and_the_setting(capture, tmp_path):
    scene = capture / "data" / "cap"
    validate_scene(scene)  # no fit needs the texture: the scene passes
    need = {"losses": ["pipeline"], "setting": "scenes/cap/fit/anchor_reference"}
    with pytest.raises(SceneError, match=r"garment/texture.png: scenes/cap/fit/anchor_reference is 'texture' .*"
                                         r"loss pipeline\) but the garment has no texture.*anchor_reference: images"):
        validate_scene(scene, fit_texture=need)
    with_tex = tmp_path / "with_texture"
    shutil.copytree(scene, with_tex)
    from anidress_core.io.files import write_png
    import numpy as np

    write_png(with_tex / "garment" / "texture.png", np.full((8, 8, 3), 0.5))
    s = validate_scene(with_tex, fit_texture=need)
    assert "garment texture for the fit's L_anchor (anchor_reference texture)" in s["checks"]


def _snakemake(wd: Path, cfg: dict, *args: str, importtime: bool = False) -> subprocess.CompletedProcess:
    (wd / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    # two jobs side by side on the 2 cores of `make test`, each on one thread as with --cores 1: the scene_files
    # listings (one job per part of the scene) before validate_scene
    cmd = [sys.executable, *(["-X", "importtime"] if importtime else []), "-m", "snakemake", *args, "-s",
           str(REPO / "Snakefile"), "--directory", str(wd), "--configfile", str(wd / "cfg.yaml"), "--cores", "2",
           "--max-threads", "1"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})


def test_the_workflow_stops_at_validate_scene_and_runs_with_images_references(capture):
    # 1. anchor_reference texture: the plan builds without torch; validate_scene fails, naming both
    res = _snakemake(capture, CFG, "-n", "--quiet", "rules", importtime=True)
    assert res.returncode == 0, res.stderr[-3000:]
    mods = {ln.rsplit("|", 1)[1].strip() for ln in res.stderr.splitlines() if ln.startswith("import time:")}
    assert "torch" not in mods and "anidress_core.io.scene_info" in mods
    res = _snakemake(capture, CFG, "results/cap/scene_check.json")
    assert res.returncode != 0
    log = (capture / "logs" / "cap" / "validate_scene.log").read_text()
    assert "garment/texture.png: fit/anchor_reference is 'texture'" in log and "anchor_reference: images" in log
    assert not (capture / "results" / "cap" / "scene_check.json").exists()
    # 2. the scene's fit on image references: no texture needed, the scene passes
    cfg = {**CFG, "scenes": {"cap": {**CFG["scenes"]["cap"], "fit": {"anchor_reference": "images"}}}}
    res = _snakemake(capture, cfg, "results/cap/scene_check.json")
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    # 3. texture references again, but the paper's loss (its L_anchor weight is 0): nothing to rerun; an
    #    ablation with the pipeline's loss needs the texture: validate_scene is planned again
    res = _snakemake(capture, {**CFG, "fit": {**CFG["fit"], "loss": "paper"}}, "results/cap/scene_check.json", "-n",
                     "--quiet", "rules")
    assert res.returncode == 0 and "validate_scene" not in res.stdout + res.stderr, res.stdout[-2000:]
    res = _snakemake(capture, {**CFG, "fit": {**CFG["fit"], "loss": "paper", "ablations": ["pipeline_no_flow"]}},
                     "results/cap/scene_check.json", "-n", "--quiet", "rules")
    assert res.returncode == 0 and "validate_scene" in res.stdout + res.stderr, res.stdout[-2000:]
