"""Cue files written by external tools: SCHP part masks, normal maps, optical flow.

Readers check what they can and raise :class:`~anidress_core.io.files.ArtifactError`
``"<path>: <problem>"``; the writers produce files the tools' own readers accept (used for the
test samples, ``tests/data/cue_files/make_samples.py``, and by the synthetic exporter). Pure
numpy; PIL (palette PNGs; installed with scikit-image) and OpenCV read and write images. Shapes:
H, W image size (rows, columns); h, w a crop's size. Every writer is atomic
(:func:`~anidress_core.io.files.atomic_path`).

Masks: SCHP (Li et al., "Self-Correction for Human Parsing", TPAMI 2020)
-------------------------------------------------------------------------
* ``GoGoDuck912/Self-Correction-Human-Parsing`` ``simple_extractor.py`` writes one PNG per input
  image, ``<image stem>.png``: ``Image.fromarray(argmax.astype(uint8))``, ``putpalette(
  get_palette(num_classes))``, ``save``. The pixel values are **palette indices**, the label's
  position in ``dataset_settings[<set>]['label']`` (:data:`SCHP_LABEL_SETS`); the palette only
  colours them (:func:`schp_palette`). PIL's ``np.array(Image.open(p))`` gives the indices; OpenCV
  gives the colours (:func:`read_label_indices` maps SCHP colours back, for files re-saved as RGB).
* CIHP (20 labels) comes from SCHP's multi-person extension (``mhp_extension``, models
  ``exp_schp_multi_cihp_{global,local}.pth``); ``simple_extractor``'s ``dataset_settings`` has no
  CIHP entry, the list here is the CIHP dataset's own order (Gong et al., ECCV 2018; also
  :data:`anidress_core.io.zju.CIHP_LABELS`). It differs from LIP at 10 only (Torso-skin for Jumpsuits).
* EasyMocap (``zju3dv/EasyMocap``) runs the multi-person pipeline of its SCHP fork
  (``extract_multi.py`` in ``xk-huang/Self-Correction-Human-Parsing``, run from
  ``EasyMocap/3rdparty/Self-Correction-Human-Parsing``; fusion by ``mhp_extension/logits_fusion.py``,
  ``result_saving``, e.g. ``chingswy/Self-Correction-Human-Parsing``) and copies into the sequence
  (the fork's current ``extract_multi.py`` copies ``mask-schp`` only; earlier versions all three):

  - ``mask-schp/<cam>/<frame:06d>_<i>.png``: **one binary silhouette per person**,
    ``cv2.imwrite((person_id == i + 1) * 255)``, 8-bit grey 0 / 255, i = 0, 1, ... (the
    detector's order); no part labels;
  - ``mask-schp-parsing/<cam>/<frame:06d>.png``: CIHP part labels of everyone, mode 'P' with
    ``get_palette(256)``;
  - ``mask-schp-instance/<cam>/<frame:06d>_vis.png``: person ids, mode 'P'.

  (``<frame:06d>`` is the image's stem; EasyMocap names images ``%06d.jpg``.) EasyMocap's
  ``scripts/preprocess/copy_dataset.py`` looks under ``mask-schp/<cam>`` for
  ``<frame:06d>.png``, then ``<frame:06d>_*.png``. :func:`schp_mask_path` resolves both layouts;
  :func:`read_schp_labels` turns a person's silhouette into body / garment labels with the
  sibling ``mask-schp-parsing`` file.

Normals
-------
* Sapiens (``facebookresearch/sapiens`` ``lite/demo/vis_normal.py``, ``img_save_and_viz``): the
  model output is resized to the input image's size (``F.interpolate(..., size=image.shape[:2],
  mode="bilinear")``), transposed to (H, W, 3) float32, divided by ``(|n| + 1e-5)`` and
  ``np.save``'d as ``<output_root>/<image stem>.npy``, unmasked (the ``--seg_dir`` mask only
  blacks out the visualisation, which sets background normals to -1, encodes
  ``((n + 1) / 2 * 255).astype(uint8)`` and writes ``[image | normals]`` side by side with
  ``cv2.imwrite``). Channel order x, y, z; the code states no camera frame beyond x along image
  columns (``NormalRandomFlip`` negates channel 0 on a horizontal flip).
* (n+1)/2 images: RGB = ((x, y, z) + 1) / 2, 8 or 16-bit PNG (or EXR). Background is black
  (0, 0, 0; Sapiens' visualisation) or the zero vector encoded as mid grey (127 / 128; ICON and
  ECON multiply the normal by the foreground mask before encoding). Both decode to the zero
  vector: :func:`read_normal_image` zeroes black pixels and decoded lengths outside
  :data:`NORMAL_LENGTH_RANGE` (unit normals decode to length 1 +- 0.014 at 8 bits).
* ICON / ECON (``YuliangXiu/ICON``, ``YuliangXiu/ECON``) estimate normals in a square crop of
  :data:`ICON_CROP_SIZE` = 512 pixels around the person. ICON's ``apps/infer.py`` encodes
  ``((normal_F + 1) * 255 / 2).astype(uint8)`` (truncation) and writes it only blended into
  ``png/<name>_overlap.png``; ECON's ``apps/infer.py`` writes ``png/<name>_crop.png`` with
  ``torchvision.utils.save_image`` (rounding): ``[crop RGB | (normal_F + 1) / 2 | (normal_B + 1) / 2]``,
  three 512-wide panels (:func:`read_econ_crop`). The crop's place in the image lives only in
  memory (``data["uncrop_param"]``: ``M_square`` pads to a square, ``M_crop`` crops the
  person's box with a 0.9 margin, ``lib/common/imutils.py``), so whoever runs them records it
  in ``crops.json`` (below).

Crop boxes: ``crops.json`` beside the crop images (``<folder>/crops.json``, the images at
``<folder>/<cam>/<frame:06d>.png``)::

    {"<cam>/<frame:06d>": [x0, y0, x1, y1], ...}

in full-image pixel coordinates with pixel centres at integers: pixel (row r, column c) is
centred at (x, y) = (c, r) and the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5]. The box is the
crop's outer edge: an (h, w) crop's pixel (i, j) covers x in [x0 + j sx, x0 + (j + 1) sx) with
sx = (x1 - x0) / w (y likewise with sy = (y1 - y0) / h), centred at x0 + (j + 0.5) sx. A box
may extend past the image (ICON / ECON pad the square with zeros) and need not be square.
From ECON's ``uncrop_param``: map the crop's corners (-0.5, -0.5) and (511.5, 511.5) through the
inverse of ``M_crop @ M_square``. :func:`paste_crop` fills an image pixel whose centre lies in
[x0, x1) x [y0, y1) by bilinear sampling at crop coordinates ((c - x0) / sx - 0.5,
(r - y0) / sy - 0.5) (crop pixel centres at integers, clamped to the edge pixels: the
``align_corners=False`` convention of ECON's ``blend_rgb_norm``), renormalised; the zero vector
outside the box and where fewer than half of the bilinear weight falls on crop pixels with a normal.

Optical flow (RAFT: ``princeton-vl/RAFT``, ``core/utils/frame_utils.py``)
------------------------------------------------------------------------
* ``.flo`` (Middlebury; ``writeFlow``): float32 202021.25 (bytes ``PIEH``), int32 width, int32
  height, then float32 (u, v) interleaved row by row, all little-endian (RAFT writes native
  order, x86). u is the displacement along x (columns), v along y (rows), in pixels. Middlebury
  marks unknown flow with |u| or |v| > 1e9 (1e10 written).
* KITTI PNG (``writeFlowKITTI`` / ``readFlowKITTI``): 16-bit, 3 channels R = 64 u + 2^15,
  G = 64 v + 2^15, B = valid (0 / 1), written through OpenCV (so stored BGR-reversed in memory:
  ``cv2.imwrite(p, uv[..., ::-1])``); values are truncated to integers (1/64 pixel steps).
  RAFT writes valid = 1 everywhere; KITTI's ground truth has 0 (and u = v = 0) where unknown.
* RAFT pads images to multiples of 8 (``core/utils/utils.py`` ``InputPadder``: 'sintel' mode
  centred, ``[pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2]``; 'kitti' mode
  rows at the bottom only); its scripts ``padder.unpad`` the flow before writing.
  :func:`check_flow` recognises a flow saved padded.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .files import ArtifactError, _require, atomic_path, read_exr, write_json

__all__ = [
    "SCHP_LABEL_SETS",
    "SCHP_GARMENT_LABELS",
    "FLOW_SUFFIXES",
    "ICON_CROP_SIZE",
    "NORMAL_LENGTH_RANGE",
    "FLO_MAGIC",
    "schp_palette",
    "read_label_indices",
    "write_schp_png",
    "schp_to_labels",
    "schp_mask_path",
    "read_schp_indices",
    "read_schp_labels",
    "read_sapiens_normals",
    "write_sapiens_normals",
    "read_normal_image",
    "write_normal_image",
    "read_econ_crop",
    "crop_key",
    "read_crops",
    "write_crops",
    "paste_crop",
    "read_flo",
    "write_flo",
    "read_kitti_flow",
    "write_kitti_flow",
    "read_flow",
    "raft_padded_shape",
    "check_flow",
]

# --------------------------------------------------------------------------- constants

SCHP_LABEL_SETS: dict[str, tuple[str, ...]] = {
    "lip": ("Background", "Hat", "Hair", "Glove", "Sunglasses", "Upper-clothes", "Dress", "Coat",
            "Socks", "Pants", "Jumpsuits", "Scarf", "Skirt", "Face", "Left-arm", "Right-arm",
            "Left-leg", "Right-leg", "Left-shoe", "Right-shoe"),
    "atr": ("Background", "Hat", "Hair", "Sunglasses", "Upper-clothes", "Skirt", "Pants", "Dress", "Belt",
            "Left-shoe", "Right-shoe", "Face", "Left-leg", "Right-leg", "Left-arm", "Right-arm", "Bag", "Scarf"),
    "cihp": ("Background", "Hat", "Hair", "Glove", "Sunglasses", "Upper-clothes", "Dress", "Coat",
             "Socks", "Pants", "Torso-skin", "Scarf", "Skirt", "Face", "Left-arm", "Right-arm",
             "Left-leg", "Right-leg", "Left-shoe", "Right-shoe"),
}
"""SCHP's label names by index: lip (20) and atr (18) as ``simple_extractor.py``'s
``dataset_settings`` lists them; cihp (20) in the CIHP dataset's order (module docstring)."""

