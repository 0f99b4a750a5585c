"""Rotations, rigid transforms, linear blend skinning and mesh operators.

Glossary of dimension letters used across ``anidress_core``:
T frames, V vertices, F faces, J body joints, B garment bones, C cameras,
H, W image size, N samples / rays / points.

Conventions: rotation matrices act on column vectors (``x' = R @ x``); 4x4 rigid
transforms are ``[[R, t], [0, 1]]``; quaternions are ``wxyz``; angles in radians,
lengths in metres. Every function is pure (tensor in, tensor out) and batched over
leading dimensions.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "skew",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "rotation_6d_to_matrix",
    "matrix_to_rotation_6d",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "make_transform",
    "nearest_rotation",
    "invert_transform",
    "transform_points",
    "lbs",
    "face_normals",
    "vertex_normals",
    "uniform_laplacian",
    "edges_of_faces",
]

_SMALL = 1e-6


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix. v: (..., 3) -> (..., 3, 3)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    """Rodrigues' formula. aa: (..., 3) axis * angle -> (..., 3, 3).

    Near zero angle the coefficients sin(t)/t and (1-cos t)/t^2 switch to their Taylor
    series, so the function and its gradient stay finite at aa = 0.
    """
    if aa.shape[-1] != 3:
        raise ValueError(f"axis_angle_to_matrix expects (..., 3), got {tuple(aa.shape)}")
    theta2 = (aa * aa).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = theta2 < _SMALL
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2 * theta2 / 120, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2 * theta2 / 720, (1 - torch.cos(theta)) / theta2_safe)
    K = skew(aa)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """Inverse of :func:`axis_angle_to_matrix` via quaternions. R: (..., 3, 3) -> (..., 3)."""
    q = matrix_to_quaternion(R)
    # q and -q are the same rotation; pick w >= 0 so the angle lies in [0, pi].
    q = torch.where(q[..., :1] < 0, -q, q)
    w, xyz = q[..., :1], q[..., 1:]
    s = xyz.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, w)
    small = s < 1e-8
    # angle / sin(angle/2) -> 2 + angle^2 / 12 as angle -> 0
    factor = torch.where(small, 2 + angle * angle / 12, angle / torch.where(small, torch.ones_like(s), s))
    return xyz * factor


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternion wxyz (..., 4) -> (..., 3, 3). Normalises its input."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    m = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return m.reshape(*q.shape[:-1], 3, 3)


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Rotation matrix (..., 3, 3) -> quaternion wxyz (..., 4), w >= 0.

    Shepperd's method: use the largest of the four candidate denominators so no
    branch divides by a small number.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"matrix_to_quaternion expects (..., 3, 3), got {tuple(R.shape)}")
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    cand = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    root = cand.clamp_min(1e-12).sqrt()  # (..., 4) = 2|q_i|
    # Each row is q scaled by 4 q_i, built from the i-th largest component.
    rows = torch.stack(
        [
            torch.stack([cand[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, cand[..., 1], m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, cand[..., 2], m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, cand[..., 3]], -1),
        ],
        dim=-2,
    )  # (..., 4, 4)
    q_all = rows / (2 * root[..., :, None])
    best = cand.argmax(-1)
    q = torch.gather(q_all, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    """Continuous 6D rotation (Zhou et al. 2019): first two columns, Gram-Schmidt.

    d6: (..., 6) -> (..., 3, 3). The 6 numbers are the first two *columns* of R.
    """
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2 / a2.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_rotation_6d(R: Tensor) -> Tensor:
    """(..., 3, 3) -> (..., 6): the first two columns, concatenated."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def nearest_rotation(H: Tensor) -> Tensor:
    """The rotation R (det +1) maximising tr(R^T H) for (..., 3, 3) H (Kabsch): with
    H = U S V^T, R = U diag(1, 1, det(U V^T)) V^T. For a nearly orthonormal H (e.g. a rotation
    stored in float32, or an average of rotations) it is the closest rotation."""
    scale = H.abs().amax((-2, -1), keepdim=True).clamp_min(torch.finfo(H.dtype).tiny)
    Us, _, Vh = torch.linalg.svd(H / scale)
    d = torch.linalg.det(Us) * torch.linalg.det(Vh)
    D = torch.ones(*d.shape, 3, dtype=H.dtype, device=H.device)
    D[..., 2] = torch.where(d < 0, -torch.ones_like(d), torch.ones_like(d))
    return (Us * D[..., None, :]) @ Vh


