"""Mask estimation: foreground by background plates, garment vs body, clean-up."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from anidress_core import synth
from anidress_core.cues import evaluate as ce
from anidress_core.cues import masks as cm
from anidress_core.geometry import lbs

from .conftest import scene_cfg


@pytest.fixture(scope="module")
def clean_frame():
    """A noise-free frame of a skirt scene (6 cameras, 192x192) whose true skirt is flared
    away from the skinned template, so the prior is imperfect (as a real skirt swings)."""
    from anidress_core.stages.synth import build_scene

    torch.manual_seed(0)
    cfg = scene_cfg(kind="skirt", image_size=[192, 192], cameras={"count": 6, "train": 4}, body={"vertices": 2000},
                    sequences=[{"name": "walk", "motion": "walk", "frames": 12}], garment={"vertices": 800},
                    render={"texture_size": 256, "noise_std": 0.0})
    a = build_scene(cfg)
    m, t = a.motions["walk"], 8
    posed = a.body.pose(m.poses[t : t + 1], m.Rh[t : t + 1], m.Th[t : t + 1], m.shapes)
    body_v, A = posed.vertices[0].float(), posed.transforms[0].float()
    g = a.garment
    g_faces = torch.from_numpy(g.faces)
    skinned = lbs(torch.from_numpy(g.verts).float(), torch.from_numpy(g.body_weights).float(), A)
    # true skirt: flared radially about the pelvis' vertical axis, more towards the hem
    root = posed.joints[0, 0].float()
    depth = (skinned[:, 2].max() - skinned[:, 2]).clamp_min(0)
    depth = depth / depth.max()
    true_v = skinned.clone()
    true_v[:, :2] = root[:2] + (skinned[:, :2] - root[:2]) * (1 + 0.25 * depth[:, None])
    layers = [synth.MeshLayer(body_v, a.body.faces, a.body.face_uv.float(), torch.from_numpy(a.body_texture), 1),
              synth.MeshLayer(true_v, g_faces, torch.from_numpy(g.face_uv).float(),
                              torch.from_numpy(a.garment_texture), 2)]
    out = synth.render_views(layers, a.cameras, a.lights, a.background, supersample=2)
    cams = a.cameras
    prior = cm.render_prior(body_v, a.body.faces, skinned, g_faces, cams.K, cams.world_to_cam, cams.height,
                            cams.width).numpy()
    return {"images": out.rgb.numpy(), "plates": a.background.numpy(), "labels": out.labels.numpy(),
            "prior": prior, "ncam": len(cams)}


def _ious(pred, gt):
    e = ce.CueErrors()
    e.add_masks(pred, gt)
    s = e.summary()
    return s["iou_subject"], s["iou_body"], s["iou_garment"]


@pytest.mark.parametrize("method", cm.MASK_METHODS)
def test_mask_estimation_iou_on_a_clean_frame(clean_frame, method):
    f = clean_frame
    p = cm.MaskParams(method=method)
    cam = np.arange(f["ncam"])
    fg = cm.refine_boundary(f["images"], f["plates"],
                            cm.foreground(cm.colour_distance(f["images"], f["plates"], p.blur_px), p), p.refine_px)
    model = cm.fit_colour_model(f["images"], cam, fg, f["prior"], f["ncam"], p)
    lab = cm.estimate_masks(f["images"], f["plates"], f["prior"], p, cam, model)
    assert lab.dtype == np.uint8 and lab.shape == f["labels"].shape and set(np.unique(lab)) <= {0, 1, 2}
    sub, body, gar = _ious(lab, f["labels"])
    prior_sub, prior_body, prior_gar = _ious(f["prior"], f["labels"])
    print(f"{method}: IoU subject {sub:.4f} body {body:.4f} garment {gar:.4f}; "
          f"prior alone {prior_sub:.4f} {prior_body:.4f} {prior_gar:.4f}")
    assert sub > 0.95
    if method != "grabcut":
        assert gar > 0.95
        assert gar > prior_gar  # the images correct the misplaced prior


def test_foreground_matches_the_truth_and_boundary_refinement_helps(clean_frame):
    f = clean_frame
    p = cm.MaskParams()
    fg = cm.foreground(cm.colour_distance(f["images"], f["plates"], p.blur_px), p)
    ref = cm.refine_boundary(f["images"], f["plates"], fg, 1)
    gt = f["labels"] > 0
    iou = lambda m: (m & gt).sum() / (m | gt).sum()  # noqa: E731
    assert iou(ref) > 0.95 and iou(ref) > iou(fg)


def test_foreground_hysteresis_and_specks():
    d = np.zeros((1, 40, 40), np.float32)
    d[0, 10:30, 10:20] = 0.5  # sure subject
    d[0, 10:30, 20:25] = 0.05  # weak, touching it: kept
    d[0, 2:4, 30:38] = 0.05  # weak, isolated: dropped
    d[0, 35, 35] = 0.9  # a one-pixel speck: opened away
    fg = cm.foreground(d, cm.MaskParams())
    assert fg[0, 11:29, 11:24].all() and fg.sum() <= 20 * 15  # (opening rounds the corners)
    assert not fg[0, 2:4, 30:38].any() and not fg[0, 35, 35]


def test_empty_frame_gives_background_only():
    img = np.full((2, 32, 32, 3), 0.4, np.float32)
    prior = np.zeros((2, 32, 32), np.uint8)
    for method in cm.MASK_METHODS:
        p = cm.MaskParams(method=method)
        model = cm.fit_colour_model(img, np.arange(2), np.zeros((2, 32, 32), bool), prior, 2, p)
        lab = cm.estimate_masks(img, img, prior, p, np.arange(2), model)
        assert not lab.any()


def test_prior_labels_and_distances():
    prior = np.zeros((1, 20, 20), np.uint8)
    prior[0, 2:8, 2:18] = 1
    prior[0, 8:16, 2:18] = 2
    fg = np.zeros((1, 20, 20), bool)
    fg[0, 1:19, 1:19] = True
    lab = cm.label_prior(fg, prior)
    assert (lab[0, 1, 5], lab[0, 18, 5], lab[0, 0, 0]) == (1, 2, 0)
    dg, db = cm.prior_distances(prior)
    assert dg[0, 10, 10] == 0 and db[0, 4, 4] == 0 and dg[0, 4, 4] > 0


def test_colour_model_separates_colours():
    rng = np.random.default_rng(0)
    img = np.zeros((1, 30, 30, 3), np.float32)
    img[0, :, :15] = [0.9, 0.1, 0.1] + 0.02 * rng.standard_normal((30, 15, 3))
    img[0, :, 15:] = [0.1, 0.2, 0.9] + 0.02 * rng.standard_normal((30, 15, 3))
    prior = np.ones((1, 30, 30), np.uint8)
    prior[0, :, 15:] = 2
    fg = np.ones((1, 30, 30), bool)
    p = cm.MaskParams(confident_px=2, hist_bins=16)  # few samples: coarser bins
    model = cm.fit_colour_model(img, np.zeros(1, int), fg, prior, 1, p)
    lr = cm.colour_log_ratio(img, np.zeros(1, int), model, p.hist_bins)
    assert (lr[0, :, :12] < -1).all() and (lr[0, :, 18:] > 1).all()


def test_clean_labels_flips_enclosed_islands_only():
    lab = np.ones((1, 30, 30), np.uint8)
    lab[0, 10:12, 10:12] = 2  # a 4-pixel garment island inside the body: becomes body
    lab[0, :, 25:] = 0
    lab[0, :4, :] = 0
    lab[0, 4:6, 22:25] = 2  # a small garment piece in the silhouette's corner, mostly next to background
    out = cm.clean_labels(lab, 12)
    assert (out[0, 10:12, 10:12] == 1).all()
    assert (out[0, 4:6, 22:25] == 2).all()
    assert (cm.clean_labels(lab, 0) == lab).all()


def test_params_are_validated():
    with pytest.raises(ValueError, match="method"):
        cm.MaskParams(method="schp")
    with pytest.raises(ValueError, match="fg_threshold_low"):
        cm.MaskParams(fg_threshold=0.02, fg_threshold_low=0.05)


def test_temporal_median_plate_recovers_the_background():
    rng = np.random.default_rng(1)
    bg = rng.random((24, 32, 3)).astype(np.float32)
    frames = np.repeat(bg[None], 5, 0)
    for t in range(5):  # a square moving across: each pixel is covered in at most 2 of 5 frames
        frames[t, 8:16, 6 * t : 6 * t + 8] = 0.5
    assert np.array_equal(cm.temporal_median_plate(frames), bg)
    with pytest.raises(ValueError, match="T, H, W, 3"):
        cm.temporal_median_plate(bg)
