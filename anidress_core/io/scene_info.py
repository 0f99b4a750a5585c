"""scene.yaml, the garment texture's path and the lens distortion of a sequence's cameras, without torch.

What the Snakemake workflow reads of a captured scene while it builds its DAG (rule undistort is
planned for a sequence whose cameras have lens distortion; rule validate_scene is told when a fit needs
a garment texture the scene lacks): kept apart from
:mod:`anidress_core.io.scene`, which imports torch, so that a no-op rerun stays a few seconds
(issue 22). :mod:`anidress_core.io.scene` re-exports these names.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from . import easymocap, files

__all__ = ["DIST_EPS", "read_scene", "garment_texture_path", "distorted_cameras", "scene_config_entry",
           "select_cameras"]

DIST_EPS = 1e-9
"""A distortion coefficient of magnitude at most this counts as zero (a pinhole camera)."""


def read_scene(scene_dir: str | os.PathLike) -> dict:
    """Parse ``<scene_dir>/scene.yaml`` with a clear error naming the file and the key."""
    path = Path(scene_dir) / "scene.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: scene description not found")
    try:
        info = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise files.ArtifactError(f"{path}: not valid YAML ({e})") from e
    for key in ("fps", "sequences", "body_model"):
        if key not in info:
            raise files.ArtifactError(f"{path}: missing key {key!r}")
    return info


def garment_texture_path(scene_dir: str | os.PathLike, info: dict) -> Path:
    """The garment template's texture: ``garment_texture`` in scene.yaml, else ``texture.png``
    beside the template (which may not exist: the texture is optional)."""
    if info.get("garment_texture"):
        return Path(scene_dir) / info["garment_texture"]
    return (Path(scene_dir) / info.get("garment_template", "garment/template.obj")).parent / "texture.png"


def distorted_cameras(scene_dir: str | os.PathLike, seq: str, info: dict | None = None) -> list[str]:
    """The cameras of sequence ``seq`` with lens distortion (a ``dist_<cam>`` coefficient over
    :data:`DIST_EPS`), among those scene.yaml uses (cameras/train + test; all of intri.yml if none)."""
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir) if info is None else info
    cams = info.get("cameras") or {}
    used = list(cams.get("train") or []) + list(cams.get("test") or [])
    intri = easymocap.read_intri(scene_dir / seq / "intri.yml", used or None)
    return [c for c, v in intri.items() if np.any(np.abs(np.asarray(v["dist"], np.float64)) > DIST_EPS)]


def scene_config_entry(info: dict) -> dict:
    """The ``scenes/<scene>`` entry of the pipeline config (workflow/schemas/config.schema.yaml) for a
    captured scene whose parsed scene.yaml is ``info``: synthetic false, kind, fps, image_size and
    the sequences (name, frames, role; no motion: a captured sequence's motion is its smpl/).

    A garment without a texture (a capture has none unless one was given) gets the scene override
    ``fit: {anchor_reference: images}``: the default ``texture`` references need the texture and
    the fit would stop on it."""
    entry = {"synthetic": False, "kind": info.get("kind", "tight"), "fps": info["fps"],
             "image_size": list(info["image_size"]),
             "sequences": [{"name": s["name"], "frames": int(s["frames"]), "role": s.get("role", "train")}
                           for s in info["sequences"]]}
    if info.get("garment_template") and not info.get("garment_texture"):
        entry["fit"] = {"anchor_reference": "images"}
    return entry


def select_cameras(info: dict, which: str | Sequence[str], scene_dir: str | os.PathLike = "") -> list[str]:
    """Camera names of a scene: ``train`` (its training cameras), ``all`` or an explicit list."""
    cams = info.get("cameras") or {}
    if isinstance(which, str):
        if which == "train":
            names = list(cams.get("train") or [])
        elif which == "all":
            names = list(cams.get("train") or []) + list(cams.get("test") or [])
        else:
            raise ValueError(f"cameras must be 'train', 'all' or a list of names, got {which!r}")
    else:
        names = list(which)
    if not names:
        raise ValueError(f"{Path(scene_dir) / 'scene.yaml'}: no cameras for selection {which!r}")
    return names
