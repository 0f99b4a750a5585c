"""Reading a scene folder (DESIGN.md §3): scene.yaml, its body model, its sequences' motions and images.

Shared by every stage that reads a scene (template, motions, cues, fit, field,
evaluate, validate) and by the command line; errors name the file and the key.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ..body.model import BodyModel, smpl_model
from ..body.motions import Motion
from ..camera import Cameras, load_cameras
from . import easymocap, files
from .images import IMAGE_EXTS, frame_file, frame_files, image_path, image_size_from_header, plate_path
from .motion import read_easymocap_smpl_dir, read_smpl_model_file, smpl_selection
from .scene_info import (DIST_EPS, distorted_cameras, garment_texture_path,  # torch-free (the workflow reads
                         read_scene)                                          # them while it builds the DAG)

__all__ = ["IMAGE_EXTS", "read_scene", "garment_texture_path", "load_body", "load_sequence_motion", "image_path",
           "frame_file", "frame_files", "plate_path", "camera_scale",
           "scene_image_size", "scene_cameras", "DIST_EPS", "UNDISTORT_RECORD", "distorted_cameras",
           "sequence_source"]

UNDISTORT_RECORD = "undistort.json"
"""The record rule undistort writes last into its folder (its presence marks a complete folder)."""

def load_body(scene_dir: str | os.PathLike, info: dict | None = None) -> BodyModel:
    """The scene's body model: the bundled mannequin file or a SMPL model file the user owns."""
    scene_dir = Path(scene_dir)
    info = info or read_scene(scene_dir)
    spec = info["body_model"]
    path = scene_dir / spec["file"]
    if spec.get("type") == "mannequin":
        a, _ = files.load_npz(path, required=("v_template", "faces", "weights", "joints_rest", "parents"))
        t = torch.from_numpy
        return BodyModel(
            v_template=t(a["v_template"]).float(), faces=t(a["faces"]).long(), weights=t(a["weights"]).float(),
            joints_rest=t(a["joints_rest"]).float(), parents=t(a["parents"]).long(),
            face_uv=t(a["face_uv"]).float() if "face_uv" in a else None,
            vertex_part=t(a["vertex_part"]).long() if "vertex_part" in a else None,
            part_names=tuple(str(n) for n in a.get("part_names", ())), name="mannequin",
        )
    if spec.get("type") == "smpl":
        try:
            return smpl_model(read_smpl_model_file(path))
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from e
    raise files.ArtifactError(f"{scene_dir / 'scene.yaml'}: body_model/type must be mannequin or smpl, "
                              f"got {spec.get('type')!r}")


def load_sequence_motion(scene_dir: str | os.PathLike, seq: str, fps: float,
                         body_dir: str | os.PathLike | None = None) -> Motion:
    """The body motion of a captured sequence from its EasyMocap ``smpl/`` folder (the person
    and the frames without them as scene.yaml's person_id / max_missing_frames say).

    ``body_dir``: the sequence's poses refined by rule refine_body
    (:func:`anidress_core.stages.refine_body.run_refine_body`, in the pipeline
    ``results/<scene>/<seq>/body``): its ``smpl/`` (one person per frame, already selected) is
    read instead of the scene's.
    """
    if body_dir is not None:
        d = read_easymocap_smpl_dir(Path(body_dir) / "smpl")
    else:
        yml = Path(scene_dir) / "scene.yaml"
        sel = smpl_selection(read_scene(scene_dir), seq, yml) if yml.is_file() else {}
        d = read_easymocap_smpl_dir(Path(scene_dir) / seq / "smpl", **sel)
    shapes = np.asarray(d["shapes"], np.float32)
    return Motion(
        name=seq, fps=float(fps), poses=torch.as_tensor(np.asarray(d["poses"], np.float32)),
        Rh=torch.as_tensor(np.asarray(d["Rh"], np.float32)), Th=torch.as_tensor(np.asarray(d["Th"], np.float32)),
        shapes=torch.as_tensor(shapes[0] if shapes.ndim == 2 else shapes),
    )


def scene_image_size(scene_dir: str | os.PathLike, seq: str, info: dict | None = None) -> tuple[int, int]:
    """(H, W) of the sequence's images: scene.yaml's ``image_size``, else the header of its first image.

    What the camera files may lack: ``intri.yml`` as EasyMocap's ``write_intri`` and OpenCV
    write it has no ``H_<cam>`` / ``W_<cam>``. validate_scene checks that every image, mask
    and the files' ``H_``/``W_`` (when present) agree with this size.
    """
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir) if info is None else info
    size = info.get("image_size")
    if size:
        return int(size[0]), int(size[1])
    root = scene_dir / seq / "images"
    for cam_dir in sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []:
        for p in sorted(cam_dir.iterdir()):
            if p.suffix.lower() in IMAGE_EXTS and p.stem.isdigit():
                return image_size_from_header(p)
    raise files.ArtifactError(f"{scene_dir / 'scene.yaml'}: no image_size and no images under {root} "
                              "to take the image size from")


