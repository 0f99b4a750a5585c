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



def _ssim_at(a: np.ndarray, b: np.ndarray, i: int, j: int, window=11, sigma=1.5) -> float:
    """Slow SSIM at pixel (i, j) of (H, W, 3) float64 images: the window centred there on the images
    padded by mirroring with the edge repeated (numpy 'symmetric'), mean over channels."""
    p = window // 2
    x = np.arange(window) - p
    g = np.exp(-0.5 * (x / sigma) ** 2)
    w = np.outer(g, g) / np.outer(g, g).sum()
    out = []
    for c in range(3):
        pa = np.pad(a[..., c], p, mode="symmetric")[i:i + window, j:j + window]
        pb = np.pad(b[..., c], p, mode="symmetric")[i:i + window, j:j + window]
        mx, my = (w * pa).sum(), (w * pb).sum()
        sxx, syy = (w * pa * pa).sum() - mx * mx, (w * pb * pb).sum() - my * my
        sxy = (w * pa * pb).sum() - mx * my
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        out.append((2 * mx * my + c1) * (2 * sxy + c2) / ((mx * mx + my * my + c1) * (sxx + syy + c2)))
    return float(np.mean(out))


def test_ssim_map_against_a_slow_reference_and_ssim():
    a, b = (t.double() for t in _imgs(2, 30, 26))
    m = M.ssim_map(a, b)
    assert m.shape == (30, 26) and m.dtype == torch.float64
    an, bn = a.numpy(), b.numpy()
    for i, j in ((0, 0), (0, 25), (29, 13), (2, 3), (15, 12), (27, 24)):  # corners, borders, the inside
        assert float(m[i, j]) == pytest.approx(_ssim_at(an, bn, i, j), abs=1e-12), (i, j)
    # its mean over the valid window positions is ssim (float32 images too)
    assert float(m[5:-5, 5:-5].mean()) == pytest.approx(M.ssim(a, b), abs=1e-12)
    af, bf = _imgs(3, 24, 20)
    assert float(M.ssim_map(af, bf)[5:-5, 5:-5].mean()) == pytest.approx(M.ssim(af, bf), abs=1e-12)
    # identical images: 1 everywhere, borders included
    assert torch.allclose(M.ssim_map(a, a), torch.ones(30, 26, dtype=torch.float64), rtol=0, atol=1e-12)
    # skimage's full map uses the same border handling (scipy.ndimage 'reflect')
    from skimage.metrics import structural_similarity

    _, full = structural_similarity(an, bn, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, data_range=1.0, full=True)
    assert np.allclose(m.numpy(), full.mean(-1), rtol=0, atol=1e-12)
    # an image smaller than the half window is mirrored repeatedly
    small = M.ssim_map(a[:3, :4], b[:3, :4])
    assert small.shape == (3, 4)
    assert float(small[1, 2]) == pytest.approx(_ssim_at(an[:3, :4], bn[:3, :4], 1, 2), abs=1e-12)
    with pytest.raises(ValueError, match="odd"):
        M.ssim_map(a, b, window=10)
    with pytest.raises(ValueError, match=r"\(30, 26, 3\) and \(5, 26, 3\)"):
        M.ssim_map(a, b[:5])


def _labels(H=12, W=10) -> torch.Tensor:
    """(H, W) labels: background 0, a body block 1 and a garment block 2 inside it."""
    lab = torch.zeros(H, W, dtype=torch.uint8)
    lab[2:10, 2:8] = 1  # 48 body-or-garment pixels
    lab[6:10, 3:7] = 2  # 16 of them garment
    return lab


def _regions(lab: torch.Tensor) -> dict:
    return {"subject": lab > 0, "garment": lab == 2, "body": lab == 1}


