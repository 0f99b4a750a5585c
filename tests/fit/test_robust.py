"""anidress_core.fit on defective cues: empty masks in one or all views, a frame without flow, NaN in a
mask, a normal map, a flow field, an image or a flow target. Never a NaN pose or a NaN stored loss,
and what the fit did is in each frame's ``notes`` (and logged by fit_sequence)."""
from __future__ import annotations

import logging
import math

import torch

from anidress_core import fit
from anidress_core.geometry import lbs
from tests.fit.scenes import PAPER, config, moving, pose, render, rmse, textured, toy
from tests.fit.test_terms import check_system, scene

torch.set_num_threads(1)

CFG = dict(max_iters=15, max_iters_first=15, smooth_passes=0)


def finite(r: fit.FrameFit) -> bool:
    return (bool(torch.isfinite(r.transforms).all()) and bool(torch.isfinite(r.verts).all())
            and math.isfinite(r.loss) and all(math.isfinite(v) for v in r.terms.values()))


def frame(seed=11, C=4, H=48, W=48):
    rig, views = toy(C=C, H=H, W=W)
    g = torch.Generator().manual_seed(seed)
    Gt = pose(rig, g, 0.1, 0.02)
    cues, xt, fr = render(rig, views, Gt)
    G0 = pose(rig, g, 0.03, 0.01, Gt)
    return rig, views, Gt, cues, xt, G0


def test_unknown_mask_pixels_keep_the_gauss_newton_system_exact():
    """L_silhouette with unknown (NaN) mask pixels: the Gauss-Newton system is still J^T J, J^T r of
    the masked residuals, and the gradient is the autograd gradient of the reference (float64)."""
    rig, views, _, _, cues, _, G0 = scene(2)
    m = cues.mask.double()
    m[0, 10:30, 10:30] = float("nan")
    m[2] = float("nan")
    cues = cues._replace(mask=m)
    cfg = config(PAPER)
    ok = torch.isfinite(m).reshape(-1).double()

    def residuals(d, pb, ev):
        from anidress_core import raster
        from tests.fit.test_terms import moved

        x = moved(rig, G0, d)
        s = raster.silhouette(x, rig.faces, views.K, views.world_to_cam, ev.fragments, rig.edges)
        return (s.reshape(-1) - torch.nan_to_num(m).reshape(-1)) * ok * (2.0 / pb.n_px) ** 0.5

    ev = check_system(rig, views, cues, G0, config(dict(PAPER, normal=0.0, flow=0.0)), residuals)
    assert math.isfinite(ev.loss) and ev.terms["silhouette"] > 0
    check_system(rig, views, cues, G0, cfg)  # with L_normal: gradient = autograd's
    pb = fit.make_problem(rig, views, cues, cfg)
    assert pb.n_px == float(torch.nan_to_num(m).sum())


def test_an_empty_view_is_dropped_and_the_fit_is_that_of_the_other_views():
    """One view's mask is empty: the view is dropped (notes['views_dropped']) and the fit equals the
    fit on the remaining views alone; kept, the silhouette pushes the garment out of that view."""
    rig, views, Gt, cues, xt, G0 = frame()
    bad = cues._replace(mask=cues.mask.clone())
    bad.mask[1] = False
    cfg = config(PAPER, **CFG)
    r = fit.fit_frame(rig, views, bad, G0, cfg, first=True)
    assert finite(r) and r.notes == {"views_dropped": [1]}
    keep = [0, 2, 3]
    sub = fit.Views(views.K[keep], views.world_to_cam[keep], views.height, views.width)
    ref = fit.fit_frame(rig, sub, fit.FrameCues(cues.mask[keep], cues.normals[keep], cues.occluder[keep]), G0, cfg,
                        first=True)
    assert not ref.notes
    # the same loss (float32 Jacobian products, other render windows: equal to ~1e-6)
    torch.testing.assert_close(r.transforms, ref.transforms, rtol=0, atol=1e-5)
    assert abs(r.loss - ref.loss) <= 1e-5 * ref.loss


def test_all_views_empty_keep_the_start_pose():
    """Every mask empty (or unknown): nothing to fit; the start pose is kept, not converged, and said."""
    rig, views, Gt, cues, xt, G0 = frame()
    cfg = config(PAPER, **CFG)
    for mask in (torch.zeros_like(cues.mask), torch.full(cues.mask.shape, float("nan"), dtype=torch.float64)):
        r = fit.fit_frame(rig, views, fit.FrameCues(mask, cues.normals, cues.occluder), G0, cfg, first=True)
        assert finite(r) and torch.equal(r.transforms, G0) and not r.converged and r.iterations == 0
        assert r.notes["no_mask"] and r.notes["views_dropped"] == [0, 1, 2, 3]


