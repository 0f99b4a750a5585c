"""Stage `template`: garment template -> cleaned, remeshed, body-attached template (DESIGN.md §4).

Reads ``data/<scene>/garment/template.obj`` (any mesh :func:`anidress_core.io.mesh.read_mesh`
reads), or builds the procedural skirt/dress when there is no file, runs
:func:`anidress_core.garment.prepare_template` and writes, atomically:

* ``template.ply``: the remeshed garment, vertex property ``band`` (uchar 0/1);
* ``template.npz`` (:mod:`anidress_core.io.template`): verts (V, 3), faces (F, 3),
  face_uv (F, 3, 2), band (V,), body_weights (V, 24), kind; header meta with the
  source and counts.
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from .. import garment
from ..garment import GarmentTemplate
from ..io.mesh import read_mesh, write_ply
from ..io.template import write_template

__all__ = ["run_template"]

log = logging.getLogger("anidress.template")


def run_template(template_path: str | os.PathLike | None, kind: str, body_model, target_vertices: int,
                 out_ply: str | os.PathLike, out_npz: str | os.PathLike, config=None) -> GarmentTemplate:
    """Prepare a garment template and write ``out_ply`` and ``out_npz``.

    template_path: garment mesh in the body's canonical T-pose frame (metres), or
    None for the procedural ``kind`` ('skirt' | 'dress') fitted to ``body_model``.
    config: anything JSON-serialisable, hashed into the npz header.
    """
    t0 = time.perf_counter()
    if template_path is None:
        make = {"skirt": garment.make_skirt, "dress": garment.make_dress}.get(kind)
        if make is None:
            raise ValueError(f"run_template: kind must be one of {garment.KINDS}, got {kind!r}")
        tpl = make(body_model, target_vertices=target_vertices)
        source = f"procedural {kind}"
    else:
        v, f, uv = read_mesh(template_path)
        try:
            tpl = garment.prepare_template(v, f, uv, kind, body_model, target_vertices)
        except ValueError as e:
            raise ValueError(f"{template_path}: {e}") from e
        source = str(Path(template_path))
    dist, inside = garment.body_clearance(tpl.verts, body_model)
    meta = {
        "source": source, "kind": kind, "target_vertices": int(target_vertices),
        "num_vertices": int(tpl.verts.shape[0]), "num_faces": int(tpl.faces.shape[0]),
        "band_vertices": int(tpl.band.sum()), "boundary_loops": len(garment.boundary_loops(tpl.faces)),
        "vertices_inside_body": int(inside.sum()), "min_body_distance_m": float(dist.min()),
        "wall_s": time.perf_counter() - t0,
    }
    if inside.any():
        log.warning("template: %d of %d garment vertices lie inside the T-posed body",
                    int(inside.sum()), tpl.verts.shape[0])
    write_ply(out_ply, tpl.verts, tpl.faces, {"band": tpl.band})
    write_template(out_npz, tpl, config=config, meta=meta)
    log.info("template: %s -> %d vertices, %d faces, %d band vertices (%.1f s)", source,
             meta["num_vertices"], meta["num_faces"], meta["band_vertices"], meta["wall_s"])
    return tpl