SCHP_GARMENT_LABELS: dict[str, tuple[int, ...]] = {
    name: tuple(labels.index(g) for g in ("Dress", "Skirt")) for name, labels in SCHP_LABEL_SETS.items()
}
"""The labels taken as the loose garment by default: Dress and Skirt (lip (6, 12), atr (7, 5),
cihp (6, 12)), the garments AniDress simulates; every other non-background label is body."""

FLOW_SUFFIXES = {".flo": "raft", ".png": "kitti", ".exr": "exr"}
"""Flow file suffix -> format (the pipeline's EXR holds channels X, Y, valid)."""

ICON_CROP_SIZE = 512
"""Side of ICON's / ECON's square normal crops, pixels."""

NORMAL_LENGTH_RANGE = (0.5, 1.5)
"""Decoded (n+1)/2 vectors whose length falls outside this range are no normal (background)."""

FLO_MAGIC = 202021.25
"""The Middlebury .flo tag (float32; the bytes ``PIEH``)."""

_UNKNOWN_FLOW_THRESH = 1e9  # Middlebury flowIO: |u| or |v| above this is unknown flow
_UNKNOWN_FLOW = 1e10  # what Middlebury's tools write there
_BACKGROUND, _BODY, _GARMENT = 0, 1, 2  # the pipeline's mask labels (anidress_core.synth.LABEL_*)


