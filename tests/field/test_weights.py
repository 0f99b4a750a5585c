"""Motion-weight volume: trilinear channel sampling, priors, decoder start."""
import pytest
import torch

from anidress_core.field.weights import (MotionWeightVolume, body_bone_priors, combine_priors, grid_points,
                                          sample_channels, sample_channels_reference, vertex_priors)

BOX = torch.tensor([[-1.0, -0.5, -0.25], [1.0, 0.5, 0.75]], dtype=torch.float64)


def test_sample_channels_matches_grid_sample_inside_and_outside_the_box():
    g = torch.Generator().manual_seed(0)
    vol = torch.randn(5, 6, 7, 8, generator=g, dtype=torch.float64)
    pts = BOX[0] + (BOX[1] - BOX[0]) * (torch.rand(40, 3, 3, generator=g, dtype=torch.float64) * 1.4 - 0.2)
    ch = torch.randint(0, 5, (40, 3), generator=g)
    assert torch.allclose(sample_channels(vol, BOX, pts, ch), sample_channels_reference(vol, BOX, pts, ch),
                          atol=1e-12)


def test_sample_channels_gradients_float64():
    g = torch.Generator().manual_seed(1)
    vol = torch.randn(3, 4, 4, 4, generator=g, dtype=torch.float64, requires_grad=True)
    pts = (BOX[0] + (BOX[1] - BOX[0]) * torch.rand(10, 2, 3, generator=g, dtype=torch.float64)).requires_grad_()
    ch = torch.randint(0, 3, (10, 2), generator=g)
    assert torch.autograd.gradcheck(lambda v, p: sample_channels(v, BOX, p, ch), (vol, pts))


def test_grid_points_span_the_box_in_zyx_order():
    p = grid_points(BOX, (3, 4, 5))
    assert p.shape == (3, 4, 5, 3)
    assert torch.allclose(p[0, 0, 0], BOX[0]) and torch.allclose(p[-1, -1, -1], BOX[1])
    assert p[1, 0, 0, 2] > p[0, 0, 0, 2] and p[0, 1, 0, 1] > p[0, 0, 0, 1] and p[0, 0, 1, 0] > p[0, 0, 0, 0]


def test_body_priors_peak_on_their_bones():
    # two joints, each owning a cloud of points around a segment
    g = torch.Generator().manual_seed(0)
    a = torch.randn(200, 3, generator=g) * torch.tensor([0.2, 0.03, 0.03])
    b = torch.randn(200, 3, generator=g) * torch.tensor([0.03, 0.2, 0.03]) + torch.tensor([1.0, 0, 0])
    verts = torch.cat([a, b])
    w = torch.zeros(400, 2)
    w[:200, 0] = 1
    w[200:, 1] = 1
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.3, 0, 0], [1.0, 0.3, 0], [0.5, 1, 0]])
    p = body_bone_priors(verts, w, torch.zeros(2, 3), pts)
    assert p.shape == (2, 5) and (p >= 0).all() and (p <= 1).all()
    assert p[0, 0] > 0.99 and p[1, 1] > 0.99
    assert p[0, 2] > p[1, 2] and p[1, 3] > p[0, 3]  # each ellipsoid is long along its own bone
    assert p[:, 4].max() < 1e-3


def test_vertex_priors_and_combination():
    verts = torch.tensor([[0.0, 0, 0], [0.1, 0, 0]])
    w = torch.tensor([[1.0, 0], [0, 1.0]])
    pts = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [0.05, 0, 0], [1.0, 1, 1]])
    prox, wg = vertex_priors(verts, w, pts, sigma=0.02)
    assert torch.allclose(prox[:2], torch.ones(2)) and prox[3] < 1e-6
    assert torch.allclose(wg.sum(0), torch.ones(4))
    assert wg[0, 0] > 0.99 and wg[1, 1] > 0.99 and torch.allclose(wg[:, 2], torch.tensor([0.5, 0.5]))
    body = torch.full((3, 4), 0.2)
    full = combine_priors(body, prox, garment_weights=wg)
    assert full.shape == (3 + 2 + 1, 4)
    assert torch.allclose(full[3:5, 0], wg[:, 0])  # at a garment vertex: the garment weights, no body
    assert torch.allclose(full[:3, 3], body[:, 3])  # far away: the body ellipsoids
    assert torch.allclose(full[-1], (1 - full[:-1].sum(0)).clamp(0, 1))
    body_only = combine_priors(body, prox, garment_body_weights=torch.full((3, 4), 1 / 3))
    assert body_only.shape == (3 + 1, 4)
    with pytest.raises(ValueError):
        combine_priors(body, prox)


def test_volume_starts_at_the_normalised_prior():
    g = torch.Generator().manual_seed(0)
    prior = torch.rand(4, 8, 8, 8, generator=g)
    vol = MotionWeightVolume(prior, BOX.float(), latent=16, width=16)
    w = vol()
    assert torch.allclose(w, prior / prior.sum(0, keepdim=True), atol=1e-6)
    # the residue is learnable: a gradient step moves the volume away from the prior
    w[0].sum().backward()
    assert vol.decoder[-1].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="R = 4"):
        MotionWeightVolume(torch.rand(4, 6, 6, 6), BOX.float())
