"""ZJU-MoCap captures: ``annots.npy`` (cameras and per-frame image lists) and mask labels.

Layout (Peng et al., "Neural Body", CVPR 2021; read by zju3dv/neuralbody
``lib/datasets/light_stage/*.py``, the code here is our own)::

    <capture>/annots.npy          np.save of a dict (a pickle inside a .npy):
        cams: {K: [C x (3, 3)], D: [C x (5, 1)], R: [C x (3, 3)], T: [C x (3, 1)]}
              X_cam = R X_world + T, T in MILLIMETRES (neuralbody divides by 1000)
        ims:  [T x {"ims": [C image paths relative to <capture>]}]
    <capture>/mask/<path>.png       person masks, 0 background, non-zero person
    <capture>/mask_cihp/<path>.png  CIHP human-parsing labels 0..19 (0 background)
    <capture>/params/<i>.npy        body parameters of frame number i (np.save of a dict:
    <capture>/new_params/<i>.npy    poses (1, 72), Rh (1, 3), Th (1, 3) metres, shapes (1, 10),
                                    EasyMocap's convention; new_params: the later refit)

``<path>`` is an image path of ``ims`` without its extension. The frame number ``i`` of
an image is its file name (``Camera_B1/000123.jpg``: 123), or for CoreView_313 / 315's
long names (``Camera (1)/CoreView_313_Camera_(1)_0001_2019-08-23_16-08-50.592.jpg``) the
fifth ``_``-separated field (1): :func:`zju_frame_number`, neuralbody's rule.

:func:`read_annots` returns our :class:`anidress_core.camera.Cameras` (metres) and the
image lists; :func:`zju_mask_labels` maps the two mask kinds to the pipeline's labels
(0 background, 1 body, 2 garment: ``anidress_core.synth.LABEL_*``);
:func:`read_zju_params` reads the body parameters of given frame numbers (or all);
:func:`zju_mask_paths` names the mask files of an image; :func:`safe_camera_names` turns
the camera folders (``Camera (1)``) into names EasyMocap's files can hold.

``annots.npy`` is a pickle: it is the one file of this module read with pickle enabled,
and even then only through the restricted unpickler of :mod:`anidress_core.io.motion`
(numpy arrays, builtin containers and strings; anything else is refused). Every other
file here is read without pickle.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..camera import Cameras
from ..synth import LABEL_BACKGROUND, LABEL_BODY, LABEL_GARMENT
from .motion import _load_npy_object, _person_params

__all__ = ["read_annots", "zju_mask_labels", "CIHP_LABELS", "CIHP_GARMENT_LABELS", "zju_frame_number",
           "read_zju_params", "zju_mask_paths", "safe_camera_names", "MASK_KINDS"]

MASK_KINDS = ("mask", "mask_cihp")
"""The two mask folders of a ZJU-MoCap capture (see the module doc)."""

CIHP_LABELS = ("background", "hat", "hair", "glove", "sunglasses", "upper_clothes", "dress", "coat", "socks",
               "pants", "torso_skin", "scarf", "skirt", "face", "left_arm", "right_arm", "left_leg", "right_leg",
               "left_shoe", "right_shoe")
"""The 20 CIHP part labels of ``mask_cihp/`` (Gong et al., "Instance-level Human Parsing", ECCV 2018), by value."""

CIHP_GARMENT_LABELS = (6, 12)
"""CIHP values taken as the loose garment by default: dress (6) and skirt (12), the garments
AniDress simulates (``garment.KINDS``); everything else of the person (tight clothes, skin,
hair) is body, as in DESIGN.md's body = SMPL + tight clothing."""

MM_PER_M = 1000.0


def _field(path: Path, cams: dict, key: str, C: int, shape: tuple[int, ...]) -> np.ndarray:
    """(C, *shape) float64 from ``cams[key]`` (a list of C arrays); errors name file and field."""
    if key not in cams:
        raise ValueError(f"{path}: 'cams' has no '{key}' (keys: {sorted(cams)})")
    items = cams[key]
    if len(items) != C:
        raise ValueError(f"{path}: 'cams/{key}' has {len(items)} cameras, 'cams/K' has {C}")
    out = []
    for c, a in enumerate(items):
        try:
            a = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: 'cams/{key}[{c}]' is not numeric ({exc})") from exc
        if a.size != int(np.prod(shape)):
            raise ValueError(f"{path}: 'cams/{key}[{c}]' must hold {int(np.prod(shape))} numbers {shape}, "
                             f"got shape {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{path}: 'cams/{key}[{c}]' has NaN or inf values")
        out.append(a.reshape(shape))
    return np.stack(out)


