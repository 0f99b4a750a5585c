"""Readers and writers for body models and body motion files.

* SMPL model files (Loper et al. 2015): ``.npz`` or ``.pkl``. Pickles are read with a
  restricted unpickler that only builds numpy arrays, scipy sparse matrices and
  plain containers; the original SMPL pickles store chumpy objects and must be
  converted to ``.npz`` first (a clear error says so).
* EasyMocap (zju3dv/EasyMocap, doc/02_output.md): ``smpl/<frame:06d>.json``, each a
  JSON list of people ``{"id", "Rh": [[3]], "Th": [[3]], "poses": [[72]],
  "shapes": [[10]]}`` (some versions wrap the list as ``{"annots": [...]}``);
  EasyMocap >= 0.2 writes ``poses`` of 69 (SMPL without the root) or 63 (SMPL-H /
  SMPL-X body, with ``handl`` / ``handr`` [/ ``expression``]): :func:`_smpl_poses`.
  Several people per file: chosen by ``person_id``; frames without the person: an
  error, or interpolated (``max_gap``); :func:`read_easymocap_smpl_dir`.
* ZJU-MoCap ``params/<i>.npy`` is read by :func:`anidress_core.io.zju.read_zju_params`
  through this module's person-parameter checks.
* AMASS ``.npz`` (Mahmood et al. 2019): ``poses`` (T, 156) SMPL-H or (T, 165) SMPL-X
  axis-angle, ``trans`` (T, 3), ``betas``, ``mocap_framerate`` (or
  ``mocap_frame_rate``); z-up world, global orientation about the pelvis (convert
  with ``anidress_core.body.model.global_orient_to_rh_th``).

Readers return float64 numpy arrays; errors name the file and what is wrong.
"""
from __future__ import annotations

import json
import os
import pickle
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .files import write_text

__all__ = [
    "read_smpl_model_file",
    "read_easymocap_smpl_dir",
    "read_easymocap_smpl_file",
    "EmptyFrameError",
    "smpl_selection",
    "write_easymocap_smpl",
    "write_easymocap_smpl_dir",
    "read_amass_npz",
    "SMPL_REQUIRED_KEYS",
]

SMPL_REQUIRED_KEYS = ("v_template", "f", "weights", "J_regressor", "kintree_table")

# --------------------------------------------------------------------- pickles
_SAFE_BUILTINS = {"object", "set", "frozenset", "slice", "complex", "list", "dict", "tuple", "bytearray",
                  "int", "float", "str", "bytes", "bool", "range"}
_SAFE_NUMPY = {
    ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy", "bool_"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
}


class _SafeUnpickler(pickle.Unpickler):
    """Builds only numpy arrays, scipy.sparse matrices and builtin containers."""

    def __init__(self, fh, path: Path):
        super().__init__(fh, encoding="latin1")
        self._path = path

    def find_class(self, module: str, name: str):
        if module.split(".")[0] == "chumpy":
            raise ValueError(
                f"{self._path}: this pickle stores chumpy objects ({module}.{name}); chumpy is not supported. "
                "Convert the model to .npz once (load it where chumpy is installed and np.savez every array, "
                "e.g. the arrays v_template, f, weights, J_regressor, kintree_table, shapedirs, posedirs)."
            )
        ok = (
            (module in ("builtins", "__builtin__") and name in _SAFE_BUILTINS)
            or (module in ("copy_reg", "copyreg") and name == "_reconstructor")
            or (module == "_codecs" and name == "encode")  # bytes in protocol-2 pickles
            or (module, name) in _SAFE_NUMPY
            or (module == "numpy.dtypes" and name.endswith("DType"))
            or (module.startswith("scipy.sparse") and (name.endswith("_matrix") or name.endswith("_array")))
        )
        if not ok:
            raise ValueError(f"{self._path}: refusing to unpickle {module}.{name} (only arrays and containers)")
        if module == "__builtin__":
            module = "builtins"
        if module == "copy_reg":
            module = "copyreg"
        return super().find_class(module, name)


