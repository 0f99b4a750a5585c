"""Helpers shared by the benchmark scripts, which run as modules from the repository root:
``.venv/bin/python -m benchmarks.<name> ...``."""
from __future__ import annotations

import platform


def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo, else :func:`platform.processor`, else the machine type."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def git_rev(paths=("anidress_core",)) -> str:
    """Short HEAD commit of the repository, with " + working tree" when any of ``paths``
    (relative to the repository root) has uncommitted changes; "?" without git."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True).stdout
        dirty = subprocess.run(["git", "status", "--porcelain", "--", *paths], cwd=root, capture_output=True,
                               text=True).stdout
    except OSError:
        return "?"
    return (rev.strip() or "?") + (" + working tree" if dirty.strip() else "")


def fit_scene(scene: str, seq: str, views: int, rig_path: str, frames: int | None = None):
    """What the fit benchmarks (fit_drift, fit_frame0) need of a synthetic scene, run from the
    repository root: scene info, the selected cameras and their ``fit.Views``, the rig (artifact
    and ``fit.RigParts``), the body and its posed sequence (the occluder), the ground truth in
    the template's topology ``Y`` (T, V, 3) and the rig floor's transforms ``floor_G`` (T, B, 4, 4).
    ``frames``: only the first ``frames`` frames of the ground truth."""
    from types import SimpleNamespace

    import torch

    from anidress_core import fit as FIT
    from anidress_core.camera import load_cameras
    from anidress_core.rig import fit_transforms
    from anidress_core.stages.fit import gt_template_vertices, select_views
    from anidress_core.stages.rig import load_rig
    from anidress_core.stages.scene import load_body, load_sequence_motion, read_scene

    d = f"data/{scene}"
    info = read_scene(d)
    names = select_views(info["cameras"]["train"], views)
    cams = load_cameras(f"{d}/{seq}/intri.yml", f"{d}/{seq}/extri.yml", names=names)
    art = load_rig(rig_path, dtype=torch.float64)
    rig = FIT.RigParts.make(art.model.rest, art.model.weights, art.model.bone_centres, torch.as_tensor(art.faces))
    body = load_body(d, info)
    motion = load_sequence_motion(d, seq, info["fps"])
    posed = body.pose(motion.poses, motion.Rh, motion.Th, motion.shapes)
    Y = gt_template_vertices(d, seq, art.model.rest, frames)[0]
    return SimpleNamespace(info=info, names=names, cams=cams, views=FIT.Views.from_cameras(cams), art=art, rig=rig,
                           body=body, posed=posed, Y=Y, floor_G=fit_transforms(art.model, Y).double())
