"""Probe: how far L_flow's targets are from the truth when made from the true garment of frame t-1.

For each synthetic scene (its first sequence, the 8 training views the fit uses) and frames t = 1 .. 29:
:func:`anidress_core.fit.flow_targets` from the ground-truth garment mesh of t-1 (its visibility with the posed
body as occluder, the masks of t-1) and the flows t-1 -> t, against the ground-truth vertices' projections at t.
Once with the ground-truth flows and masks (data/<scene>/<seq>/gt), once with the pipeline's (results/<scene>/<seq>).
Prints one row per scene and source: targets, end-point error (px) mean / median / p95, and the error along the
motion over the motion (sum over targets, negative = under-estimated), and the mean motion (px).

    PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/flow_targets.py suite_00 suite_02 ... > flow_targets.txt
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anidress_core import fit as FIT, raster  # noqa: E402
from anidress_core.fit.problem import occluder_depth  # noqa: E402
from anidress_core.io import files  # noqa: E402
from anidress_core.io.scene import load_body, load_sequence_motion, read_scene, scene_cameras  # noqa: E402
from anidress_core.stages.fit import CueReader, select_views, sequence_source  # noqa: E402

FRAMES, VIEWS = 30, 8


def check(scene: str) -> list[str]:
    sd = Path("data") / scene
    info = read_scene(sd)
    seq = info["sequences"][0]["name"] if isinstance(info["sequences"][0], dict) else info["sequences"][0]
    names = select_views(info["cameras"]["train"], VIEWS)
    cams = scene_cameras(sd, seq, names, info, seq_dir=sequence_source(sd, seq, None, info))
    views = FIT.Views.from_cameras(cams)
    a, _ = files.load_npz(sd / seq / "gt" / "meshes.npz", required=("garment_vertices", "garment_faces"))
    Y = torch.as_tensor(a["garment_vertices"][:FRAMES]).double()
    F = torch.as_tensor(a["garment_faces"].astype(np.int64))
    body = load_body(sd, info)
    motion = load_sequence_motion(sd, seq, info["fps"])
    posed = body.pose(motion.poses, motion.Rh, motion.Th, motion.shapes)
    rows = []
    for source, root in (("ground truth", sd / seq / "gt"), ("pipeline", Path("results") / scene / seq)):
        rd = CueReader(cams, root / "masks", None, root / "flows", posed.vertices.double(), body.faces, views,
                       torch.device("cpu"))
        err, along, motion_px = [], [0.0, 0.0], []
        for t in range(1, min(FRAMES, Y.shape[0])):
            mask = rd.cues(t - 1).mask
            occ = occluder_depth(posed.vertices[t - 1].double(), body.faces, views)
            frags = raster.occlude(raster.rasterize(Y[t - 1], F, views.K, views.world_to_cam, views.height,
                                                    views.width, with_bary=False), occ)
            fl = rd.flow(t)
            tg = FIT.flow_targets(Y[t - 1], views, frags, fl[0], fl[1], mask)
            uv1 = raster.project_vertices(Y[t], views.K, views.world_to_cam)[0][tg.cam, tg.vert]
            uv0 = raster.project_vertices(Y[t - 1], views.K, views.world_to_cam)[0][tg.cam, tg.vert]
            d, m = tg.target - uv1, uv1 - uv0
            err.append(d.norm(dim=-1))
            motion_px.append(m.norm(dim=-1))
            along[0] += float((d * m).sum())
            along[1] += float((m * m).sum())
        rd.close()
        e, mo = torch.cat(err), torch.cat(motion_px)
        rows.append(f"| {scene}/{seq} | {source} | {e.numel()} | {mo.mean():.2f} | {e.mean():.3f} | {e.median():.3f} | "
                    f"{e.quantile(0.95):.3f} | {100 * along[0] / along[1]:+.1f} |")
    return rows


if __name__ == "__main__":
    print("| scene | flows and masks | targets | motion px | EPE mean px | median | p95 | along % |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for s in sys.argv[1:]:
        print("\n".join(check(s)), flush=True)
