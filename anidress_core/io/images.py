"""Image files: where a frame's image is (any extension validate_scene accepts, any padding and letter case),
and their headers: size and integrity of PNG / JPEG files and the OpenEXR magic, without decoding.

Cheap checks for the scene validation (:mod:`anidress_core.stages.validate`): every
image of a capture gets its header and end marker read. Errors are
:class:`~anidress_core.io.files.ArtifactError` naming the file and the problem.

Formats: PNG (ISO/IEC 15948: 8-byte signature, IHDR first with width, height as
big-endian uint32, IEND last), JPEG (ITU T.81: SOI, marker segments with big-endian
lengths, a SOFn frame header with height, width, EOI at the end), OpenEXR (magic
number 76 2f 31 01).
"""
from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import NoReturn

from .files import ArtifactError

__all__ = ["IMAGE_EXTS", "frame_file", "frame_files", "image_path", "plate_path", "image_size_from_header",
           "check_exr_magic"]

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
"""Extensions of a sequence's ``images/<cam>/<frame>.<ext>`` files (any letter case), in the order they are
looked for."""


def frame_files(folder: Path, exts: tuple[str, ...] = IMAGE_EXTS) -> dict[int, Path]:
    """{frame: path} of the ``<digits>.<ext>`` files of ``folder``: any zero padding, the (lower-case)
    extensions ``exts`` in any letter case (as validate_scene accepts them); {} for a missing folder. Where a
    frame has several files, the first extension of ``exts`` wins (validate_scene refuses that case). The
    listing is kept per folder and extensions until the folder changes (its mtime)."""
    folder = Path(folder)
    try:
        stamp = folder.stat().st_mtime_ns
    except (FileNotFoundError, NotADirectoryError):
        return {}
    key = (str(folder), tuple(exts))
    hit = _FRAME_FILES.get(key)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    found = sorted((p for p in folder.iterdir() if p.suffix.lower() in exts and p.stem.isdigit()),
                   key=lambda p: (int(p.stem), exts.index(p.suffix.lower()), p.name))
    out: dict[int, Path] = {}
    for p in found:
        out.setdefault(int(p.stem), p)
    _FRAME_FILES[key] = (stamp, out)
    return out


_FRAME_FILES: dict[tuple[str, tuple[str, ...]], tuple[int, dict[int, Path]]] = {}


def frame_file(folder: Path, frame: int) -> Path:
    """The image file of frame ``frame`` in a camera folder: ``<frame:06d>.png``, ``.jpg`` or ``.jpeg`` when
    there, else any padding and letter case (:func:`frame_files`); the ``<frame:06d>.png`` path if there is
    none (its reader then names the missing file)."""
    base = Path(folder) / f"{int(frame):06d}"
    for ext in IMAGE_EXTS:
        p = base.with_suffix(ext)
        if p.is_file():
            return p
    return frame_files(folder).get(int(frame), base.with_suffix(".png"))


def image_path(seq_dir: Path, cam: str, frame: int) -> Path:
    """The image of frame ``frame`` of camera ``cam``: ``<seq_dir>/images/<cam>/<frame>.<ext>`` (:func:`frame_file`)."""
    return frame_file(Path(seq_dir) / "images" / cam, frame)


def plate_path(seq_dir: Path, cam: str) -> Path:
    """The background plate ``<seq_dir>/backgrounds/<cam>.<ext>`` (an image extension in any letter case;
    ``<cam>.png`` if there is none)."""
    folder = Path(seq_dir) / "backgrounds"
    if folder.is_dir():
        for p in sorted(folder.iterdir(), key=lambda p: (IMAGE_EXTS.index(p.suffix.lower())
                                                          if p.suffix.lower() in IMAGE_EXTS else 9, p.name)):
            if p.stem == cam and p.suffix.lower() in IMAGE_EXTS:
                return p
    return folder / f"{cam}.png"

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"
_EXR_MAGIC = b"\x76\x2f\x31\x01"


def _fail(path: str | os.PathLike, problem: str) -> NoReturn:
    raise ArtifactError(f"{path}: {problem}")


def _jpeg_size(fh, path: Path) -> tuple[int, int]:
    """(H, W) from the first SOF segment of a JPEG (markers walked by their lengths)."""
    pos = 2
    while True:
        fh.seek(pos)
        m = fh.read(4)
        if len(m) < 2 or m[0] != 0xFF:
            _fail(path, "corrupt JPEG: broken marker structure before the frame header")
        marker = m[1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            pos += 2
            continue
        if marker in (0xD9, 0xDA) or len(m) < 4:
            _fail(path, "corrupt JPEG: no frame header (SOF) before the image data")
        length = struct.unpack(">H", m[2:4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            sof = fh.read(5)
            if len(sof) < 5:
                _fail(path, "truncated JPEG frame header")
            h, w = struct.unpack(">HH", sof[1:5])
            return h, w
        pos += 2 + length


def image_size_from_header(path: str | os.PathLike) -> tuple[int, int]:
    """(H, W) of a PNG or JPEG from its header, after checking its start and end markers.

    No pixel is decoded: a PNG must start with the PNG signature and an IHDR chunk and
    end with the IEND chunk; a JPEG must start with SOI and end with EOI (within its
    last 4 KiB) and have a frame header. Raises ArtifactError naming the file otherwise.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(32)
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 4096))
            tail = fh.read()
            if head[:8] == _PNG_SIG:
                if head[12:16] != b"IHDR" or len(head) < 24:
                    _fail(path, "corrupt PNG: no IHDR header chunk")
                if not tail.endswith(_PNG_END):
                    _fail(path, "truncated or corrupt PNG: it does not end with the IEND chunk")
                w, h = struct.unpack(">II", head[16:24])
                return h, w
            if head[:3] == b"\xff\xd8\xff":
                if b"\xff\xd9" not in tail:
                    _fail(path, "truncated JPEG: no end-of-image marker")
                return _jpeg_size(fh, path)
    except OSError as e:
        _fail(path, f"cannot read the image file ({e.strerror or e})")
    if size == 0:
        _fail(path, "unreadable image: the file is empty")
    _fail(path, f"unreadable image: not a PNG or JPEG file (it starts with bytes {head[:8].hex(' ')})")


def check_exr_magic(path: str | os.PathLike) -> None:
    """Check that ``path`` starts with the OpenEXR magic number (nothing decoded)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
    except OSError as e:
        _fail(path, f"cannot read the file ({e.strerror or e})")
    if head != _EXR_MAGIC:
        _fail(path, "not an OpenEXR file (bad magic number)")
