import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from anidress_core.body.kinematic import JOINT_INDEX as JI
from anidress_core.body.kinematic import SMPL_JOINT_NAMES
from anidress_core.body.model import smpl_model
from anidress_core.body.motions import (
    EULER_ORDER,
    JOINT_LIMITS,
    MOTIONS,
    Motion,
    clamp_to_joint_limits,
    concatenate,
    euler_to_matrix,
    joint_limit_violation,
    make_motion,
    matrix_to_euler,
    resample,
    transform_motion,
)
from anidress_core.geometry import axis_angle_to_matrix, invert_transform, transform_points

from .conftest import make_tiny_smpl

NAMES = sorted(MOTIONS)
T_TEST = 60


@pytest.fixture(scope="module")
def motions(mannequin):
    return {n: make_motion(n, T_TEST, fps=30.0, seed=0, body=mannequin) for n in NAMES}


def test_library_has_the_required_motions():
    assert {"walk", "run", "twirl", "sway", "dance", "arms_up", "jump"} <= set(MOTIONS)


def test_euler_matches_scipy():
    a = torch.rand(200, 3, dtype=torch.float64) * 2 - 1
    a[:, 2] *= 1.4  # theta_z in (-80, 80) deg
    R = euler_to_matrix(a)
    # scipy's intrinsic "XZY" takes the angles in composition order (x, z, y).
    ref = Rotation.from_euler(EULER_ORDER, a[:, [0, 2, 1]].numpy()).as_matrix()
    np.testing.assert_allclose(R.numpy(), ref, atol=1e-12)
    torch.testing.assert_close(matrix_to_euler(R), a)


def _violation_reference(poses: np.ndarray) -> float:
    """Largest joint-limit excess (radians) via scipy's Euler decomposition."""
    worst = 0.0
    rot = poses.reshape(-1, 24, 3)
    for j, name in enumerate(SMPL_JOINT_NAMES):
        lim = JOINT_LIMITS[name]
        if lim is None:
            continue
        xzy = Rotation.from_rotvec(rot[:, j]).as_euler(EULER_ORDER)  # (x, z, y)
        e = xzy[:, [0, 2, 1]]
        worst = max(worst, float(np.max(np.maximum(np.asarray(lim.lower) - e, e - np.asarray(lim.upper)))))
    return worst


@pytest.mark.parametrize("name", NAMES)
def test_motion_shapes_and_limits(name, motions):
    m = motions[name]
    assert isinstance(m, Motion) and m.name == name and m.fps == 30.0
    assert m.poses.shape == (T_TEST, 72) and m.Rh.shape == (T_TEST, 3) and m.Th.shape == (T_TEST, 3)
    assert m.shapes.shape == (10,)
    assert torch.isfinite(m.poses).all() and torch.isfinite(m.Rh).all() and torch.isfinite(m.Th).all()
    assert (m.poses[:, :3] == 0).all()  # global rotation lives in Rh (EasyMocap)
    assert _violation_reference(m.poses.double().numpy()) < 1e-4
    assert joint_limit_violation(m.poses).max() < 1e-4
    torch.testing.assert_close(clamp_to_joint_limits(m.poses), m.poses, atol=1e-5, rtol=0)


def test_clamp_projects_into_limits():
    poses = torch.randn(50, 72, dtype=torch.float64) * 1.5
    assert joint_limit_violation(poses).max() > 0.1
    c = clamp_to_joint_limits(poses)
    assert _violation_reference(c.numpy()) < 1e-9
    torch.testing.assert_close(c[:, :3], poses[:, :3])  # the root is unlimited
    torch.testing.assert_close(clamp_to_joint_limits(c), c)
    with pytest.raises(ValueError, match="72"):
        clamp_to_joint_limits(torch.zeros(3, 69))