def read_annots(path: str | os.PathLike, height: int | None = None, width: int | None = None,
                names: Sequence[str] | None = None, dtype: torch.dtype = torch.float64) -> dict[str, Any]:
    """Read a ZJU-MoCap ``annots.npy``.

    Returns dict(cameras :class:`Cameras` (C cameras, T in metres: the file's
    millimetres / 1000), ims list (T frames) of lists (C) of image paths relative to the
    file's folder (str, as stored)).

    Camera names: the folder of each camera's image in the first frame (``Camera_B1``,
    ``Camera (1)``), or ``names`` when given (C strings). The image size is not in the
    file: ``height`` / ``width`` when given, else the size of the first frame's image of
    the first camera (ZJU-MoCap: 1024 x 1024), which must then exist.

    Read with pickle enabled (restricted to arrays and containers): see the module doc.
    Errors name the file and the field (``cams/T[2]``, ``ims[5]``).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such file")
    obj = _load_npy_object(p)
    if not isinstance(obj, dict):
        raise ValueError(f"{p}: expected a pickled dict with 'cams' and 'ims', got {type(obj).__name__}")
    for key in ("cams", "ims"):
        if key not in obj:
            raise ValueError(f"{p}: missing key '{key}' (found {sorted(obj)})")
    cams = obj["cams"]
    if not isinstance(cams, dict) or "K" not in cams:
        raise ValueError(f"{p}: 'cams' must be a dict of per-camera lists K, D, R, T")
    C = len(cams["K"])
    if C == 0:
        raise ValueError(f"{p}: 'cams/K' lists no camera")
    K = _field(p, cams, "K", C, (3, 3))
    D = _field(p, cams, "D", C, (5,))
    R = _field(p, cams, "R", C, (3, 3))
    T = _field(p, cams, "T", C, (3,)) / MM_PER_M
    # 1. image lists: every frame lists one image per camera
    ims = []
    for t, entry in enumerate(obj["ims"]):
        lst = entry.get("ims") if isinstance(entry, dict) else None
        if lst is None:
            raise ValueError(f"{p}: 'ims[{t}]' must be a dict with an 'ims' list, got {type(entry).__name__}")
        lst = [str(x) for x in np.asarray(lst).reshape(-1)]
        if len(lst) != C:
            raise ValueError(f"{p}: 'ims[{t}]' lists {len(lst)} images for {C} cameras")
        ims.append(lst)
    if not ims:
        raise ValueError(f"{p}: 'ims' lists no frame")
    # 2. names
    if names is None:
        names = [os.path.dirname(x).replace("\\", "/").split("/")[-1] or f"{c:02d}" for c, x in enumerate(ims[0])]
        if len(set(names)) != C:
            names = [f"{c:02d}" for c in range(C)]
    names = list(names)
    if len(names) != C or not all(isinstance(n, str) for n in names):
        raise ValueError(f"read_annots: names must be {C} strings for the cameras of {p}, got {names!r}")
    # 3. image size
    if height is None or width is None:
        first = p.parent / ims[0][0]
        import cv2

        img = cv2.imread(str(first), cv2.IMREAD_UNCHANGED) if first.is_file() else None
        if img is None:
            raise ValueError(f"{p}: no image size in the file and {first} is not a readable image: "
                             "pass height and width")
        height, width = img.shape[:2]
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    return {"cameras": Cameras(names, t(K), t(D), t(R), t(T), int(height), int(width)), "ims": ims}


def zju_mask_labels(mask: np.ndarray | None = None, cihp: np.ndarray | None = None,
                    garment_labels: Sequence[int] = CIHP_GARMENT_LABELS) -> np.ndarray:
    """Pipeline labels (H, W) uint8 from ZJU-MoCap masks: 0 background, 1 body, 2 garment.

    mask: (H, W) a ``mask/`` image (0 background, any non-zero value person; the files
    hold 0/1 or 0/255). cihp: (H, W) a ``mask_cihp/`` image (CIHP part labels 0..19, see
    :data:`CIHP_LABELS`). The person is the union of the two (as neuralbody reads them);
    person pixels whose CIHP label is in ``garment_labels`` are garment (2), the others
    body (1). Without ``cihp`` there is no garment information: every person pixel is
    body. Colour-saved masks (H, W, 3) use their first channel.
    """
    if mask is None and cihp is None:
        raise ValueError("zju_mask_labels: give mask (mask/) or cihp (mask_cihp/) or both")
    arrays = {}
    for key, a in (("mask", mask), ("cihp", cihp)):
        if a is None:
            continue
        a = np.asarray(a)
        if a.ndim == 3:
            a = a[..., 0]
        if a.ndim != 2:
            raise ValueError(f"zju_mask_labels: '{key}' must be (H, W), got {a.shape}")
        arrays[key] = a
    if len({a.shape for a in arrays.values()}) != 1:
        raise ValueError(f"zju_mask_labels: mask {arrays['mask'].shape} and cihp {arrays['cihp'].shape} differ")
    person = np.zeros(next(iter(arrays.values())).shape, dtype=bool)
    for a in arrays.values():
        person |= a != 0
    labels = np.where(person, LABEL_BODY, LABEL_BACKGROUND).astype(np.uint8)
    if "cihp" in arrays:
        c = arrays["cihp"]
        if c.min() < 0 or c.max() >= len(CIHP_LABELS):
            raise ValueError(f"zju_mask_labels: cihp values must be CIHP labels 0..{len(CIHP_LABELS) - 1}, "
                             f"got {int(c.min())}..{int(c.max())}")
        labels[np.isin(c, np.asarray(list(garment_labels))) & person] = LABEL_GARMENT
    return labels


def zju_frame_number(image: str) -> int:
    """The frame number ``i`` of a ZJU-MoCap image path (its ``params/<i>.npy``), neuralbody's rule.

    ``Camera_B1/000123.jpg`` -> 123 (the file name); CoreView_313 / 315's
    ``Camera (1)/CoreView_313_Camera_(1)_0001_2019-08-23_16-08-50.592.jpg`` -> 1 (the fifth
    ``_``-separated field of the name). Any other name raises ValueError naming it.
    """
    name = os.path.basename(str(image).replace("\\", "/"))
    stem = os.path.splitext(name)[0]
    if stem.isdigit():
        return int(stem)
    parts = name.split("_")
    if len(parts) > 4 and parts[4].isdigit():
        return int(parts[4])
    raise ValueError(f"{image!r}: no frame number in the image name (expected <number>.jpg, or CoreView_313's "
                     "<...>_Camera_(<c>)_<number>_<time>.jpg)")


def read_zju_params(directory: str | os.PathLike, numbers: Sequence[int] | None = None) -> dict[str, Any]:
    """Body parameters from ``<directory>/<i>.npy`` (ZJU-MoCap's ``params/`` or ``new_params/``).

    ``numbers``: the frame numbers i to read, in that order; None reads every ``<i>.npy`` in
    numeric order. Returns dict(poses (T, 72), Rh (T, 3), Th (T, 3) metres, shapes (T, S))
    float64 and ``frames`` (list[int], the numbers read). Each file is a pickled dict (read
    through the restricted unpickler) with ``poses``, ``Rh``, ``Th`` and optionally ``shapes``
    (default 10 zeros); ``poses`` of any EasyMocap layout (72, 69, 63, ...:
    :mod:`anidress_core.io.motion`). A missing file, a missing key or a wrong size raises
    ValueError naming the file and the field.
    """
    d = Path(directory)
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: body parameter folder not found")
    if numbers is None:
        numbers = sorted(int(f.stem) for f in d.iterdir() if f.suffix == ".npy" and re.fullmatch(r"\d+", f.stem))
        if not numbers:
            raise ValueError(f"{d}: no <i>.npy parameter files")
    recs = []
    for i in numbers:
        f = d / f"{int(i)}.npy"
        if not f.is_file():
            raise ValueError(f"{f}: missing: no body parameters for frame number {int(i)}")
        obj = _load_npy_object(f)
        if not isinstance(obj, dict):
            raise ValueError(f"{f}: expected a pickled dict with poses, Rh, Th, shapes; got {type(obj).__name__}")
        recs.append(_person_params(f, obj))
    if not recs:
        raise ValueError(f"{d}: no frame numbers to read")
    sizes = {r["shapes"].size for r in recs}
    if len(sizes) != 1:
        raise ValueError(f"{d}: 'shapes' sizes differ between frames: {sorted(sizes)}")
    out: dict[str, Any] = {k: np.stack([r[k] for r in recs]) for k in ("poses", "Rh", "Th", "shapes")}
    out["frames"] = [int(i) for i in numbers]
    return out


def zju_mask_paths(capture: str | os.PathLike, image: str) -> dict[str, Path]:
    """``{kind: <capture>/<kind>/<image without extension>.png}`` for ``kind`` in :data:`MASK_KINDS`
    (the files may not exist)."""
    stem = os.path.splitext(str(image).replace("\\", "/"))[0]
    return {kind: Path(capture) / kind / f"{stem}.png" for kind in MASK_KINDS}


_UNSAFE = re.compile(r"[^A-Za-z0-9_-]+")


def safe_camera_names(names: Sequence[str]) -> list[str]:
    """Camera names an EasyMocap ``intri.yml`` holds without quoting trouble (letters, digits, ``_``, ``-``).

    Each run of other characters becomes one ``_``, leading and trailing ``_`` go
    (``Camera (1)`` -> ``Camera_1``, ``Camera_B1`` unchanged, ``01`` unchanged: written
    quoted). When that leaves an empty name, ``none``, or two equal names, every camera is
    named by its 1-based index instead (``01``, ``02``, ...), so the names stay distinct.
    """
    out = [_UNSAFE.sub("_", str(n)).strip("_") for n in names]
    if any(not n or n == "none" for n in out) or len(set(out)) != len(out):
        width = max(2, len(str(len(out))))
        out = [f"{c + 1:0{width}d}" for c in range(len(out))]
    return out