# --------------------------------------------------------------------------- SCHP masks


def schp_palette(n: int = 256) -> np.ndarray:
    """SCHP's ``get_palette(n)`` as (n, 3) uint8 RGB, 1 <= n <= 256.

    Colour j spreads the bits of j over the channels, most significant bit first: bit 3i of j
    sets bit 7 - i of red, bit 3i + 1 of green, bit 3i + 2 of blue (the PASCAL VOC colour map).
    """
    if not 1 <= n <= 256:
        raise ValueError(f"a PNG palette holds 1..256 colours, got {n}")
    j = np.arange(n)
    pal = np.zeros((n, 3), np.int64)
    for i in range(3):  # 3 groups of 3 bits cover j < 512
        for c in range(3):
            pal[:, c] |= ((j >> (3 * i + c)) & 1) << (7 - i)
    return pal.astype(np.uint8)


def _open_pil(path: Path):
    from PIL import Image

    _require(path)
    try:
        img = Image.open(path)
        img.load()
    except Exception as e:  # PIL raises several kinds for corrupt files
        raise ArtifactError(f"{path}: unreadable or corrupt image ({e})") from e
    return img


def read_label_indices(path: str | os.PathLike) -> np.ndarray:
    """A label PNG as (H, W) uint8 label values.

    Mode 'P' (SCHP): the palette indices, whatever the palette; 'L' / '1' / 16-bit grey: the
    values (at most 255); RGB / RGBA (a palette PNG re-saved as colours): each colour mapped back
    to its index in :func:`schp_palette`, an error if a colour is not SCHP's (the indices are lost).
    """
    path = Path(path)
    img = _open_pil(path)
    mode = img.mode
    if mode == "P":
        return np.array(img, dtype=np.uint8)
    if mode in ("L", "1", "LA", "I;16", "I;16B", "I;16L", "I"):
        arr = np.array(img.getchannel(0) if mode == "LA" else img)
        if arr.size and int(arr.max()) > 255:
            raise ArtifactError(f"{path}: label values up to {int(arr.max())}; labels must lie in 0..255")
        return arr.astype(np.uint8)
    if mode in ("RGB", "RGBA"):
        rgb = np.array(img.convert("RGB"), dtype=np.uint8)
        return _colours_to_indices(rgb, path)
    raise ArtifactError(f"{path}: image mode {mode!r} holds no label values (expected a palette 'P' PNG as "
                        f"SCHP writes, or 8-bit grey)")


def _colours_to_indices(rgb: np.ndarray, path: Path) -> np.ndarray:
    """(H, W, 3) uint8 SCHP colours -> (H, W) uint8 indices, or the error naming a stray colour."""
    pal = schp_palette(256).astype(np.int64)
    pal_code = (pal[:, 0] << 16) | (pal[:, 1] << 8) | pal[:, 2]
    order = np.argsort(pal_code)
    code = (rgb[..., 0].astype(np.int64) << 16) | (rgb[..., 1].astype(np.int64) << 8) | rgb[..., 2]
    pos = np.clip(np.searchsorted(pal_code[order], code), 0, 255)
    found = pal_code[order][pos] == code
    if not found.all():
        r, c = np.argwhere(~found)[0]
        grey = bool((rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all())
        hint = (" (a grey image saved as colour: save label values as a single-channel PNG)" if grey else
                ": the palette indices were lost (the mask was re-saved as colours, and not with SCHP's); "
                "use SCHP's original palette PNG (mode 'P')")
        raise ArtifactError(f"{path}: RGB image, colour {tuple(int(v) for v in rgb[r, c])} at row {r}, "
                            f"column {c} is not in SCHP's palette{hint}")
    return order[pos].astype(np.uint8)


def write_schp_png(path: str | os.PathLike, indices: np.ndarray, num_classes: int | None = None) -> None:
    """Write (H, W) label indices as SCHP does: PIL mode 'P' with ``get_palette(num_classes)``.

    num_classes: palette length (``simple_extractor.py`` passes the label set's size, the
    multi-person ``logits_fusion.py`` 256); None: 256. Indices must lie below it.
    """
    from PIL import Image

    idx = np.asarray(indices)
    if idx.ndim != 2:
        raise ValueError(f"{path}: label indices are (H, W), got {idx.shape}")
    n = 256 if num_classes is None else int(num_classes)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"{path}: label indices must lie in 0..{n - 1}, got {idx.min()}..{idx.max()}")
    img = Image.fromarray(np.ascontiguousarray(idx, dtype=np.uint8))  # mode 'L'
    img.putpalette(schp_palette(n).reshape(-1).tolist())  # 'L' -> 'P', the values become the indices
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG")


