"""``results/<scene>/<seq>/<variant>/field.pt``: a trained radiance field (stage ``train``, DESIGN.md §4).

A ``torch.save`` dict, written atomically:

* ``format`` (:data:`FIELD_FORMAT`), ``variant``, ``scene``, ``sequence``;
* ``field_config`` (the architecture, ``dataclasses.asdict`` of
  :class:`anidress_core.field.model.FieldConfig`), ``train_config``;
* ``state_dict``: name -> CPU tensor (canonical field, motion-weight volume incl. its
  prior ``weights.log_prior`` and the canonical box ``canonical.box``);
* ``num_body_joints`` (24), ``num_bones`` (B; 0 for body_only / tight), ``history``
  (per logged step: loss, batch PSNR, samples per ray), ``wall_s``, ``cpu_s``,
  ``steps``, ``frames``, ``cameras``, ``lpips``, ``sampling``, ``config_hash``,
  ``code_version``, ``device``, ``stage_wall_s``.

While training, ``field.pt.ckpt`` (:func:`training_state_path`) holds the last
training state (``model``, ``optimizer``, ``scheduler`` state dicts, ``step``,
``history``, ``config_hash``, ``resume_key``: the settings and data it continues, see
:func:`anidress_core.stages.field.run_train` and :func:`anidress_core.field.train.train_field`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from . import files

__all__ = ["FIELD_FORMAT", "FieldCheckpoint", "read_field_checkpoint", "write_field_checkpoint",
           "training_state_path", "read_training_state", "write_training_state"]

FIELD_FORMAT = "anidress-field/2"
"""2: the hash table entry-major (L T, F) and the fixed-point warp (``field_config.warp_iterations``)."""


@dataclass(frozen=True, eq=False)
class FieldCheckpoint:
    """``field.pt`` as read by :func:`read_field_checkpoint`."""

    meta: dict[str, Any]
    """Every entry but the weights (``format``, ``field_config``, ``history`` ...; see the module docstring)."""
    state_dict: dict[str, torch.Tensor]
    """Parameter and buffer name -> tensor (CPU), as ``AnimatableField.state_dict()``."""


def write_field_checkpoint(path: str | os.PathLike, ckpt: FieldCheckpoint) -> None:
    """Write ``field.pt`` atomically (the weights are moved to the CPU)."""
    with files.atomic_path(path) as tmp:
        torch.save({**ckpt.meta, "state_dict": {k: v.cpu() for k, v in ckpt.state_dict.items()}}, tmp)


def read_field_checkpoint(path: str | os.PathLike) -> FieldCheckpoint:
    """Read ``field.pt`` (on the CPU); a wrong format or a missing entry raises ArtifactError naming the file
    and the field."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: field checkpoint not found")
    try:
        d = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise files.ArtifactError(f"{path}: not a readable torch file ({e})") from e
    if not isinstance(d, dict) or not str(d.get("format", "")).startswith("anidress-field/"):
        raise files.ArtifactError(f"{path}: not an AniDress field ({FIELD_FORMAT})")
    if d["format"] != FIELD_FORMAT:
        raise files.ArtifactError(f"{path}: written by another version of the field ({d['format']}; this code reads "
                                  f"{FIELD_FORMAT}): train it again")
    missing = [k for k in ("field_config", "state_dict") if k not in d]
    if missing:
        raise files.ArtifactError(f"{path}: missing entries {missing}")
    sd = d["state_dict"]
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise files.ArtifactError(f"{path}: state_dict must map names to tensors")
    absent = [k for k in ("canonical.box", "weights.log_prior") if k not in sd]
    if absent:
        raise files.ArtifactError(f"{path}: state_dict lacks {absent}")
    return FieldCheckpoint(meta={k: v for k, v in d.items() if k != "state_dict"}, state_dict=sd)


def training_state_path(field_pt: str | os.PathLike) -> Path:
    """``<field.pt>.ckpt``: where the training state of ``field_pt`` is kept while training."""
    return Path(str(field_pt) + ".ckpt")


def write_training_state(path: str | os.PathLike, state: dict) -> None:
    """Write a training state dict atomically (``torch.save``)."""
    with files.atomic_path(path) as tmp:
        torch.save(state, tmp)


def read_training_state(path: str | os.PathLike, device: str | torch.device = "cpu") -> dict:
    """Read a training state written by :func:`write_training_state`, its tensors on ``device``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: training state not found")
    try:
        st = torch.load(path, map_location=device, weights_only=False)
    except Exception as e:
        raise files.ArtifactError(f"{path}: not a readable torch file ({e})") from e
    if not isinstance(st, dict) or "step" not in st:
        raise files.ArtifactError(f"{path}: not a training state (no 'step')")
    return st
