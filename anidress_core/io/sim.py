"""``results/<scene>/sim/<motion>.npz``: one simulated garment sequence (stage ``simulate``, DESIGN.md §4).

Arrays:

* ``frames`` (T, V, 3) float32: garment vertices per frame, world, metres;
* ``faces`` (F, 3) int64: the template's triangles;
* ``fps`` () float64: frames per second of the body motion;
* per-frame stability statistics, each (T,): ``max_stretch`` and ``p99_stretch``
  (edge length / rest length), ``max_penetration_m`` (deepest free particle inside
  the body, metres), ``nan_count`` (non-finite coordinates), ``substeps``;
* ``spread`` (T, V) float32, an ensemble's mean only (``sim_ensemble/seq-<seq>.npz``, rule
  simulate_ensemble): per vertex, the members' RMS distance from their mean, metres;
* ``members`` (M, T, V, 3) float32, an ensemble's mean only: every member's frames (for studies; the fit
  reads the mean and the spread);

plus the header (code version, hash of the cloth parameters, ``meta``: motion name,
cloth parameters, recoveries, wall time).

Only ``frames`` is required when reading (the other fields are None when a file
lacks them, e.g. a hand-made sequence).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import files

__all__ = ["SimSequence", "read_sim", "write_sim", "SIM_STATS"]

SIM_STATS = ("max_stretch", "p99_stretch", "max_penetration_m", "nan_count", "substeps")
"""The per-frame (T,) statistics, in file order."""


@dataclass(frozen=True, eq=False)
class SimSequence:
    """A simulated sequence as read by :func:`read_sim` (numpy arrays)."""

    frames: np.ndarray
    """(T, V, 3) float32 garment vertices, world, metres."""
    faces: np.ndarray | None = None
    """(F, 3) int64 triangles."""
    fps: float | None = None
    """Frames per second."""
    max_stretch: np.ndarray | None = None
    """(T,) max edge length / rest length."""
    p99_stretch: np.ndarray | None = None
    """(T,) 99th percentile of edge length / rest length."""
    max_penetration_m: np.ndarray | None = None
    """(T,) deepest free particle inside the body, metres (0 if none)."""
    nan_count: np.ndarray | None = None
    """(T,) non-finite vertex coordinates."""
    substeps: np.ndarray | None = None
    """(T,) substeps used for the frame."""
    spread: np.ndarray | None = None
    """(T, V) an ensemble's mean only: per vertex, the members' RMS distance from their mean, metres."""
    members: np.ndarray | None = None
    """(M, T, V, 3) float32 an ensemble's mean only: every member's frames, world, metres."""
    meta: dict = field(default_factory=dict)
    """Header metadata: ``motion``, ``params`` (cloth), ``recoveries`` (list of dicts), ``wall_s``."""

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])


def write_sim(path: str | os.PathLike, seq: SimSequence, config: Any = None) -> None:
    """Write ``seq`` atomically (fields that are None are left out); ``config`` is hashed into the header."""
    arrays = {"frames": np.asarray(seq.frames).astype(np.float32)}
    if seq.faces is not None:
        arrays["faces"] = seq.faces
    if seq.fps is not None:
        arrays["fps"] = np.float64(seq.fps)
    for k in SIM_STATS:
        if getattr(seq, k) is not None:
            arrays[k] = getattr(seq, k)
    if seq.spread is not None:
        arrays["spread"] = np.asarray(seq.spread).astype(np.float32)
    if seq.members is not None:
        arrays["members"] = np.asarray(seq.members).astype(np.float32)
    files.save_npz(path, arrays, config=config, meta=seq.meta)


def read_sim(path: str | os.PathLike, members: bool = True) -> SimSequence:
    """Read ``sim/<motion>.npz``; a missing ``frames`` or a wrong shape raises ArtifactError naming the file and the field.
    ``members=False`` leaves an ensemble's ``members`` (M, T, V, 3) unread (``SimSequence.members`` None): the
    largest array, which only the member weighting uses."""
    a, h = files.load_npz(path, required=("frames",), skip=() if members else ("members",))
    x = a["frames"]
    if x.ndim != 3 or x.shape[-1] != 3:
        raise files.ArtifactError(f"{path}: frames must be (T, V, 3), got {x.shape}")
    T = x.shape[0]
    faces = a.get("faces")
    if faces is not None and (faces.ndim != 2 or faces.shape[1] != 3):
        raise files.ArtifactError(f"{path}: faces must be (F, 3), got {faces.shape}")
    stats = {}
    for k in SIM_STATS:
        if k in a:
            if a[k].shape != (T,):
                raise files.ArtifactError(f"{path}: {k} must be ({T},) (one per frame), got {a[k].shape}")
            stats[k] = a[k]
    spread = a.get("spread")
    if spread is not None and spread.shape != x.shape[:2]:
        raise files.ArtifactError(f"{path}: spread must be {x.shape[:2]} (one per frame and vertex), got "
                                  f"{spread.shape}")
    members = a.get("members")
    if members is not None and (members.ndim != 4 or members.shape[1:] != x.shape):
        raise files.ArtifactError(f"{path}: members must be (M, {', '.join(map(str, x.shape))}) (every member's "
                                  f"frames), got {members.shape}")
    return SimSequence(frames=x, faces=faces.astype(np.int64) if faces is not None else None, spread=spread,
                       members=members,
                       fps=float(a["fps"]) if "fps" in a else None, meta=h.get("meta", {}), **stats)