def schp_to_labels(indices: np.ndarray, label_set: str, garment_labels: Sequence[int] | None = None,
                   path: str | os.PathLike | None = None) -> np.ndarray:
    """SCHP label indices (H, W) -> the pipeline's labels (H, W) uint8: 0 background, 1 body, 2 garment.

    garment_labels: indices taken as the garment (default :data:`SCHP_GARMENT_LABELS`
    [label_set]); index 0 is background, every other index body. path: the file the indices
    came from, named in the error raised when a value lies outside the label set.
    """
    if label_set not in SCHP_LABEL_SETS:
        raise ValueError(f"unknown SCHP label set {label_set!r} (known: {', '.join(SCHP_LABEL_SETS)})")
    n = len(SCHP_LABEL_SETS[label_set])
    garment = SCHP_GARMENT_LABELS[label_set] if garment_labels is None else tuple(int(g) for g in garment_labels)
    bad = [g for g in garment if not 0 < g < n]
    if bad:
        raise ValueError(f"garment labels {bad} are not labels of SCHP's {label_set} set (1..{n - 1})")
    idx = np.asarray(indices)
    if idx.ndim != 2:
        raise ValueError(f"{path}: label indices are (H, W), got {idx.shape}")
    top = int(idx.max()) if idx.size else 0
    if top >= n or (idx.size and int(idx.min()) < 0):
        vals = np.unique(idx)
        hint = ""
        if set(vals.tolist()) <= {0, 255}:
            hint = (" (values 0 / 255: a binary silhouette, e.g. EasyMocap's mask-schp/<cam>/<frame>_<i>.png, "
                    "whose part labels are in mask-schp-parsing/; see read_schp_labels)")
        elif label_set == "atr" and top < 20:
            hint = " (20 labels: LIP or CIHP output? set the label set to lip or cihp)"
        raise ArtifactError(f"{path}: label values {vals[vals >= n].tolist()[:5]} lie outside SCHP's "
                            f"{label_set} set (0..{n - 1}){hint}")
    out = np.full(idx.shape, _BODY, np.uint8)
    out[idx == 0] = _BACKGROUND
    out[np.isin(idx, garment)] = _GARMENT
    return out


def _frame_entries(d: Path, frame: int) -> tuple[list[str], dict[int, list[str]]]:
    """Names in ``d`` of frame ``frame``: plain ``<frame>.png`` and per-person ``<frame>_<i>.png``,
    any zero padding."""
    want = str(int(frame)).lstrip("0")
    plain: list[str] = []
    persons: dict[int, list[str]] = {}
    for name in os.listdir(d):
        if name[-4:].lower() != ".png":
            continue
        head, sep, tail = name[:-4].partition("_")
        if not head.isdigit() or head.lstrip("0") != want:
            continue
        if not sep:
            plain.append(name)
        elif tail.isdigit():
            persons.setdefault(int(tail), []).append(name)
    return sorted(plain), persons


def schp_mask_path(folder: str | os.PathLike, cam: str, frame: int, person: int | None = None) -> Path:
    """The SCHP mask file of camera ``cam`` at frame ``frame`` under ``folder``.

    Layouts: ``<folder>/<cam>/<frame>.png`` (SCHP run on a folder of images) or EasyMocap's
    ``<folder>/<cam>/<frame>_<i>.png``, one per person i (module docstring); the frame number
    with any zero padding (``1.png``, ``000001.png``). person: whose file in the per-person
    layout (None: the only person; an error listing them when there are several); ignored in
    the plain layout, whose one file holds everyone.
    """
    d = Path(folder) / str(cam)
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: folder of SCHP masks for camera {cam!r} not found")
    plain, persons = _frame_entries(d, frame)
    if len(plain) > 1:
        raise ArtifactError(f"{d}: several mask files for frame {frame}: {plain}; keep one")
    if plain and persons:
        raise ArtifactError(f"{d}: frame {frame} has a mask {plain[0]} and per-person masks "
                            f"{sorted(n for v in persons.values() for n in v)}; keep one layout")
    if plain:
        return d / plain[0]
    if not persons:
        raise FileNotFoundError(f"{d}: no SCHP mask for frame {frame} (looked for {int(frame):06d}.png or "
                                f"{int(frame):06d}_<person>.png, any zero padding)")
    dup = {i: v for i, v in persons.items() if len(v) > 1}
    if dup:
        raise ArtifactError(f"{d}: several files for frame {frame}, person {min(dup)}: {dup[min(dup)]}; keep one")
    ids = sorted(persons)
    if person is None:
        if len(ids) > 1:
            raise ArtifactError(f"{d}: frame {frame} has masks of {len(ids)} persons {ids} "
                                f"({', '.join(persons[i][0] for i in ids)}); choose one with the person setting "
                                f"(scene.yaml cues/masks/person)")
        return d / persons[ids[0]][0]
    if int(person) not in persons:
        raise FileNotFoundError(f"{d}: frame {frame} has no mask of person {person} (persons present: {ids})")
    return d / persons[int(person)][0]


