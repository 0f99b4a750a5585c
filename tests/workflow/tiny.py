"""The tiny two-scene config of the workflow tests and helpers to run Snakemake on it (conftest.py builds it
once per session as fixture ``tiny_run``)."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]

TINY = {
    "run_scenes": ["tiny", "tinyskirt"],
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
        },
        "tinyskirt": {
            "synthetic": True,
            "kind": "skirt",
            "image_size": [48, 48],
            "cameras": {"count": 6, "train": 4},  # half the default ring: the fit, cues, fields run on 4 views
            "sequences": [{"name": "walk", "motion": "walk", "frames": 4, "role": "train"}],
            "garment": {"vertices": 600, "cloth": {"settle_frames": 5}},
            "render": {"texture_size": 128},
        },
    },
    "template": {"vertices": 600},
    "simulate": {"library": ["sway"], "library_frames": 5, "cloth": {"settle_frames": 5},
                 "ensemble_bend_stiffness": [1.0e-4, 1.0e-3], "ensemble_settle_frames": [3, 6]},
    "rig": {"bones": 6, "iters": 10},
    "fit": {"max_iters": 5, "max_iters_first": 10},
    "field": {
        "train": {"steps": 20, "rays_per_step": 256, "images_per_step": 4, "checkpoint_every": 10},
        "render": {"frame_stride": 2, "library": ["sway"], "library_frame_stride": 2, "skip_res": 32},
    },
}

# as profiles/default without `code` and `software-env` (no script or environment changes here)
RERUN_TRIGGERS = ("--rerun-triggers", "params", "input", "mtime")


def snakemake_cmd(workdir: Path, *args: str, cores: int = 2) -> list[str]:
    """The command line of a Snakemake run of the workflow in ``workdir`` with its tiny.yaml (targets first:
    ``--rerun-triggers`` takes every word after it)."""
    return [sys.executable, "-m", "snakemake", *args, "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
            "--configfile", str(workdir / "tiny.yaml"), "--cores", str(cores)]


def snakemake(workdir: Path, *args: str, cores: int = 2, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run(snakemake_cmd(workdir, *args, cores=cores), capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})


def planned_jobs(workdir: Path, cfg: dict | None = None, triggers: tuple[str, ...] = ()) -> dict[str, int]:
    """{rule: jobs} of a dry run (with ``cfg`` as tiny.yaml for its duration; the file is restored after)."""
    if cfg is not None:
        (workdir / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    try:
        res = snakemake(workdir, "-n", "--quiet", "rules", *triggers)
    finally:
        (workdir / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    return job_counts(res)


def job_counts(res: subprocess.CompletedProcess) -> dict[str, int]:
    """{rule: jobs} from the output of a successful ``snakemake -n --quiet rules`` (its table of job counts)."""
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    jobs = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit() and parts[0] not in ("total", "job"):
            jobs[parts[0]] = int(parts[1])
    return jobs


def copy_run(src: Path, dst: Path) -> Path:
    """A copy of a run folder (outputs, logs and Snakemake's metadata, modification times kept)."""
    shutil.copytree(src, dst, symlinks=True)
    return dst
