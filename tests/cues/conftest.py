"""Shared fixtures: a tiny synthetic skirt scene on disk and a clean in-memory frame."""
from __future__ import annotations

import pytest
import yaml

from anidress_core.config import default_schema_path, validate_config


def scene_cfg(**scene) -> dict:
    cfg = validate_config({"run_scenes": ["t"], "scenes": {"t": scene}}, yaml.safe_load(default_schema_path().read_text()))
    return cfg["scenes"]["t"]


TINY_SKIRT = {
    "kind": "skirt",
    "image_size": [64, 64],
    "cameras": {"count": 6, "train": 4},
    "body": {"vertices": 2000},
    "sequences": [{"name": "walk", "motion": "walk", "frames": 4}],
    "garment": {"vertices": 600, "cloth": {"settle_frames": 5}},
    "render": {"texture_size": 128, "noise_std": 0.003},
}


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """(scene_dir, template_npz) of a 64x64, 6-camera (4 train), 4-frame skirt scene."""
    from anidress_core.io.scene import load_body
    from anidress_core.stages.synth import run_synth
    from anidress_core.stages.template import run_template

    root = tmp_path_factory.mktemp("cues_scene")
    scene_dir = root / "data" / "t"
    run_synth(scene_cfg(**TINY_SKIRT), "t", scene_dir, threads=1, progress=False)
    npz = root / "template.npz"
    run_template(None, "skirt", load_body(scene_dir), 600, root / "template.ply", npz)
    return scene_dir, npz


@pytest.fixture(scope="session")
def cues_config() -> dict:
    """The default `cues` config section (schema defaults)."""
    cfg = validate_config({"run_scenes": ["t"], "scenes": {"t": {}}}, yaml.safe_load(default_schema_path().read_text()))
    return cfg["cues"]