def read_schp_indices(folder: str | os.PathLike, cam: str, frame: int,
                      person: int | None = None) -> tuple[np.ndarray, Path]:
    """SCHP label indices (H, W) uint8 of one camera and frame, and the file they come from.

    Plain layout: the file's indices. EasyMocap's per-person layout: the person's 0 / 255 silhouette
    selects that person's pixels of the part labels in the sibling folder ``<folder>-parsing``
    (``mask-schp-parsing``, CIHP labels), 0 elsewhere; a per-person file holding label values
    (not 0 / 255) is used as indices directly.
    """
    path = schp_mask_path(folder, cam, frame, person)
    idx = read_label_indices(path)
    if "_" not in path.stem or not set(np.unique(idx).tolist()) <= {0, 255}:
        return idx, path
    folder = Path(folder)
    parsing_dir = folder.with_name(folder.name + "-parsing")
    try:
        ppath = schp_mask_path(parsing_dir, cam, frame)
    except FileNotFoundError as e:
        raise ArtifactError(f"{path}: a per-person silhouette (0 / 255) without part labels; EasyMocap keeps them "
                            f"in {parsing_dir}/<cam>/<frame>.png, which is missing ({e})") from e
    parsing = read_label_indices(ppath)
    if parsing.shape != idx.shape:
        raise ArtifactError(f"{ppath}: {parsing.shape[0]}x{parsing.shape[1]} part labels for the "
                            f"{idx.shape[0]}x{idx.shape[1]} silhouette {path}")
    return np.where(idx > 0, parsing, 0).astype(np.uint8), ppath


def read_schp_labels(folder: str | os.PathLike, cam: str, frame: int, label_set: str,
                     garment_labels: Sequence[int] | None = None, person: int | None = None) -> np.ndarray:
    """The pipeline's labels (H, W) uint8 (0 background, 1 body, 2 garment) from SCHP masks in either layout
    (:func:`read_schp_indices`, then :func:`schp_to_labels`)."""
    idx, path = read_schp_indices(folder, cam, frame, person)
    return schp_to_labels(idx, label_set, garment_labels, path)


# --------------------------------------------------------------------------- normals


def _unit(n: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(..., 3) vectors normalised where ``valid`` (and of non-zero length), the zero vector elsewhere."""
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = valid[..., None] & (length > 1e-12)
    return np.where(ok, n / np.where(ok, length, 1.0), 0.0).astype(np.float32)


def read_sapiens_normals(path: str | os.PathLike) -> np.ndarray:
    """A Sapiens normal map ``.npy`` (as ``lite/demo/vis_normal.py`` saves it) -> (H, W, 3) float32.

    Checks the layout (H, W, 3) float; non-finite values are an error. Returns unit vectors
    (the demo stores n / (|n| + 1e-5)); zero vectors stay zero.
    """
    path = Path(path)
    _require(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:
        raise ArtifactError(f"{path}: not a readable .npy array ({e})") from e
    if arr.ndim != 3 or arr.shape[-1] != 3:
        hint = (" (channel-first? Sapiens' demo saves (H, W, 3), transposed from the model's (3, H, W))"
                if arr.ndim == 3 and arr.shape[0] == 3 else "")
        raise ArtifactError(f"{path}: a Sapiens normal map is (H, W, 3), got {arr.shape}{hint}")
    if arr.dtype.kind != "f":
        raise ArtifactError(f"{path}: normals must be floating point, got {arr.dtype}")
    arr = arr.astype(np.float32)
    bad = ~np.isfinite(arr).all(axis=-1)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ArtifactError(f"{path}: {int(bad.sum())} pixels with non-finite normals (first at row {r}, column {c})")
    return _unit(arr, np.ones(arr.shape[:2], bool))


def write_sapiens_normals(path: str | os.PathLike, normals: np.ndarray) -> None:
    """``np.save`` normals (H, W, 3) as float32, the layout Sapiens' demo writes (values as given)."""
    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[-1] != 3:
        raise ValueError(f"{path}: normals are (H, W, 3), got {n.shape}")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.ascontiguousarray(n, dtype=np.float32))


