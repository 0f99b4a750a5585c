"""Synthetic scene machinery: textures, rendering, and the exactness of ground-truth flow."""
import cv2
import numpy as np
import pytest
import torch

from anidress_core import synth
from anidress_core.config import default_schema_path, validate_config
from anidress_core.stages.synth import build_scene, split_cameras

import yaml


def tiny_scene_cfg(**over):
    scene = {
        "image_size": [96, 96],
        "cameras": {"count": 12, "train": 8},
        "body": {"vertices": 6500},
        "sequences": [{"name": "walk", "motion": "walk", "frames": 30}, {"name": "dance", "motion": "dance", "frames": 4, "role": "novel_pose"}],
        "render": {"texture_size": 256, "noise_std": 0.0},
    }
    scene.update(over)
    cfg = validate_config({"run_scenes": ["t"], "scenes": {"t": scene}}, yaml.safe_load(default_schema_path().read_text()))
    return cfg["scenes"]["t"]


@pytest.fixture(scope="module")
def assets():
    return build_scene(tiny_scene_cfg())


def test_split_cameras_spreads_training_views():
    tr, te = split_cameras(12, 8)
    assert len(tr) == 8 and len(te) == 4 and not set(tr) & set(te)
    gaps = np.diff(sorted(te))
    assert gaps.min() >= 2  # test cameras are not neighbours


@pytest.mark.parametrize("material", synth.MATERIALS)
def test_material_textures_have_detail(material):
    tex = synth.material_texture(material, 128, seed=3)
    assert tex.shape == (128, 128, 3) and tex.dtype == np.float32
    assert 0 <= tex.min() and tex.max() <= 1
    # texture detail: local gradients are not flat (flow and appearance need them)
    grad = np.abs(np.diff(tex.mean(-1), axis=1)).mean()
    assert grad > 1e-3
    assert np.array_equal(tex, synth.material_texture(material, 128, seed=3))  # deterministic


def test_plain_fabric_is_one_colour_with_a_faint_weave():
    """material 'plain' (issue 23: most real skirts are one colour): the chromaticity is the same on
    every texel (what L_anchor reads carries no placement), the brightness varies by a few percent
    (a weave that flow can still see up close); a printed fabric differs by orders of magnitude.
    The scene config selects it (scenes/<scene>/garment/texture) and build_scene uses it."""
    def chroma_spread(tex):
        c = tex.astype(np.float64) / tex.astype(np.float64).sum(-1, keepdims=True)
        return float(c.reshape(-1, 3).std(0).max())

    tex = synth.material_texture("plain", 256, seed=5)
    lum = tex.mean(-1)
    assert chroma_spread(tex) < 1e-5  # measured ~1e-8 (float32 rounding)
    assert 0.005 < float(lum.std() / lum.mean()) < 0.05
    assert chroma_spread(synth.material_texture("floral", 256, seed=5)) > 0.02
    assert chroma_spread(synth.material_texture("plaid", 256, seed=5)) > 100 * chroma_spread(tex)
    cfg = tiny_scene_cfg(kind="skirt", seed=5, garment={"texture": "plain", "vertices": 300},
                         sequences=[{"name": "walk", "motion": "walk", "frames": 2}])
    assert cfg["garment"]["texture"] == "plain"
    a = build_scene(cfg)
    assert np.array_equal(a.garment_texture, synth.material_texture("plain", 256, seed=5 + 17))


def _frame(assets, seq, t):
    m = assets.motions[seq]
    posed = assets.body.pose(torch.as_tensor(m.poses[t : t + 1]), torch.as_tensor(m.Rh[t : t + 1]),
                             torch.as_tensor(m.Th[t : t + 1]), torch.as_tensor(m.shapes))
    verts = posed.vertices[0].float()
    layer = synth.MeshLayer(verts, assets.body.faces, assets.body.face_uv.float(),
                            torch.from_numpy(assets.body_texture), synth.LABEL_BODY)
    return verts, synth.render_views([layer], assets.cameras, assets.lights, assets.background, supersample=2)


def test_render_labels_normals_and_background(assets):
    _, out = _frame(assets, "walk", 1)
    C, H, W = out.labels.shape
    assert (C, H, W) == (12, 96, 96)
    body = out.labels == 1
    frac = body.float().mean().item()
    assert 0.03 < frac < 0.6  # the performer is in view and not filling it
    n = out.normals_cam[body]
    assert torch.allclose(n.norm(dim=-1), torch.ones(n.shape[0]), atol=1e-4)
    rays = synth.raster_view_dirs(assets.cameras.K.float(), H, W)[body]
    assert ((n * rays).sum(-1) <= 1e-6).all()  # visible normals face the camera
    # away from the silhouette (anti-aliased by supersampling) the background plate shows unchanged
    near = torch.nn.functional.max_pool2d(body[:, None].float(), 3, stride=1, padding=1)[:, 0] > 0
    far = ~near
    assert torch.allclose(out.rgb[far], assets.background[far].to(out.rgb.dtype), atol=1e-6)


