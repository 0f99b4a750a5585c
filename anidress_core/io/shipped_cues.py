"""The cue files a captured sequence ships, in the format scene.yaml names, read in the pipeline's form.

A sequence may ship ``masks/``, ``normals/`` and ``flows/`` written by the tools a user runs on
their own machine; scene.yaml's ``cues`` section names their formats
(:func:`anidress_core.io.scene_info.cue_formats`; the file formats: :mod:`anidress_core.io.cue_files`)::

    cues:
      masks:   {format: schp, label_set: lip, garment_labels: [6, 12], person: 0}
      normals: {format: sapiens}
      flows:   {format: raft}

Formats (the file of camera ``cam`` and frame ``f``), each read as the pipeline's form:

* masks, read as (H, W) uint8 labels 0 background, 1 body, 2 garment: ``labels`` (the default):
  ``<cam>/<f>.png`` 0 / 1 / 2; ``schp``: SCHP palette PNGs ``<cam>/<f>.png``, or EasyMocap's
  ``mask-schp`` layout, one 0 / 255 silhouette per person ``<cam>/<f>_<i>.png`` with the CIHP
  labels in ``masks-parsing/<cam>/<f>.png``;
* normals, read as (H, W, 3) float32 camera-space unit normals in the *file's* axes, 0 where
  there is none: ``exr`` (the default) ``<cam>/<f>.exr``; ``sapiens`` ``<cam>/<f>.npy``; ``png``
  ``<cam>/<f>.png`` or ``.exr`` holding (n+1)/2; ``icon`` ``<cam>/<f>.png`` crops placed in the
  image by ``crops.json``;
* flows, read as (H, W, 2) float32 pixels and (H, W) bool validity: ``exr`` (the default)
  ``<cam>/<f>.exr`` X, Y, valid; ``raft`` ``<cam>/<f>.flo``; ``kitti`` ``<cam>/<f>.png`` 16-bit.

``<f>``: the frame number, any zero padding. A flow file of frame ``f`` holds the forward flow
from frame ``f - 1`` to ``f`` on frame ``f - 1``'s pixel grid (the pipeline's convention,
DESIGN.md §7); the first frame has none. Rule undistort writes a distorted capture's normals and
flows in the pipeline's own formats (exr) and keeps masks as label indices
(:func:`source_format`). The axis convention of shipped normals is checked against the posed
body by rule normals (:func:`anidress_core.cues.normals.find_convention`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import cue_files, files
from .images import frame_files

__all__ = ["CUE_SUFFIX", "suffixes", "source_format", "cue_frames", "garment_labels", "read_mask_labels", "read_normals",
           "read_flow", "CROPS_FILE"]

CUE_SUFFIX = {("masks", "labels"): ".png", ("masks", "schp"): ".png", ("normals", "exr"): ".exr",
              ("normals", "sapiens"): ".npy", ("normals", "png"): ".png", ("normals", "icon"): ".png",
              ("flows", "exr"): ".exr", ("flows", "raft"): ".flo", ("flows", "kitti"): ".png"}
"""File extension of each (kind, format) (:func:`suffixes`: every one it is read from)."""


def suffixes(kind: str, fmt: str) -> tuple[str, ...]:
    """The file extensions of a (kind, format), in the order they are looked for: (n+1)/2 normal maps as PNG or
    EXR, every other format one."""
    return (".png", ".exr") if (kind, fmt) == ("normals", "png") else (CUE_SUFFIX[(kind, fmt)],)
CROPS_FILE = "crops.json"
"""ICON / ECON normal crops: ``normals/crops.json`` places each crop in its image
(:func:`anidress_core.io.cue_files.read_crops`)."""


def source_format(seq_dir: str | Path, kind: str, fmt: str) -> str:
    """The format of ``<seq_dir>/<kind>``: ``fmt`` (scene.yaml's) in the scene's folder; in rule undistort's
    folder (it holds ``undistort.json``) normals and flows are the pipeline's exr, masks keep their format."""
    if kind in ("normals", "flows") and (Path(seq_dir) / "undistort.json").is_file():
        return "exr"
    return fmt


def _mask_frames(cam_dir: Path) -> dict[int, Path]:
    """{frame: file} of a schp camera folder in either layout (``<f>.png`` or ``<f>_<i>.png``: the first)."""
    out: dict[int, Path] = {}
    if not cam_dir.is_dir():
        return out
    for p in sorted(cam_dir.iterdir()):
        if p.suffix.lower() != ".png":
            continue
        head = p.stem.split("_", 1)
        if head[0].isdigit() and (len(head) == 1 or head[1].isdigit()):
            out.setdefault(int(head[0]), p)
    return out


def cue_frames(cam_dir: str | Path, kind: str, fmt: str) -> dict[int, Path]:
    """{frame: file} of one camera's cue folder ``cam_dir`` in format ``fmt`` (any zero padding)."""
    cam_dir = Path(cam_dir)
    if kind == "masks" and fmt == "schp":
        return _mask_frames(cam_dir)
    return frame_files(cam_dir, suffixes(kind, fmt))


def garment_labels(cfg: dict) -> tuple[int, ...]:
    """The label values that are the garment of scene.yaml's ``cues/masks`` (its garment_labels, else the
    label set's default)."""
    gl = cfg.get("garment_labels")
    return tuple(gl) if gl is not None else tuple(cue_files.SCHP_GARMENT_LABELS[cfg["label_set"]])


def read_mask_labels(root: str | Path, cam: str, frame: int, cfg: dict, shape: tuple[int, int] | None = None,
                     garment: bool = True) -> np.ndarray:
    """Labels (H, W) uint8 (0 background, 1 body, 2 garment) of a shipped mask.

    root: the ``masks/`` folder; cfg: scene.yaml's ``cues/masks`` (:func:`cue_formats`); garment False: a
    tight-clothed scene (every person pixel is body).
    """
    root = Path(root)
    if cfg["format"] == "labels":
        path = frame_files(root / cam, (".png",)).get(int(frame), root / cam / f"{int(frame):06d}.png")
        lab = files.read_mask(path)
        if lab.max(initial=0) > 2:
            raise files.ArtifactError(f"{path}: labels must be 0 background, 1 body, 2 garment; found "
                                      f"{int(lab.max())} (a human parser's masks: set scene.yaml cues/masks/format: "
                                      "schp and its label_set)")
    else:
        idx, path = cue_files.read_schp_indices(root, cam, frame, cfg.get("person"))
        lab = cue_files.schp_to_labels(idx, cfg["label_set"], garment_labels(cfg), path=path)
    if shape is not None and lab.shape != tuple(shape):
        raise files.ArtifactError(f"{path}: mask is {lab.shape[1]}x{lab.shape[0]}, the images are "
                                  f"{shape[1]}x{shape[0]}")
    if not garment:
        lab = np.minimum(lab, 1).astype(np.uint8)
    return lab


def read_normals(root: str | Path, cam: str, frame: int, fmt: str, shape: tuple[int, int],
                 crops: dict | None = None) -> np.ndarray:
    """Normals (H, W, 3) float32 of a shipped normal map, in the file's own axes, 0 where there is none.

    root: the ``normals/`` folder; fmt: :data:`~anidress_core.io.scene_info.SHIPPED_CUE_FORMATS` ``normals``;
    crops (icon): :func:`anidress_core.io.cue_files.read_crops` of ``root/crops.json`` (read once by the caller).
    """
    root = Path(root)
    exts = suffixes("normals", fmt)
    path = frame_files(root / cam, exts).get(int(frame), root / cam / f"{int(frame):06d}{exts[0]}")
    if fmt == "exr":
        n = files.read_exr(path)
        if n.ndim != 3 or n.shape[-1] < 3:
            raise files.ArtifactError(f"{path}: normal map must be (H, W, 3), got {n.shape}")
        n = np.asarray(n[..., :3], np.float32)
    elif fmt == "sapiens":
        n = cue_files.read_sapiens_normals(path)
    elif fmt == "png":
        n = cue_files.read_normal_image(path)
    elif fmt == "icon":
        key = f"{cam}/{int(frame):06d}"
        if crops is None or key not in crops:
            raise files.ArtifactError(f"{root / CROPS_FILE}: no crop box for {key} (ICON / ECON normals are crops: "
                                      "the file gives [x0, y0, x1, y1] of each in its image)")
        n = cue_files.paste_crop(cue_files.read_normal_image(path), crops[key], shape[0], shape[1])
    else:
        raise ValueError(f"unknown normal format {fmt!r}")
    if n.shape[:2] != tuple(shape):
        raise files.ArtifactError(f"{path}: normal map is {n.shape[1]}x{n.shape[0]}, the images are "
                                  f"{shape[1]}x{shape[0]}")
    if not np.isfinite(n).all():
        raise files.ArtifactError(f"{path}: normal map has NaN or inf values")
    return n


def read_flow(root: str | Path, cam: str, frame: int, fmt: str, shape: tuple[int, int]) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """Forward flow (H, W, 2) float32 from frame ``frame - 1`` to ``frame`` and its validity (H, W) bool, of a
    shipped flow file (checked: size, RAFT's padding, finite at valid pixels)."""
    root = Path(root)
    suffix = CUE_SUFFIX[("flows", fmt)]
    path = frame_files(root / cam, (suffix,)).get(int(frame), root / cam / f"{int(frame):06d}{suffix}")
    flow, valid = cue_files.read_flow(path)  # the reader of the format's suffix
    cue_files.check_flow(flow, valid, tuple(shape), path)
    return flow, valid