def _decode_normals(v: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) encoded (n+1)/2 in [0, 1] -> unit normals (H, W, 3) float32, 0 on background."""
    black = (v <= 0.0).all(axis=-1)
    n = 2.0 * v.astype(np.float64) - 1.0
    length = np.linalg.norm(n, axis=-1)
    valid = ~black & (length >= NORMAL_LENGTH_RANGE[0]) & (length <= NORMAL_LENGTH_RANGE[1])
    if alpha is not None:
        valid &= alpha > 0
    return _unit(n, valid)


def read_normal_image(path: str | os.PathLike) -> np.ndarray:
    """A normal image holding (n+1)/2 -> (H, W, 3) float32 unit normals n = 2v - 1 (renormalised).

    PNG (8 or 16-bit; RGB = x, y, z, read through OpenCV and reordered from its BGR; an alpha
    channel of 0 marks background) or EXR (the first three channels, R, G, B). The zero vector
    where the pixel is black (0, 0, 0) or the decoded length lies outside
    :data:`NORMAL_LENGTH_RANGE` (the zero vector ICON / ECON encode as mid grey).
    """
    path = Path(path)
    _require(path)
    if path.suffix.lower() == ".exr":
        v = read_exr(path)
        if v.shape[-1] < 3:
            raise ArtifactError(f"{path}: a normal image needs 3 channels, the EXR has {v.shape[-1]}")
        v3 = v[..., :3]
        if not np.isfinite(v3).all():
            raise ArtifactError(f"{path}: non-finite values in the normal image")
        return _decode_normals(v3)
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ArtifactError(f"{path}: unreadable or corrupt image")
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise ArtifactError(f"{path}: a normal image has 3 colour channels, got shape {img.shape}")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        raise ArtifactError(f"{path}: 8 or 16-bit PNG expected, got {img.dtype}")
    rgb = img[..., 2::-1].astype(np.float64) / scale  # BGR(A) -> RGB
    alpha = img[..., 3] if img.shape[-1] == 4 else None
    return _decode_normals(rgb, alpha)


def write_normal_image(path: str | os.PathLike, normals: np.ndarray, bits: int = 8) -> None:
    """Write normals (H, W, 3) as an (n+1)/2 RGB PNG of 8 or 16 bits (rounded); zero vectors black."""
    import cv2

    n = np.asarray(normals, np.float64)
    if n.ndim != 3 or n.shape[-1] != 3:
        raise ValueError(f"{path}: normals are (H, W, 3), got {n.shape}")
    if bits not in (8, 16):
        raise ValueError(f"{path}: bits must be 8 or 16, got {bits}")
    if not np.isfinite(n).all():
        raise ValueError(f"{path}: non-finite normals")
    top = 255 if bits == 8 else 65535
    q = np.floor(np.clip((n + 1.0) / 2.0, 0.0, 1.0) * top + 0.5)
    q[(n == 0).all(axis=-1)] = 0
    img = q.astype(np.uint8 if bits == 8 else np.uint16)[..., ::-1]  # RGB -> OpenCV's BGR
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"{path}: OpenCV could not write the image")


def read_econ_crop(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """ECON's ``png/<name>_crop.png`` ([crop RGB | front (n+1)/2 | back (n+1)/2], three square
    panels side by side) -> (front, back) normals, each (h, h, 3) float32 (h = 512 for ECON)."""
    path = Path(path)
    n = read_normal_image(path)
    h, w = n.shape[:2]
    if w != 3 * h:
        raise ArtifactError(f"{path}: ECON's crop image is three {h}x{h} panels side by side ({h}x{3 * h}), "
                            f"got {h}x{w}")
    return n[:, h:2 * h].copy(), n[:, 2 * h:].copy()


def crop_key(cam: str, frame: int) -> str:
    """The ``crops.json`` key of a camera and frame: ``"<cam>/<frame:06d>"``."""
    return f"{cam}/{int(frame):06d}"


def read_crops(path: str | os.PathLike) -> dict[str, tuple[float, float, float, float]]:
    """``crops.json`` -> ``{"<cam>/<frame:06d>": (x0, y0, x1, y1)}`` (module docstring: conventions).

    Frame numbers of any zero padding are accepted and re-keyed with six digits.
    """
    path = Path(path)
    _require(path)
    try:
        raw = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ArtifactError(f"{path}: invalid JSON ({e})") from e
    if not isinstance(raw, dict):
        raise ArtifactError(f"{path}: crops.json is an object {{\"<cam>/<frame>\": [x0, y0, x1, y1]}}, "
                            f"got {type(raw).__name__}")
    out: dict[str, tuple[float, float, float, float]] = {}
    for key, box in raw.items():
        cam, sep, frame = str(key).rpartition("/")
        if not sep or not cam or not frame.isdigit():
            raise ArtifactError(f"{path}: key {key!r} is not \"<cam>/<frame>\" (e.g. \"01/000000\")")
        if (not isinstance(box, list) or len(box) != 4
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in box)):
            raise ArtifactError(f"{path}: {key}: a box is [x0, y0, x1, y1] (4 numbers), got {box!r}")
        x0, y0, x1, y1 = (float(v) for v in box)
        if not all(math.isfinite(v) for v in (x0, y0, x1, y1)) or x1 <= x0 or y1 <= y0:
            raise ArtifactError(f"{path}: {key}: box {box} needs finite x0 < x1 and y0 < y1")
        k = crop_key(cam, int(frame))
        if k in out:
            raise ArtifactError(f"{path}: two boxes for {k} (keys with different zero padding)")
        out[k] = (x0, y0, x1, y1)
    return out


def write_crops(path: str | os.PathLike, crops: Mapping[str, Sequence[float]]) -> None:
    """Write ``crops.json`` from ``{"<cam>/<frame:06d>": (x0, y0, x1, y1)}`` (see :func:`crop_key`)."""
    out = {}
    for key, box in crops.items():
        b = [float(v) for v in box]
        if len(b) != 4 or b[2] <= b[0] or b[3] <= b[1]:
            raise ValueError(f"{path}: {key}: a box is (x0, y0, x1, y1) with x0 < x1, y0 < y1, got {box!r}")
        out[str(key)] = b
    write_json(path, dict(sorted(out.items())))


def _bilinear_axis(coord: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crop coordinates (pixel centres at integers) -> (lower index, upper index, weight of upper),
    clamped to [0, size - 1]."""
    c = np.clip(coord, 0.0, size - 1.0)
    i0 = np.floor(c).astype(np.int64)
    i1 = np.minimum(i0 + 1, size - 1)
    return i0, i1, c - i0