def test_region_psnr_of_a_known_error():
    """An error of 0.1 on every garment pixel (all 3 channels), none elsewhere: garment 20 dB, body +inf
    (identical), subject 20 dB - 10 log10(garment pixels / subject pixels) (the same error over more pixels)."""
    lab = _labels()
    gt = torch.rand(12, 10, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 0.8
    pred = torch.where((lab == 2)[..., None], gt + 0.1, gt)
    st = M.region_stats(pred, gt, _regions(lab))
    assert (st["subject"].pixels, st["garment"].pixels, st["body"].pixels) == (48, 16, 32)
    assert st["garment"].sq_err == pytest.approx(16 * 3 * 0.01, rel=1e-12) and st["body"].sq_err == 0
    garment, body, subject = (M.region_score(st[k]) for k in ("garment", "body", "subject"))
    assert garment.psnr_db == pytest.approx(20.0, abs=1e-9)
    assert body.psnr_db == math.inf
    assert subject.psnr_db == pytest.approx(20.0 - 10 * math.log10(16 / 48), abs=1e-9)
    # SSIM in a region: the map's mean over its pixels
    smap = M.ssim_map(pred, gt)
    for k, m in _regions(lab).items():
        assert M.region_score(st[k]).ssim == pytest.approx(float(smap[m].mean()), abs=1e-12)
    assert M.region_stats(gt, gt, _regions(lab))["subject"].ssim_sum == pytest.approx(48.0, abs=1e-9)
    # pooled with a finite region the +inf body becomes finite; with another identical one it stays +inf
    assert M.region_score(st["body"] + st["body"]).psnr_db == math.inf
    assert math.isfinite(M.region_score(st["body"] + st["garment"]).psnr_db)


def test_pooled_psnr_is_not_the_mean_of_per_image_psnr():
    """Image 1: error 0.1 on 16 garment pixels; image 2: error 0.2 on 48. Pooled: one MSE over the 64 pixels,
    (16 * 0.01 + 48 * 0.04) / 64 = 0.0325 -> 14.881 dB, not the mean of 20 and 13.979 dB (16.990)."""
    g = torch.Generator().manual_seed(5)
    lab1 = _labels()
    lab2 = torch.zeros(12, 10, dtype=torch.uint8)
    lab2[0:6, 0:8] = 2  # 48 garment pixels
    stats = []
    for lab, e in ((lab1, 0.1), (lab2, 0.2)):
        gt = torch.rand(12, 10, 3, generator=g, dtype=torch.float64) * 0.7
        pred = torch.where((lab == 2)[..., None], gt + e, gt)
        stats.append(M.region_stats(pred, gt, _regions(lab))["garment"])
    per_image = [M.region_score(s).psnr_db for s in stats]
    assert per_image == pytest.approx([20.0, -10 * math.log10(0.04)], abs=1e-9)
    pooled = M.region_score(stats[0] + stats[1])
    assert pooled.psnr_db == pytest.approx(-10 * math.log10((16 * 0.01 + 48 * 0.04) / 64), abs=1e-9)
    assert pooled.psnr_db < np.mean(per_image) - 2  # the larger, worse image weighs more
    assert pooled.ssim == pytest.approx((stats[0].ssim_sum + stats[1].ssim_sum) / 64, abs=1e-12)


def test_an_empty_region_is_nan_and_adds_nothing_to_a_pool():
    a, b = (t.double() for t in _imgs(6, 12, 10))
    lab = _labels()
    lab[lab == 2] = 1  # no garment in view
    st = M.region_stats(a, b, _regions(lab))
    assert st["garment"] == M.RegionStats() and st["garment"].pixels == 0
    assert all(math.isnan(v) for v in M.region_score(st["garment"]))
    other = M.region_stats(a, b, _regions(_labels()))["garment"]
    assert M.region_score(other + st["garment"]) == M.region_score(other)


def test_region_stats_reject_masks_of_another_size():
    a, b = _imgs(7, 12, 10)
    with pytest.raises(ValueError, match=r"'garment' \(12, 9\) does not match image \(12, 10, 3\)"):
        M.region_stats(a, b, {"subject": torch.ones(12, 10, dtype=torch.bool),
                              "garment": torch.ones(12, 9, dtype=torch.bool)})
    with pytest.raises(ValueError, match="must be bool"):
        M.region_stats(a, b, {"subject": torch.ones(12, 10, dtype=torch.uint8)})
    with pytest.raises(ValueError, match=r"\(12, 10, 3\) and \(11, 10, 3\)"):
        M.region_stats(a, b[:11], {})

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
