"""End to end: the Snakemake workflow on a tiny scene, then a no-op second run."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]

TINY = {
    "run_scenes": ["tiny"],
    "scenes": {
        "tiny": {
            "synthetic": True,
            "kind": "tight",
            "image_size": [48, 48],
            "cameras": {"count": 12, "train": 8},
            "sequences": [
                {"name": "walk", "motion": "walk", "frames": 3, "role": "train"},
                {"name": "jump", "motion": "jump", "frames": 3, "role": "novel_pose"},
            ],
            "render": {"texture_size": 128, "noise_std": 0.003},
        }
    },
}


def _snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(workdir / "tiny.yaml"), "--cores", "2", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONUNBUFFERED": "1"})


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    wd = tmp_path_factory.mktemp("wf")
    (wd / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    res = _snakemake(wd)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return wd


def test_tiny_scene_layout(tiny_run):
    root = tiny_run / "data" / "tiny"
    scene = yaml.safe_load((root / "scene.yaml").read_text())
    assert len(scene["cameras"]["train"]) == 8 and len(scene["cameras"]["test"]) == 4
    cams = scene["cameras"]["train"] + scene["cameras"]["test"]
    for seq in ("walk", "jump"):
        s = root / seq
        assert (s / "intri.yml").is_file() and (s / "extri.yml").is_file()
        for cam in cams:
            assert sorted(p.name for p in (s / "images" / cam).iterdir()) == ["000000.png", "000001.png", "000002.png"]
            assert len(list((s / "gt" / "masks" / cam).iterdir())) == 3
            assert len(list((s / "gt" / "normals" / cam).iterdir())) == 3
            assert sorted(p.name for p in (s / "gt" / "flows" / cam).iterdir()) == ["000001.exr", "000002.exr"]
            assert (s / "backgrounds" / f"{cam}.png").is_file()
        assert len(list((s / "smpl").iterdir())) == 3
        meshes = np.load(s / "gt" / "meshes.npz")
        assert meshes["body_vertices"].shape[0] == 3
    assert (tiny_run / "logs" / "tiny" / "synth.log").is_file()
    # nothing half-written is left beside the scene
    assert [p.name for p in (tiny_run / "data").iterdir()] == ["tiny"]


def test_second_run_has_nothing_to_do(tiny_run):
    res = _snakemake(tiny_run, "-n")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "Nothing to be done" in res.stdout + res.stderr


def test_param_change_reruns_synth(tiny_run):
    cfg = yaml.safe_load((tiny_run / "tiny.yaml").read_text())
    cfg["scenes"]["tiny"]["render"]["noise_std"] = 0.01
    alt = tiny_run / "alt"
    alt.mkdir(exist_ok=True)
    (tiny_run / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    try:
        res = _snakemake(tiny_run, "-n")
        out = res.stdout + res.stderr
        assert "synth" in out and "Nothing to be done" not in out
    finally:
        (tiny_run / "tiny.yaml").write_text(yaml.safe_dump(TINY))
