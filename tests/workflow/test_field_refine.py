"""The field's garment-pose refinement (field/train/refine_garment) through the stage functions, on the tiny
garment scene the workflow tests build (its masks, template, rig and fitted garment poses)."""
import numpy as np
import torch

from anidress_core.config import load_config
from anidress_core.io.garment_poses import read_garment_poses
from anidress_core.stages.field import load_field, run_render, run_train
from tests.workflow.tiny import REPO, TINY


def _merged(base: dict, over: dict) -> dict:
    """``over`` on ``base`` key by key at every depth (as Snakemake merges a --configfile)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


def test_refined_garment_poses_are_kept_and_pose_the_training_renders(tiny_run, tmp_path):
    wd = tiny_run
    res, data = wd / "results" / "tinyskirt", wd / "data" / "tinyskirt"
    params = _merged(load_config(REPO / "config" / "config.yaml")["field"], TINY["field"])
    params["train"] = dict(params["train"], refine_garment=True, refine_lr=1e-2, refine_regrid_every=5, steps=12)
    kw = dict(template_npz=res / "template.npz", rig_npz=res / "rig.npz",
              garment_poses_npz=res / "walk" / "garment_poses.npz", progress=False)
    out = tmp_path / "field.pt"
    meta = run_train(data, "walk", "full", res / "walk" / "masks", out, params, **kw)
    fit = torch.as_tensor(read_garment_poses(res / "walk" / "garment_poses.npz", 4, meta["num_bones"]).transforms)
    refined = load_field(out).meta["refined_garment_transforms"]
    assert refined.shape == (len(meta["frames"]), meta["num_bones"], 4, 4) and torch.isfinite(refined).all()
    # rigid corrections of the fit: moved, still rigid, and near it (regularised)
    moved = (refined[:, :, :3, 3] - fit[meta["frames"]][:, :, :3, 3].float()).norm(dim=-1)
    assert moved.max() > 0 and moved.max() < 0.05
    R = refined[:, :, :3, :3] @ torch.linalg.inv(fit[meta["frames"]][:, :, :3, :3].float())
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=1e-4)
    assert np.isfinite(meta["refinement"]["translation_mm_mean"]) and meta["refinement"]["translation_mm_mean"] > 0
    r = run_render(out, data, tmp_path / "nv", params, seq="walk", cameras=["02"], frame_stride=2, **kw)
    assert "refined through the images" in r["garment_poses"]