def _safe_pickle_load(fh, path: Path) -> Any:
    try:
        return _SafeUnpickler(fh, path).load()
    except ValueError:
        raise
    except Exception as exc:  # truncated / corrupt pickle
        raise ValueError(f"{path}: cannot unpickle ({type(exc).__name__}: {exc})") from exc


def _load_npy_object(path: Path) -> Any:
    """np.load for .npy files, with pickled (object) payloads read by the safe unpickler."""
    with open(path, "rb") as fh:
        try:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                _, _, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version == (2, 0):
                _, _, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                raise ValueError(f"unsupported .npy version {version}")
        except ValueError as exc:
            raise ValueError(f"{path}: not a valid .npy file ({exc})") from exc
        if dtype.hasobject:
            obj = _safe_pickle_load(fh, path)
            if isinstance(obj, np.ndarray) and obj.dtype == object and obj.ndim == 0:
                obj = obj.item()
            return obj
    return np.load(path, allow_pickle=False)


# ------------------------------------------------------------------- helpers
def _to_array(value: Any) -> np.ndarray:
    if hasattr(value, "toarray"):  # scipy.sparse
        value = value.toarray()
    return np.asarray(value)


def _check_finite(path: Path, key: str, a: np.ndarray) -> None:
    if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        raise ValueError(f"{path}: '{key}' contains NaN or inf values")


def _require(path: Path, data: dict, keys) -> None:
    missing = [k for k in keys if k not in data]
    if missing:
        raise ValueError(f"{path}: missing key(s) {missing}; found {sorted(data)}")


def _exists(path: str | os.PathLike, kind: str = "file") -> Path:
    p = Path(path)
    if kind == "file" and not p.is_file():
        raise FileNotFoundError(f"{p}: no such file")
    if kind == "dir" and not p.is_dir():
        raise FileNotFoundError(f"{p}: no such directory")
    return p