def paste_crop(crop_normals: np.ndarray, box: Sequence[float], height: int, width: int) -> np.ndarray:
    """Place a crop's normals (h, w, 3) into a (height, width, 3) float32 image.

    box: (x0, y0, x1, y1), the crop's outer edges in image pixel coordinates (module
    docstring). Bilinear, renormalised; the zero vector outside the box and where the crop has
    no normal (zero vectors count as none: less than half the bilinear weight on crop pixels with
    a normal gives none).
    """
    crop = np.asarray(crop_normals, np.float64)
    if crop.ndim != 3 or crop.shape[-1] != 3 or crop.shape[0] < 1 or crop.shape[1] < 1:
        raise ValueError(f"crop normals are (h, w, 3), got {crop.shape}")
    x0, y0, x1, y1 = (float(v) for v in box)
    if not x1 > x0 or not y1 > y0:
        raise ValueError(f"box (x0, y0, x1, y1) needs x0 < x1 and y0 < y1, got {tuple(box)}")
    h, w = crop.shape[:2]
    out = np.zeros((height, width, 3), np.float32)
    # 1. the image pixels whose centres lie in [x0, x1) x [y0, y1)
    cols = np.arange(max(0, math.ceil(x0)), min(width, math.ceil(x1)))
    rows = np.arange(max(0, math.ceil(y0)), min(height, math.ceil(y1)))
    if cols.size == 0 or rows.size == 0:
        return out
    # 2. their crop coordinates: cx = (c - x0) / sx - 0.5 (crop pixel centres at integers)
    jx0, jx1, fx = _bilinear_axis((cols - x0) * (w / (x1 - x0)) - 0.5, w)
    iy0, iy1, fy = _bilinear_axis((rows - y0) * (h / (y1 - y0)) - 0.5, h)
    # 3. bilinear blend of the vectors and of "has a normal" (zero vectors have none)
    has = (np.linalg.norm(crop, axis=-1) > 1e-6).astype(np.float64)
    vals = np.concatenate([crop * has[..., None], has[..., None]], axis=-1)  # (h, w, 4)
    wx, wy = fx[None, :, None], fy[:, None, None]
    top = vals[np.ix_(iy0, jx0)] * (1 - wx) + vals[np.ix_(iy0, jx1)] * wx
    bot = vals[np.ix_(iy1, jx0)] * (1 - wx) + vals[np.ix_(iy1, jx1)] * wx
    blend = top * (1 - wy) + bot * wy
    # 4. renormalise where at least half the weight has a normal
    out[np.ix_(rows, cols)] = _unit(blend[..., :3], blend[..., 3] >= 0.5)
    return out


# --------------------------------------------------------------------------- optical flow


def read_flo(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """A Middlebury ``.flo`` (RAFT's ``writeFlow``) -> (flow (H, W, 2) float32, valid (H, W) bool).

    The magic number and the file size are checked; Middlebury's unknown-flow marker (|u| or
    |v| > 1e9) is invalid (its flow set to 0). Non-finite values stay valid: :func:`check_flow`
    rejects them.
    """
    path = Path(path)
    _require(path)
    data = path.read_bytes()
    if len(data) < 12:
        raise ArtifactError(f"{path}: {len(data)} bytes, too short for a .flo header (12 bytes)")
    magic = float(np.frombuffer(data[:4], "<f4")[0])
    if magic != FLO_MAGIC:
        raise ArtifactError(f"{path}: not a Middlebury .flo file (magic number {magic!r}, bytes {data[:4]!r}; "
                            f"expected {FLO_MAGIC} = b'PIEH')")
    w, h = (int(v) for v in np.frombuffer(data[4:12], "<i4"))
    if w <= 0 or h <= 0 or w * h > 1 << 28:
        raise ArtifactError(f"{path}: implausible .flo size {w}x{h} (width x height)")
    want = 12 + 8 * w * h
    if len(data) != want:
        raise ArtifactError(f"{path}: a {w}x{h} .flo file has {want} bytes, this one {len(data)} "
                            f"({'truncated' if len(data) < want else 'trailing bytes'})")
    flow = np.frombuffer(data[12:], "<f4").reshape(h, w, 2).astype(np.float32)
    with np.errstate(invalid="ignore"):
        unknown = (np.abs(flow) > _UNKNOWN_FLOW_THRESH).any(axis=-1)
    flow[unknown] = 0.0
    return flow, ~unknown


def write_flo(path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Write flow (H, W, 2) as a ``.flo`` byte-identical to RAFT's ``writeFlow``.

    valid: (H, W) bool, optional; invalid pixels get Middlebury's unknown marker (1e10, 1e10).
    """
    f = np.asarray(flow)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ValueError(f"{path}: flow is (H, W, 2), got {f.shape}")
    h, w = f.shape[:2]
    body = f.astype("<f4")
    if valid is not None:
        v = np.asarray(valid, bool)
        if v.shape != (h, w):
            raise ValueError(f"{path}: valid is (H, W) = {(h, w)}, got {v.shape}")
        body = body.copy()
        body[~v] = _UNKNOWN_FLOW
    header = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
    with atomic_path(path) as tmp:
        tmp.write_bytes(header + np.ascontiguousarray(body).tobytes())


def read_kitti_flow(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """A KITTI flow PNG (RAFT's ``writeFlowKITTI``, KITTI ground truth) -> (flow (H, W, 2) float32,
    valid (H, W) bool): flow = (value - 2^15) / 64, valid = third channel > 0 (flow 0 where invalid)."""
    import cv2

    path = Path(path)
    _require(path)
    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if img is None:
        raise ArtifactError(f"{path}: unreadable or corrupt image")
    if img.dtype != np.uint16:
        raise ArtifactError(f"{path}: a KITTI flow PNG is 16-bit, this one is {img.dtype} (an 8-bit image, "
                            f"e.g. a flow visualisation?)")
    rgb = img[..., ::-1].astype(np.float32)  # OpenCV's BGR -> (u, v, valid)
    valid = rgb[..., 2] > 0
    flow = (rgb[..., :2] - 32768.0) / 64.0
    flow[~valid] = 0.0
    return flow, valid


def write_kitti_flow(path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Write flow (H, W, 2) as a KITTI 16-bit PNG the way RAFT's ``writeFlowKITTI`` does
    (64 flow + 2^15, truncated; clamped to 0..65535, which RAFT does not); valid (H, W) bool,
    default all: invalid pixels are written (0, 0, 0) as in KITTI's ground truth."""
    import cv2

    f = np.asarray(flow)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ValueError(f"{path}: flow is (H, W, 2), got {f.shape}")
    v = np.ones(f.shape[:2], bool) if valid is None else np.asarray(valid, bool)
    if v.shape != f.shape[:2]:
        raise ValueError(f"{path}: valid is (H, W) = {f.shape[:2]}, got {v.shape}")
    if not np.isfinite(f[v]).all():
        raise ValueError(f"{path}: non-finite flow at valid pixels")
    uv = np.clip(np.where(v[..., None], f, 0) * 64.0 + 2.0 ** 15, 0, 65535)
    img = np.concatenate([uv, v[..., None]], axis=-1).astype(np.uint16)
    img[~v] = 0
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img[..., ::-1])):
            raise OSError(f"{path}: OpenCV could not write the image")


