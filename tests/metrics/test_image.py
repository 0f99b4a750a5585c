"""Image metrics: PSNR / SSIM against slow references, IoU, subject box, and LPIPS / DISTS
loading (weights the test writes in the real file formats; unavailable without them)."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from anidress_core.metrics import image as M


def _imgs(seed=0, H=24, W=20):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(H, W, 3, generator=g)
    b = (a + 0.1 * torch.randn(H, W, 3, generator=g)).clamp(0, 1)
    return a, b


def test_psnr_matches_definition_inside_a_mask():
    a, b = _imgs()
    m = torch.zeros(24, 20, dtype=torch.bool)
    m[3:10, 4:15] = True
    an, bn, mn = a.numpy().astype(np.float64), b.numpy().astype(np.float64), m.numpy()
    ref = 10 * np.log10(1.0 / np.mean((an[mn] - bn[mn]) ** 2))
    assert M.psnr(a, b, m) == pytest.approx(ref, rel=1e-9)
    assert M.psnr(a, a) == math.inf
    assert math.isnan(M.psnr(a, b, torch.zeros_like(m)))
    with pytest.raises(ValueError):
        M.psnr(a, b[:5])


def test_ssim_matches_skimage():
    from skimage.metrics import structural_similarity

    a, b = _imgs(1, 40, 33)
    ref = structural_similarity(a.numpy().astype(np.float64), b.numpy().astype(np.float64), channel_axis=-1,
                                gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0)
    assert M.ssim(a, b) == pytest.approx(ref, abs=1e-6)
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-9)
    assert math.isnan(M.ssim(a[:5, :5], b[:5, :5]))


def test_iou():
    alpha = torch.zeros(4, 4)
    alpha[:2] = 0.9
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[1:3] = True
    assert M.iou(alpha, mask) == pytest.approx(4 / 12)
    assert M.iou(torch.zeros(3, 3), torch.zeros(3, 3, dtype=torch.bool)) == 1.0


def test_subject_box_mask_covers_the_projected_points():
    from anidress_core.camera import ring_cameras

    cams = ring_cameras(1, 3.0, 1.0, (0.0, 0.0, 1.0), focal_px=60, image_height=64, image_width=64)
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(50, 3, generator=g) * torch.tensor([0.4, 0.4, 1.2]) + torch.tensor([-0.2, -0.2, 0.3])
    m = M.subject_box_mask(pts, cams.K[0], cams.world_to_cam[0], 64, 64, pad_m=0.05)
    Xc = pts @ cams.R[0].T + cams.T[0]
    uv = (Xc @ cams.K[0].T)[:, :2] / Xc[:, 2:]
    px = uv.round().long()
    assert m[px[:, 1], px[:, 0]].all()
    assert 0.05 < m.float().mean() < 0.8
    y0, y1, x0, x1 = M.box_rect(m)
    assert m[y0:y1, x0:x1].sum() == m.sum()


# --------------------------------------------------------------------------- LPIPS / DISTS


def _backbone_file(tmp_path, net: str, seed: int = 0):
    """A state_dict in torchvision's key layout (features.* + a classifier key we must ignore)."""
    torch.manual_seed(seed)
    m = M.AlexNetFeatures() if net == "alex" else M.VGG16Features()
    sd = {k: v.clone() for k, v in m.state_dict().items()}
    sd["classifier.1.weight"] = torch.zeros(4, 4)
    p = tmp_path / M.BACKBONE_FILES[net]
    torch.save(sd, p)
    return p, sd


def test_lpips_unavailable_without_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty_torch_home"))
    r = M.load_lpips("alex")
    assert not r and isinstance(r, M.Unavailable) and "backbone" in r.reason
    r = M.load_lpips("alex", backbone=tmp_path / "missing.pth")
    assert not r and "missing.pth" in r.reason
    d = M.load_dists()
    assert not d and isinstance(d, M.Unavailable)


def test_lpips_loads_weights_and_follows_its_definition(tmp_path):
    bb, sd = _backbone_file(tmp_path, "alex")
    g = torch.Generator().manual_seed(1)
    lin = {f"lin{k}.model.1.weight": torch.zeros(1, c, 1, 1) for k, c in enumerate(M.AlexNetFeatures.channels)}
    lin["lin0.model.1.weight"] = torch.rand(1, 64, 1, 1, generator=g)
    lp = tmp_path / "alex.pth"
    torch.save(lin, lp)
    model = M.load_lpips("alex", backbone=bb, linear=lp)
    assert isinstance(model, M.LPIPS)
    x = torch.rand(2, 3, 48, 48, generator=g)
    y = torch.rand(2, 3, 48, 48, generator=g)
    d = model(x, y)
    assert d.shape == (2,) and (d > 0).all()
    assert torch.allclose(model(x, x), torch.zeros(2), atol=1e-7)
    # only lin0 is non-zero: the distance is the first ReLU layer's weighted normalised difference
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def feat(z):
        z = ((2 * z - 1) - shift) / scale
        f = F.relu(F.conv2d(z, sd["features.0.weight"], sd["features.0.bias"], stride=4, padding=2))
        return f / (f.square().sum(1, keepdim=True).sqrt() + 1e-10)

    ref = ((feat(x) - feat(y)) ** 2 * lin["lin0.model.1.weight"]).sum(1).mean((1, 2))
    assert torch.allclose(d, ref, rtol=1e-5)


def test_lpips_rejects_a_wrong_file(tmp_path):
    bb, _ = _backbone_file(tmp_path, "alex")
    bad = tmp_path / "lin.pth"
    torch.save({"lin0.model.1.weight": torch.zeros(1, 3, 1, 1)}, bad)
    with pytest.raises(ValueError, match="lin.pth"):
        M.load_lpips("alex", backbone=bb, linear=bad)
    vgg_bad = tmp_path / "vgg.pth"
    torch.save({"features.0.weight": torch.zeros(1)}, vgg_bad)
    with pytest.raises(ValueError, match="vgg.pth"):
        M.load_dists(backbone=vgg_bad, alpha_beta=bad)


def test_dists_loads_weights_from_the_hub_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    ck = tmp_path / "hub" / "checkpoints"
    ck.mkdir(parents=True)
    _, sd = _backbone_file(ck, "vgg")
    n = sum(M.DISTS.chns)
    g = torch.Generator().manual_seed(2)
    torch.save({"alpha": torch.rand(1, n, 1, 1, generator=g), "beta": torch.rand(1, n, 1, 1, generator=g)},
               ck / "dists_weights.pt")
    model = M.load_dists()
    assert isinstance(model, M.DISTS)
    x = torch.rand(1, 3, 40, 40, generator=g)
    y = (x + 0.2 * torch.rand(1, 3, 40, 40, generator=g)).clamp(0, 1)
    assert abs(float(model(x, x)[0])) < 1e-5
    d = float(model(x, y)[0])
    assert 0 < d < 1
    # the image stage alone (alpha/beta zero elsewhere) is the SSIM-like statistic of the pixels
    model.alpha.data.zero_()
    model.beta.data.zero_()
    model.alpha.data[0, :3] = 1.0
    xm, ym = x.mean((2, 3)), y.mean((2, 3))
    s1 = (2 * xm * ym + 1e-6) / (xm**2 + ym**2 + 1e-6)
    assert float(model(x, y)[0]) == pytest.approx(float(1 - s1.sum() / 3), abs=1e-6)
