"""anidress_core.fit.images and L_anchor's references (update_anchor, texture_anchor)."""
from __future__ import annotations

import math

import pytest
import torch

from anidress_core import fit, raster
from anidress_core.fit.images import CHROMA_EPS
from tests.fit.scenes import config, render, toy

torch.set_num_threads(1)


def test_image_features_derivatives_are_exact_on_a_linear_image():
    """The derivative channels of image_features (L_anchor's Gauss-Newton Jacobian) are exact on a
    linear image; a Gaussian keeps a linear image."""
    C, H, W = 4, 64, 64
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    lin = torch.stack([0.01 * xx, 0.02 * yy, 0.005 * xx + 0.01 * yy], -1)  # (H, W, 3)
    feat = fit.image_features(lin[None].expand(C, -1, -1, -1), blur=0.0)
    torch.testing.assert_close(feat[:, 3:6], torch.tensor([0.01, 0.0, 0.005], dtype=torch.float64)[None, :, None, None]
                               .expand(C, 3, H, W))
    torch.testing.assert_close(feat[:, 6:9], torch.tensor([0.0, 0.02, 0.01], dtype=torch.float64)[None, :, None, None]
                               .expand(C, 3, H, W))
    blurred = fit.image_features(lin[None], blur=1.0)[0, :3, 8:-8, 8:-8]
    torch.testing.assert_close(blurred, lin.permute(2, 0, 1)[:, 8:-8, 8:-8])


def test_sample_blurred_matches_filtering_the_whole_image():
    """sample_blurred (the stencil at the points only, used by update_anchor) equals the
    reference: blur the whole image (blurred), then sample it bilinearly (sample) -- inside,
    on and beyond the border, and with a NaN pixel."""
    g = torch.Generator().manual_seed(21)
    C, H, W = 3, 17, 23
    img = torch.rand(C, H, W, 3, generator=g, dtype=torch.float64)
    img[1, 4, 5, 0] = float("nan")
    uv = torch.rand(C, 40, 2, generator=g, dtype=torch.float64) * torch.tensor([W + 3.0, H + 3.0]) - 1.5
    uv[0, :3] = torch.tensor([[W - 1.0, H - 1.0], [0.0, 0.0], [W - 1.0, 3.5]], dtype=torch.float64)
    cam = torch.arange(C).repeat_interleave(uv.shape[1])
    for blur in (0.0, 0.5, 1.3):
        ref = fit.sample(fit.blurred(img, blur), uv)  # (C, V, 3)
        got = fit.sample_blurred(img, cam, uv.reshape(-1, 2), blur).view(C, -1, 3)
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)


def test_update_anchor_gives_first_seen_references_and_keeps_them():
    C, H, W = 4, 64, 64
    rig, views = toy(C=C, H=H, W=W, n_theta=40, n_h=12)
    G = torch.eye(4, dtype=torch.float64).expand(rig.weights.shape[1], 4, 4).clone()
    cues, x, fr = render(rig, views, G)
    cfg = config(image_blur=0.0)
    flat = torch.tensor([0.6, 0.3, 0.1], dtype=torch.float64).expand(C, H, W, 3)
    a = fit.update_anchor(None, x, views, fr, flat, cues.mask, cfg)
    vis = raster.visible_vertices(x, views.K, views.world_to_cam, fr, cfg.visibility_depth_tol).any(0)
    assert 0 < int(a.seen.sum()) <= int(vis.sum()) and not bool((a.seen & ~vis).any())
    torch.testing.assert_close(a.chroma[a.seen], (flat[0, 0, 0] / (1.0 + CHROMA_EPS)).expand(int(a.seen.sum()), 3))
    # a later frame: the seen vertices keep their reference, newly seen ones get this frame's
    b = fit.update_anchor(a._replace(seen=a.seen & (torch.arange(a.seen.numel()) % 2 == 0)), x, views, fr,
                          flat.flip(-1), cues.mask, cfg)
    even = torch.arange(a.seen.numel()) % 2 == 0
    torch.testing.assert_close(b.chroma[a.seen & even], a.chroma[a.seen & even])
    torch.testing.assert_close(b.chroma[a.seen & ~even], (flat[0, 0, 0].flip(-1) / (1.0 + CHROMA_EPS))
                               .expand(int((a.seen & ~even).sum()), 3))
    assert torch.equal(b.seen, a.seen)


