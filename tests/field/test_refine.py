"""Photometric pose refinement: the corrections' algebra, gradients, and a tiny field recovering known offsets."""
import torch

from anidress_core.field.refine import PoseRefiner, corrected_pose
from anidress_core.field.sampler import SurfacePart, build_occupancy
from anidress_core.field.train import TrainConfig, train_field
from anidress_core.geometry import axis_angle_to_matrix, lbs, make_transform

from .tiny_scene import new_model, tiny_scene


def test_zero_correction_is_the_identity_and_rotations_keep_the_centre():
    g = torch.Generator().manual_seed(0)
    S = make_transform(axis_angle_to_matrix(torch.randn(3, 5, 3, generator=g)), torch.randn(3, 5, 3, generator=g))
    centres = torch.randn(3, 2, 3, generator=g)
    assert torch.allclose(corrected_pose(S, torch.zeros(3, 2, 6), 2, centres), S)
    delta = torch.zeros(3, 2, 6)
    delta[..., :3] = torch.randn(3, 2, 3, generator=g) * 0.3
    out = corrected_pose(S, delta, 2, centres)
    assert torch.equal(out[:, :2], S[:, :2]) and torch.equal(out[:, 4:], S[:, 4:])
    # the correction of joint j maps its centre to itself (a rotation about the centre)
    C = out[:, 2:4] @ torch.linalg.inv(S[:, 2:4])
    moved = (C[..., :3, :3] @ centres[..., None])[..., 0] + C[..., :3, 3]
    assert torch.allclose(moved, centres, atol=1e-5)
    # a pure translation moves it by the translation
    delta = torch.zeros(3, 2, 6)
    delta[..., 3:] = 0.05
    C = corrected_pose(S, delta, 2, centres)[:, 2:4] @ torch.linalg.inv(S[:, 2:4])
    assert torch.allclose(C[..., :3, 3], torch.full((3, 2, 3), 0.05), atol=1e-5)


def test_corrections_gradcheck_float64():
    g = torch.Generator().manual_seed(1)
    S = make_transform(axis_angle_to_matrix(torch.randn(2, 3, 3, generator=g, dtype=torch.float64)),
                       torch.randn(2, 3, 3, generator=g, dtype=torch.float64))
    c = torch.randn(2, 2, 3, generator=g, dtype=torch.float64)
    d = (torch.randn(2, 2, 6, generator=g, dtype=torch.float64) * 0.2).requires_grad_()
    assert torch.autograd.gradcheck(lambda d_: corrected_pose(S, d_, 1, c), (d,))


def test_a_field_recovers_known_per_frame_offsets(small_body):
    """The tiny scene (80 px) is rendered with the true poses; the field is given the second frame's joints all
    shifted by 5 cm in x and -5 cm in z. Refined through the images (every joint, both frames, no regulariser:
    only the frames' relative place is observable, the canonical field absorbs a common shift), the second
    frame's correction relative to the first's undoes at least 30% of the shift along it, the median joint's
    relative error falls to 60% of the shift (7.1 cm) or below, and the images fit better than without."""
    torch.set_num_threads(1)
    data, box, prior = tiny_scene(small_body, size=80)
    off = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, -0.05]])  # world metres, per frame
    wrong = data.transforms.clone()
    wrong[:, :, :3, 3] += off[:, None]
    J = small_body.joints_rest
    centres = (wrong[..., :3, :3] @ J[None, :, :, None])[..., 0] + wrong[..., :3, 3]  # the joints' posed places

    def regrid(pose):  # the body surface posed by the (refined) joints
        v = lbs(small_body.v_template, small_body.weights, pose.detach())
        return build_occupancy([SurfacePart(v, small_body.faces, small_body.weights, 0.03)], (32, 32, 32), 8)

    data = data._replace(transforms=wrong, grid=regrid(wrong))
    cfg = TrainConfig(steps=250, rays_per_step=256, images_per_step=4, step_m=0.01, checkpoint_every=0,
                      refine_lr=5e-3, refine_weight=0.0, refine_regrid_every=50)
    refiner = PoseRefiner(centres, first=0)
    res = train_field(new_model(box, prior), data, cfg, progress=False, log_every=50, refiner=refiner, regrid=regrid)
    C = refiner(wrong).detach() @ torch.linalg.inv(wrong)
    moved = (C[..., :3, :3] @ centres[..., None])[..., 0] + C[..., :3, 3] - centres  # (2, 24, 3)
    rel = moved[1] - moved[0]
    shift = off[1] - off[0]
    along = float((rel.mean(0) * -shift).sum() / shift.square().sum())
    err = (rel + shift).norm(dim=-1)
    assert along > 0.3, along
    assert err.median() < 0.6 * shift.norm(), err.median()
    plain = train_field(new_model(box, prior), data, cfg, progress=False, log_every=50)
    assert res.history[-1]["loss"] < plain.history[-1]["loss"]


def test_resume_with_refinement_equals_an_uninterrupted_run(small_body):
    """The corrections and the pose the occupancy grid was last rebuilt from are part of the training state."""
    import copy

    import pytest

    torch.set_num_threads(1)
    data, box, prior = tiny_scene(small_body)
    J = small_body.joints_rest
    S = data.transforms
    centres = (S[..., :3, :3] @ J[None, :, :, None])[..., 0] + S[..., :3, 3]

    def regrid(pose):
        v = lbs(small_body.v_template, small_body.weights, pose.detach())
        return build_occupancy([SurfacePart(v, small_body.faces, small_body.weights, 0.03)], (32, 32, 32), 8)

    cfg = TrainConfig(steps=20, rays_per_step=128, images_per_step=2, step_m=0.015, checkpoint_every=8,
                      refine_regrid_every=5)
    full, rf = new_model(box, prior), PoseRefiner(centres, 0)
    train_field(full, data, cfg, progress=False, refiner=rf, regrid=regrid)

    class Stop(Exception):
        pass

    saved = {}

    def ckpt(state):
        saved["state"] = copy.deepcopy(state)
        if state["step"] == 16:
            raise Stop

    with pytest.raises(Stop):
        train_field(new_model(box, prior), data, cfg, checkpoint=ckpt, progress=False, refiner=PoseRefiner(centres, 0),
                    regrid=regrid)
    assert saved["state"]["grid_pose"] is not None
    resumed, rr = new_model(box, prior, seed=7), PoseRefiner(centres, 0)
    train_field(resumed, data, cfg, state=saved["state"], progress=False, refiner=rr, regrid=regrid)
    assert torch.equal(rf.delta, rr.delta)
    for k, v in full.state_dict().items():
        assert torch.equal(v, resumed.state_dict()[k]), k
