"""``results/<scene>/motions/<name>.npz``: a body motion to simulate (stage ``motions``, DESIGN.md §4).

Arrays: ``poses`` (T, 72), ``Rh`` (T, 3), ``Th`` (T, 3), ``shapes`` (S,) float32
(EasyMocap convention, see :class:`anidress_core.body.motions.Motion`), ``fps`` ()
float64; header meta ``name`` (the motion name, e.g. ``seq-walk``, ``lib-twirl``)
and ``frames``; the simulation config is hashed into the header.

The readers of foreign motion formats (EasyMocap, ZJU-MoCap, AMASS) are in
:mod:`anidress_core.io.motion`.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..body.motions import Motion
from . import files

__all__ = ["read_motion", "write_motion", "MOTION_ARRAYS"]

MOTION_ARRAYS = ("poses", "Rh", "Th", "shapes", "fps")


def write_motion(path: str | os.PathLike, motion: Motion, config: Any = None, meta: dict | None = None) -> None:
    """Write ``motion`` atomically.

    meta: header metadata (default ``{"name": motion.name, "frames": T}``); ``config``
    is hashed into the header.
    """
    if meta is None:
        meta = {"name": motion.name, "frames": int(motion.poses.shape[0])}
    files.save_npz(path, {"poses": motion.poses.numpy(), "Rh": motion.Rh.numpy(), "Th": motion.Th.numpy(),
                          "shapes": motion.shapes.numpy(), "fps": np.float64(motion.fps)},
                   config=config, meta=meta)


def read_motion(path: str | os.PathLike) -> Motion:
    """Read ``motions/<name>.npz`` -> Motion (float32 tensors; name from the header, else the file stem).

    A missing array or a wrong shape raises ArtifactError naming the file and the field.
    """
    a, h = files.load_npz(path, required=MOTION_ARRAYS)
    t = lambda k: torch.from_numpy(a[k]).float()  # noqa: E731
    try:
        return Motion(name=h.get("meta", {}).get("name", Path(path).stem), fps=float(a["fps"]), poses=t("poses"),
                      Rh=t("Rh"), Th=t("Th"), shapes=t("shapes"))
    except ValueError as e:
        raise files.ArtifactError(f"{path}: {e}") from e
