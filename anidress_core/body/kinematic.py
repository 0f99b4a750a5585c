"""The SMPL 24-joint kinematic tree and batched forward kinematics.

Joint order and parents follow SMPL (Loper et al., "SMPL: A Skinned Multi-Person
Linear Model", SIGGRAPH Asia 2015). Every joint frame is aligned with the canonical
body frame in the rest pose (y up, facing +z, x towards the body's left), so a
joint's local rotation is expressed in axes parallel to the canonical ones.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from ..geometry import make_transform

__all__ = [
    "SMPL_JOINT_NAMES",
    "SMPL_PARENTS",
    "NUM_JOINTS",
    "JOINT_INDEX",
    "FKResult",
    "forward_kinematics",
    "check_parents",
]

SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee",
    "spine2", "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot",
    "neck", "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
)

# Parent of each joint; -1 marks the root (SMPL kintree_table row 0).
SMPL_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)

NUM_JOINTS = 24
JOINT_INDEX: dict[str, int] = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}


class FKResult(NamedTuple):
    """Output of :func:`forward_kinematics`.

    transforms: (..., J, 4, 4) rest-pose space -> posed space (inverse bind baked in,
        ready for :func:`anidress_core.geometry.lbs`).
    joints: (..., J, 3) posed joint positions.
    """

    transforms: Tensor
    joints: Tensor


def check_parents(parents: Sequence[int] | Tensor, num_joints: int) -> list[int]:
    """Validate a parent list (root -1, every parent before its child); return it as ints."""
    p = [int(x) for x in (parents.tolist() if isinstance(parents, Tensor) else parents)]
    if len(p) != num_joints:
        raise ValueError(f"parents has {len(p)} entries, expected J={num_joints}")
    for j, pj in enumerate(p):
        if j == 0:
            if pj != -1:
                raise ValueError(f"parents[0] must be -1 (root), got {pj}")
        elif not 0 <= pj < j:
            raise ValueError(
                f"parents must be topologically sorted with one root: parents[{j}] = {pj}"
            )
    return p


def forward_kinematics(
    rotmats: Tensor, joints_rest: Tensor, parents: Sequence[int] | Tensor
) -> FKResult:
    """Batched forward kinematics of a joint tree (SMPL, Loper et al. 2015, eq. 4).

    rotmats: (..., J, 3, 3) local joint rotations (joint 0 is the global orientation
        about the root joint).
    joints_rest: (J, 3) or (..., J, 3) rest joint positions (broadcast against rotmats).
    parents: (J,) parent indices, -1 for the root, each parent before its children.

    Returns FKResult(transforms (..., J, 4, 4), joints (..., J, 3)); transforms map
    REST-pose points to posed space: ``x' = G_j [I, -J_j] x``.
    """
    if rotmats.ndim < 3 or rotmats.shape[-2:] != (3, 3):
        raise ValueError(f"forward_kinematics: rotmats must be (..., J, 3, 3), got {tuple(rotmats.shape)}")
    J = rotmats.shape[-3]
    if joints_rest.ndim < 2 or joints_rest.shape[-2:] != (J, 3):
        raise ValueError(
            f"forward_kinematics: joints_rest must be (..., {J}, 3) to match rotmats "
            f"{tuple(rotmats.shape)}, got {tuple(joints_rest.shape)}"
        )
    par = check_parents(parents, J)
    # (torch.broadcast_shapes imports sympy on first use: 0.3-2 s per process; numpy's is instant)
    batch = np.broadcast_shapes(tuple(rotmats.shape[:-3]), tuple(joints_rest.shape[:-2]))
    rotmats = rotmats.expand(*batch, J, 3, 3)
    joints_rest = joints_rest.to(rotmats.dtype).expand(*batch, J, 3)

    # 1. Bone offsets in the rest pose: t_j = J_j - J_parent(j) (t_0 = J_0).
    parent_idx = torch.tensor([max(p, 0) for p in par], device=rotmats.device)
    offsets = joints_rest - joints_rest[..., parent_idx, :] * (
        torch.tensor([p >= 0 for p in par], dtype=rotmats.dtype, device=rotmats.device)[:, None]
    )
    # 2. Local transforms L_j = [R_j, t_j].
    local = make_transform(rotmats, offsets)  # (..., J, 4, 4)
    # 3. Compose down the tree: G_j = G_parent(j) L_j (one step per joint, batched).
    chain = [local[..., 0, :, :]]
    for j in range(1, J):
        chain.append(chain[par[j]] @ local[..., j, :, :])
    G = torch.stack(chain, dim=-3)  # (..., J, 4, 4)
    joints_posed = G[..., :3, 3]
    # 4. Bake in the inverse bind matrix [I, -J_j]: A_j = [R_Gj, t_Gj - R_Gj J_j].
    t = joints_posed - torch.einsum("...ij,...j->...i", G[..., :3, :3], joints_rest)
    A = make_transform(G[..., :3, :3], t)
    return FKResult(A, joints_posed)