def test_texture_anchor_samples_the_blurred_texture_chromaticity_at_the_uvs():
    """texture_anchor: each vertex's reference is the chromaticity of the (blurred) texture at the
    UV of its first face corner; with no blur, a texel-centre UV reads that texel exactly."""
    g = torch.Generator().manual_seed(4)
    tex = torch.rand(16, 20, 3, generator=g, dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [2, 1, 3]])
    rows, cols = torch.tensor([3, 7, 12, 0]), torch.tensor([5, 19, 2, 11])
    uv_v = torch.stack([(cols + 0.5) / 20, 1 - (rows + 0.5) / 16], -1).double()  # texel centres (OBJ v up)
    face_uv = uv_v[faces].clone()
    face_uv[1, 0] = torch.tensor([0.9, 0.9])  # vertex 2 on a "seam": its first face's UV counts
    ref = fit.texture_anchor(faces, face_uv, tex, 0.0)
    assert ref.seen.all() and ref.chroma.shape == (4, 3)
    torch.testing.assert_close(ref.chroma, fit.chromaticity(tex[rows, cols]))
    flat = fit.texture_anchor(faces, face_uv, torch.full((16, 20, 3), 0.4, dtype=torch.float64), 2.0)
    torch.testing.assert_close(flat.chroma, torch.full((4, 3), 0.4 / 1.25, dtype=torch.float64))
    blur = fit.texture_anchor(faces, face_uv, tex, 2.0)
    assert float(blur.chroma.std()) < float(ref.chroma.std())
    with pytest.raises(ValueError):
        fit.texture_anchor(faces, face_uv[:, :2], tex, 1.0)
    with pytest.raises(ValueError, match="no face"):  # a fifth vertex that no face uses
        fit.texture_anchor(faces, face_uv, tex, 1.0, num_vertices=5)


def test_texture_anchor_equals_blurring_the_whole_texture():
    """texture_anchor blurs only around the V sample points: the same references as blurring the whole
    texture and sampling it (raster.sample_texture, clamped border), UVs at the borders included."""
    g = torch.Generator().manual_seed(5)
    tex = torch.rand(24, 30, 3, generator=g, dtype=torch.float64)
    V = 40
    faces = torch.arange(V).view(-1, 4)[:, :3].reshape(-1, 3)
    faces = torch.cat([faces, torch.arange(V).view(-1, 4)[:, 1:]])  # every vertex in a face
    uv_v = torch.rand(V, 2, generator=g, dtype=torch.float64) * 1.1 - 0.05  # some outside [0, 1]
    uv_v[:4] = torch.tensor([[0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0]], dtype=torch.float64)
    face_uv = uv_v[faces]
    for blur in (0.0, 0.7, 2.5):
        ref = fit.texture_anchor(faces, face_uv, tex, blur, num_vertices=V)
        whole = fit.blurred(fit.chromaticity(tex)[None], blur)[0].permute(1, 2, 0)
        torch.testing.assert_close(ref.chroma, raster.sample_texture(whole, uv_v), rtol=0, atol=1e-12)


def test_texture_blur_matches_the_pixel_footprint():
    """A unit square textured over the whole texture, seen head-on from 2 m with focal 100 px:
    one pixel covers 2 cm = 0.02 * 512 texels; times sqrt(1/12 + blur^2)."""
    rest = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    face_uv = rest[:, :2][faces]
    K = torch.tensor([[[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]], dtype=torch.float64)
    E = torch.eye(4, dtype=torch.float64)[None].clone()
    E[0, 2, 3] = 2.0
    views = fit.Views(K, E, 100, 100)
    b = fit.texture_blur_texels(rest, faces, face_uv, (512, 512), rest, views, 0.5)
    assert abs(b - math.sqrt(1 / 12 + 0.25) * 0.02 * 512) < 1e-9
