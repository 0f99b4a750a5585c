"""``results/<scene>/template.npz``: the prepared garment template (stage ``template``, DESIGN.md §4).

Arrays (see :class:`anidress_core.garment.GarmentTemplate` for the conventions):

* ``verts`` (V, 3) float32: rest vertices, metres, body canonical frame;
* ``faces`` (F, 3) int64;
* ``face_uv`` (F, 3, 2) float32: per-corner UVs;
* ``band`` (V,) bool: vertices held by the body;
* ``body_weights`` (V, 24) float32: body skinning weights;
* ``kind`` () str: 'skirt' | 'dress';

plus the usual header (code version, config hash, ``meta``: source and counts).
"""
from __future__ import annotations

import os
from typing import Any, Mapping

import numpy as np

from ..garment import GarmentTemplate
from . import files

__all__ = ["read_template", "write_template", "TEMPLATE_ARRAYS"]

TEMPLATE_ARRAYS = ("verts", "faces", "face_uv", "band", "body_weights", "kind")


def write_template(path: str | os.PathLike, tpl: GarmentTemplate, config: Any = None,
                   meta: Mapping[str, Any] | None = None) -> None:
    """Write ``tpl`` atomically; ``config`` is hashed into the header, ``meta`` stored as given."""
    files.save_npz(path, {"verts": tpl.verts, "faces": tpl.faces, "face_uv": tpl.face_uv, "band": tpl.band,
                          "body_weights": tpl.body_weights, "kind": np.asarray(tpl.kind)},
                   config=config, meta=meta)


def read_template(path: str | os.PathLike) -> GarmentTemplate:
    """Read ``template.npz``; a missing array or a wrong shape raises ArtifactError naming the file and the field."""
    arrays, _ = files.load_npz(path, required=TEMPLATE_ARRAYS)
    try:
        return GarmentTemplate(verts=arrays["verts"], faces=arrays["faces"].astype(np.int64),
                               face_uv=arrays["face_uv"], band=arrays["band"].astype(bool),
                               body_weights=arrays["body_weights"], kind=str(arrays["kind"]))
    except ValueError as e:
        raise files.ArtifactError(f"{path}: {e}") from e