def test_limits_are_mirror_symmetric():
    for name in SMPL_JOINT_NAMES:
        if name.startswith("left_"):
            L, R = JOINT_LIMITS[name], JOINT_LIMITS["right_" + name[5:]]
            assert L.lower[0] == R.lower[0] and L.upper[0] == R.upper[0]
            for a in (1, 2):
                assert L.lower[a] == -R.upper[a] and L.upper[a] == -R.lower[a]


@pytest.mark.parametrize("name", NAMES)
def test_starts_at_rest_and_is_smooth(name, motions, mannequin):
    m = motions[name]
    # Every motion starts from the same rest standing pose, at rest (eased in).
    torch.testing.assert_close(m.poses[0], motions["walk"].poses[0], atol=1e-6, rtol=0)
    assert (m.poses[1] - m.poses[0]).abs().max() < 0.01
    # Rh = heading * (+90 deg about x) * tilt: canonical up -> world up at frame 0.
    up = axis_angle_to_matrix(m.Rh[0]) @ torch.tensor([0.0, 1.0, 0.0])
    torch.testing.assert_close(up, torch.tensor([0.0, 0.0, 1.0]), atol=1e-5, rtol=0)
    # C2-ish: sampling 4x finer must divide the second differences by ~16 (a kink,
    # i.e. a velocity jump, would only divide them by 4; a jump by 1).
    fine = make_motion(name, 4 * (T_TEST - 1) + 1, fps=120.0, seed=0, body=mannequin)

    def acc(x):
        x = x.double()
        return (x[2:] - 2 * x[1:-1] + x[:-2]).abs().amax()

    def rot(mm):
        return axis_angle_to_matrix(mm.poses.double().reshape(mm.num_frames, 24, 3))

    assert acc(rot(fine)) <= acc(rot(m)) / 10 + 1e-6
    # Th follows the lowest sole point; in the run the support switches between feet
    # moving at ~1 m/s vertically, which leaves a mild velocity kink (ratio ~1/4).
    assert acc(fine.Th) <= acc(m.Th) / (3 if name == "run" else 10) + 1e-6
    assert acc(axis_angle_to_matrix(fine.Rh)) <= acc(axis_angle_to_matrix(m.Rh)) / 10 + 1e-6


def test_motions_are_deterministic(mannequin, motions):
    again = make_motion("dance", T_TEST, seed=0, body=mannequin)
    assert torch.equal(again.poses, motions["dance"].poses) and torch.equal(again.Th, motions["dance"].Th)
    other = make_motion("dance", T_TEST, seed=1, body=mannequin)
    assert not torch.equal(other.poses, motions["dance"].poses)


def _yaw(Rh):
    f = axis_angle_to_matrix(Rh.double())[..., :, 2]  # canonical forward in the world
    return torch.atan2(f[..., 1], f[..., 0])


def test_motion_character(motions):
    walk, run = motions["walk"], motions["run"]
    # Walk/run progress forward: at heading 0 the body faces world -y.
    assert walk.Th[-1, 1] < -0.6 and abs(float(walk.Th[-1, 0])) < 0.05
    assert run.Th[-1, 1] < walk.Th[-1, 1] - 0.5
    # Twirl: 1-2 full turns in place.
    yaw = np.unwrap(_yaw(motions["twirl"].Rh).numpy())
    turns = abs(yaw[-1] - yaw[0]) / (2 * math.pi)
    assert 1.0 <= turns <= 2.0
    assert motions["twirl"].Th[:, :2].norm(dim=-1).max() < 0.1
    # Jump leaves the ground by > 10 cm; arms_up raises the wrists above the head.
    assert motions["jump"].Th[:, 2].max() - motions["jump"].Th[:, 2].min() > 0.15


def _part_mask(body, parts):
    ids = [body.part_names.index(p) for p in parts]
    return torch.isin(body.vertex_part, torch.tensor(ids))


def _seg_dist(p, a, b):
    """Distance of points p (T, N, 3) to segments a, b (T, 3)."""
    ab = b - a
    t = (((p - a[:, None]) * ab[:, None]).sum(-1) / (ab * ab).sum(-1, keepdim=True)).clamp(0, 1)
    return (p - (a[:, None] + t[..., None] * ab[:, None])).norm(dim=-1)


