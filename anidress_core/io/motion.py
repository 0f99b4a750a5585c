"""Readers and writers for body models and body motion files.

* SMPL model files (Loper et al. 2015): ``.npz`` or ``.pkl``. Pickles are read with a
  restricted unpickler that only builds numpy arrays, scipy sparse matrices and
  plain containers; the original SMPL pickles store chumpy objects and must be
  converted to ``.npz`` first (a clear error says so).
* EasyMocap (zju3dv/EasyMocap, doc/02_output.md): ``smpl/<frame:06d>.json``, each a
  JSON list of people ``{"id", "Rh": [[3]], "Th": [[3]], "poses": [[72]],
  "shapes": [[10]]}`` (some versions wrap the list as ``{"annots": [...]}``).
* ZJU-MoCap ``params/<i>.npy``: a pickled dict with poses (1, 72), Rh (1, 3),
  Th (1, 3), shapes (1, 10) (EasyMocap convention).
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
    "write_easymocap_smpl",
    "write_easymocap_smpl_dir",
    "read_zju_params_dir",
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


def read_easymocap_smpl_file(path: str | os.PathLike, person_id: int | None = None) -> dict[str, np.ndarray]:
    """One EasyMocap smpl json: dict(poses (72,), Rh (3,), Th (3,), shapes (S,), id).

    person_id: the person to take (None: the first entry of the file).
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
    if not isinstance(data, list) or not data or not all(isinstance(d, dict) for d in data):
        raise ValueError(f"{p}: expected a non-empty JSON list of people (dicts)")
    if person_id is None:
        person = data[0]
    else:
        match = [d for d in data if int(d.get("id", d.get("personID", -1))) == person_id]
        if not match:
            ids = [d.get("id", d.get("personID")) for d in data]
            raise ValueError(f"{p}: no person with id {person_id} (ids: {ids})")
        person = match[0]
    out = _person_params(p, person)
    out["id"] = np.asarray(int(person.get("id", person.get("personID", 0))))
    return out


def read_easymocap_smpl_dir(directory: str | os.PathLike, person_id: int | None = None) -> dict[str, Any]:
    """All ``<frame>.json`` files of an EasyMocap ``smpl`` folder, sorted by frame.

    Returns dict(poses (T, 72), Rh (T, 3), Th (T, 3), shapes (T, S), frames list[int]).
    """
    d = _exists(directory, "dir")
    files = [f for f in d.iterdir() if f.suffix == ".json"]
    bad = [f.name for f in files if not re.fullmatch(r"\d+", f.stem)]
    if bad:
        raise ValueError(f"{d}: file names must be frame numbers like 000000.json, found {bad[:3]}")
    files.sort(key=lambda f: int(f.stem))
    if not files:
        raise ValueError(f"{d}: no <frame>.json files")
    recs = [read_easymocap_smpl_file(f, person_id) for f in files]
    sizes = {r["shapes"].size for r in recs}
    if len(sizes) != 1:
        raise ValueError(f"{d}: 'shapes' sizes differ between frames: {sorted(sizes)}")
    return {
        "poses": np.stack([r["poses"] for r in recs]),
        "Rh": np.stack([r["Rh"] for r in recs]),
        "Th": np.stack([r["Th"] for r in recs]),
        "shapes": np.stack([r["shapes"] for r in recs]),
        "frames": [int(f.stem) for f in files],
    }


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


# ---------------------------------------------------------------------- ZJU-MoCap
def read_zju_params_dir(directory: str | os.PathLike) -> dict[str, Any]:
    """ZJU-MoCap ``params/<i>.npy`` files, sorted by i.

    Returns dict(poses (T, 72), Rh (T, 3), Th (T, 3), shapes (T, S), frames list[int]).
    """
    d = _exists(directory, "dir")
    files = [f for f in d.iterdir() if f.suffix == ".npy" and re.fullmatch(r"\d+", f.stem)]
    if not files:
        raise ValueError(f"{d}: no <i>.npy parameter files")
    files.sort(key=lambda f: int(f.stem))
    recs = []
    for f in files:
        obj = _load_npy_object(f)
        if not isinstance(obj, dict):
            raise ValueError(f"{f}: expected a pickled dict with poses, Rh, Th, shapes; got {type(obj).__name__}")
        recs.append(_person_params(f, obj))
    sizes = {r["shapes"].size for r in recs}
    if len(sizes) != 1:
        raise ValueError(f"{d}: 'shapes' sizes differ between frames: {sorted(sizes)}")
    return {
        "poses": np.stack([r["poses"] for r in recs]),
        "Rh": np.stack([r["Rh"] for r in recs]),
        "Th": np.stack([r["Th"] for r in recs]),
        "shapes": np.stack([r["shapes"] for r in recs]),
        "frames": [int(f.stem) for f in files],
    }


# ------------------------------------------------------------------------ AMASS
def read_amass_npz(path: str | os.PathLike) -> dict[str, Any]:
    """An AMASS motion: dict(poses (T, 72), trans (T, 3), betas (S,), fps float, gender str).

    poses keeps AMASS's convention (poses[:, :3] = global orientation about the
    pelvis, z-up world). SMPL-H (156) / SMPL-X (165) poses: the first 22 joints
    (66 numbers: root + 21 body joints) are shared with SMPL; SMPL's joints 22-23
    (left_hand, right_hand) have no SMPL-H counterpart (SMPL-H's joint 22 is the
    left index finger root) and are set to ZERO rather than copied from a finger.
    """
    p = _exists(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
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

