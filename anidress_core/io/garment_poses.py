"""``results/<scene>/<seq>/garment_poses.npz``: the fitted garment poses (stage ``fit``, DESIGN.md §8).

Arrays:

* ``transforms`` (T, B, 4, 4) float32: bone transforms rest -> world, the rig's convention
  ``x = sum_b W[i, b] (M[b, :3, :3] rest_i + M[b, :3, 3])``;
* ``verts`` (T, V, 3) float32 fitted meshes, ``faces`` (F, 3) int64;
* ``loss`` (T,) float64: the weighted total at each frame's result, and ``loss_<term>`` (T,)
  float64 for every term of the fit (silhouette, normal, flow, anchor, prior, collision:
  :data:`anidress_core.fit.terms.TERM_NAMES`), unweighted, so that
  ``loss == sum_term weights[term] * loss_<term>`` with the weights of ``meta['weights']``;
* ``iterations`` (T,) int64; ``converged`` (T,) bool; ``wall_s`` (T,) float64 per frame (cue
  loading included); ``flow_targets`` (T,) int64;
* ``curve`` (T, L) float64: weighted loss after each accepted step, NaN-padded;

plus the header (``meta``: the loss variant that ran, every weight as used, the whole
FitConfig, cameras, cue folders, first-frame start, timings).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from . import files

__all__ = ["GarmentPoses", "read_garment_poses", "load_garment_poses", "save_garment_poses"]


@dataclass
class GarmentPoses:
    """The arrays of a ``garment_poses.npz`` (see the module docstring) and its header."""

    transforms: np.ndarray  # (T, B, 4, 4) float32
    verts: np.ndarray  # (T, V, 3) float32
    faces: np.ndarray  # (F, 3) int64
    loss: np.ndarray  # (T,) float64 weighted total
    terms: dict = field(default_factory=dict)  # term -> (T,) float64 unweighted (files before the rename: none)
    weights: dict = field(default_factory=dict)  # term -> weight as used (meta['weights']; older files: none)
    iterations: np.ndarray | None = None  # (T,) int64
    header: dict = field(default_factory=dict)


def load_garment_poses(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    """Read ``garment_poses.npz`` (arrays, header) with its shapes checked."""
    a, h = files.load_npz(path, required=("transforms", "verts", "faces", "loss", "iterations"))
    T = a["transforms"].shape[0]
    if a["transforms"].ndim != 4 or a["transforms"].shape[2:] != (4, 4) or a["verts"].ndim != 3 or \
            a["verts"].shape[0] != T:
        raise files.ArtifactError(f"{path}: transforms must be (T, B, 4, 4) and verts (T, V, 3), got "
                                  f"{a['transforms'].shape}, {a['verts'].shape}")
    return a, h


def read_garment_poses(path: str | os.PathLike, frames: int | None = None, bones: int | None = None) -> GarmentPoses:
    """The typed contents of ``garment_poses.npz``; ``frames`` / ``bones``: the T and B the caller
    needs (checked, with the file named), and the transforms must be finite."""
    a, h = load_garment_poses(path)
    G = a["transforms"]
    if bones is not None and G.shape[1] != bones:
        raise files.ArtifactError(f"{path}: transforms must be (T, {bones}, 4, 4) to match the rig, got {tuple(G.shape)}")
    if frames is not None and G.shape[0] != frames:
        raise files.ArtifactError(f"{path}: {G.shape[0]} frames of garment poses for a {frames}-frame sequence")
    if not np.isfinite(G).all():
        raise files.ArtifactError(f"{path}: transforms contain NaN or inf")
    meta = h.get("meta", {}) or {}
    terms = {k[len("loss_"):]: v for k, v in a.items() if k.startswith("loss_")}
    return GarmentPoses(G, a["verts"], a["faces"], a["loss"], terms, dict(meta.get("weights") or {}),
                        a["iterations"], h)


def save_garment_poses(path: str | os.PathLike, transforms: np.ndarray, verts: np.ndarray, faces: np.ndarray,
                       loss: np.ndarray, terms: Mapping[str, np.ndarray], weights: Mapping[str, float],
                       iterations: np.ndarray, converged: np.ndarray, wall_s: np.ndarray, flow_targets: np.ndarray,
                       curve: np.ndarray, config: Mapping, meta: Mapping) -> None:
    """Write ``garment_poses.npz`` (module docstring). ``terms``: every weighted term's unweighted
    values (T,); ``weights``: term -> weight as used (stored in ``meta['weights']``)."""
    T = transforms.shape[0]
    missing = sorted(set(weights) - set(terms))
    if missing:
        raise ValueError(f"{path}: weights of terms {missing} without values")
    arrays = {"transforms": np.asarray(transforms, np.float32), "verts": np.asarray(verts, np.float32),
              "faces": np.asarray(faces, np.int64), "loss": np.asarray(loss, np.float64)}
    for k, v in terms.items():
        v = np.asarray(v, np.float64)
        if v.shape != (T,):
            raise ValueError(f"{path}: loss_{k} must be ({T},), got {v.shape}")
        arrays[f"loss_{k}"] = v
    arrays.update({"iterations": np.asarray(iterations, np.int64), "converged": np.asarray(converged, bool),
                   "wall_s": np.asarray(wall_s, np.float64), "flow_targets": np.asarray(flow_targets, np.int64),
                   "curve": np.asarray(curve, np.float64)})
    files.save_npz(path, arrays, config=dict(config), meta={**dict(meta), "weights": {k: float(v) for k, v in weights.items()}})
