import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from anidress_core.body.kinematic import (
    JOINT_INDEX,
    NUM_JOINTS,
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    check_parents,
    forward_kinematics,
)
from anidress_core.geometry import axis_angle_to_matrix


def _reference_fk(R: np.ndarray, J: np.ndarray, parents) -> tuple[np.ndarray, np.ndarray]:
    """Slow reference: recursive composition of explicit 4x4 matrices, float64.

    R: (24, 3, 3), J: (24, 3) -> (A (24, 4, 4) rest->posed, joints (24, 3)).
    """

    def local(j):
        M = np.eye(4)
        M[:3, :3] = R[j]
        M[:3, 3] = J[j] - (J[parents[j]] if parents[j] >= 0 else 0.0)
        return M

    def world(j):
        return local(j) if parents[j] < 0 else world(parents[j]) @ local(j)

    A = np.zeros((len(parents), 4, 4))
    joints = np.zeros((len(parents), 3))
    for j in range(len(parents)):
        G = world(j)
        unbind = np.eye(4)
        unbind[:3, 3] = -J[j]
        A[j] = G @ unbind
        joints[j] = G[:3, 3]
    return A, joints


def test_tree_is_smpl():
    assert len(SMPL_JOINT_NAMES) == len(SMPL_PARENTS) == NUM_JOINTS == 24
    assert SMPL_JOINT_NAMES[:4] == ("pelvis", "left_hip", "right_hip", "spine1")
    assert SMPL_JOINT_NAMES[-2:] == ("left_hand", "right_hand")
    assert SMPL_PARENTS[0] == -1
    assert SMPL_PARENTS[JOINT_INDEX["head"]] == JOINT_INDEX["neck"]
    assert SMPL_PARENTS[JOINT_INDEX["left_shoulder"]] == JOINT_INDEX["left_collar"]
    assert SMPL_PARENTS[JOINT_INDEX["right_wrist"]] == JOINT_INDEX["right_elbow"]
    check_parents(SMPL_PARENTS, 24)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fk_matches_slow_reference(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(24, random_state=seed).as_matrix()
    J = rng.normal(size=(24, 3))
    A_ref, j_ref = _reference_fk(R, J, SMPL_PARENTS)
    out = forward_kinematics(torch.from_numpy(R), torch.from_numpy(J), SMPL_PARENTS)
    np.testing.assert_allclose(out.transforms.numpy(), A_ref, atol=1e-12)
    np.testing.assert_allclose(out.joints.numpy(), j_ref, atol=1e-12)


def test_fk_batched_shapes_and_broadcast():
    aa = torch.randn(2, 5, 24, 3, dtype=torch.float64) * 0.5
    R = axis_angle_to_matrix(aa)
    J = torch.randn(24, 3, dtype=torch.float64)
    out = forward_kinematics(R, J, torch.tensor(SMPL_PARENTS))
    assert out.transforms.shape == (2, 5, 24, 4, 4)
    assert out.joints.shape == (2, 5, 24, 3)
    one = forward_kinematics(R[1, 3], J, SMPL_PARENTS)
    torch.testing.assert_close(out.transforms[1, 3], one.transforms)
    # Per-batch rest joints broadcast too.
    Jb = J.expand(2, 5, 24, 3)
    torch.testing.assert_close(forward_kinematics(R, Jb, SMPL_PARENTS).transforms, out.transforms)


def test_fk_identity_and_joint_consistency():
    J = torch.randn(24, 3)
    eye = torch.eye(3).expand(24, 3, 3)
    out = forward_kinematics(eye, J, SMPL_PARENTS)
    torch.testing.assert_close(out.transforms, torch.eye(4).expand(24, 4, 4))
    torch.testing.assert_close(out.joints, J)
    # A_j maps the rest joint j to the posed joint j.
    R = axis_angle_to_matrix(torch.randn(24, 3))
    out = forward_kinematics(R, J, SMPL_PARENTS)
    mapped = torch.einsum("jab,jb->ja", out.transforms[:, :3, :3], J) + out.transforms[:, :3, 3]
    torch.testing.assert_close(mapped, out.joints, atol=1e-5, rtol=1e-5)


def test_fk_gradcheck():
    aa = (torch.randn(1, 24, 3, dtype=torch.float64) * 0.3).requires_grad_()
    J = torch.randn(24, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda a, j: forward_kinematics(axis_angle_to_matrix(a), j, SMPL_PARENTS).transforms, (aa, J)
    )


def test_fk_float32():
    R = axis_angle_to_matrix(torch.randn(3, 24, 3))
    out = forward_kinematics(R, torch.randn(24, 3), SMPL_PARENTS)
    assert out.transforms.dtype == torch.float32


@pytest.mark.parametrize(
    "parents",
    [[-1] + [0] * 22, [0] + [0] * 23, [-1, 2, 0] + [0] * 21, [-1, -1] + [0] * 22],
)
def test_bad_parents_raise(parents):
    with pytest.raises(ValueError, match="parents"):
        forward_kinematics(torch.eye(3).expand(24, 3, 3), torch.zeros(24, 3), parents)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\(\.\.\., J, 3, 3\)"):
        forward_kinematics(torch.zeros(24, 3), torch.zeros(24, 3), SMPL_PARENTS)
    with pytest.raises(ValueError, match="joints_rest"):
        forward_kinematics(torch.eye(3).expand(24, 3, 3), torch.zeros(23, 3), SMPL_PARENTS)
