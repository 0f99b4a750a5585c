"""EasyMocap camera files: ``intri.yml`` and ``extri.yml``.

The layout follows EasyMocap's ``easymocap/mytools/camera_utils.py`` (zju3dv/EasyMocap:
``FileStorage``, ``read_camera``, ``write_camera``, ``write_intri``, ``write_extri``);
the code here is our own. Both files are OpenCV ``FileStorage`` YAML, written by hand
with CRLF line ends::

    %YAML:1.0
    ---
    names:
      - "01"
    K_01: !!opencv-matrix
      rows: 3
      cols: 3
      dt: d
      data: [...]

``intri.yml`` holds, per camera name, ``K_<cam>`` (3x3), ``dist_<cam>`` (1x5, OpenCV
k1 k2 p1 p2 k3) and optionally the image size ``H_<cam>`` / ``W_<cam>`` (plain ints).
``extri.yml`` holds ``R_<cam>`` (3x1 Rodrigues vector), ``Rot_<cam>`` (3x3) and
``T_<cam>`` (3x1) with ``X_cam = R X_world + T`` (metres).

Facts about the format that the readers and writers here honour:

* EasyMocap takes the camera list from ``names`` in ``intri.yml`` only. List items
  that are numbers become ``str(int(value))`` and items equal to ``none`` are skipped.
  A hand-written ``- 01`` (unquoted) is the number 1 to YAML, while the keys say
  ``K_01``: when the file has no ``<key>_1`` but exactly one zero-padded spelling of
  it (``K_01``), the name is read as that spelling (``"01"``); otherwise a missing
  key of a numeric name says to quote camera names.
* EasyMocap's ``read_camera`` ignores ``Rot_`` and rebuilds the rotation from ``R_``
  with ``cv2.Rodrigues``. We read ``Rot_`` when present (it is what round-trips
  exactly) and fall back to ``Rodrigues(R_)``; when both are present they must agree.
* ``dist_`` may be missing in files of some datasets that use ``D_`` instead;
  EasyMocap falls back to ``D_`` and so do we. Four coefficients mean k3 = 0.
* EasyMocap writes every number with ``'{:.6f}'``, i.e. six decimals. Our writers
  default to the shortest repr that parses back to the same double (``decimals=None``),
  so a write/read round trip is exact; ``decimals=6`` reproduces EasyMocap's bytes.

Readers return ``{name: {"K": (3, 3), "dist": (5,), "R": (3, 3), "T": (3,),
["H": int, "W": int]}}`` of float64 numpy arrays, in the file's camera order.
Every error names the file and the camera / key. Writers are atomic.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Iterable, Mapping

import cv2
import numpy as np

from .files import write_text

__all__ = [
    "read_names",
    "extrinsic_names",
    "read_intri",
    "read_extri",
    "read_camera",
    "write_intri",
    "write_extri",
    "write_camera",
]

PathLike = str | os.PathLike

# Camera names become parts of YAML keys (``K_<name>``); keep them to a safe set.
_NAME_RE = re.compile(r"^[A-Za-z0-9_\-]+$")
# Prefixes of the per-camera keys (``K_<cam>`` ...) of intri.yml and extri.yml.
_CAM_KEY_PREFIXES = ("K_", "dist_", "D_", "H_", "W_", "R_", "Rot_", "T_")
_QUOTE_HINT = "camera names must be strings: quote them ('01'); YAML reads an unquoted 01 as the number 1"
# Max |Rot_ - Rodrigues(R_)| tolerated when a file holds both (six-decimal files
# differ by ~1e-6).
_ROT_TOL = 1e-4


# --------------------------------------------------------------------------- files


def _open(path: PathLike) -> tuple[Path, cv2.FileStorage]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EasyMocap camera file not found: {path}")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as e:  # cv2.error, or SystemError wrapping it for parse errors
        raise ValueError(f"{path}: not a readable OpenCV YAML file ({e.__class__.__name__})") from e
    if not fs.isOpened():
        raise ValueError(f"{path}: not a readable OpenCV YAML file")
    return path, fs


# --------------------------------------------------------------------------- reading


def _node(fs: cv2.FileStorage, key: str):
    """The node ``key`` or None when absent."""
    node = fs.getNode(key)
    return None if node.empty() or node.isNone() else node


def _padded_name(fs: cv2.FileStorage, number: int) -> str:
    """The spelling of camera ``number`` in the file's keys: ``str(number)`` unless the
    keys spell it only one other way with leading zeros (``K_01`` for 1)."""
    plain = str(number)
    spellings = set()
    for key in fs.root().keys():
        for prefix in _CAM_KEY_PREFIXES:
            if key.startswith(prefix):
                suffix = key[len(prefix):]
                if suffix.isdigit() and int(suffix) == number:
                    spellings.add(suffix)
    if plain in spellings or len(spellings) != 1:
        return plain
    return spellings.pop()


def _read_names(fs: cv2.FileStorage, path: Path) -> list[str]:
    node = _node(fs, "names")
    if node is None or not node.isSeq():
        raise ValueError(f"{path}: missing key 'names' (a list of camera names)")
    names = []
    for i in range(node.size()):
        item = node.at(i)
        if item.isString():
            name = item.string()
        elif item.isInt() or item.isReal():
            # EasyMocap: an unquoted number becomes str(int(value)), so `- 01` reads "1";
            # we take the keys' zero-padded spelling ("01") when it is the only one.
            name = _padded_name(fs, int(item.real()))
        else:
            raise ValueError(f"{path}: 'names' item {i} is not a string or a number")
        if name != "none":  # EasyMocap skips 'none' entries
            names.append(name)
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: 'names' has duplicates: {names}")
    return names


def _read_matrix(fs: cv2.FileStorage, path: Path, cam: str, key: str, sizes: tuple[int, ...]) -> np.ndarray | None:
    """Matrix node ``key`` flattened to float64 (n,), None when absent.

    Raises ValueError naming file, camera and key when the node is not an
    ``!!opencv-matrix`` or holds a number of elements not in ``sizes``.
    """
    node = _node(fs, key)
    if node is None:
        return None
    try:
        m = node.mat()
    except Exception as e:  # cv2.error: e.g. rows * cols != len(data), or not a map
        raise ValueError(f"{path}: camera '{cam}': key '{key}' is a malformed !!opencv-matrix") from e
    if m is None:
        raise ValueError(f"{path}: camera '{cam}': key '{key}' is not an !!opencv-matrix")
    m = np.asarray(m, dtype=np.float64).reshape(-1)
    if m.size not in sizes:
        raise ValueError(
            f"{path}: camera '{cam}': key '{key}' has {m.size} elements, expected {' or '.join(map(str, sizes))}"
        )
    if not np.isfinite(m).all():
        raise ValueError(f"{path}: camera '{cam}': key '{key}' has non-finite values")
    return m


def _missing(path: Path, cam: str, *keys: str) -> ValueError:
    hint = f" ({_QUOTE_HINT})" if cam.isdigit() else ""
    return ValueError(f"{path}: camera '{cam}': missing key " + " / ".join(f"'{k}'" for k in keys) + hint)


def _pick(names_in_file: list[str], names: Iterable[str] | None, path: Path) -> list[str]:
    if names is None:
        return names_in_file
    names = list(names)
    not_str = [n for n in names if not isinstance(n, str)]
    if not_str:
        raise ValueError(f"{path}: cameras {not_str} asked for are not strings: {_QUOTE_HINT} "
                         f"(in scene.yaml cameras/train and cameras/test too); the file's cameras: {names_in_file}")
    unknown = [n for n in names if n not in names_in_file]
    if unknown:
        raise ValueError(f"{path}: cameras {unknown} not in 'names' {names_in_file}")
    return names


def read_names(path: PathLike) -> list[str]:
    """The camera names of ``intri.yml`` or ``extri.yml`` (``names``), as the readers here see them.

    Items that are ``none`` are skipped; an unquoted number takes the zero-padded spelling
    of the file's keys when there is exactly one (``- 01`` with ``K_01`` reads ``"01"``).
    """
    path, fs = _open(path)
    try:
        return _read_names(fs, path)
    finally:
        fs.release()


def read_intri(path: PathLike, names: Iterable[str] | None = None) -> dict[str, dict[str, Any]]:
    """Read ``intri.yml``: ``{name: {"K": (3, 3), "dist": (5,), ["H": int, "W": int]}}``.

    ``names`` selects (and orders) cameras; by default all of ``names`` in the file.
    ``H``/``W`` appear only when the file has ``H_<cam>``/``W_<cam>`` > 0.
    """
    path, fs = _open(path)
    try:
        cams = {}
        for cam in _pick(_read_names(fs, path), names, path):
            K = _read_matrix(fs, path, cam, f"K_{cam}", (9,))
            if K is None:
                raise _missing(path, cam, f"K_{cam}")
            # 1. distortion: 'dist_' with EasyMocap's fallback 'D_'; OpenCV allows 4, 5,
            #    8, 12 or 14 coefficients, we model the first five (extras must be zero).
            dist = _read_matrix(fs, path, cam, f"dist_{cam}", (4, 5, 8, 12, 14))
            if dist is None:
                dist = _read_matrix(fs, path, cam, f"D_{cam}", (4, 5, 8, 12, 14))
            if dist is None:
                raise _missing(path, cam, f"dist_{cam}", f"D_{cam}")
            if dist.size > 5 and np.any(dist[5:] != 0):
                raise ValueError(
                    f"{path}: camera '{cam}': distortion has {dist.size} coefficients, "
                    f"{int(np.count_nonzero(dist[5:]))} of them non-zero beyond k1 k2 p1 p2 k3; "
                    "only k1 k2 p1 p2 k3 are supported"
                )
            dist = np.concatenate([dist, np.zeros(1)])[:5] if dist.size == 4 else dist[:5]
            entry: dict[str, Any] = {"K": K.reshape(3, 3), "dist": dist}
            # 2. optional image size (EasyMocap's write_camera writes it, write_intri not)
            for k in ("H", "W"):
                node = _node(fs, f"{k}_{cam}")
                if node is None:
                    continue
                if not (node.isInt() or node.isReal()):
                    raise ValueError(f"{path}: camera '{cam}': key '{k}_{cam}' is not a number")
                if node.real() > 0:  # EasyMocap uses -1 for "unknown"
                    entry[k] = int(node.real())
            cams[cam] = entry
        return cams
    finally:
        fs.release()


def read_extri(path: PathLike, names: Iterable[str] | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Read ``extri.yml``: ``{name: {"R": (3, 3), "T": (3,)}}``, world -> camera.

    ``R`` is ``Rot_<cam>`` when present, else ``cv2.Rodrigues(R_<cam>)`` (what EasyMocap
    does). ``names`` defaults to the ``names`` list of this file.
    """
    path, fs = _open(path)
    try:
        cams = {}
        names = _read_names(fs, path) if names is None else list(names)
        not_str = [n for n in names if not isinstance(n, str)]
        if not_str:
            raise ValueError(f"{path}: cameras {not_str} asked for are not strings: {_QUOTE_HINT}")
        for cam in names:
            rvec = _read_matrix(fs, path, cam, f"R_{cam}", (3,))
            rot = _read_matrix(fs, path, cam, f"Rot_{cam}", (9,))
            T = _read_matrix(fs, path, cam, f"T_{cam}", (3,))
            if rvec is None and rot is None:
                raise _missing(path, cam, f"Rot_{cam}", f"R_{cam}")
            if T is None:
                raise _missing(path, cam, f"T_{cam}")
            if rot is None:
                R = cv2.Rodrigues(rvec.reshape(3, 1))[0]
            else:
                R = rot.reshape(3, 3)
                if rvec is not None:
                    # EasyMocap itself would use R_; refuse a file where the two disagree.
                    err = np.abs(cv2.Rodrigues(rvec.reshape(3, 1))[0] - R).max()
                    if err > _ROT_TOL:
                        raise ValueError(
                            f"{path}: camera '{cam}': 'Rot_{cam}' and Rodrigues('R_{cam}') disagree "
                            f"(max abs difference {err:.3g})"
                        )
            cams[cam] = {"R": np.asarray(R, dtype=np.float64), "T": T}
        return cams
    finally:
        fs.release()