def camera_scale(info: dict, scene_dir: str | os.PathLike = "") -> float | None:
    """scene.yaml ``cameras/scale``: the images are this factor of the size the calibration was made for
    (e.g. 0.5 for 960x540 images of a 1920x1080 calibration); None when absent (1)."""
    s = (info.get("cameras") or {}).get("scale")
    if s is None:
        return None
    if isinstance(s, bool) or not isinstance(s, (int, float)) or not (0 < float(s) < 100):
        raise files.ArtifactError(f"{Path(scene_dir) / 'scene.yaml'}: cameras/scale must be a number in (0, 100) (the "
                                  f"images' size over the calibration's), got {s!r}")
    return None if float(s) == 1.0 else float(s)


def scene_cameras(scene_dir: str | os.PathLike, seq: str, names: list[str] | None = None,
                  info: dict | None = None, dtype: torch.dtype = torch.float64,
                  seq_dir: str | os.PathLike | None = None) -> Cameras:
    """The cameras of sequence ``seq`` (``<scene_dir>/<seq>/intri.yml``, ``extri.yml``) with the
    scene's image size (:func:`scene_image_size`), so that ``intri.yml`` without ``H_``/``W_``
    loads. Every stage that reads a scene's cameras goes through this function.

    names: the cameras to keep, in that order (default: all, in file order); seq_dir: the
    folder the stage reads the sequence from (:func:`sequence_source`; default
    ``<scene_dir>/<seq>``). Returns :class:`anidress_core.camera.Cameras` in ``dtype``.
    """
    scene_dir = Path(scene_dir)
    seq_dir = scene_dir / seq if seq_dir is None else Path(seq_dir)
    intri = seq_dir / "intri.yml"
    info = read_scene(scene_dir) if info is None else info
    h, w = scene_image_size(scene_dir, seq, info)
    # scene.yaml cameras/scale applies to the capture's files; rule undistort writes its working cameras scaled
    scale = camera_scale(info, scene_dir) if not (seq_dir / UNDISTORT_RECORD).is_file() else None
    try:
        return load_cameras(intri, seq_dir / "extri.yml", names, height=h, width=w, dtype=dtype, scale=scale)
    except (ValueError, KeyError) as e:
        msg = str(e)
        raise ValueError(msg if str(intri) in msg else f"{intri}: {msg}") from e


def sequence_source(scene_dir: str | os.PathLike, seq: str, undistorted_dir: str | os.PathLike | None = None,
                    info: dict | None = None) -> Path:
    """The folder a stage reads sequence ``seq``'s images, shipped masks / normals and cameras from.

    The one decision of which images and cameras a stage reads: the scene's own
    ``<scene_dir>/<seq>`` when its cameras are pinholes, else ``undistorted_dir``: the
    sequence undistorted to pinhole working cameras by rule ``undistort``
    (:func:`anidress_core.stages.undistort.run_undistort`, in the pipeline
    ``results/<scene>/<seq>/undistorted``), same layout (``images/``, ``masks/``, ``normals/``,
    ``gt/masks``, ``intri.yml``, ``extri.yml``). The body motion is not in it: the scene's ``smpl/``,
    or its refinement by rule refine_body (:func:`load_sequence_motion`).
    """
    scene_dir = Path(scene_dir)
    bad = distorted_cameras(scene_dir, seq, info)
    if not bad:
        return scene_dir / seq
    intri = scene_dir / seq / "intri.yml"
    if undistorted_dir is None:
        raise ValueError(f"{intri}: cameras {', '.join(bad)} have lens distortion: the stages read the sequence "
                         "undistorted to pinhole working cameras by rule undistort (anidress undistort); "
                         "pass its folder (command line: --undistorted DIR; Python: undistorted_dir=)")
    d = Path(undistorted_dir)
    if not (d / UNDISTORT_RECORD).is_file():
        raise FileNotFoundError(f"{d / UNDISTORT_RECORD}: not found: {d} is not a complete undistorted sequence "
                                f"of {scene_dir / seq} (run rule undistort / anidress undistort)")
    return d