# ------------------------------------------------------------------ SMPL model
def read_smpl_model_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Arrays of an SMPL-format model file (.npz or chumpy-free .pkl).

    Returns a dict of numpy arrays (sparse matrices densified, ``f`` and
    ``kintree_table`` as int64; non-array entries such as 'bs_style' become 0-d
    arrays). Requires the keys in SMPL_REQUIRED_KEYS; see
    ``anidress_core.body.model.smpl_model`` for their shapes.
    """
    p = _exists(path)
    suffix = p.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(p, allow_pickle=False) as z:
                raw = {k: z[k] for k in z.files}
        except ValueError as exc:
            raise ValueError(
                f"{p}: cannot read without pickle ({exc}); store plain numeric arrays (no objects) in the .npz"
            ) from exc
        except (OSError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{p}: not a valid .npz file ({exc})") from exc
    elif suffix == ".pkl":
        with open(p, "rb") as fh:
            raw = _safe_pickle_load(fh, p)
        if not isinstance(raw, dict):
            raise ValueError(f"{p}: expected a pickled dict, got {type(raw).__name__}")
    else:
        raise ValueError(f"{p}: unsupported SMPL model file type '{suffix}' (use .npz or .pkl)")
    out: dict[str, np.ndarray] = {}
    for k, v in raw.items():
        a = _to_array(v)
        if a.dtype == object:
            raise ValueError(f"{p}: entry '{k}' is not a numeric array ({type(v).__name__})")
        out[str(k)] = a
    _require(p, out, SMPL_REQUIRED_KEYS)
    for k in ("f", "kintree_table"):
        out[k] = out[k].astype(np.int64)
    for k, a in out.items():
        _check_finite(p, k, a)
    v = out["v_template"]
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{p}: 'v_template' must be (V, 3), got {v.shape}")
    if out["f"].ndim != 2 or out["f"].shape[1] != 3:
        raise ValueError(f"{p}: 'f' must be (F, 3), got {out['f'].shape}")
    if out["weights"].shape[0] != v.shape[0]:
        raise ValueError(f"{p}: 'weights' must be (V={v.shape[0]}, J), got {out['weights'].shape}")
    return out


# -------------------------------------------------------------------- EasyMocap
POSES_ACCEPTED = (
    "72 (SMPL: root + joints 1-23), "
    "69 (SMPL without the root: EasyMocap >= 0.2 SMPLModel(use_root_rot=False), the root orientation is 'Rh'), "
    "63 (SMPL-H / SMPL-X body without the root: EasyMocap >= 0.2 SMPLHModel / SMPLXModel, hands in "
    "'handl' / 'handr'), "
    "66 or more than 72 (EasyMocap 0.1 SMPL-H / SMPL-X with PCA hands, e.g. 78 / 87, or full SMPL-H 156 / "
    "SMPL-X 165: root + joints 1-21 first)"
)
"""The lengths of an EasyMocap / ZJU-MoCap ``poses`` entry :func:`_smpl_poses` reads, in words."""


def _smpl_poses(path: Path, poses: np.ndarray, key: str = "poses") -> np.ndarray:
    """(72,) SMPL axis-angle pose (root + joints 1..23) from the ``poses`` of an EasyMocap body file.

    EasyMocap's layouts (zju3dv/EasyMocap ``easymocap/bodymodel/smpl.py``, ``smplx.py``,
    and 0.1's ``easymocap/smplmodel/body_model.py``):

    * 72: SMPL with the root (0.1, and >= 0.2 with ``use_root_rot=True``); kept as is.
    * 69: SMPL without the root (>= 0.2, ``use_root_rot=False``, the default): EasyMocap
      prepends three zeros before skinning and applies the global orientation ``Rh``
      afterwards; we do the same (root = 0, ``Rh`` read separately).
    * 63: SMPL-H / SMPL-X body without the root (>= 0.2 ``SMPLHModel`` / SMPL-X): the 21
      body joints 1..21 shared with SMPL. Root = 0 (it is ``Rh``).
    * 66 and > 72: 0.1's SMPL-H / SMPL-X (root + 21 body joints + PCA hands [+ jaw, eyes],
      e.g. 78 / 87) and full SMPL-H (156) / SMPL-X (165): the first 66 numbers are root +
      joints 1..21.

    SMPL's joints 22, 23 (left / right hand) are set to ZERO for every layout but 72:
    SMPL-H / SMPL-X hands are MANO finger joints (``handl`` / ``handr``: PCA
    coefficients of MANO's licensed basis, or 15 finger joints each), none of which is
    SMPL's rigid hand joint, so no hand pose says otherwise. Any other length is refused
    with a message listing the accepted ones.
    """
    n = poses.size
    if n == 72:
        return poses
    if n == 69:
        return np.concatenate([np.zeros(3), poses])
    if n == 63:
        return np.concatenate([np.zeros(3), poses, np.zeros(6)])
    if n == 66 or n > 72:
        return np.concatenate([poses[:66], np.zeros(6)])
    raise ValueError(f"{path}: '{key}' holds {n} numbers; accepted lengths: {POSES_ACCEPTED}")


def _person_params(path: Path, person: dict) -> dict[str, np.ndarray]:
    """poses (72,), Rh (3,), Th (3,), shapes (S,) of one person entry (see :func:`_smpl_poses`).

    ``handl`` / ``handr`` / ``expression`` (EasyMocap >= 0.2 SMPL-H / SMPL-X) are checked
    (numeric, finite) but not returned: they do not move SMPL's joints.
    """
    if not isinstance(person, dict):
        raise ValueError(f"{path}: a person entry must be a dict of parameters, got {type(person).__name__}")
    _require(path, person, ("Rh", "Th", "poses"))
    out = {}
    for key in ("Rh", "Th", "poses", "shapes", "handl", "handr", "expression"):
        if key not in person:
            continue
        try:
            a = np.asarray(person[key], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: '{key}' is not numeric ({exc})") from exc
        _check_finite(path, key, a)
        out[key] = a
    for key in ("Rh", "Th"):
        if out[key].shape != (3,):
            raise ValueError(f"{path}: '{key}' must hold 3 numbers, got {out[key].size}")
    out["poses"] = _smpl_poses(path, out["poses"])
    for key in ("handl", "handr", "expression"):
        out.pop(key, None)
    if "shapes" not in out:
        out["shapes"] = np.zeros(10)
    return out


class EmptyFrameError(ValueError):
    """An EasyMocap body file without the chosen person (no one detected in that frame)."""


def _person_id(person: dict) -> int | None:
    pid = person.get("id", person.get("personID"))
    try:
        return None if pid is None else int(pid)
    except (TypeError, ValueError):
        return None


def _select_person(p: Path, data: list, person_id: int | None) -> dict:
    """The entry of ``person_id`` in a file's list of people (see :func:`read_easymocap_smpl_file`)."""
    ids = [d.get("id", d.get("personID")) if isinstance(d, dict) else None for d in data]
    if not data:
        raise EmptyFrameError(f"{p}: no person in this frame (an empty list: the capture detected nobody)")
    if person_id is None:
        if len(data) > 1:
            raise ValueError(f"{p}: holds {len(data)} people (ids {ids}); choose one with person_id "
                             "(scene.yaml 'person_id'), the order of people may change between frames")
        return data[0]
    match = [d for d in data if isinstance(d, dict) and _person_id(d) == int(person_id)]
    if not match:
        raise EmptyFrameError(f"{p}: no person with id {person_id} in this frame (ids: {ids})")
    if len(match) > 1:
        raise ValueError(f"{p}: person id {person_id} appears {len(match)} times")
    return match[0]


def read_easymocap_smpl_file(path: str | os.PathLike, person_id: int | None = None) -> dict[str, np.ndarray]:
    """One EasyMocap smpl json: dict(poses (72,), Rh (3,), Th (3,), shapes (S,), id).

    The file is a JSON list of people (EasyMocap ``write_smpl``; some versions wrap it
    as ``{"annots": [...]}``), each ``{"id", "Rh", "Th", "poses", "shapes"[, "handl",
    "handr", "expression"]}``. ``poses`` may hold any layout of :data:`POSES_ACCEPTED`.

    person_id: the ``id`` of the person to take. None: the file must hold exactly one
    person; a file with several raises naming the ids found (taking "the first" would
    follow whoever EasyMocap listed first, which may change between frames). A frame
    without that person (``[]``, EasyMocap's output when nobody was detected, or other
    ids only) raises :class:`EmptyFrameError` (a ValueError) naming the file.
    """
    p = _exists(path)
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: invalid JSON ({exc})") from exc
    if isinstance(data, dict):
        data = data.get("annots", data)
        if isinstance(data, dict):
            data = [data]
    if not isinstance(data, list) or not all(isinstance(d, dict) for d in data):
        raise ValueError(f"{p}: expected a JSON list of people (dicts with Rh, Th, poses, shapes)")
    person = _select_person(p, data, person_id)
    out = _person_params(p, person)
    pid = _person_id(person)
    out["id"] = np.asarray(0 if pid is None else pid)
    return out


def _interpolate_gaps(d: Path, frames: list[int], recs: list, missing: list[int], max_gap: int) -> None:
    """Fill ``recs[i] is None`` (i in ``missing``) from the nearest frames before and after (in place).

    Th, shapes: linear in the frame number; Rh and every joint of poses: spherical
    linear interpolation of the rotations (scipy Slerp on the axis-angle vectors).
    A gap longer than ``max_gap`` files, or one at the start or end of the sequence
    (no neighbour on one side), raises naming the file.
    """
    from scipy.spatial.transform import Rotation, Slerp

    have = [i for i, r in enumerate(recs) if r is not None]
    if not have:
        raise EmptyFrameError(f"{d}: no frame holds the person (every file is empty or lacks the id)")
    i = 0
    while i < len(missing):
        j = i
        while j + 1 < len(missing) and missing[j + 1] == missing[j] + 1:
            j += 1
        lo, hi = missing[i] - 1, missing[j] + 1
        gap = missing[j] - missing[i] + 1
        first = d / f"{frames[missing[i]]:06d}.json"
        if lo < 0 or hi >= len(recs):
            side = "first" if lo < 0 else "last"
            raise EmptyFrameError(f"{first}: the person is missing in {gap} file(s) at the {side} frames of the "
                                  "sequence: nothing to interpolate from on that side (trim the sequence)")
        if gap > max_gap:
            raise EmptyFrameError(f"{first}: the person is missing in {gap} consecutive files, more than "
                                  f"max_gap={max_gap} to interpolate")
        a, b = recs[lo], recs[hi]
        fa, fb = frames[lo], frames[hi]
        for k in range(missing[i], missing[j] + 1):
            w = (frames[k] - fa) / (fb - fa)
            rot = {}
            for key, n in (("Rh", 1), ("poses", 24)):
                ra = Rotation.from_rotvec(a[key].reshape(n, 3))
                rb = Rotation.from_rotvec(b[key].reshape(n, 3))
                rot[key] = np.stack([Slerp([0.0, 1.0], Rotation.concatenate([ra[m], rb[m]]))(w).as_rotvec()
                                     for m in range(n)]).reshape(-1)
            recs[k] = {"poses": rot["poses"], "Rh": rot["Rh"], "Th": (1 - w) * a["Th"] + w * b["Th"],
                       "shapes": (1 - w) * a["shapes"] + w * b["shapes"]}
        i = j + 1


def read_easymocap_smpl_dir(directory: str | os.PathLike, person_id: int | None = None,
                            max_gap: int = 0) -> dict[str, Any]:
    """All ``<frame>.json`` files of an EasyMocap ``smpl`` folder, sorted by frame.

    Returns dict(poses (T, 72), Rh (T, 3), Th (T, 3), shapes (T, S), frames list[int],
    interpolated list[int]).

    person_id: as in :func:`read_easymocap_smpl_file` (None: every file must hold one
    person). Frames without the person (an empty list or other ids only): with
    ``max_gap`` = 0 (the default) the first such file is the error
    (:class:`EmptyFrameError`, naming it and how many files lack the person); with
    ``max_gap`` = k > 0, gaps of at most k consecutive files between two frames that
    hold the person are interpolated (Th, shapes linearly, rotations by slerp) and
    their frame numbers listed in ``interpolated``; a longer gap, or one at the start
    or the end of the sequence, is still an error.
    """
    d = _exists(directory, "dir")
    if isinstance(max_gap, bool) or not isinstance(max_gap, (int, np.integer)) or max_gap < 0:
        raise ValueError(f"read_easymocap_smpl_dir: max_gap must be a non-negative int, got {max_gap!r}")
    files = [f for f in d.iterdir() if f.suffix == ".json"]
    bad = [f.name for f in files if not re.fullmatch(r"\d+", f.stem)]
    if bad:
        raise ValueError(f"{d}: file names must be frame numbers like 000000.json, found {bad[:3]}")
    files.sort(key=lambda f: int(f.stem))
    if not files:
        raise ValueError(f"{d}: no <frame>.json files")
    recs: list = []
    missing: list[int] = []
    empty_errors: list[EmptyFrameError] = []
    for i, f in enumerate(files):
        try:
            recs.append(read_easymocap_smpl_file(f, person_id))
        except EmptyFrameError as exc:
            recs.append(None)
            missing.append(i)
            empty_errors.append(exc)
    frames = [int(f.stem) for f in files]
    if missing:
        if max_gap == 0:
            n = len(missing)
            raise EmptyFrameError(f"{empty_errors[0]}" + (f" ({n} files of {d} lack the person)" if n > 1 else "")
                                  + "; pass max_gap (scene.yaml 'max_missing_frames') to interpolate short gaps")
        _interpolate_gaps(d, frames, recs, missing, int(max_gap))
    sizes = {r["shapes"].size for r in recs}
    if len(sizes) != 1:
        raise ValueError(f"{d}: 'shapes' sizes differ between frames: {sorted(sizes)}")
    return {
        "poses": np.stack([r["poses"] for r in recs]),
        "Rh": np.stack([r["Rh"] for r in recs]),
        "Th": np.stack([r["Th"] for r in recs]),
        "shapes": np.stack([r["shapes"] for r in recs]),
        "frames": frames,
        "interpolated": [frames[i] for i in missing],
    }


def smpl_selection(info: dict, seq: str, where: str | os.PathLike = "scene.yaml") -> dict[str, Any]:
    """``person_id`` / ``max_gap`` of :func:`read_easymocap_smpl_dir` from a parsed scene.yaml.

    Keys (optional): ``person_id`` (int: the EasyMocap ``id`` to take when files hold
    several people) and ``max_missing_frames`` (int >= 0, default 0: how many
    consecutive frames without the person are interpolated), at the top level or in a
    ``sequences`` entry (which wins). ``where`` names the file in errors.
    """
    entry = next((s for s in info.get("sequences") or [] if isinstance(s, dict) and s.get("name") == seq), {})
    out: dict[str, Any] = {}
    for key, arg, lo in (("person_id", "person_id", None), ("max_missing_frames", "max_gap", 0)):
        value = entry.get(key, info.get(key))
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or (lo is not None and value < lo):
            raise ValueError(f"{where}: '{key}' must be " + ("a non-negative integer" if lo is not None else
                             "an integer (an EasyMocap person id)") + f", got {value!r}")
        out[arg] = value
    return out


def _flat(name: str, x, n: int | None) -> list[float]:
    a = np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64).reshape(-1)
    if n is not None and a.size != n:
        raise ValueError(f"write_easymocap_smpl: '{name}' must hold {n} numbers, got shape {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"write_easymocap_smpl: '{name}' contains NaN or inf values")
    return [float(v) for v in a]


def write_easymocap_smpl(path: str | os.PathLike, poses, Rh, Th, shapes, person_id: int = 0) -> None:
    """Write one frame, one person, as an EasyMocap smpl json (atomically).

    poses (72,), Rh (3,), Th (3,), shapes (S,) (numpy, torch or lists); the values
    are written with full float64 precision so reading them back is exact.
    """
    person = {
        "id": int(person_id),
        "Rh": [_flat("Rh", Rh, 3)],
        "Th": [_flat("Th", Th, 3)],
        "poses": [_flat("poses", poses, 72)],
        "shapes": [_flat("shapes", shapes, None)],
    }
    write_text(Path(path), json.dumps([person], indent=1) + "\n")


def write_easymocap_smpl_dir(directory: str | os.PathLike, poses, Rh, Th, shapes, start_frame: int = 0,
                             person_id: int = 0) -> list[Path]:
    """Write a motion as ``<directory>/<frame:06d>.json``; poses (T, 72), Rh, Th (T, 3),
    shapes (S,) or (T, S). Returns the written paths."""
    P = np.asarray(poses.detach().cpu() if hasattr(poses, "detach") else poses, dtype=np.float64)
    R = np.asarray(Rh.detach().cpu() if hasattr(Rh, "detach") else Rh, dtype=np.float64)
    T_ = np.asarray(Th.detach().cpu() if hasattr(Th, "detach") else Th, dtype=np.float64)
    S = np.asarray(shapes.detach().cpu() if hasattr(shapes, "detach") else shapes, dtype=np.float64)
    n = P.shape[0]
    if P.shape != (n, 72) or R.shape != (n, 3) or T_.shape != (n, 3) or S.ndim not in (1, 2):
        raise ValueError(f"write_easymocap_smpl_dir: expected poses (T, 72), Rh (T, 3), Th (T, 3), shapes (S,) or "
                         f"(T, S); got {P.shape}, {R.shape}, {T_.shape}, {S.shape}")
    if S.ndim == 1:
        S = np.broadcast_to(S, (n, S.shape[0]))
    out = []
    for i in range(n):
        path = Path(directory) / f"{start_frame + i:06d}.json"
        write_easymocap_smpl(path, P[i], R[i], T_[i], S[i], person_id)
        out.append(path)
    return out


# ------------------------------------------------------------------------ AMASS
AMASS_KEYS = ("poses", "trans", "betas", "mocap_framerate", "mocap_frame_rate", "gender")
"""The only keys :func:`read_amass_npz` reads from an AMASS .npz (the others are never loaded)."""


def read_amass_npz(path: str | os.PathLike) -> dict[str, Any]:
    """An AMASS motion: dict(poses (T, 72), trans (T, 3), betas (S,), fps float, gender str).

    poses keeps AMASS's convention (poses[:, :3] = global orientation about the
    pelvis, z-up world). SMPL-H (156) / SMPL-X (165) poses: the first 22 joints
    (66 numbers: root + 21 body joints) are shared with SMPL; SMPL's joints 22-23
    (left_hand, right_hand) have no SMPL-H counterpart (SMPL-H's joint 22 is the
    left index finger root) and are set to ZERO rather than copied from a finger.

    Only the keys of :data:`AMASS_KEYS` are read, without pickle: the SMPL-X stage-II
    files' other entries (``markers_latent_vids``, a pickled dict, ``root_orient``,
    ``pose_body`` ...) are not loaded, so they neither fail nor get unpickled.
    """
    p = _exists(path)
    data = {}
    try:
        with np.load(p, allow_pickle=False) as z:
            # np.load of an .npz is lazy per key: read only the keys used here, so a
            # pickled object array beside them (SMPL-X stage-II 'markers_latent_vids',
            # a dict) is never unpickled nor refused.
            for k in AMASS_KEYS:
                if k not in z.files:
                    continue
                try:
                    data[k] = z[k]
                except ValueError as exc:  # "Object arrays cannot be loaded when allow_pickle=False"
                    raise ValueError(f"{p}: key '{k}' is a pickled object array; AMASS stores it as a plain "
                                     "numeric / string array (it is not unpickled here)") from exc
    except ValueError as exc:
        if str(exc).startswith(str(p)):
            raise
        raise ValueError(f"{p}: not a readable AMASS .npz ({exc})") from exc
    except (OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{p}: not a readable AMASS .npz ({exc})") from exc
    _require(p, data, ("poses", "trans"))
    poses = np.asarray(data["poses"], dtype=np.float64)
    trans = np.asarray(data["trans"], dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] < 66 or poses.shape[1] % 3:
        raise ValueError(f"{p}: 'poses' must be (T, 3K) with K >= 22 joints, got {poses.shape}")
    T = poses.shape[0]
    if trans.shape != (T, 3):
        raise ValueError(f"{p}: 'trans' must be ({T}, 3) to match poses, got {trans.shape}")
    _check_finite(p, "poses", poses)
    _check_finite(p, "trans", trans)
    if poses.shape[1] != 72:
        poses = np.concatenate([poses[:, :66], np.zeros((T, 6))], axis=1)
    fps_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data), None)
    if fps_key is None:
        raise ValueError(f"{p}: missing frame rate key ('mocap_framerate' or 'mocap_frame_rate')")
    fps = float(np.asarray(data[fps_key]).reshape(-1)[0])
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"{p}: '{fps_key}' must be a positive number, got {fps}")
    betas = np.asarray(data.get("betas", np.zeros(10)), dtype=np.float64)
    if betas.ndim == 2:  # some exports repeat the betas per frame
        betas = betas[0]
    betas = betas.reshape(-1)
    _check_finite(p, "betas", betas)
    gender = data.get("gender")
    if gender is not None:
        g = np.asarray(gender).reshape(-1)[0]
        gender = g.decode() if isinstance(g, bytes) else str(g)
    return {"poses": poses, "trans": trans, "betas": betas, "fps": fps, "gender": gender or "neutral"}