def extrinsic_names(path: PathLike, names: Iterable[str]) -> list[str]:
    """The cameras of ``names`` (in order) that ``extri.yml`` at ``path`` has a pose for: a rotation
    (``Rot_<cam>`` or ``R_<cam>``) and ``T_<cam>``. The values are not checked here (:func:`read_extri` does)."""
    path, fs = _open(path)
    try:
        return [cam for cam in names if (_node(fs, f"Rot_{cam}") is not None or _node(fs, f"R_{cam}") is not None)
                and _node(fs, f"T_{cam}") is not None]
    finally:
        fs.release()


def read_camera(
    intri_path: PathLike, extri_path: PathLike, names: Iterable[str] | None = None
) -> dict[str, dict[str, Any]]:
    """Read both files: ``{name: {"K", "dist", "R", "T", ["H", "W"]}}``.

    The camera list is ``names`` of ``intri.yml`` (as in EasyMocap), or ``names`` given
    here (a subset, in the order given).
    """
    intri = read_intri(intri_path, names)
    extri = read_extri(extri_path, list(intri))
    return {cam: {**intri[cam], **extri[cam]} for cam in intri}


# --------------------------------------------------------------------------- writing


def _fmt(x: float, decimals: int | None) -> str:
    # repr(float) is the shortest string that parses back to the same double.
    return repr(float(x)) if decimals is None else f"{x:.{decimals}f}"


