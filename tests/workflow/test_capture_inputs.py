"""Edits inside a captured scene rerun what reads the edited file (issue 24 item 6).

A captured scene's files are inputs one by one of rule scene_files, one job per part of the scene
(workflow/rules/scene_files.smk), whose manifests the stage rules take: editing walk/intri.yml, a
smpl/*.json body file or an image plans that part's manifest, rule validate_scene and the jobs that read
the part and what depends on them; an edit of a file no rule reads plans nothing. An AMASS file named in
the config is an input of its motion. The outputs are made up to date without running the jobs (empty
files, then `snakemake --touch`): these are dry runs of the plan only.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.test_undistort_stage import build_distorted_capture
from tests.workflow.tiny import job_counts

REPO = Path(__file__).resolve().parents[2]
CFG = {"run_scenes": ["cap"],
       "scenes": {"cap": {"synthetic": False, "kind": "skirt", "sequences": [{"name": "walk", "frames": 3}]}},
       "simulate": {"library": [], "amass": ["amass/clip.npz"], "ensemble_bend_stiffness": [1.0e-4, 1.0e-3], "ensemble_settle_frames": []}, "field": {"render": {"library": []}}}
DIRECTORY_RULES = {"undistort", "masks", "flows", "render_novel_view", "render_novel_pose", "render_library"}
# what reads the cameras and images of a distorted sequence, and everything after it (the rig reads no scene file)
CAMERA_JOBS = {"scene_files": 1, "validate_scene": 1, "undistort": 1, "flows": 1, "normals": 1, "fit": 1, "train_field": 2,
               "render_novel_view": 2, "evaluate_field": 2, "report": 1, "all": 1}


def _snakemake(wd: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", *args, "-s", str(REPO / "Snakefile"), "--directory", str(wd),
           "--configfile", str(wd / "cfg.yaml"), "--cores", "1"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})


def _jobs(wd: Path) -> dict[str, int]:
    return job_counts(_snakemake(wd, "-n", "--quiet", "rules"))


def mark_up_to_date(wd: Path) -> None:
    """Every output of the workflow made present (empty) and up to date without running a job."""
    res = _snakemake(wd, "--summary")
    assert res.returncode == 0, res.stderr[-3000:]
    for line in res.stdout.splitlines()[1:]:
        cols = line.split("\t")
        if len(cols) < 3 or not cols[0].startswith("results/"):
            continue
        out = wd / cols[0]
        if cols[2] in DIRECTORY_RULES:
            out.mkdir(parents=True, exist_ok=True)
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.touch()
    for _ in range(6):  # --touch touches the jobs it plans; a job skipped by snakemake#4166 is planned next time
        if not _jobs(wd):
            return
        res = _snakemake(wd, "--touch")
        assert res.returncode == 0, res.stderr[-3000:]
    raise AssertionError(f"still planned after --touch: {_jobs(wd)}")


@pytest.fixture(scope="module")
def wd(tmp_path_factory):
    root = tmp_path_factory.mktemp("capture_inputs")
    data, _, _ = build_distorted_capture(root / "build")
    wd = root / "wd"
    shutil.copytree(data, wd / "data" / "cap")
    meta = yaml.safe_load((wd / "data" / "cap" / "scene.yaml").read_text())
    meta.update(name="cap", synthetic=False)
    (wd / "data" / "cap" / "scene.yaml").write_text(yaml.safe_dump(meta))
    (wd / "amass").mkdir()
    np.savez(wd / "amass" / "clip.npz", poses=np.zeros((4, 156)), trans=np.zeros((4, 3)), betas=np.zeros(16),
             mocap_framerate=np.float64(30.0), gender=np.str_("neutral"))
    (wd / "cfg.yaml").write_text(yaml.safe_dump(CFG))
    mark_up_to_date(wd)
    return wd


class edited:
    """Within the block, ``path`` holds ``content`` (bytes) with a newer mtime; restored after (bytes and times)."""

    def __init__(self, path: Path, content: bytes | None):
        self.path, self.content = path, content

    def __enter__(self):
        self.old = self.path.read_bytes() if self.path.exists() else None
        self.stat = self.path.stat() if self.path.exists() else None
        time.sleep(0.01)
        self.path.write_bytes(self.content if self.content is not None else self.old)
        os.utime(self.path, (time.time() + 5, time.time() + 5))
        return self.path

    def __exit__(self, *exc):
        if self.old is None:
            self.path.unlink()
        else:
            self.path.write_bytes(self.old)
            os.utime(self.path, ns=(self.stat.st_atime_ns, self.stat.st_mtime_ns))


def test_an_intri_edit_reruns_validation_undistortion_and_what_reads_the_cameras(wd):
    from anidress_core.io import easymocap

    intri = wd / "data" / "cap" / "walk" / "intri.yml"
    raw = easymocap.read_intri(intri)
    raw["01"]["K"][0, 0] += 0.5  # a focal length corrected by half a pixel
    new = wd / "intri_new.yml"
    easymocap.write_intri(new, raw)
    with edited(intri, new.read_bytes()):
        assert _jobs(wd) == CAMERA_JOBS
    assert _jobs(wd) == {}


def test_a_body_file_edit_reruns_its_motion_and_what_reads_the_body(wd):
    body = wd / "data" / "cap" / "walk" / "smpl" / "000001.json"
    people = json.loads(body.read_text())
    people[0]["Th"][0][0] += 0.01  # one centimetre
    with edited(body, json.dumps(people).encode()):
        # normals too: rule normals checks the shipped normals' axes against the posed body
        assert _jobs(wd) == {"scene_files": 1, "validate_scene": 1, "motions": 1, "simulate": 1, "simulate_ensemble": 1,
                             "rig": 1, "flows": 1, "normals": 1, "fit": 1, "train_field": 2, "render_novel_view": 2,
                             "evaluate_field": 2, "report": 1, "all": 1}


def test_an_image_edit_reruns_what_reads_the_images(wd):
    from anidress_core.io.files import read_image, write_png

    img = wd / "data" / "cap" / "walk" / "images" / "02" / "000001.png"
    new = wd / "image_new.png"
    write_png(new, np.clip(read_image(img) * 0.9, 0, 1))
    with edited(img, new.read_bytes()):
        # normals too: the sequence is distorted, rule normals reads the undistorted copy undistort rewrites
        assert _jobs(wd) == CAMERA_JOBS


def test_an_image_edit_in_a_pinhole_capture_spares_the_normals(wd, tmp_path):
    from anidress_core.io import easymocap
    from anidress_core.io.files import read_image, write_png

    pin = tmp_path / "pin"
    shutil.copytree(wd, pin, ignore=shutil.ignore_patterns("results", "logs", "benchmarks", ".snakemake"))
    intri = pin / "data" / "cap" / "walk" / "intri.yml"
    raw = easymocap.read_intri(intri)
    easymocap.write_intri(intri, {c: dict(v, dist=v["dist"] * 0) for c, v in raw.items()})
    mark_up_to_date(pin)
    img = pin / "data" / "cap" / "walk" / "images" / "02" / "000001.png"
    new = pin / "image_new.png"
    write_png(new, np.clip(read_image(img) * 0.9, 0, 1))
    with edited(img, new.read_bytes()):
        # rule normals reads the shipped normals and the cameras, not the images; no undistort job at all
        assert _jobs(pin) == {k: v for k, v in CAMERA_JOBS.items() if k not in ("normals", "undistort")}


def test_an_amass_file_edit_reruns_its_motion_only_downstream(wd):
    with edited(wd / "amass" / "clip.npz", None):
        assert _jobs(wd) == {"motions": 1, "simulate": 1, "rig": 1, "fit": 1, "train_field": 1,
                             "render_novel_view": 1, "evaluate_field": 1, "report": 1, "all": 1}


def test_an_unrelated_edit_plans_nothing(wd):
    with edited(wd / "data" / "cap" / "body_texture.png", None):  # synth's texture: no rule reads it
        assert _jobs(wd) == {}
    with edited(wd / "data" / "cap" / "notes.txt", b"captured on a Tuesday\n"):  # a new file beside the scene
        assert _jobs(wd) == {}