def make_transform(R: Tensor, t: Tensor) -> Tensor:
    """R (..., 3, 3), t (..., 3) -> (..., 4, 4) rigid transform [[R, t], [0, 1]]."""
    # (torch.broadcast_shapes imports sympy on first use: seconds; numpy's is instant)
    batch = np.broadcast_shapes(tuple(R.shape[:-2]), tuple(t.shape[:-1]))
    M = torch.zeros(*batch, 4, 4, dtype=R.dtype, device=R.device)
    M[..., :3, :3] = R
    M[..., :3, 3] = t
    M[..., 3, 3] = 1
    return M


def invert_transform(M: Tensor) -> Tensor:
    """Inverse of a rigid (rotation + translation) transform (..., 4, 4)."""
    R = M[..., :3, :3]
    t = M[..., :3, 3]
    Rt = R.transpose(-1, -2)
    return make_transform(Rt, -(Rt @ t[..., None])[..., 0])


def transform_points(M: Tensor, x: Tensor) -> Tensor:
    """Apply (..., 4, 4) transforms to points (..., N, 3) -> (..., N, 3)."""
    # x'[..., n, i] = sum_j M[..., i, j] x[..., n, j] + M[..., i, 3]
    return torch.einsum("...ij,...nj->...ni", M[..., :3, :3], x) + M[..., None, :3, 3]


def lbs(rest: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """Linear blend skinning.

    rest: (V, 3) rest-pose vertices; weights: (V, K) convex weights; transforms:
    (..., K, 4, 4) mapping rest to posed space (column vectors).
    Returns (..., V, 3): x[v] = sum_k w[v, k] (R_k rest[v] + t_k).
    """
    if rest.ndim != 2 or rest.shape[-1] != 3:
        raise ValueError(f"lbs: rest must be (V, 3), got {tuple(rest.shape)}")
    if weights.shape[0] != rest.shape[0] or weights.shape[1] != transforms.shape[-3]:
        raise ValueError(
            f"lbs: weights {tuple(weights.shape)} do not match rest {tuple(rest.shape)} "
            f"and transforms {tuple(transforms.shape)}"
        )
    # A[..., v] = sum_k w[v, k] M[..., k]  (blend the 3x4 matrices, then apply once)
    A = torch.einsum("vk,...kij->...vij", weights, transforms[..., :3, :])
    return torch.einsum("...vij,vj->...vi", A[..., :3], rest) + A[..., 3]


def face_normals(verts: Tensor, faces: Tensor, normalize: bool = True) -> Tensor:
    """verts (..., V, 3), faces (F, 3) -> (..., F, 3) (area-weighted if not normalised)."""
    v0, v1, v2 = (verts[..., faces[:, i], :] for i in range(3))
    n = torch.cross(v1 - v0, v2 - v0, dim=-1)
    if normalize:
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return n


def vertex_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """Area-weighted vertex normals. verts (..., V, 3), faces (F, 3) -> (..., V, 3)."""
    fn = face_normals(verts, faces, normalize=False)  # (..., F, 3)
    vn = torch.zeros_like(verts)
    idx = faces.reshape(-1)  # (3F,)
    contrib = fn.unsqueeze(-2).expand(*fn.shape[:-1], 3, 3).reshape(*fn.shape[:-2], -1, 3)
    vn = vn.index_add(-2, idx, contrib)
    return vn / vn.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def edges_of_faces(faces: Tensor) -> Tensor:
    """Unique undirected edges (E, 2) with i < j of a triangle mesh faces (F, 3)."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 0)
    e = torch.sort(e, dim=1).values
    return torch.unique(e, dim=0)


def uniform_laplacian(faces: Tensor, num_vertices: int, dtype=torch.float32) -> Tensor:
    """Sparse (V, V) uniform graph Laplacian L = I - D^-1 A (rows sum to zero).

    Isolated vertices get a zero row.
    """
    e = edges_of_faces(faces)
    i = torch.cat([e[:, 0], e[:, 1]])
    j = torch.cat([e[:, 1], e[:, 0]])
    deg = torch.zeros(num_vertices, dtype=dtype).index_add_(0, i, torch.ones(i.shape[0], dtype=dtype))
    inv = torch.where(deg > 0, 1.0 / deg.clamp_min(1), torch.zeros_like(deg))
    has = (deg > 0).nonzero()[:, 0]
    rows = torch.cat([has, i])
    cols = torch.cat([has, j])
    vals = torch.cat([torch.ones(has.shape[0], dtype=dtype), -inv[i]])
    return torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, (num_vertices, num_vertices)).coalesce()