def test_ground_truth_flow_warps_previous_frame_onto_next(assets):
    """Warping frame t by the GT flow reproduces frame t-1 on visible, non-occluded pixels."""
    errs, checked, zero_errs = [], [], []
    for t in (12, 18, 24):  # mid-motion (motions ease in from rest)
        _, prev = _frame(assets, "walk", t - 1)
        verts_t, cur = _frame(assets, "walk", t)
        gt = synth.forward_flow(prev.fragments, verts_t, assets.body.faces, assets.cameras, cur.depth)
        for c in range(len(assets.cameras)):
            img0 = prev.rgb[c].numpy().astype(np.float32)
            img1 = cur.rgb[c].numpy().astype(np.float32)
            flow = gt.flow[c].numpy().astype(np.float32)
            H, W = flow.shape[:2]
            xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
            warped = cv2.remap(img1, xs + flow[..., 0], ys + flow[..., 1], cv2.INTER_LINEAR)
            # subject pixels visible in both frames, away from silhouettes (bilinear mixes there)
            body0 = (prev.labels[c].numpy() > 0).astype(np.uint8)
            interior = cv2.erode(body0, np.ones((3, 3), np.uint8)) > 0
            sel = interior & gt.valid[c].numpy()
            moving = sel & (np.linalg.norm(flow, axis=-1) > 0.25)
            if moving.sum() == 0:
                continue
            errs.append(np.abs(warped - img0)[moving].mean())
            zero_errs.append(np.abs(img1 - img0)[moving].mean())
            checked.append(moving.sum() / max(interior.sum(), 1))
    err, zero_err, frac = float(np.mean(errs)), float(np.mean(zero_errs)), float(np.mean(checked))
    print(f"photometric error with GT flow {err:.4f}, without flow {zero_err:.4f}, fraction of body pixels checked {frac:.2f}")
    assert frac > 0.3
    assert err < 0.02
    assert err < 0.5 * zero_err  # the flow explains the motion


def test_occlusion_is_detected():
    """A plane sliding behind a fixed occluder: pixels it moves under are marked invalid."""
    from anidress_core.camera import ring_cameras

    cams = ring_cameras(n=1, radius=3.0, height=0.0, target=(0.0, 0.0, 0.0), focal_px=60.0, image_height=48, image_width=48)
    # camera at (3,0,0) looking at the origin along -x; back plane at x=-1, occluder at x=1
    def quad(x, y0, y1, z0, z1):
        v = torch.tensor([[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1]], dtype=torch.float32)
        return v, torch.tensor([[0, 1, 2], [0, 2, 3]])
    vb, fb = quad(-1.0, -1.0, 1.0, -1.0, 1.0)
    vo, fo = quad(1.0, -0.1, 0.1, -1.0, 1.0)
    verts0 = torch.cat([vb, vo]); faces = torch.cat([fb, fo + 4])
    verts1 = verts0.clone(); verts1[:4, 1] += 0.3  # back plane slides sideways
    from anidress_core import raster
    f0 = raster.rasterize(verts0, faces, cams.K, cams.world_to_cam, 48, 48)
    f1 = raster.rasterize(verts1, faces, cams.K, cams.world_to_cam, 48, 48)
    gt = synth.forward_flow(f0, verts1, faces, cams, f1.depth)
    back = (f0.face_id[0] >= 0) & (f0.face_id[0] < 2)
    assert (~gt.valid[0][back]).any()  # some back-plane points slide behind the occluder
    assert gt.valid[0][back].float().mean() > 0.5
    occl = (f0.face_id[0] >= 2)
    assert gt.flow[0][occl].abs().max() < 1e-3  # static occluder: zero flow


def test_degraded_normals_lose_detail_but_keep_orientation():
    gen = torch.Generator().manual_seed(0)
    H = W = 32
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    # a wrinkled surface: normals tilting with a 4-pixel period, facing the camera (-z)
    tilt = 0.5 * torch.sin(2 * np.pi * xs / 4.0)
    n = torch.stack([tilt, torch.zeros_like(tilt), -torch.ones_like(tilt)], -1)
    n = (n / n.norm(dim=-1, keepdim=True))[None].float()
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    mask[:, 4:28, 4:28] = True
    out = synth.degrade_normals(n * mask[..., None], mask, blur_px=2.0, noise_std=0.05, generator=gen)
    assert torch.isfinite(out).all() and (out[~mask] == 0).all()
    assert torch.allclose(out[mask].norm(dim=-1), torch.ones(int(mask.sum())), atol=1e-5)
    assert out[mask][:, 0].std() < 0.5 * n[mask][:, 0].std()  # wrinkles blurred away
    assert (out[mask][:, 2] < -0.8).all()  # still facing the camera