# Torso proxy: ellipsoids rigidly attached to the pelvis, spine1 and spine3 frames,
# ~80% of the mannequin's hip / waist / chest primitives, so they sit strictly
# inside the torso in every pose. A limb vertex inside one of them has gone through
# the body wall. Checking rigid proxies in their bones' frames (instead of
# `contains` on the posed torso mesh) keeps the test fast and independent of LBS
# artefacts of the torso surface itself.
TORSO_PROXY = [
    ("pelvis", (0.0, -0.02, -0.005), (0.13, 0.10, 0.085)),
    ("spine1", (0.0, 0.16, 0.0), (0.105, 0.12, 0.072)),
    ("spine3", (0.0, 0.32, 0.005), (0.125, 0.115, 0.085)),
]
ARM_PARTS = [f"{s}_{p}" for s in ("left", "right") for p in ("upper_arm", "lower_arm", "hand")]


def _arm_in_torso(body, posed) -> float:
    """Largest (1 - normalised ellipsoid radius) of arm vertices; > 0 means inside."""
    arms = _part_mask(body, ARM_PARTS)
    worst = -math.inf
    for joint, c, r in TORSO_PROXY:
        local = transform_points(invert_transform(posed.transforms[:, JI[joint]]), posed.vertices[:, arms])
        q = ((local - torch.tensor(c)) / torch.tensor(r)).norm(dim=-1)
        worst = max(worst, float((1 - q).max()))
    return worst


def _leg_in_leg(body, posed) -> float:
    """Largest depth (m) of one leg's vertices inside the other leg's bone capsules
    (thigh from 30% below the hip to the knee, r = 4.5 cm; shin r = 3.5 cm)."""
    worst = -math.inf
    J = posed.joints
    for own, other in (("left", "right"), ("right", "left")):
        P = posed.vertices[:, _part_mask(body, [f"{own}_upper_leg", f"{own}_lower_leg", f"{own}_foot"])]
        for a, b, rad, f0 in ((f"{other}_hip", f"{other}_knee", 0.045, 0.3), (f"{other}_knee", f"{other}_ankle", 0.035, 0.0)):
            pa, pb = J[:, JI[a]], J[:, JI[b]]
            pa = pa + f0 * (pb - pa)
            worst = max(worst, float((rad - _seg_dist(P, pa, pb)).max()))
    return worst


@pytest.mark.parametrize("name", NAMES)
def test_no_self_penetration_and_ground_contact(name, motions, mannequin):
    m = motions[name]
    idx = torch.arange(0, T_TEST, 3)
    posed = mannequin.pose(m.poses[idx], m.Rh[idx], m.Th[idx])
    assert _arm_in_torso(mannequin, posed) < 0.0
    assert _leg_in_leg(mannequin, posed) < 0.0
    feet = _part_mask(mannequin, ["left_foot", "right_foot"])
    lowest = posed.vertices[:, feet, 2].amin(1)
    assert lowest.min() > -0.02  # never more than 2 cm below ground
    assert posed.vertices[..., 2].min() > -0.02
    if name != "jump":
        assert lowest.max() < 0.02  # always standing on the ground
    else:
        assert lowest.min() < 0.02 and lowest.max() > 0.1


def test_penetration_checks_catch_bad_poses(mannequin):
    """Negative control: an arm folded across the chest and crossed legs are flagged."""
    m = make_motion("walk", 2, body=mannequin)
    poses = m.poses[:1].clone().reshape(1, 24, 3)
    # Left arm swung down and across the chest (-140 deg about z from the T-pose).
    poses[0, JI["left_shoulder"]] = torch.tensor([0.0, 0.0, math.radians(-140)])
    poses[0, JI["left_elbow"]] = 0.0
    # Left thigh adducted 30 deg across the right one.
    poses[0, JI["left_hip"]] = torch.tensor([0.0, 0.0, math.radians(-30)])
    posed = mannequin.pose(poses.reshape(1, 72), m.Rh[:1], m.Th[:1])
    assert _arm_in_torso(mannequin, posed) > 0.0
    assert _leg_in_leg(mannequin, posed) > 0.0


