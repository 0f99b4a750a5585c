import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from anidress_core.body.kinematic import SMPL_PARENTS
from anidress_core.body.model import (
    BodyModel,
    global_orient_to_rh_th,
    rh_th_to_global_orient,
    smpl_model,
)
from anidress_core.geometry import axis_angle_to_matrix, lbs

from .conftest import make_tiny_smpl


def _reference_smpl(arrays, poses, Rh, Th, betas):
    """Slow SMPL (Loper et al. 2015) for ONE frame, float64, explicit loops.

    poses (72,), Rh (3,), Th (3,), betas (S,) -> (vertices (V, 3), joints (24, 3)).
    """
    v_t = np.asarray(arrays["v_template"], np.float64)
    S = arrays["shapedirs"]
    n = min(len(betas), S.shape[-1])
    v_shaped = v_t + sum(betas[l] * S[:, :, l] for l in range(n))
    J = arrays["J_regressor"] @ v_shaped
    R = [Rotation.from_rotvec(poses[3 * j:3 * j + 3]).as_matrix() for j in range(24)]
    feat = np.concatenate([(R[j] - np.eye(3)).ravel() for j in range(1, 24)])
    v_posed = v_shaped + np.einsum("vkp,p->vk", arrays["posedirs"], feat)
    G = [None] * 24
    for j in range(24):
        L = np.eye(4)
        L[:3, :3] = R[j]
        L[:3, 3] = J[j] - (J[SMPL_PARENTS[j]] if j else 0)
        G[j] = L if j == 0 else G[SMPL_PARENTS[j]] @ L
    verts = np.zeros_like(v_t)
    for i in range(len(v_t)):
        M = np.zeros((4, 4))
        for j in range(24):
            unbind = np.eye(4)
            unbind[:3, 3] = -J[j]
            M += arrays["weights"][i, j] * (G[j] @ unbind)
        verts[i] = (M @ np.append(v_posed[i], 1.0))[:3]
    Rg = Rotation.from_rotvec(Rh).as_matrix()
    joints = np.stack([g[:3, 3] for g in G])
    return verts @ Rg.T + Th, joints @ Rg.T + Th


def test_smpl_model_matches_slow_reference(tiny_smpl):
    model = smpl_model(tiny_smpl)
    assert model.shapedirs.shape == (40, 3, 10)
    assert model.posedirs.shape == (207, 120)
    assert model.parents.tolist() == list(SMPL_PARENTS)
    rng = np.random.default_rng(3)
    T = 3
    poses = rng.normal(scale=0.4, size=(T, 72))
    Rh = rng.normal(size=(T, 3))
    Th = rng.normal(size=(T, 3))
    betas = rng.normal(size=10)
    out = model.pose(torch.from_numpy(poses), torch.from_numpy(Rh), torch.from_numpy(Th), torch.from_numpy(betas))
    for t in range(T):
        v_ref, j_ref = _reference_smpl(tiny_smpl, poses[t], Rh[t], Th[t], betas)
        np.testing.assert_allclose(out.vertices[t].numpy(), v_ref, atol=2e-5)
        np.testing.assert_allclose(out.joints[t].numpy(), j_ref, atol=2e-5)


