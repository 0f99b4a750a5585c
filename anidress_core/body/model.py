"""Skinned body models (SMPL or the procedural mannequin) and their posing.

SMPL: Loper, Mahmood, Romero, Pons-Moll, Black, "SMPL: A Skinned Multi-Person Linear
Model", SIGGRAPH Asia 2015. Posing follows the paper: shape blend shapes, joints
regressed from the shaped template, pose-corrective blend shapes driven by
``R_j - I`` of joints 1..23, forward kinematics, linear blend skinning.

Global placement follows EasyMocap (zju3dv/EasyMocap, doc/02_output.md): the posed
body (``poses[:3]`` normally zero) is rotated by ``Rh`` about the WORLD ORIGIN and
translated by ``Th``: ``x_world = R(Rh) x_posed + Th``. SMPL/AMASS instead rotate by
``global_orient`` about the pelvis joint; :func:`global_orient_to_rh_th` converts.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Mapping, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..geometry import axis_angle_to_matrix, lbs, make_transform
from .kinematic import NUM_JOINTS, check_parents, forward_kinematics

__all__ = [
    "BodyModel",
    "PosedBody",
    "mannequin_model",
    "smpl_model",
    "global_orient_to_rh_th",
    "rh_th_to_global_orient",
]


class PosedBody(NamedTuple):
    """Output of :meth:`BodyModel.pose`.

    vertices: (T, V, 3) world vertices.
    joints: (T, 24, 3) world joints.
    transforms: (T, 24, 4, 4) rest (shaped, pose-corrected) space -> world,
        including Rh/Th, so ``lbs(rest, weights, transforms) == vertices`` when the
        model has no pose correctives and a single shape.
    """

    vertices: Tensor
    joints: Tensor
    transforms: Tensor


@dataclass(frozen=True, eq=False)
class BodyModel:
    """A skinned body in the SMPL canonical frame (y up, facing +z, metres).

    Tensors are float32 unless noted; the model is immutable (``dataclasses.replace``
    to derive a modified copy) and compares by identity.
    """

    v_template: Tensor
    """(V, 3) rest (T-pose) vertices."""
    faces: Tensor
    """(F, 3) int64 triangles, counter-clockwise seen from outside."""
    weights: Tensor
    """(V, 24) convex skinning weights."""
    joints_rest: Tensor
    """(24, 3) rest joints of ``v_template`` (used when there is no J_regressor)."""
    parents: Tensor
    """(24,) int64 parent of each joint, -1 for the root."""
    face_uv: Tensor | None = None
    """(F, 3, 2) per-corner UVs in [0, 1], or None."""
    vertex_part: Tensor | None = None
    """(V,) int64 index into ``part_names``, or None."""
    part_names: tuple[str, ...] = ()
    """Names of the body parts / UV charts."""
    shapedirs: Tensor | None = None
    """(V, 3, S) shape blend shapes, or None (no shape space: ``shapes`` are ignored)."""
    posedirs: Tensor | None = None
    """(P, V*3) pose-corrective blend shapes with P = 9 * 23, or None."""
    J_regressor: Tensor | None = None
    """(24, V) joint regressor, or None (then ``joints_rest`` is used for every shape)."""
    name: str = "body"
    """Free-form label (``"mannequin"``, ``"smpl"``)."""

    def __post_init__(self):
        V = self.v_template.shape[0]
        if self.v_template.shape != (V, 3):
            raise ValueError(f"BodyModel: v_template must be (V, 3), got {tuple(self.v_template.shape)}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"BodyModel: faces must be (F, 3), got {tuple(self.faces.shape)}")
        if self.weights.shape != (V, NUM_JOINTS):
            raise ValueError(f"BodyModel: weights must be ({V}, {NUM_JOINTS}), got {tuple(self.weights.shape)}")
        if self.joints_rest.shape != (NUM_JOINTS, 3):
            raise ValueError(f"BodyModel: joints_rest must be ({NUM_JOINTS}, 3), got {tuple(self.joints_rest.shape)}")
        check_parents(self.parents, NUM_JOINTS)
        F = self.faces.shape[0]
        if self.face_uv is not None and self.face_uv.shape != (F, 3, 2):
            raise ValueError(f"BodyModel: face_uv must be ({F}, 3, 2), got {tuple(self.face_uv.shape)}")
        if self.vertex_part is not None and self.vertex_part.shape != (V,):
            raise ValueError(f"BodyModel: vertex_part must be ({V},), got {tuple(self.vertex_part.shape)}")
        if self.shapedirs is not None and (self.shapedirs.ndim != 3 or self.shapedirs.shape[:2] != (V, 3)):
            raise ValueError(f"BodyModel: shapedirs must be ({V}, 3, S), got {tuple(self.shapedirs.shape)}")
        if self.posedirs is not None and self.posedirs.shape != (9 * (NUM_JOINTS - 1), V * 3):
            raise ValueError(
                f"BodyModel: posedirs must be ({9 * (NUM_JOINTS - 1)}, {V * 3}), got {tuple(self.posedirs.shape)}"
            )
        if self.J_regressor is not None and self.J_regressor.shape != (NUM_JOINTS, V):
            raise ValueError(f"BodyModel: J_regressor must be ({NUM_JOINTS}, {V}), got {tuple(self.J_regressor.shape)}")

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_betas(self) -> int:
        return 0 if self.shapedirs is None else self.shapedirs.shape[-1]

    def shaped(self, shapes: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Rest vertices and joints for a shape: ((V, 3), (24, 3)) or ((T, V, 3), (T, 24, 3)).

        shapes: (S,), (T, S) or None. Extra betas beyond the model's are ignored and
        missing ones are zero (as smplx does); ignored entirely without shapedirs.
        """
        v = self.v_template
        if shapes is not None and self.shapedirs is not None:
            if shapes.ndim not in (1, 2):
                raise ValueError(f"shapes must be (S,) or (T, S), got {tuple(shapes.shape)}")
            n = min(shapes.shape[-1], self.num_betas)
            betas = shapes[..., :n].to(v.dtype)
            # v[..., m, k] = v_template[m, k] + sum_l betas[..., l] shapedirs[m, k, l]
            v = v + torch.einsum("...l,mkl->...mk", betas, self.shapedirs[..., :n])
        if self.J_regressor is not None:
            # J[..., j, k] = sum_m J_regressor[j, m] v[..., m, k]
            J = torch.einsum("jm,...mk->...jk", self.J_regressor, v)
        else:
            J = self.joints_rest.expand(*v.shape[:-2], NUM_JOINTS, 3)
        return v, J

    def pose(self, poses: Tensor, Rh: Tensor | None = None, Th: Tensor | None = None,
             shapes: Tensor | None = None) -> PosedBody:
        """Pose the body (SMPL, Loper et al. 2015) and place it in the world (EasyMocap).

        poses: (T, 72) axis-angle per joint (first 3 = rotation about the pelvis joint,
            normally zero in EasyMocap data); Rh, Th: (T, 3) or None (zero);
        shapes: (S,), (T, S) or None.
        Returns PosedBody(vertices (T, V, 3), joints (T, 24, 3), transforms (T, 24, 4, 4)).
        """
        if poses.ndim != 2 or poses.shape[-1] != 3 * NUM_JOINTS:
            raise ValueError(f"pose: poses must be (T, {3 * NUM_JOINTS}), got {tuple(poses.shape)}")
        T = poses.shape[0]
        dtype = self.v_template.dtype
        poses = poses.to(dtype)
        Rh = torch.zeros(T, 3, dtype=dtype) if Rh is None else Rh.to(dtype)
        Th = torch.zeros(T, 3, dtype=dtype) if Th is None else Th.to(dtype)
        if Rh.shape != (T, 3) or Th.shape != (T, 3):
            raise ValueError(f"pose: Rh and Th must be ({T}, 3), got {tuple(Rh.shape)} and {tuple(Th.shape)}")
        if shapes is not None and shapes.ndim == 2 and shapes.shape[0] != T:
            raise ValueError(f"pose: per-frame shapes must be ({T}, S), got {tuple(shapes.shape)}")
        # 1. Shape: rest vertices and joints (shared or per frame).
        v_shaped, J = self.shaped(shapes)
        # 2. Joint rotations.
        R = axis_angle_to_matrix(poses.reshape(T, NUM_JOINTS, 3))  # (T, 24, 3, 3)
        # 3. Pose correctives: feature (R_j - I) of joints 1..23, flattened (SMPL eq. 9).
        if self.posedirs is not None:
            eye = torch.eye(3, dtype=dtype)
            feat = (R[:, 1:] - eye).reshape(T, -1)  # (T, 207)
            # offsets[t, m] = sum_p feat[t, p] posedirs[p, m]
            v_rest = v_shaped + (feat @ self.posedirs).reshape(T, -1, 3)
        else:
            v_rest = v_shaped
        # 4. Forward kinematics in the body frame, then the EasyMocap world placement
        #    M = [R(Rh), Th] applied after posing, about the world origin.
        fk = forward_kinematics(R, J, self.parents)
        M = make_transform(axis_angle_to_matrix(Rh), Th)  # (T, 4, 4)
        A = M[:, None] @ fk.transforms  # (T, 24, 4, 4)
        joints = torch.einsum("tij,tnj->tni", M[:, :3, :3], fk.joints) + Th[:, None]
        # 5. Linear blend skinning.
        if v_rest.ndim == 2:
            verts = lbs(v_rest, self.weights, A)
        else:
            verts = _lbs_per_frame(v_rest, self.weights, A)
        return PosedBody(verts, joints, A)


