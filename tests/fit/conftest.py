"""Shared fixture of the stage tests of the fit (rules fit and fit_eval): a tiny synthetic skirt scene."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch


def write_gt_rig(data: Path, tpl, out: Path, num_bones: int, iters: int) -> None:
    """Write to ``out`` a rig of ``num_bones`` bones decomposed (SSDR) from the ground-truth garment of ``data``'s
    walk carried onto the template ``tpl`` (rule template's result): a stand-in for rule rig in stage tests."""
    from anidress_core import rig as R
    from anidress_core.io import files
    from anidress_core.io.mesh import read_mesh
    from anidress_core.metrics.mesh import barycentric_transfer
    from anidress_core.stages.fit_eval import gt_correspondence

    a, _ = files.load_npz(data / "walk" / "gt" / "meshes.npz")
    rv, rf, _ = read_mesh(data / "garment" / "template.obj")
    face, bary, _ = gt_correspondence(tpl.verts, rv, rf)
    Y = barycentric_transfer(torch.as_tensor(a["garment_vertices"]).double(), torch.as_tensor(rf),
                             torch.as_tensor(face), torch.as_tensor(bary))
    model = R.ssdr(torch.as_tensor(tpl.verts).double(), Y, torch.as_tensor(tpl.faces), num_bones=num_bones,
                   iters=iters, nnz=4)
    files.save_npz(out, {
        "rest": tpl.verts.astype(np.float32), "faces": tpl.faces.astype(np.int64),
        "weights": model.weights.float().numpy(), "bone_centres": model.bone_centres.float().numpy(),
        "transforms": model.transforms.float().numpy(), "sequences": np.asarray(["seq-walk"]),
        "offsets": np.asarray([0, Y.shape[0]], np.int64), "rmse_per_sequence": np.asarray([model.rmse]),
        "rmse": np.float64(model.rmse)})


@pytest.fixture(scope="session")
def tiny_skirt(tmp_path_factory):
    """(data, results) of a 6-camera (4 train), 4-frame skirt scene at 64 x 64 with its template, a rig and the
    stiffness ensemble of walk."""
    import yaml

    from anidress_core.config import default_schema_path, validate_config
    from anidress_core.io.scene import load_body, read_scene
    from anidress_core.stages.synth import run_synth
    from anidress_core.stages.template import run_template

    root = tmp_path_factory.mktemp("fitscene")
    scene = {"kind": "skirt", "image_size": [64, 64], "cameras": {"count": 6, "train": 4},
             "sequences": [{"name": "walk", "motion": "walk", "frames": 4}],
             "garment": {"vertices": 500, "cloth": {"settle_frames": 4}},
             "render": {"texture_size": 64, "noise_std": 0.0, "supersample": 1}}
    cfg = validate_config({"run_scenes": ["s"], "scenes": {"s": scene}},
                          yaml.safe_load(default_schema_path().read_text()))
    data = run_synth(cfg["scenes"]["s"], "s", root / "data" / "s", threads=1, progress=False)
    info = read_scene(data)
    res = root / "results"
    tpl = run_template(data / "garment" / "template.obj", "skirt", load_body(data, info), 500, res / "template.ply",
                       res / "template.npz")
    write_gt_rig(data, tpl, res / "rig.npz", num_bones=6, iters=5)  # stands in for rule rig
    # the observed motion simulated at two bending stiffnesses, their mean (rule simulate_ensemble): L_prior's reference
    from anidress_core.stages.simulate import run_motion, run_simulate_ensemble

    run_motion("seq-walk", data, cfg["simulate"], res / "motions" / "seq-walk.npz")
    run_simulate_ensemble(res / "template.npz", res / "motions" / "seq-walk.npz", data, tiny_cloth(cfg), [1e-4, 1e-3],
                          ensemble(res), progress=False)
    return data, res


def tiny_cloth(cfg: dict) -> dict:
    """The pipeline's cloth settings with a short settling (a fast simulation of the tiny scene)."""
    return {**cfg["simulate"]["cloth"], "settle_frames": 4}


def ensemble(res: Path) -> Path:
    """The tiny scene's ensemble mean simulation of walk."""
    return res / "sim_ensemble" / "seq-walk.npz"
