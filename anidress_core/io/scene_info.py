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
           "select_cameras", "SHIPPED_CUE_FORMATS", "SCHP_LABEL_SET_NAMES", "cue_formats", "undistort_mem_mb"]

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


SHIPPED_CUE_FORMATS = {"masks": ("labels", "schp"), "normals": ("exr", "sapiens", "png", "icon"),
                       "flows": ("exr", "raft", "kitti")}
"""The formats of the cue files a captured sequence may ship (scene.yaml ``cues/<kind>/format``), the
pipeline's own first (the default). Readers: :mod:`anidress_core.io.shipped_cues`."""
SCHP_LABEL_SET_NAMES = ("lip", "atr", "cihp")
"""The label sets of SCHP's palette masks (``cues/masks/label_set``)."""


def cue_formats(info: dict, scene_dir: str | os.PathLike = "") -> dict:
    """scene.yaml ``cues``: the formats of the cue files the scene's sequences ship, checked.

    Returns ``{"masks": {"format", "label_set", "garment_labels", "person"}, "normals": {"format"},
    "flows": {"format"}}``, every key present: ``format`` defaults to the pipeline's own (labels,
    exr, exr); ``label_set`` (schp masks: lip | atr | cihp, default lip); ``garment_labels``
    (a list of label values, None: the label set's default, :data:`anidress_core.io.cue_files.SCHP_GARMENT_LABELS`);
    ``person`` (EasyMocap's per-person ``<frame>_<i>.png`` masks: whose file; None: the only one).
    """
    where = Path(scene_dir) / "scene.yaml"
    sec = info.get("cues") or {}
    if not isinstance(sec, dict):
        raise files.ArtifactError(f"{where}: cues must be a mapping (masks, normals, flows), got {sec!r}")
    unknown = set(sec) - set(SHIPPED_CUE_FORMATS)
    if unknown:
        raise files.ArtifactError(f"{where}: cues/{sorted(unknown)[0]}: unknown key (known: masks, normals, flows)")
    allowed = {"masks": {"format", "label_set", "garment_labels", "person"}, "normals": {"format"},
               "flows": {"format"}}
    out = {}
    for kind, formats in SHIPPED_CUE_FORMATS.items():
        c = sec.get(kind) or {}
        if not isinstance(c, dict):
            raise files.ArtifactError(f"{where}: cues/{kind} must be a mapping with a format, got {c!r}")
        bad = set(c) - allowed[kind]
        if bad:
            raise files.ArtifactError(f"{where}: cues/{kind}/{sorted(bad)[0]}: unknown key (known: "
                                      f"{', '.join(sorted(allowed[kind]))})")
        fmt = c.get("format", formats[0])
        if fmt not in formats:
            raise files.ArtifactError(f"{where}: cues/{kind}/format must be one of {list(formats)}, got {fmt!r}")
        out[kind] = {"format": fmt}
    m, msec = out["masks"], sec.get("masks") or {}
    m["label_set"] = msec.get("label_set", "lip")
    if m["label_set"] not in SCHP_LABEL_SET_NAMES:
        raise files.ArtifactError(f"{where}: cues/masks/label_set must be one of {list(SCHP_LABEL_SET_NAMES)}, "
                                  f"got {m['label_set']!r}")
    gl = msec.get("garment_labels")
    if gl is not None and (not isinstance(gl, list) or not all(isinstance(v, int) and not isinstance(v, bool)
                                                               and 0 <= v < 256 for v in gl)):
        raise files.ArtifactError(f"{where}: cues/masks/garment_labels must be a list of label values 0..255, "
                                  f"got {gl!r}")
    m["garment_labels"] = gl
    person = msec.get("person")
    if person is not None and (isinstance(person, bool) or not isinstance(person, int) or person < 0):
        raise files.ArtifactError(f"{where}: cues/masks/person must be a person index >= 0, got {person!r}")
    m["person"] = person
    if m["format"] != "schp" and any(k in msec for k in ("label_set", "garment_labels", "person")):
        raise files.ArtifactError(f"{where}: cues/masks: label_set, garment_labels and person apply to format "
                                  f"schp, the format is {m['format']!r}")
    return out


def undistort_mem_mb(height: int, width: int) -> int:
    """Memory (MB) rule undistort asks for with images of ``height`` x ``width`` pixels: twice its measured peak,
    at least 2000. The stage holds one camera's maps and an image per thread; its peak resident memory,
    interpreter and torch included, was 0.35 GB with 1024 x 1024 images and 0.44 GB with 1920 x 1080
    (issue 47), about 260 MB + 90 MB per megapixel: 2 (300 + 100 MP)."""
    mp = int(height) * int(width) / 1e6
    return max(2000, int(2 * (300 + 100 * mp)))


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
    the sequences (name, frames, role; no motion: a captured sequence's motion is its smpl/)."""
    entry = {"synthetic": False, "kind": info.get("kind", "tight"), "fps": info["fps"],
             "image_size": list(info["image_size"]),
             "sequences": [{"name": s["name"], "frames": int(s["frames"]), "role": s.get("role", "train")}
                           for s in info["sequences"]]}
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
