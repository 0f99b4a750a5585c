"""Backward deformation: exact inverse LBS, HumanNeRF warp round trips, priors reproduce body LBS."""
import torch

from anidress_core.field.deform import backward_warp, forward_lbs, inverse_lbs
from anidress_core.field.sampler import SurfacePart, build_occupancy
from anidress_core.field.subject import BodyRest, canonical_setup
from anidress_core.field.weights import MotionWeightVolume, sample_channels
from anidress_core.geometry import axis_angle_to_matrix, lbs, make_transform

from .conftest import bent_pose


def _rigid(g, K, dtype=torch.float64, angle=0.8):
    R = axis_angle_to_matrix(torch.randn(K, 3, generator=g, dtype=dtype) * angle)
    t = torch.randn(K, 3, generator=g, dtype=dtype) * 0.3
    return make_transform(R, t)


def test_inverse_lbs_round_trip_is_exact():
    g = torch.Generator().manual_seed(0)
    x_c = torch.randn(500, 3, generator=g, dtype=torch.float64)
    w = torch.rand(500, 6, generator=g, dtype=torch.float64) ** 4
    w = w / w.sum(1, keepdim=True)
    T = _rigid(g, 6, angle=0.5)
    x_o = forward_lbs(x_c, w, T)
    assert torch.allclose(x_o, lbs(x_c, w, T))
    assert (inverse_lbs(x_o, w, T) - x_c).abs().max() < 1e-10
    # per-point transforms (N, K, 4, 4) too
    Tn = T.expand(500, 6, 4, 4)
    assert (inverse_lbs(forward_lbs(x_c, w, Tn), w, Tn) - x_c).abs().max() < 1e-10


def test_backward_warp_round_trip_on_rigid_parts():
    """Two parts owned by one joint each (one-hot volume): forward-skin, warp back, error ~0."""
    g = torch.Generator().manual_seed(1)
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    R = 16
    vol = torch.zeros(3, R, R, R, dtype=torch.float64)  # joints 0, 1 + background
    vol[0, :, :, : R // 2] = 1  # x < 0: joint 0
    vol[1, :, :, R // 2:] = 1  # x > 0: joint 1
    # canonical points well inside each half (away from the interpolated border)
    x_c = torch.rand(400, 3, generator=g, dtype=torch.float64) * torch.tensor([0.7, 1.6, 1.6]) \
        - torch.tensor([0.85, 0.8, 0.8])
    x_c[200:, 0] += 1.0
    owner = (x_c[:, 0] > 0).long()
    T = _rigid(g, 2)
    x_o = forward_lbs(x_c, torch.nn.functional.one_hot(owner, 2).double(), T)
    # only points whose other-joint proposal lands outside that joint's region
    cand = torch.tensor([[0, 1]]).expand(400, 2)
    warp = backward_warp(x_o, None, torch.linalg.inv(T), cand, vol, box)
    other = (torch.linalg.inv(T)[1 - owner][:, :3, :3] @ x_o[..., None])[..., 0] + torch.linalg.inv(T)[1 - owner][:, :3, 3]
    w_other = sample_channels(vol, box, other[:, None], (1 - owner)[:, None])[:, 0]
    clean = w_other == 0
    assert clean.sum() > 200
    assert (warp.x_c[clean] - x_c[clean]).abs().max() < 1e-9
    assert torch.allclose(warp.fg[clean], torch.ones(int(clean.sum()), dtype=torch.float64))
    # the "no joint" candidate index K contributes nothing
    cand_pad = torch.cat([cand, torch.full((400, 1), 2)], 1)
    warp2 = backward_warp(x_o, None, torch.linalg.inv(T), cand_pad, vol, box)
    assert torch.allclose(warp2.x_c, warp.x_c) and (warp2.weights[:, 2] == 0).all()


def test_priors_alone_reproduce_body_lbs(small_body):
    """Body posed by LBS, mapped back by the prior volume only (no learned residue, as at
    the start of training): the rest vertices come back, and the volume's weights skin
    the rest body close to the body's own LBS."""
    body = small_body
    br = BodyRest(body.v_template, body.faces, body.weights, body.joints_rest)
    box, prior = canonical_setup(br, None, "full", res=32)
    vol = MotionWeightVolume(prior, box)
    with torch.no_grad():
        W = vol()
    posed = body.pose(bent_pose())
    x_o = posed.vertices[0]
    inv = torch.linalg.inv(posed.transforms[0])
    motion = (x_o - body.v_template).norm(dim=-1)
    # 1. backward warp of the posed vertices, candidates from the occupancy grid
    grid = build_occupancy([SurfacePart(posed.vertices, body.faces, body.weights, 0.03)], (48, 48, 48), 8)
    row, _ = grid.lookup(torch.zeros(x_o.shape[0], dtype=torch.long), x_o)
    assert (row >= 0).all()
    warp = backward_warp(x_o, None, inv, grid.cand[row].long(), W, box)
    err = (warp.x_c - body.v_template).norm(dim=-1)
    assert err.median() < 0.012 and torch.quantile(err, 0.9) < 0.03
    assert err.mean() < 0.1 * motion[motion > 0.05].mean()
    # 2. the volume's body weights at the rest vertices skin the body like its own weights
    K = 24
    v = body.v_template
    wv = sample_channels(W, box, v[:, None].expand(-1, K, 3), torch.arange(K)[None].expand(v.shape[0], K))
    wv = wv / wv.sum(1, keepdim=True)
    d = (lbs(v, wv, posed.transforms[0]) - x_o).norm(dim=-1)
    assert d.median() < 0.01 and torch.quantile(d, 0.9) < 0.03