class _Writer:
    """Accumulates lines of an OpenCV YAML file in EasyMocap's layout (CRLF ends)."""

    def __init__(self, path: Path, decimals: int | None):
        self.path = path
        self.decimals = decimals
        self.lines = ["%YAML:1.0", "---"]

    def names(self, names: list[str]) -> None:
        self.lines.append("names:")
        self.lines += [f'  - "{n}"' for n in names]

    def mat(self, cam: str, key: str, value: Any, shape: tuple[int, int]) -> None:
        a = np.asarray(value, dtype=np.float64)
        if a.size != shape[0] * shape[1]:
            raise ValueError(
                f"{self.path}: camera '{cam}': '{key}' needs {shape[0] * shape[1]} values, got shape {a.shape}"
            )
        if not np.isfinite(a).all():
            raise ValueError(f"{self.path}: camera '{cam}': '{key}' has non-finite values")
        data = ", ".join(_fmt(x, self.decimals) for x in a.reshape(-1))
        self.lines += [
            f"{key}: !!opencv-matrix",
            f"  rows: {shape[0]}",
            f"  cols: {shape[1]}",
            "  dt: d",
            f"  data: [{data}]",
        ]

    def int(self, key: str, value: int) -> None:
        self.lines.append(f"{key}: {int(value)}")

    def save(self) -> None:
        write_text(self.path, "".join(line + "\r\n" for line in self.lines), newline="")