def _lbs_per_frame(rest: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """LBS with a different rest mesh per frame (belongs next to geometry.lbs).

    rest: (T, V, 3); weights: (V, K); transforms: (T, K, 4, 4) -> (T, V, 3).
    """
    # A[t, v] = sum_k w[v, k] M[t, k]
    A = torch.einsum("vk,tkij->tvij", weights, transforms[..., :3, :])
    return torch.einsum("tvij,tvj->tvi", A[..., :3], rest) + A[..., 3]


def global_orient_to_rh_th(global_orient: Tensor, transl: Tensor, joints_rest_root: Tensor) -> tuple[Tensor, Tensor]:
    """SMPL/AMASS placement -> EasyMocap placement.

    SMPL rotates the posed body by ``global_orient`` about the root joint J0 and adds
    ``transl``: x = R (x0 - J0) + J0 + transl, x0 being the body posed with a zero
    root rotation. EasyMocap writes x = R x0 + Th, so Rh = global_orient and
    Th = transl + J0 - R J0.

    global_orient, transl: (T, 3); joints_rest_root: (3,) root joint of the SHAPED
    rest body (depends on betas for SMPL; zero for the mannequin).
    Returns (Rh (T, 3), Th (T, 3)).
    """
    if global_orient.shape[-1] != 3 or transl.shape != global_orient.shape or joints_rest_root.shape != (3,):
        raise ValueError(
            "global_orient_to_rh_th: expected global_orient (T, 3), transl (T, 3), joints_rest_root (3,), got "
            f"{tuple(global_orient.shape)}, {tuple(transl.shape)}, {tuple(joints_rest_root.shape)}"
        )
    J0 = joints_rest_root.to(global_orient.dtype)
    R = axis_angle_to_matrix(global_orient)
    Th = transl + J0 - torch.einsum("...ij,j->...i", R, J0)
    return global_orient.clone(), Th


def rh_th_to_global_orient(Rh: Tensor, Th: Tensor, joints_rest_root: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`global_orient_to_rh_th`: returns (global_orient, transl)."""
    if Rh.shape[-1] != 3 or Th.shape != Rh.shape or joints_rest_root.shape != (3,):
        raise ValueError(
            "rh_th_to_global_orient: expected Rh (T, 3), Th (T, 3), joints_rest_root (3,), got "
            f"{tuple(Rh.shape)}, {tuple(Th.shape)}, {tuple(joints_rest_root.shape)}"
        )
    J0 = joints_rest_root.to(Rh.dtype)
    R = axis_angle_to_matrix(Rh)
    transl = Th - J0 + torch.einsum("...ij,j->...i", R, J0)
    return Rh.clone(), transl


@functools.lru_cache(maxsize=4)
def mannequin_model(height: float = 1.70, target_vertices: int = 6500) -> BodyModel:
    """The procedural mannequin as a BodyModel (built once, cached on disk and in memory).

    See :mod:`anidress_core.body.mannequin`. No shape space or pose correctives.
    """
    from .mannequin import load_or_build_mannequin

    d = load_or_build_mannequin(height, target_vertices)
    t = torch.from_numpy
    return BodyModel(
        v_template=t(d.vertices).float(), faces=t(d.faces).long(), weights=t(d.weights).float(),
        joints_rest=t(d.joints_rest).float(), parents=t(d.parents).long(), face_uv=t(d.face_uv).float(),
        vertex_part=t(d.vertex_part).long(), part_names=tuple(d.part_names), name="mannequin",
    )


def _arr(arrays: Mapping[str, object], key: str) -> np.ndarray:
    if key not in arrays:
        raise ValueError(f"smpl_model: missing key '{key}' (have {sorted(arrays)})")
    a = arrays[key]
    if hasattr(a, "toarray"):  # scipy.sparse (official J_regressor)
        a = a.toarray()
    return np.asarray(a)


def smpl_model(arrays: Mapping[str, object], name: str = "smpl") -> BodyModel:
    """A BodyModel from the arrays of an SMPL model file (see io.motion.read_smpl_model_file).

    Keys: v_template (V, 3), f (F, 3), weights (V, 24), J_regressor (24, V),
    kintree_table (2, 24) (row 0 = parents, root parent any value outside 0..23,
    e.g. 2**32-1), and optionally shapedirs (V, 3, S) and posedirs (V, 3, 207).
    """
    v = _arr(arrays, "v_template").astype(np.float32)
    V = v.shape[0]
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"smpl_model: v_template must be (V, 3), got {v.shape}")
    f = _arr(arrays, "f").astype(np.int64)
    W = _arr(arrays, "weights").astype(np.float32)
    Jr = _arr(arrays, "J_regressor").astype(np.float32)
    kin = _arr(arrays, "kintree_table").astype(np.int64)
    if kin.ndim != 2 or kin.shape != (2, NUM_JOINTS):
        raise ValueError(f"smpl_model: kintree_table must be (2, {NUM_JOINTS}), got {kin.shape}")
    parents = kin[0].copy()
    parents[(parents < 0) | (parents >= NUM_JOINTS)] = -1
    if Jr.shape != (NUM_JOINTS, V):
        raise ValueError(f"smpl_model: J_regressor must be ({NUM_JOINTS}, {V}), got {Jr.shape}")
    shapedirs = posedirs = None
    if "shapedirs" in arrays:
        shapedirs = torch.from_numpy(_arr(arrays, "shapedirs").astype(np.float32))
    if "posedirs" in arrays:
        pd = _arr(arrays, "posedirs").astype(np.float32)
        if pd.shape != (V, 3, 9 * (NUM_JOINTS - 1)):
            raise ValueError(f"smpl_model: posedirs must be ({V}, 3, {9 * (NUM_JOINTS - 1)}), got {pd.shape}")
        # (V, 3, P) -> (P, V*3), the layout that multiplies the flattened pose feature.
        posedirs = torch.from_numpy(np.ascontiguousarray(pd.reshape(V * 3, -1).T))
    vt = torch.from_numpy(v)
    Jt = torch.from_numpy(Jr)
    return BodyModel(
        v_template=vt, faces=torch.from_numpy(f), weights=torch.from_numpy(W),
        joints_rest=Jt @ vt, parents=torch.from_numpy(parents), shapedirs=shapedirs, posedirs=posedirs,
        J_regressor=Jt, name=name,
    )

