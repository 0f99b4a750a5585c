"""Optical flow: known translations/rotations recovered below a pixel; region logic."""
import cv2
import numpy as np
import pytest

from anidress_core.cues import flow as cf
from anidress_core.synth import material_texture


def _textured(size: int = 160, seed: int = 3) -> np.ndarray:
    tex = material_texture("floral", 256, seed)  # (256, 256, 3) float in [0, 1], fine detail
    return cv2.resize(tex, (size, size), interpolation=cv2.INTER_AREA)


def _warp(img: np.ndarray, A: np.ndarray) -> np.ndarray:
    """img1 with img1(A p) = img0(p) for the 2x3 affine map A (pixel centres at integers)."""
    H, W = img.shape[:2]
    return cv2.warpAffine(img, A, (W, H), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def _true_flow(A: np.ndarray, H: int, W: int) -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    p = np.stack([xs, ys, np.ones_like(xs)], -1)
    return (p @ A.T - p[..., :2]).astype(np.float32)


CASES = {
    "translation": np.array([[1.0, 0.0, 2.6], [0.0, 1.0, -1.7]]),
    "rotation": cv2.getRotationMatrix2D((79.5, 79.5), 4.0, 1.0),
}


@pytest.mark.parametrize("method", cf.FLOW_METHODS)
@pytest.mark.parametrize("case", sorted(CASES))
def test_known_motion_recovered_below_a_pixel(method, case):
    img0 = _textured()
    A = CASES[case]
    img1 = _warp(img0, A)
    H, W = img0.shape[:2]
    res = cf.estimate_flow(img0, img1, method)
    gt = _true_flow(A, H, W)
    interior = np.zeros((H, W), bool)
    interior[16:-16, 16:-16] = True  # away from the border (pixels leave the image there)
    epe = np.linalg.norm(res.flow - gt, axis=-1)[interior].mean()
    print(f"{method} {case}: EPE {epe:.3f} px (motion {np.linalg.norm(gt, axis=-1)[interior].mean():.2f} px)")
    assert res.valid.all() and res.region == cf.Region(0, H, 0, W)
    assert epe < 1.0


def test_region_restricts_processing_and_marks_valid():
    img0 = _textured()
    A = CASES["translation"]
    img1 = _warp(img0, A)
    region = cf.Region(40, 120, 30, 110)
    res = cf.estimate_flow(img0, img1, "dis_medium", region)
    assert res.valid[40:120, 30:110].all() and res.valid.sum() == 80 * 80
    assert np.all(res.flow[~res.valid] == 0)
    inner = np.linalg.norm(res.flow - _true_flow(A, 160, 160), axis=-1)[56:104, 46:94]
    assert inner.mean() < 1.0


def test_flow_region_box_margin_and_clamp():
    m0 = np.zeros((100, 120), np.uint8)
    m1 = np.zeros_like(m0)
    m0[30:50, 40:60] = 1
    m1[45:70, 55:80] = 2
    r = cf.flow_region(m0, m1, margin=5)
    assert r == cf.Region(25, 75, 35, 85)
    # clamped at the image border
    m0[:] = 0
    m0[0:10, 110:120] = 1
    assert cf.flow_region(m0, np.zeros_like(m0), margin=8, min_size=0) == cf.Region(0, 18, 102, 120)
    # grows to the minimum size about the centre, inside the image
    tiny = np.zeros((100, 120), np.uint8)
    tiny[98:100, 0:2] = 1
    r = cf.flow_region(tiny, tiny, margin=0, min_size=32)
    assert r == cf.Region(68, 100, 0, 32)
    assert cf.flow_region(np.zeros_like(tiny), np.zeros_like(tiny), 4) is None


def test_bad_inputs_raise():
    img = _textured(64)
    with pytest.raises(ValueError, match="unknown flow method"):
        cf.estimate_flow(img, img, "raft")
    with pytest.raises(ValueError, match="outside"):
        cf.estimate_flow(img, img, "dis_fast", cf.Region(0, 80, 0, 10))
    with pytest.raises(ValueError, match="must match"):
        cf.estimate_flow(img, _textured(48), "dis_fast")


def test_lk_refinement_restores_an_under_estimated_motion():
    img0 = _textured()
    A = CASES["rotation"]  # the motion varies over the image
    img1 = _warp(img0, A)
    H, W = img0.shape[:2]
    gt = _true_flow(A, H, W)
    where = np.zeros((H, W), bool)
    where[32:128, 32:128] = True
    start = 0.8 * gt  # what a smoothing estimator gives where the motion peaks (a hem)
    out, n = cf.refine_lk(img0, img1, start, where)
    e0 = np.linalg.norm(start - gt, axis=-1)[where].mean()
    e1 = np.linalg.norm(out - gt, axis=-1)[where].mean()
    print(f"LK refinement: EPE {e0:.3f} -> {e1:.3f} px, {n} of {where.sum()} pixels")
    # window 7: the bias goes; what remains is the small window's noise (on this smooth texture
    # DIS alone is at 0.08 px on the true motion -- the trade-off of refine_lk's docstring)
    assert n > 0.9 * where.sum() and e1 < 0.25 and e1 < 0.5 * e0
    assert (out[~where] == start[~where]).all()  # only the pixels asked for


def test_lk_refinement_keeps_the_start_where_it_cannot_track():
    flat = np.full((48, 48), 128, np.uint8)  # no texture: nothing to track
    start = np.full((48, 48, 2), 0.5, np.float32)
    out, n = cf.refine_lk(flat, flat, start, np.ones((48, 48), bool))
    assert n == 0 and (out == start).all()
    img0 = _textured()
    img1 = _warp(img0, CASES["translation"])
    H, W = img0.shape[:2]
    start = _true_flow(CASES["translation"], H, W) + 3.0  # far off: LK wanders or finds the truth 3 px away
    out, n = cf.refine_lk(img0, img1, start, np.ones((H, W), bool), max_change=1.0)
    assert np.abs(out - start).max() <= 1.0 + 1e-5  # any move further than max_change is rejected
    with pytest.raises(ValueError, match="odd"):
        cf.refine_lk(img0, img1, start, np.ones((H, W), bool), window=8)
    with pytest.raises(ValueError, match="must be"):
        cf.refine_lk(img0, img1, start[:10], np.ones((H, W), bool))


def test_initial_flow_turns_an_aliased_motion_into_a_residual():
    """A periodic texture moved by most of its period: from scratch the estimators alias; started
    near the truth (as by the body/garment prior) they recover it."""
    H = W = 128
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    period = 8.0
    pattern = lambda x, y: 0.5 + 0.25 * np.sin(2 * np.pi * x / period) + 0.15 * np.sin(2 * np.pi * y / 23.0)  # noqa: E731
    shift = 6.0  # 3/4 of the period: the nearest match is -2 px
    img0 = np.repeat(pattern(xs, ys)[..., None], 3, -1)
    img1 = np.repeat(pattern(xs - shift, ys)[..., None], 3, -1)  # img1(x + shift) = img0(x)
    interior = (slice(16, -16), slice(16, -16))
    truth = np.zeros((H, W, 2), np.float32)
    truth[..., 0] = shift
    plain = cf.estimate_flow(img0, img1, "dis_medium")
    init = truth + np.float32([1.2, -0.8])  # a prior off by about a pixel and a half
    guided = cf.estimate_flow(img0, img1, "dis_medium", init=init)
    e_plain = np.linalg.norm(plain.flow - truth, axis=-1)[interior].mean()
    e_guided = np.linalg.norm(guided.flow - truth, axis=-1)[interior].mean()
    print(f"aliased shift: EPE {e_plain:.2f} px from scratch, {e_guided:.2f} px from the prior")
    assert e_plain > 1.5 and e_guided < 0.5
    with pytest.raises(ValueError, match="init must be"):
        cf.estimate_flow(img0, img1, "dis_fast", init=truth[:10])


def test_mesh_flow_matches_the_ground_truth_flow_of_the_synthetic_scenes():
    """mesh_flow against synth.forward_flow (the scenes' exact flow) on a moving sphere."""
    import torch
    import trimesh

    from anidress_core import raster, synth
    from anidress_core.camera import ring_cameras

    m = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    v0 = torch.tensor(m.vertices, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    faces = torch.tensor(m.faces)
    # rotate about z and translate: every pixel moves differently
    a = 0.08
    Rz = torch.tensor([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], dtype=torch.float64)
    v1 = (v0 - v0.mean(0)) @ Rz.T + v0.mean(0) + torch.tensor([0.03, -0.02, 0.01], dtype=torch.float64)
    cams = ring_cameras(n=3, radius=3.0, height=1.0, target=(0.0, 0.0, 1.0), focal_px=90.0, image_height=64,
                        image_width=64).to(dtype=torch.float64)
    frags = raster.rasterize(v0, faces, cams.K, cams.world_to_cam, 64, 64)
    ours = cf.mesh_flow(frags.face_id, frags.bary, v1, faces, cams.K, cams.world_to_cam)
    depth1 = raster.rasterize(v1, faces, cams.K, cams.world_to_cam, 64, 64).depth
    ref = synth.forward_flow(frags, v1, faces, cams, depth1)
    hit = frags.face_id >= 0
    assert hit.sum() > 500
    assert torch.allclose(ours[hit], ref.flow[hit], atol=1e-6)
    assert (ours[~hit] == 0).all()


def test_extend_flow_fills_near_the_covered_region_only():
    f = np.zeros((40, 40, 2), np.float32)
    cov = np.zeros((40, 40), bool)
    cov[10:20, 10:20] = True
    f[cov] = [2.0, -1.0]
    ext = cf.extend_flow(f, cov, sigma_px=3.0)
    assert np.allclose(ext[cov], [2.0, -1.0])
    assert np.allclose(ext[15, 22], [2.0, -1.0], atol=1e-5)  # just outside: the neighbours' value
    assert (ext[39, 39] == 0).all()  # far away: nothing
    assert not cf.extend_flow(f, np.zeros_like(cov)).any()
