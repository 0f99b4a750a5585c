"""Artifact files: float maps (EXR), masks and images (PNG/JPG), npz with a header.

Every writer is atomic: it writes a temporary file beside the target and renames it
into place, so an interrupted job never leaves a half-written artifact that a later
run would take for a finished one. Every reader raises an error that names the file
and what is wrong with it.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from .. import __version__

__all__ = [
    "ArtifactError",
    "SceneError",
    "atomic_path",
    "atomic_dir",
    "write_text",
    "write_exr",
    "read_exr",
    "write_png",
    "read_image",
    "write_mask",
    "read_mask",
    "save_npz",
    "load_npz",
    "config_hash",
    "write_json",
    "read_json",
]

HEADER_KEY = "__anidress_header__"

# mkstemp creates 0600 files; finished artifacts get the usual umask-based mode
_UMASK = os.umask(0)
os.umask(_UMASK)


class ArtifactError(ValueError):
    """A file exists but cannot be used (corrupt, wrong shape, wrong contents)."""


class SceneError(ValueError):
    """An input scene folder is malformed (a file missing, unreadable or inconsistent).

    Raised by :func:`anidress_core.stages.validate.validate_scene` with one message that
    names the file and the problem, before any long computation starts.
    """


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    On any exception the temporary file is removed and ``path`` is left untouched.
    The temporary name keeps the target's suffix (some writers choose the format by
    extension).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix or path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def atomic_dir(out_dir: str | os.PathLike) -> Iterator[Path]:
    """Yield a hidden temporary sibling of ``out_dir``; on success it replaces ``out_dir``.

    On any exception the temporary folder is removed and ``out_dir`` is left as it was.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_UMASK)
        if out_dir.exists():
            shutil.rmtree(out_dir)
        os.replace(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_text(path: str | os.PathLike, text: str, newline: str | None = None) -> None:
    """Write a text file atomically (UTF-8; ``newline=""`` keeps line ends as given)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline=newline) as fh:
            fh.write(text)


def _require(path: Path) -> None:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")


# --------------------------------------------------------------------------- EXR

_DEFAULT_CHANNELS = {1: ("Y",), 2: ("X", "Y"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


def write_exr(path: str | os.PathLike, array: np.ndarray, channels: tuple[str, ...] | None = None,
              half: bool = False) -> None:
    """Write a float map (H, W) or (H, W, C) as a ZIP-compressed scanline EXR.

    Channel names default to Y / X,Y / R,G,B / R,G,B,A; their order is stored in the
    header attribute ``anidress_channels`` so :func:`read_exr` restores it (EXR itself
    sorts channels by name).
    """
    import OpenEXR

    arr = np.asarray(array)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise ValueError(f"{path}: write_exr expects (H, W) or (H, W, C), got {arr.shape}")
    names = channels or _DEFAULT_CHANNELS.get(arr.shape[-1])
    if names is None or len(names) != arr.shape[-1]:
        raise ValueError(f"{path}: {arr.shape[-1]} channels need explicit names, got {channels}")
    dtype = np.float16 if half else np.float32
    data = {n: np.ascontiguousarray(arr[..., i].astype(dtype)) for i, n in enumerate(names)}
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "anidress_channels": ",".join(names),
    }
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, data) as f:
            f.write(str(tmp))


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an EXR written by :func:`write_exr` (or any single-part float EXR).

    Returns (H, W, C) float32 with channels in the stored order (or R,G,B(,A) /
    alphabetical for foreign files).
    """
    import OpenEXR

    path = Path(path)
    _require(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            # read what we need inside the context: the binding empties the header
            # dict when the file closes
            order = f.header().get("anidress_channels")
            chans = {k: np.array(v.pixels) for k, v in f.channels().items()}
    except Exception as e:  # OpenEXR raises bare exceptions for corrupt files
        raise ArtifactError(f"{path}: not a readable EXR file ({e})") from e
    if order:
        names = order.split(",")
    elif {"R", "G", "B"} <= set(chans):
        names = [c for c in ("R", "G", "B", "A") if c in chans]
    else:
        names = sorted(chans)
    missing = [n for n in names if n not in chans]
    if missing:
        raise ArtifactError(f"{path}: EXR lacks channels {missing}")
    return np.stack([chans[n].astype(np.float32) for n in names], axis=-1)


# --------------------------------------------------------------------------- PNG / images


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an image (H, W, 3) float in [0, 1] (RGB) or uint8/uint16 as PNG/JPG by extension."""
    import cv2

    img = np.asarray(image)
    if img.dtype.kind == "f":
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 3 and img.shape[-1] == 3:
        img = img[..., ::-1]  # RGB -> OpenCV's BGR
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"{path}: OpenCV could not write the image")


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a colour image as (H, W, 3) float32 RGB in [0, 1]."""
    import cv2

    path = Path(path)
    _require(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ArtifactError(f"{path}: unreadable or corrupt image")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return (img[..., ::-1].astype(np.float32) / scale).copy()


def write_mask(path: str | os.PathLike, labels: np.ndarray) -> None:
    """Write a label mask (H, W) of small integers (0 background, 1 body, 2 garment) as PNG."""
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise ValueError(f"{path}: a mask is (H, W), got {lab.shape}")
    if lab.size and (lab.min() < 0 or lab.max() > 255):
        raise ValueError(f"{path}: mask labels must lie in [0, 255]")
    write_png(path, lab.astype(np.uint8))


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a label mask PNG as (H, W) uint8."""
    import cv2

    path = Path(path)
    _require(path)
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise ArtifactError(f"{path}: unreadable or corrupt mask")
    if m.ndim == 3:  # a colour-saved mask: take one channel
        m = m[..., 0]
    return m.astype(np.uint8)


# --------------------------------------------------------------------------- NPZ artifacts


def config_hash(cfg: Any) -> str:
    """Short stable hash of a JSON-serialisable configuration."""
    blob = json.dumps(cfg, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def save_npz(path: str | os.PathLike, arrays: Mapping[str, Any], config: Any = None,
             meta: Mapping[str, Any] | None = None, compress: bool = True) -> None:
    """Save arrays with a small JSON header: code version, config hash, free metadata."""
    header = {
        "code_version": __version__,
        "config_hash": config_hash(config) if config is not None else None,
        "meta": dict(meta or {}),
    }
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    if HEADER_KEY in payload:
        raise ValueError(f"{path}: array name {HEADER_KEY!r} is reserved")
    payload[HEADER_KEY] = np.array(json.dumps(header, default=str))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            (np.savez_compressed if compress else np.savez)(fh, **payload)


def load_npz(path: str | os.PathLike, required: tuple[str, ...] = (),
             skip: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray], dict]:
    """Load an npz artifact -> (arrays, header). ``required`` names arrays that must exist; ``skip`` names arrays
    left unread (the caller does not need them)."""
    path = Path(path)
    _require(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k not in skip}
    except Exception as e:
        raise ArtifactError(f"{path}: not a readable npz file ({e})") from e
    raw = arrays.pop(HEADER_KEY, None)
    header = json.loads(str(raw)) if raw is not None else {}
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ArtifactError(f"{path}: missing arrays {missing} (has {sorted(arrays)})")
    return arrays, header


def write_json(path: str | os.PathLike, obj: Any) -> None:
    write_text(path, json.dumps(obj, indent=1, default=str))


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    _require(path)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ArtifactError(f"{path}: invalid JSON ({e})") from e
