"""Backward deformation: exact inverse LBS, HumanNeRF warp round trips, priors reproduce body LBS."""
import pytest
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
    assert torch.allclose(warp2.x_c, warp.x_c) and torch.allclose(warp2.fg, warp.fg)


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


def _random_warp_problem(seed: int, N: int = 300, K: int = 5, T: int = 3, M: int = 4, dtype=torch.float64):
    """Random frames of K joints, a smooth random weight volume over a box and candidates (some 'no joint')."""
    g = torch.Generator().manual_seed(seed)
    box = torch.tensor([[-1.0, -1.2, -0.8], [1.1, 1.0, 0.9]], dtype=dtype)
    R = 8
    vol = torch.rand(K + 1, R, R, R, generator=g, dtype=dtype) + 0.05
    vol = vol / vol.sum(0, keepdim=True)
    S = torch.stack([_rigid(g, K, dtype, angle=0.4) for _ in range(T)])  # (T, K, 4, 4)
    frame = torch.randint(T, (N,), generator=g)
    x_c = torch.rand(N, 3, generator=g, dtype=dtype) * 1.4 - 0.7
    w = torch.rand(N, K, generator=g, dtype=dtype) ** 2
    w = w / w.sum(1, keepdim=True)
    x_o = forward_lbs(x_c, w, S[frame])
    cand = torch.stack([torch.randperm(K, generator=g)[:M] for _ in range(N)])
    cand[:20, 2:] = K  # fewer candidates
    cand[20:25] = K  # no joint at all
    return x_o, frame, S, cand, vol, box


@pytest.mark.parametrize("iterations", [1, 3])
def test_warp_kernels_match_the_torch_path_in_values_and_gradients(iterations):
    """backward_warp with the Warp kernels (placement + last step) against the torch path, float64:
    the canonical points, the foreground likelihood and the gradients for the volume and the transforms."""
    x_o, frame, S, cand, vol0, box = _random_warp_problem(3)
    out = {}
    for backend in ("warp", "torch"):
        vol = vol0.clone().requires_grad_()
        T = S.clone().requires_grad_()
        r = backward_warp(x_o, frame, torch.linalg.inv(T.detach()), cand, vol, box, transforms=T,
                          iterations=iterations, backend=backend)
        gx = torch.sin(torch.arange(r.x_c.numel(), dtype=x_o.dtype)).view_as(r.x_c)
        ((r.x_c * gx).sum() + (r.fg * torch.cos(torch.arange(r.fg.numel(), dtype=x_o.dtype))).sum()).backward()
        out[backend] = (r.x_c.detach(), r.fg.detach(), vol.grad, T.grad)
    for a, b in zip(out["warp"], out["torch"]):
        assert torch.allclose(a, b, atol=1e-10, rtol=1e-8)
    assert out["warp"][2].abs().sum() > 0 and out["warp"][3].abs().sum() > 0
    with torch.no_grad():  # rendering: one kernel for every step
        r = backward_warp(x_o, frame, torch.linalg.inv(S), cand, vol0, box, transforms=S, iterations=iterations)
    assert torch.allclose(r.x_c, out["torch"][0], atol=1e-10) and torch.allclose(r.fg, out["torch"][1], atol=1e-10)
    # samples without a candidate keep their blend (the origin) and no foreground
    assert (out["warp"][1][20:25] == 0).all()


def test_warp_step_kernel_gradcheck():
    """The kernel's hand-written backward pass against finite differences of its own forward (float64)."""
    from anidress_core.field.deform import channel_last, StepWarp, volume_frame

    x_o, frame, S, cand, vol, box = _random_warp_problem(4, N=12, K=3, T=2, M=3)
    x_bar = backward_warp(x_o, frame, torch.linalg.inv(S), cand, vol, box).x_c.detach()
    dhw, lo, scale = volume_frame(vol, box, x_o.dtype)
    table = S[..., :3, :].reshape(-1, 12).clone().requires_grad_()
    flat = channel_last(vol, vol.dtype).clone().requires_grad_()

    def f(v, t):
        x_c, s = StepWarp.apply(v, t, x_o, x_bar, frame.to(torch.int32), cand.to(torch.int16), 3, lo, scale, dhw, 1e-4)
        return x_c, s

    assert torch.autograd.gradcheck(f, (flat, table), atol=1e-6)


def test_warp_kernels_on_an_empty_batch():
    x_o, frame, S, cand, vol, box = _random_warp_problem(5)
    v = vol.clone().requires_grad_()
    r = backward_warp(x_o[:0], frame[:0], torch.linalg.inv(S), cand[:0], v, box, transforms=S, iterations=2)
    assert r.x_c.shape == (0, 3) and r.fg.shape == (0,)
    (r.x_c.sum() + r.fg.sum()).backward()
    assert v.grad is None or (v.grad == 0).all()


def test_fixed_point_registers_where_the_blend_does_not():
    """Joints that move differently and overlapping weights (a garment's virtual bones): the blend of
    the proposals lands off the canonical point, the fixed point of forward skinning on it."""
    x_o, frame, S, cand, vol, box = _random_warp_problem(6, N=400, K=4, M=4)
    g = torch.Generator().manual_seed(7)
    K = 4
    # the points' true weights are the volume's at their canonical position (forward LBS with W)
    x_c = torch.rand(400, 3, generator=g, dtype=torch.float64) * 1.0 - 0.5
    allc = torch.arange(K)[None].expand(400, K)
    w = sample_channels(vol, box, x_c[:, None].expand(-1, K, 3), allc)
    w = w / w.sum(1, keepdim=True)
    x_o = forward_lbs(x_c, w, S[frame])
    inv = torch.linalg.inv(S)
    blend = backward_warp(x_o, frame, inv, allc, vol, box).x_c
    fixed = backward_warp(x_o, frame, inv, allc, vol, box, transforms=S, iterations=10).x_c
    e_blend = (blend - x_c).norm(dim=-1).median()
    e_fixed = (fixed - x_c).norm(dim=-1).median()
    assert e_fixed < 1e-3 and e_fixed < 0.1 * e_blend