def read_flow(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Any flow file by suffix (:data:`FLOW_SUFFIXES`) -> (flow (H, W, 2) float32, valid (H, W) bool).

    ``.exr``: the pipeline's channels X, Y, valid (> 0.5; all valid without a third channel).
    """
    path = Path(path)
    fmt = FLOW_SUFFIXES.get(path.suffix.lower())
    if fmt == "raft":
        return read_flo(path)
    if fmt == "kitti":
        return read_kitti_flow(path)
    if fmt == "exr":
        arr = read_exr(path)
        if arr.ndim != 3 or arr.shape[-1] < 2:
            raise ArtifactError(f"{path}: a flow EXR has channels X, Y (, valid), got an array of shape {arr.shape}")
        valid = arr[..., 2] > 0.5 if arr.shape[-1] > 2 else np.ones(arr.shape[:2], bool)
        return np.ascontiguousarray(arr[..., :2], dtype=np.float32), valid
    raise ArtifactError(f"{path}: unknown flow file suffix {path.suffix!r} (known: {', '.join(FLOW_SUFFIXES)})")


def raft_padded_shape(height: int, width: int) -> tuple[int, int]:
    """(H, W) rounded up to multiples of 8, the size RAFT's ``InputPadder`` pads images to."""
    return -(-int(height) // 8) * 8, -(-int(width) // 8) * 8


def check_flow(flow: np.ndarray, valid: np.ndarray, shape: tuple[int, int], path: str | os.PathLike) -> None:
    """Check a flow (H', W', 2) and its validity (H', W') against the image size ``shape`` (H, W).

    A wrong size is an error; one equal to the image size rounded up to multiples of 8 says the
    flow was saved padded by RAFT's ``InputPadder`` (and where 'sintel' / 'kitti' mode put the
    padding). Non-finite values at valid pixels are an error.
    """
    f = np.asarray(flow)
    v = np.asarray(valid)
    H, W = (int(s) for s in shape)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ArtifactError(f"{path}: a flow is (H, W, 2), got {f.shape}")
    h, w = f.shape[:2]
    if (h, w) != (H, W):
        if (h, w) == raft_padded_shape(H, W):
            ph, pw = h - H, w - W
            raise ArtifactError(
                f"{path}: flow is {h}x{w} (H x W) but the images are {H}x{W}: it is padded to multiples of 8 by "
                f"RAFT's InputPadder ('sintel' mode: {ph // 2} rows top, {ph - ph // 2} bottom; 'kitti' mode: "
                f"{ph} rows at the bottom; both {pw // 2} columns left, {pw - pw // 2} right); call "
                f"padder.unpad(flow) before saving the flow")
        raise ArtifactError(f"{path}: flow is {h}x{w} (H x W) but the images are {H}x{W}")
    if v.shape != (h, w):
        raise ArtifactError(f"{path}: validity is {v.shape}, the flow {h}x{w}")
    bad = v.astype(bool) & ~np.isfinite(f).all(axis=-1)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ArtifactError(f"{path}: {int(bad.sum())} valid pixels with non-finite flow "
                            f"(first at row {r}, column {c})")
