"""``results/<scene>/rig.npz``: the garment rigging model (stage ``rig``, DESIGN.md §4, paper §3.1).

Arrays:

* ``rest`` (V, 3) float32: the template's rest vertices (body canonical frame, metres);
* ``faces`` (F, 3) int64;
* ``weights`` (V, B) float32: convex skinning weights, at most ``nnz`` non-zeros per
  row (stored dense, zeros off the support);
* ``bone_centres`` (B, 3) float32: weighted rest centroid of each bone;
* ``transforms`` (N, B, 4, 4) float32: rest -> frame transforms (column vectors) of
  every simulated frame, sequences concatenated in the order of ``sequences``;
* ``sequences`` (S,) str and ``offsets`` (S + 1,) int64: frames of sequence s are
  ``transforms[offsets[s]:offsets[s + 1]]``;
* ``rmse_per_sequence`` (S,) float64 (metres) and ``rmse`` () float64: reconstruction
  error of the rig on the simulated frames;

plus the header (code version, config hash of the rig parameters, ``meta``:
parameters, timings, iteration history).

Also the files of ``anidress rig-decompose`` (Dem Bones' layout, plain npz without a
header): its input :class:`DemBonesSequence` (``rest`` (V, 3), ``frames`` (T, V, 3),
optional ``faces`` (F, 3)) and its output :class:`DemBonesRig` (``weights`` (B, V),
``transforms`` (T, B, 4, 4), ``bone_centres`` (B, 3), ``rmse`` ()).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from ..rig import RigModel
from . import files

__all__ = ["RigArtifact", "read_rig", "write_rig", "RIG_ARRAYS", "DemBonesSequence", "read_dembones_sequence",
           "write_dembones_sequence", "DemBonesRig", "read_dembones_rig", "write_dembones_rig"]

RIG_ARRAYS = ("rest", "faces", "weights", "bone_centres", "transforms", "sequences", "offsets", "rmse_per_sequence",
              "rmse")


@dataclass(frozen=True)
class RigArtifact:
    """``rig.npz`` as read by :func:`read_rig`."""

    model: RigModel
    """rest (V, 3), weights (V, B), transforms (N, B, 4, 4), bone_centres (B, 3), rmse (the total, metres)."""
    faces: np.ndarray
    """(F, 3) int64."""
    sequences: dict[str, slice]
    """Simulated motion name -> its frames in ``model.transforms`` (in file order)."""
    rmse_per_sequence: dict[str, float]
    """Simulated motion name -> reconstruction RMSE (m)."""
    meta: dict
    """Header metadata (parameters, timings, iteration history)."""

    def transforms_of(self, name: str) -> torch.Tensor:
        """(T, B, 4, 4) bone transforms of simulated motion ``name``."""
        if name not in self.sequences:
            raise KeyError(f"rig has no simulated sequence {name!r} (has {sorted(self.sequences)})")
        return self.model.transforms[self.sequences[name]]


def write_rig(path: str | os.PathLike, rig: RigArtifact, config: Any = None) -> None:
    """Write ``rig`` atomically (float32 geometry); ``config`` is hashed into the header.

    ``rig.sequences`` must tile ``model.transforms`` in order (offsets 0 .. N).
    """
    names = list(rig.sequences)
    offsets = [0] + [int(rig.sequences[n].stop) for n in names]
    starts = [int(rig.sequences[n].start) for n in names]
    if starts != offsets[:-1] or offsets[-1] != rig.model.transforms.shape[0]:
        raise ValueError(f"{path}: sequences {rig.sequences} do not tile {rig.model.transforms.shape[0]} frames")
    f32 = lambda x: x.float().cpu().numpy()  # noqa: E731
    files.save_npz(path, {
        "rest": f32(rig.model.rest), "faces": np.asarray(rig.faces).astype(np.int64),
        "weights": f32(rig.model.weights), "bone_centres": f32(rig.model.bone_centres),
        "transforms": f32(rig.model.transforms), "sequences": np.asarray(names),
        "offsets": np.asarray(offsets, np.int64),
        "rmse_per_sequence": np.asarray([rig.rmse_per_sequence[n] for n in names], np.float64),
        "rmse": np.float64(rig.model.rmse),
    }, config=config, meta=rig.meta)


def read_rig(path: str | os.PathLike, device: str | torch.device = "cpu",
             dtype: torch.dtype = torch.float32) -> RigArtifact:
    """Read ``rig.npz``; missing arrays or inconsistent shapes raise ArtifactError naming the file and the field."""
    a, h = files.load_npz(path, required=RIG_ARRAYS)
    if a["weights"].ndim != 2:
        raise files.ArtifactError(f"{path}: weights must be (V, B), got {a['weights'].shape}")
    V, B = a["weights"].shape
    if a["rest"].shape != (V, 3) or a["transforms"].shape[1:] != (B, 4, 4) or a["bone_centres"].shape != (B, 3):
        raise files.ArtifactError(f"{path}: inconsistent shapes: rest {a['rest'].shape}, weights "
                                  f"{a['weights'].shape}, transforms {a['transforms'].shape}")
    names = [str(n) for n in a["sequences"]]
    off = a["offsets"]
    if off.shape != (len(names) + 1,) or off[-1] != a["transforms"].shape[0]:
        raise files.ArtifactError(f"{path}: offsets {off.tolist()} do not cover {a['transforms'].shape[0]} frames")
    if a["rmse_per_sequence"].shape != (len(names),):
        raise files.ArtifactError(f"{path}: rmse_per_sequence must be ({len(names)},) like sequences, got "
                                  f"{a['rmse_per_sequence'].shape}")
    t = lambda k: torch.as_tensor(a[k], dtype=dtype, device=device)  # noqa: E731
    model = RigModel(rest=t("rest"), weights=t("weights"), transforms=t("transforms"),
                     bone_centres=t("bone_centres"), rmse=float(a["rmse"]))
    return RigArtifact(model=model, faces=a["faces"].astype(np.int64),
                       sequences={n: slice(int(off[i]), int(off[i + 1])) for i, n in enumerate(names)},
                       rmse_per_sequence={n: float(r) for n, r in zip(names, a["rmse_per_sequence"])},
                       meta=h.get("meta", {}))


# --------------------------------------------------------------------------- Dem Bones layout (rig-decompose)
class DemBonesSequence(NamedTuple):
    """Input of ``anidress rig-decompose``."""

    rest: np.ndarray
    """(V, 3) rest vertices."""
    frames: np.ndarray
    """(T, V, 3) animated vertices."""
    faces: np.ndarray | None
    """(F, 3) triangles (optional: the weight smoothing uses the mesh edges)."""


class DemBonesRig(NamedTuple):
    """Output of ``anidress rig-decompose``: x[t,i] = sum_b W[b,i] (M[t,b,:3,:3] rest[i] + M[t,b,:3,3])."""

    weights: np.ndarray
    """(B, V) convex skinning weights (Dem Bones' order: bones first)."""
    transforms: np.ndarray
    """(T, B, 4, 4) rest -> frame transforms, column vectors."""
    bone_centres: np.ndarray
    """(B, 3) weighted rest centroid of each bone."""
    rmse: float
    """Reconstruction RMSE over all frames and vertices."""


def _load_plain_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise files.ArtifactError(f"{path}: not a readable npz ({e})") from e


def write_dembones_sequence(path: str | os.PathLike, seq: DemBonesSequence) -> None:
    """Write a sequence for ``rig-decompose`` (plain npz, atomic)."""
    arrays = {"rest": seq.rest, "frames": seq.frames}
    if seq.faces is not None:
        arrays["faces"] = seq.faces
    with files.atomic_path(path) as tmp:
        np.savez(tmp, **arrays)


def read_dembones_sequence(path: str | os.PathLike) -> DemBonesSequence:
    """Read the input of ``rig-decompose``; a missing array raises ArtifactError naming the file and the field
    (the shapes are checked by :func:`anidress_core.rig.ssdr`)."""
    path = Path(path)
    z = _load_plain_npz(path)
    missing = [k for k in ("rest", "frames") if k not in z]
    if missing:
        raise files.ArtifactError(f"{path}: missing arrays {missing} (needs rest (V,3), frames (T,V,3), faces (F,3))")
    return DemBonesSequence(rest=z["rest"], frames=z["frames"], faces=z.get("faces"))


def write_dembones_rig(path: str | os.PathLike, rig: DemBonesRig) -> None:
    """Write the output of ``rig-decompose`` (plain npz, atomic)."""
    out = {"weights": rig.weights, "transforms": rig.transforms, "bone_centres": rig.bone_centres,
           "rmse": np.float64(rig.rmse)}
    with files.atomic_path(path) as tmp:
        np.savez(tmp, **out)


def read_dembones_rig(path: str | os.PathLike) -> DemBonesRig:
    """Read the output of ``rig-decompose``; missing arrays or inconsistent shapes raise ArtifactError naming
    the file and the field."""
    path = Path(path)
    z = _load_plain_npz(path)
    missing = [k for k in ("weights", "transforms", "bone_centres", "rmse") if k not in z]
    if missing:
        raise files.ArtifactError(f"{path}: missing arrays {missing}")
    B = z["weights"].shape[0] if z["weights"].ndim == 2 else -1
    if B < 0 or z["transforms"].ndim != 4 or z["transforms"].shape[1:] != (B, 4, 4) \
            or z["bone_centres"].shape != (B, 3):
        raise files.ArtifactError(f"{path}: inconsistent shapes: weights {z['weights'].shape} (B, V), transforms "
                                  f"{z['transforms'].shape} (T, B, 4, 4), bone_centres {z['bone_centres'].shape}")
    return DemBonesRig(weights=z["weights"], transforms=z["transforms"], bone_centres=z["bone_centres"],
                       rmse=float(z["rmse"]))