def test_per_frame_shapes_equal_single_frame_calls(tiny_smpl):
    model = smpl_model(tiny_smpl)
    T = 4
    poses = torch.randn(T, 72) * 0.3
    shapes = torch.randn(T, 10)
    batched = model.pose(poses, shapes=shapes)
    for t in range(T):
        single = model.pose(poses[t:t + 1], shapes=shapes[t])
        torch.testing.assert_close(batched.vertices[t], single.vertices[0], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(batched.joints[t], single.joints[0], atol=1e-5, rtol=1e-5)
    # Fewer betas than the model: the rest are zero; more: the extra are ignored.
    few = model.pose(poses[:1], shapes=shapes[0, :4])
    pad = torch.cat([shapes[0, :4], torch.zeros(6)])
    torch.testing.assert_close(few.vertices, model.pose(poses[:1], shapes=pad).vertices)
    more = model.pose(poses[:1], shapes=torch.cat([pad, torch.ones(6)]))
    torch.testing.assert_close(more.vertices, few.vertices)


@pytest.mark.parametrize("which", ["mannequin", "smpl"])
def test_identity_pose_reproduces_template(which, mannequin, tiny_smpl):
    model = mannequin if which == "mannequin" else smpl_model(tiny_smpl)
    out = model.pose(torch.zeros(3, 72))
    for t in range(3):
        torch.testing.assert_close(out.vertices[t], model.v_template, atol=1e-6, rtol=0)
        torch.testing.assert_close(out.joints[t], model.joints_rest, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.transforms, torch.eye(4).expand(3, 24, 4, 4), atol=1e-6, rtol=0)


def test_rh_th_is_a_rigid_transform_about_the_origin(mannequin):
    T = 5
    poses = torch.randn(T, 72) * 0.2
    poses[:, :3] = 0
    Rh = torch.randn(T, 3)
    Th = torch.randn(T, 3)
    base = mannequin.pose(poses)
    moved = mannequin.pose(poses, Rh, Th)
    R = axis_angle_to_matrix(Rh)
    expect = torch.einsum("tij,tvj->tvi", R, base.vertices) + Th[:, None]
    torch.testing.assert_close(moved.vertices, expect, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(moved.joints, torch.einsum("tij,tvj->tvi", R, base.joints) + Th[:, None],
                               atol=1e-5, rtol=1e-5)
    # The returned transforms skin the rest mesh straight to the world.
    torch.testing.assert_close(lbs(mannequin.v_template, mannequin.weights, moved.transforms), moved.vertices,
                               atol=1e-5, rtol=1e-5)


def test_global_orient_round_trip(tiny_smpl):
    """SMPL/AMASS (rotation about the pelvis + transl) and EasyMocap (rotation about
    the origin + Th) give the same vertices after conversion."""
    model = smpl_model(tiny_smpl)
    betas = torch.randn(10)
    T = 4
    go = torch.randn(T, 3)
    transl = torch.randn(T, 3)
    body = torch.randn(T, 72) * 0.3
    body[:, :3] = 0
    smpl_poses = body.clone()
    smpl_poses[:, :3] = go
    ref = model.pose(smpl_poses, None, transl, betas)  # SMPL convention: root rotation in poses
    J0 = model.shaped(betas)[1][0]
    Rh, Th = global_orient_to_rh_th(go, transl, J0)
    easy = model.pose(body, Rh, Th, betas)
    torch.testing.assert_close(easy.vertices, ref.vertices, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(easy.joints, ref.joints, atol=1e-5, rtol=1e-5)
    go2, transl2 = rh_th_to_global_orient(Rh, Th, J0)
    torch.testing.assert_close(go2, go)
    torch.testing.assert_close(transl2, transl, atol=1e-6, rtol=1e-6)


def test_mannequin_model_fields(mannequin):
    assert isinstance(mannequin, BodyModel)
    assert mannequin.name == "mannequin"
    assert mannequin.shapedirs is None and mannequin.posedirs is None and mannequin.J_regressor is None
    assert mannequin.face_uv is not None and mannequin.vertex_part is not None
    # Without a shape space, shapes are ignored.
    p = torch.randn(2, 72) * 0.2
    torch.testing.assert_close(mannequin.pose(p, shapes=torch.randn(10)).vertices, mannequin.pose(p).vertices)
    with pytest.raises(dataclasses.FrozenInstanceError):
        mannequin.name = "x"


def test_pose_validates_shapes(mannequin):
    with pytest.raises(ValueError, match=r"\(T, 72\)"):
        mannequin.pose(torch.zeros(2, 69))
    with pytest.raises(ValueError, match="Rh and Th"):
        mannequin.pose(torch.zeros(2, 72), torch.zeros(3, 3), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="per-frame shapes"):
        smpl_model(make_tiny_smpl()).pose(torch.zeros(2, 72), shapes=torch.zeros(3, 10))


def test_smpl_model_validates_arrays(tiny_smpl):
    bad = dict(tiny_smpl)
    del bad["J_regressor"]
    with pytest.raises(ValueError, match="J_regressor"):
        smpl_model(bad)
    bad = dict(tiny_smpl, weights=tiny_smpl["weights"][:, :23])
    with pytest.raises(ValueError, match="weights"):
        smpl_model(bad)
    bad = dict(tiny_smpl, posedirs=tiny_smpl["posedirs"][..., :100])
    with pytest.raises(ValueError, match="posedirs"):
        smpl_model(bad)
    bad = dict(tiny_smpl, kintree_table=np.zeros((2, 23), np.int64))
    with pytest.raises(ValueError, match="kintree_table"):
        smpl_model(bad)
    # Without blend shapes the model still poses (pure LBS on J_regressor joints).
    lite = {k: v for k, v in tiny_smpl.items() if k not in ("shapedirs", "posedirs")}
    m = smpl_model(lite)
    assert m.shapedirs is None and m.posedirs is None
    assert m.pose(torch.zeros(1, 72)).vertices.shape == (1, 40, 3)


def test_gradients_flow_through_pose(tiny_smpl):
    model = smpl_model(tiny_smpl)
    poses = (torch.randn(2, 72) * 0.2).requires_grad_()
    Th = torch.zeros(2, 3, requires_grad=True)
    out = model.pose(poses, torch.zeros(2, 3), Th, torch.zeros(10))
    out.vertices.square().sum().backward()
    assert torch.isfinite(poses.grad).all() and poses.grad.abs().sum() > 0
    assert Th.grad.abs().sum() > 0