def _check_names(cameras: Mapping[str, Any], path: Path) -> list[str]:
    names = list(cameras)
    if not names:
        raise ValueError(f"{path}: no cameras to write")
    for n in names:
        if not isinstance(n, str) or not _NAME_RE.match(n) or n == "none":
            raise ValueError(f"{path}: camera name {n!r} must be letters, digits, '_' or '-' (and not 'none')")
    return names


def _get(cam_dict: Mapping[str, Any], key: str, path: Path, cam: str) -> Any:
    if key not in cam_dict:
        raise ValueError(f"{path}: camera '{cam}': no '{key}' to write")
    return cam_dict[key]


def write_intri(path: PathLike, cameras: Mapping[str, Mapping[str, Any]], decimals: int | None = None) -> None:
    """Write ``intri.yml``: per camera ``K`` (3, 3), ``dist`` (4 or 5 values), optional ``H``, ``W``.

    ``decimals=None`` writes exact doubles; ``decimals=6`` matches EasyMocap byte for byte.
    """
    path = Path(path)
    w = _Writer(path, decimals)
    w.names(_check_names(cameras, path))
    for cam, val in cameras.items():
        w.mat(cam, f"K_{cam}", _get(val, "K", path, cam), (3, 3))
        dist = np.asarray(_get(val, "dist", path, cam), dtype=np.float64).reshape(-1)
        if dist.size not in (4, 5):
            raise ValueError(f"{path}: camera '{cam}': 'dist' needs 4 or 5 values, got shape {dist.shape}")
        w.mat(cam, f"dist_{cam}", dist, (1, dist.size))
        if val.get("H") is not None and val.get("W") is not None:  # as EasyMocap: both or neither
            w.int(f"H_{cam}", val["H"])
            w.int(f"W_{cam}", val["W"])
    w.save()


def write_extri(path: PathLike, cameras: Mapping[str, Mapping[str, Any]], decimals: int | None = None) -> None:
    """Write ``extri.yml``: per camera ``R_`` (Rodrigues of ``R``), ``Rot_`` = ``R``, ``T_``.

    ``R`` (3, 3) and ``T`` (3,) or (3, 1) map world to camera.
    """
    path = Path(path)
    w = _Writer(path, decimals)
    w.names(_check_names(cameras, path))
    for cam, val in cameras.items():
        R = np.asarray(_get(val, "R", path, cam), dtype=np.float64)
        if R.shape != (3, 3) or not np.isfinite(R).all():
            raise ValueError(f"{path}: camera '{cam}': 'R' must be a finite (3, 3) matrix, got shape {R.shape}")
        rvec = cv2.Rodrigues(R)[0]
        w.mat(cam, f"R_{cam}", rvec, (3, 1))
        w.mat(cam, f"Rot_{cam}", R, (3, 3))
        w.mat(cam, f"T_{cam}", _get(val, "T", path, cam), (3, 1))
    w.save()


def write_camera(
    intri_path: PathLike,
    extri_path: PathLike,
    cameras: Mapping[str, Mapping[str, Any]],
    decimals: int | None = None,
) -> None:
    """Write both files, like EasyMocap's ``write_camera`` (which takes their folder).

    Each file is replaced atomically on its own.
    """
    write_intri(intri_path, cameras, decimals)
    write_extri(extri_path, cameras, decimals)
