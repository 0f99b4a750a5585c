"""anidress_core.metrics.mesh against brute-force references."""
from __future__ import annotations

import math

import pytest
import torch

from anidress_core.metrics import mesh as MM


def grid(n=12, size=1.0, z=0.0):
    """A flat square (V, 3), (F, 3) in the plane z."""
    s = torch.linspace(0, size, n, dtype=torch.float64)
    x, y = torch.meshgrid(s, s, indexing="ij")
    v = torch.stack([x, y, torch.full_like(x, z)], -1).reshape(-1, 3)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [[a, a + n, a + 1], [a + 1, a + n, a + n + 1]]
    return v, torch.tensor(f)


def test_vertex_rmse_matches_loop():
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(4, 50, 3, generator=g), torch.randn(4, 50, 3, generator=g)
    got = MM.vertex_rmse(a, b)
    for t in range(4):
        want = math.sqrt(sum(float(((a[t, i] - b[t, i]) ** 2).sum()) for i in range(50)) / 50)
        assert abs(float(got[t]) - want) < 1e-5
    assert MM.vertex_rmse(a[0], a[0]).shape == (1,) and float(MM.vertex_rmse(a[0], a[0])) == 0
    with pytest.raises(ValueError):
        MM.vertex_rmse(a, b[:, :10])


def test_jitter_and_acceleration_error():
    t = torch.arange(6, dtype=torch.float64)[:, None, None]
    v = torch.zeros(6, 5, 3, dtype=torch.float64) + t * torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose(MM.temporal_jitter(v), torch.zeros(4, dtype=torch.float64))  # constant velocity
    noisy = v.clone()
    noisy[3, :, 2] += 0.01  # one frame bumped by 1 cm
    j = MM.temporal_jitter(noisy)
    # second differences at t = 2, 3, 4: +0.01, -0.02, +0.01
    torch.testing.assert_close(j, torch.tensor([0.0, 0.01, 0.02, 0.01], dtype=torch.float64))
    torch.testing.assert_close(MM.acceleration_error(noisy, v), j)
    assert MM.temporal_jitter(v[:2]).numel() == 0


def test_barycentric_transfer():
    v, f = grid(4)
    seq = torch.stack([v, v * 2])
    face = torch.tensor([0, 5])
    bary = torch.tensor([[1.0, 0, 0], [0.2, 0.3, 0.5]], dtype=torch.float64)
    out = MM.barycentric_transfer(seq, f, face, bary)
    assert out.shape == (2, 2, 3)
    torch.testing.assert_close(out[0, 0], v[f[0, 0]])
    torch.testing.assert_close(out[1, 1], 2 * (0.2 * v[f[5, 0]] + 0.3 * v[f[5, 1]] + 0.5 * v[f[5, 2]]))


def test_surface_samples_are_uniform_and_on_the_surface():
    v, f = grid(8)
    s = MM.surface_samples(v, f, 4000, torch.Generator().manual_seed(1))
    assert s.points.shape == (4000, 3)
    assert torch.all(s.points[:, 2] == 0) and torch.allclose(s.normals.abs(), torch.tensor([0.0, 0, 1]).double())
    # uniform over the unit square: mean 1/2, quarter of the samples per quadrant
    assert abs(float(s.points[:, 0].mean()) - 0.5) < 0.03
    q = ((s.points[:, 0] < 0.5) & (s.points[:, 1] < 0.5)).double().mean()
    assert abs(float(q) - 0.25) < 0.03
    with pytest.raises(ValueError):
        MM.surface_samples(v * 0, f, 10)


def test_chamfer_and_normal_consistency_against_brute_force():
    g = torch.Generator().manual_seed(2)
    v, f = grid(10)
    a = MM.surface_samples(v, f, 800, g)
    # a bent copy: lift one half and tilt it
    w = v.clone()
    w[:, 2] = 0.3 * w[:, 0].clamp_min(0.5) - 0.15
    b = MM.surface_samples(w, f, 900, g)
    got = MM.chamfer_normal(a, b)
    d = torch.cdist(a.points, b.points)
    dab, iab = d.min(1)
    dba, iba = d.min(0)
    want = 0.5 * (dab.mean() + dba.mean())
    nc = 0.5 * ((a.normals * b.normals[iab]).sum(-1).abs().mean() + (b.normals * a.normals[iba]).sum(-1).abs().mean())
    assert abs(got.chamfer - float(want)) < 1e-12 and abs(got.normal_consistency - float(nc)) < 1e-12
    assert 0 < got.normal_consistency < 1
    # a parallel copy 5 mm away: Chamfer ~ 5 mm (plus the sampling gap), normals aligned
    c = MM.surface_samples(v + torch.tensor([0, 0, 0.005]).double(), f, 5000, g)
    dd = MM.chamfer_normal(MM.surface_samples(v, f, 5000, g), c)
    assert 0.005 <= dd.chamfer < 0.012 and dd.normal_consistency > 0.999
    same = MM.chamfer_normal(a, a)
    assert same.chamfer == 0 and abs(same.normal_consistency - 1) < 1e-12


def test_reprojection_error_matches_a_pinhole_loop_and_skips_points_behind_a_camera():
    from anidress_core.camera import ring_cameras

    cams = ring_cameras(3, radius=3.0, height=1.0, target=(0.0, 0.0, 1.0), focal_px=200.0, image_height=64,
                        image_width=48, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    gt = torch.randn(2, 30, 3, generator=g, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, 1.0],
                                                                                        dtype=torch.float64)
    pred = gt + 0.02 * torch.randn(2, 30, 3, generator=g, dtype=torch.float64)
    pred[1, 0] = cams.centers[0] + 2.0 * (cams.centers[0] - torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    got = MM.reprojection_error(pred, gt, cams)

    def pix(x, c):  # the slow reference: one point, one camera, no distortion
        xc = cams.R[c] @ x + cams.T[c]
        return (float(cams.K[c, 0, 0] * xc[0] / xc[2] + cams.K[c, 0, 2]),
                float(cams.K[c, 1, 1] * xc[1] / xc[2] + cams.K[c, 1, 2]), float(xc[2]))

    for t in range(2):
        dists = []
        for c in range(3):
            for v in range(30):
                (ua, va, za), (ub, vb, zb) = pix(pred[t, v], c), pix(gt[t, v], c)
                if za > 0 and zb > 0:
                    dists.append(math.hypot(ua - ub, va - vb))
        assert len(dists) == (90 if t == 0 else 89)  # frame 1: vertex 0 is behind camera 0
        assert float(got[t]) == pytest.approx(sum(dists) / len(dists), rel=1e-9)
    assert float(MM.reprojection_error(gt, gt, cams).abs().max()) == 0.0
    with pytest.raises(ValueError, match="shapes differ"):
        MM.reprojection_error(pred[:, :5], gt, cams)