@pytest.mark.parametrize("name", ["walk", "jump", "arms_up"])
def test_no_collapse_at_joints(name, motions, mannequin):
    """LBS keeps the volume (no candy-wrapper collapse) and no edge shrinks to a point."""
    m = motions[name]
    F = mannequin.faces
    posed = mannequin.pose(m.poses[::4], m.Rh[::4], m.Th[::4]).vertices

    def volume(v):
        t = v[..., F, :]
        return (t[..., 0, :] * torch.cross(t[..., 1, :], t[..., 2, :], dim=-1)).sum((-1, -2)) / 6

    ratio = volume(posed) / volume(mannequin.v_template)
    assert ((ratio > 0.95) & (ratio < 1.05)).all(), ratio
    e = torch.cat([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    rest = (mannequin.v_template[e[:, 0]] - mannequin.v_template[e[:, 1]]).norm(dim=-1)
    now = (posed[:, e[:, 0]] - posed[:, e[:, 1]]).norm(dim=-1)
    assert (now / rest).min() > 0.1


def test_make_motion_with_an_smpl_body():
    body = smpl_model(make_tiny_smpl())
    m = make_motion("walk", 10, body=body)
    assert m.poses.shape == (10, 72) and torch.isfinite(m.Th).all()


def test_make_motion_validates():
    with pytest.raises(ValueError, match="unknown motion"):
        make_motion("moonwalk", 10)
    with pytest.raises(ValueError, match="num_frames"):
        make_motion("walk", 1)


def test_resample(motions):
    m = motions["dance"]
    up = resample(m, 60.0)
    assert up.fps == 60.0 and up.num_frames == 2 * T_TEST - 1
    torch.testing.assert_close(up.poses[::2], m.poses, atol=1e-5, rtol=0)
    torch.testing.assert_close(up.Th[::2], m.Th, atol=1e-6, rtol=0)
    # Midpoints of the rotations lie between their neighbours.
    R = axis_angle_to_matrix(up.poses.reshape(-1, 24, 3))
    mid_gap = (R[1:-1:2] - R[0:-2:2]).abs().amax()
    assert mid_gap <= (R[2::2] - R[0:-2:2]).abs().amax() + 1e-6
    down = resample(m, 15.0)
    assert down.num_frames == 30
    torch.testing.assert_close(down.poses, m.poses[::2], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="fps"):
        resample(m, 0.0)


def test_concatenate_and_transform(motions, mannequin):
    a, b = motions["walk"], motions["twirl"]
    cat = concatenate([a, b], blend=8)
    assert cat.num_frames == a.num_frames + b.num_frames - 8
    torch.testing.assert_close(cat.poses[:40], a.poses[:40])
    # Continuous: no jump in position or heading at the junction.
    step = (cat.Th[1:] - cat.Th[:-1]).norm(dim=-1)
    assert step.max() < 0.1
    yaw = np.unwrap(_yaw(cat.Rh).numpy())
    assert np.abs(np.diff(yaw)).max() < 0.5
    # The second motion continues from where the first one got to.
    assert cat.Th[-1, 1] < -0.6
    # transform_motion is a world rigid motion of the posed body.
    Rz = torch.tensor(Rotation.from_euler("z", 30, degrees=True).as_matrix(), dtype=torch.float32)
    t = torch.tensor([1.0, 2.0, 0.0])
    moved = transform_motion(b, Rz, t)
    v0 = mannequin.pose(b.poses[:5], b.Rh[:5], b.Th[:5]).vertices
    v1 = mannequin.pose(moved.poses[:5], moved.Rh[:5], moved.Th[:5]).vertices
    torch.testing.assert_close(v1, v0 @ Rz.T + t, atol=1e-4, rtol=1e-4)
