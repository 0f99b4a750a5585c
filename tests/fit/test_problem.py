"""anidress_core.fit.problem: render windows, the body occluder."""
from __future__ import annotations

import torch

from anidress_core import fit, raster
from anidress_core.geometry import lbs
from tests.fit.scenes import PAPER, config, pose, render, toy

torch.set_num_threads(1)


def test_crop_windows_keep_the_loss():
    """Rendering windows around the garment gives the loss of the whole images."""
    rig, views = toy(C=3, H=64, W=72)
    g = torch.Generator().manual_seed(8)
    Gt = pose(rig, g, 0.1, 0.02)
    cues, xt, fr = render(rig, views, Gt)
    x = lbs(rig.rest, rig.weights, pose(rig, g, 0.03, 0.01, Gt))
    uv, _ = raster.project_vertices(xt, views.K, views.world_to_cam)
    ft = fit.FlowTargets(torch.tensor([0, 1, 2]), torch.tensor([3, 40, 100]), uv[[0, 1, 2], [3, 40, 100]])
    cfg = config(PAPER)
    whole = fit.evaluate(fit.make_problem(rig, views, cues, cfg, flow=ft), x)
    win = fit.crop_window(views, cues.mask, x, 4)
    assert win.height < 64 and win.width < 72
    v2, c2, f2 = fit.crop_frame(views, cues, ft, win)
    part = fit.evaluate(fit.make_problem(rig, v2, c2, cfg, flow=f2), x)
    assert abs(part.loss - whole.loss) < 1e-9 * whole.loss
    back = fit.uncrop_fragments(part.fragments, win, 64, 72, cues.occluder)
    assert torch.equal(back.face_id, whole.fragments.face_id)


def test_body_occlusion_is_respected():
    """A garment pixel hidden by an occluder is not garment: fitting to occluded masks keeps the pose."""
    rig, views = toy(C=2, H=64, W=64)
    g = torch.Generator().manual_seed(6)
    Gt = pose(rig, g, 0.1, 0.02)
    x = lbs(rig.rest, rig.weights, Gt)
    fr = raster.rasterize(x, rig.faces, views.K, views.world_to_cam, 64, 64)
    occ = torch.full_like(fr.depth, float("inf"))
    occ[:, :, 20:34] = 1.0  # a vertical bar in front of the garment ("an arm")
    cues, _, _ = render(rig, views, Gt, occluder=occ)
    assert not bool(cues.mask[:, :, 20:34].any()) and bool(cues.mask.any())
    cfg = config(PAPER)
    ev = fit.evaluate(fit.make_problem(rig, views, cues, cfg), x)
    # at the true pose the silhouette residual is only the sub-pixel coverage of crossed pixels
    assert ev.terms["silhouette"] < 0.5
    un = fit.make_problem(rig, views, fit.FrameCues(cues.mask, cues.normals, torch.full_like(occ, float("inf"))),
                          cfg)
    assert fit.evaluate(un, x).terms["silhouette"] > 5 * ev.terms["silhouette"]  # ignoring the occluder: worse


def test_terms_without_weight_or_inputs_are_off():
    rig, views = toy(C=2, H=32, W=32, n_theta=12, n_h=4)
    cues, x, _ = render(rig, views, torch.eye(4, dtype=torch.float64).expand(rig.weights.shape[1], 4, 4))
    pb = fit.make_problem(rig, views, cues, config({"normal": 0.0, "anchor": 1.0}))
    assert all(pb.states[k] is None for k in ("normal", "anchor", "flow", "collision", "prior"))
    ev = fit.evaluate(pb, x)
    assert ev.terms["normal"] == 0.0 and ev.terms["anchor"] == 0.0 and ev.terms["flow"] == 0.0