def test_nan_in_mask_normals_and_image_are_left_out_and_counted():
    """NaN pixels of a float mask, of the normal maps and of the colour images: finite poses and losses
    (the frame is fitted), each count in the notes, the NaN mask pixels out of L_silhouette
    (pixel_ok) and of the normaliser; L_anchor's references never take a NaN colour."""
    rig, views = toy(C=4, H=64, W=64)
    g = torch.Generator().manual_seed(4)
    Gt = pose(rig, g, 0.1, 0.02)

    def colour_of(p):
        th = torch.atan2(p[:, 1], p[:, 0])
        return torch.stack([0.5 + 0.4 * torch.sin(4 * th), 0.5 + 0.4 * torch.cos(3 * th), 0.5 + 0.2 * p[:, 2]], -1)

    cues, xt = textured(rig, views, Gt, colour_of)
    m = cues.mask.double()
    m[0, 20:40, 20:40] = float("nan")
    n = cues.normals.clone()
    n[1, 30:50] = float("nan")
    img = cues.image.clone()
    img[2, :, 25:35] = float("nan")
    bad = cues._replace(mask=m, normals=n, image=img)
    G0 = pose(rig, g, 0.03, 0.01, Gt)
    cfg = config(dict(PAPER, anchor=1e4), anchor_reference="images", **CFG)
    ref = fit.update_anchor(None, xt, views, render(rig, views, Gt)[2], img, m, cfg)
    assert bool(torch.isfinite(ref.chroma).all()) and int(ref.seen.sum()) > 100
    r = fit.fit_frame(rig, views, bad, G0, cfg, first=True, anchor=ref)
    assert finite(r) and r.terms["anchor"] > 0
    assert r.notes["mask_unknown_px"] == 400
    assert r.notes["normals_nonfinite_px"] == int((~torch.isfinite(n).all(-1) & cues.mask).sum()) > 0
    assert r.notes["image_nonfinite_px"] == 64 * 10
    assert r.iterations > 0 and r.loss < r.curve[0]  # fitted, not kept
    pb = fit.make_problem(rig, views, bad, cfg, anchor=ref)
    assert pb.n_px == float(torch.nan_to_num(m).sum()) and int((pb.states["silhouette"].known == 0).sum()) == 400


def test_frames_without_flow_and_nan_flow(caplog):
    """A sequence where frame 1 has no flow (flow_of -> None), frame 2 a flow field that is NaN
    everywhere (no target survives) and frame 3 a partly NaN flow: finite fits, L_flow off where it
    has no target, 'no_flow' noted and logged; NaN flow targets passed in are dropped and counted."""
    rig, views = toy(C=4, H=48, W=48)
    g, Gs, frames = moving(rig, views, 4, seed=5)
    C, H, W = frames[0][0].mask.shape

    def flow_of(t):
        if t == 1:
            return None
        f = torch.zeros(C, H, W, 2, dtype=torch.float64)
        if t == 2:
            f[:] = float("nan")
        else:
            f[0, 5:30] = float("nan")
        return f, None

    cfg = config(PAPER, **CFG)
    start = pose(rig, g, 0.03, 0.01, Gs[0])
    with caplog.at_level(logging.WARNING, logger="anidress.test"):
        res = fit.fit_sequence(fit.FitPlan(cfg, rig, views, 4, start), lambda t: frames[t][0], flow_of, progress=False,
                               log=logging.getLogger("anidress.test"))
    assert all(finite(r) for r in res)
    assert [r.notes.get("no_flow", False) for r in res] == [False, True, True, False]
    assert [r.terms["flow_targets"] for r in res][:3] == [0, 0, 0] and res[3].terms["flow_targets"] > 0
    assert res[1].terms["flow"] == 0.0 and res[3].terms["flow"] >= 0.0
    assert "frame 1 has no flow" in caplog.text and "frame 2: {'no_flow': True}" in caplog.text
    # NaN targets handed to fit_frame
    x0 = frames[0][1]
    ft = fit.flow_targets(x0, views, frames[0][2], torch.zeros(C, H, W, 2, dtype=torch.float64), None,
                          frames[0][0].mask)
    tgt = ft.target.clone()
    tgt[:7] = float("nan")
    r = fit.fit_frame(rig, views, frames[1][0], Gs[0], cfg, flow=fit.FlowTargets(ft.cam, ft.vert, tgt))
    assert finite(r) and r.notes == {"flow_targets_nonfinite": 7}
    tgt[:] = float("nan")
    r = fit.fit_frame(rig, views, frames[1][0], Gs[0], cfg, flow=fit.FlowTargets(ft.cam, ft.vert, tgt))
    assert finite(r) and r.terms["flow"] == 0.0 and r.notes["flow_targets_nonfinite"] == ft.cam.numel()


def test_a_sequence_through_a_blind_frame_recovers():
    """Frame 1 with every mask empty keeps frame 0's pose (noted, not converged); frame 2 is fitted again
    from there (its loss falls)."""
    rig, views = toy(C=4, H=48, W=48)
    _, Gs, frames = moving(rig, views, 3, seed=8, rot=0.01, trans=0.004)

    def cues_of(t):
        c = frames[t][0]
        return c._replace(mask=torch.zeros_like(c.mask)) if t == 1 else c

    res = fit.fit_sequence(fit.FitPlan(config(PAPER, **CFG), rig, views, 3, Gs[0]), cues_of, lambda t: None,
                           progress=False)
    assert all(finite(r) for r in res)
    assert res[1].notes["no_mask"] and not res[1].converged and torch.equal(res[1].transforms, res[0].transforms)
    assert res[2].iterations > 0 and res[2].loss < res[2].curve[0] and res[2].notes == {"no_flow": True}
