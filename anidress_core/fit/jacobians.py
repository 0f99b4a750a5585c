"""The bone increments of the fit and the Jacobians chained through them (AniDress §3.2).

The unknowns are increments (omega_b, tau_b) of every bone: a rotation by the axis-angle
omega_b about the bone's current centre (the rig's rest centroid carried by G_b) followed by
a translation tau_b, composed onto G_b after each step (a local exponential chart, so no
parameterisation singularity is ever reached; the accumulated rotations are stored as
matrices). Skinning is linear in the weights, so dx/d(omega, tau) is exact
(:func:`skin_jacobian`); :func:`projection_jacobian` chains pixel residuals to vertices.
Shapes: V vertices, B bones, C cameras.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..geometry import axis_angle_to_matrix

__all__ = ["JACOBIAN_DTYPE", "apply_increment", "skin_jacobian", "projection_jacobian"]


#: dtype of the large Jacobian products in the Levenberg-Marquardt steps: float32 is ~20 %
#: faster per Gauss-Newton system than float64 at ~2e-7 relative error in H and g (skirt, 8
#: views), far below what the step needs; residuals, poses and H, g themselves stay float64.
JACOBIAN_DTYPE = torch.float32


def apply_increment(transforms: Tensor, centres: Tensor, delta: Tensor) -> Tensor:
    """Compose per-bone increments onto transforms.

    transforms (B, 4, 4) rest -> world; centres (B, 3) rest bone centres; delta (B, 6)
    = (omega, tau): rotate by axis-angle omega about the bone's current world centre
    c_w = R c + t, then translate by tau. ``x' = exp(omega) (R r + t - c_w) + c_w + tau``.
    """
    R, t = transforms[:, :3, :3], transforms[:, :3, 3]
    cw = torch.einsum("bij,bj->bi", R, centres) + t
    Q = axis_angle_to_matrix(delta[:, :3])
    out = transforms.clone()
    out[:, :3, :3] = Q @ R
    out[:, :3, 3] = torch.einsum("bij,bj->bi", Q, t - cw) + cw + delta[:, 3:]
    return out


def skin_jacobian(rig: RigParts, transforms: Tensor) -> Tensor:
    """dx/d(delta) at delta = 0: (V, 3, B * 6), columns (bone, [omega, tau]).

    x_v = sum_b W_vb (R_b r_v + t_b); d x_v / d omega_b = -W_vb [a_vb]_x with
    a_vb = R_b (r_v - c_b) (the vertex relative to the bone centre); d x_v / d tau_b = W_vb I.
    Written straight into the (V, 3, B, 6) layout (no stacked skew matrices, no permuted copy).
    """
    R = transforms[:, :3, :3]
    W = rig.weights
    V, B = W.shape
    a = torch.einsum("vj,bij->vbi", rig.rest, R) - torch.einsum("bij,bj->bi", R, rig.centres)[None]  # (V, B, 3)
    x, y, z = (W[..., None] * a).unbind(-1)
    J = torch.zeros(V, 3, B, 6, dtype=a.dtype, device=a.device)
    J[:, 0, :, 1], J[:, 0, :, 2] = z, -y  # -W [a]_x, rows of [[0, z, -y], [-z, 0, x], [y, -x, 0]]
    J[:, 1, :, 0], J[:, 1, :, 2] = -z, x
    J[:, 2, :, 0], J[:, 2, :, 1] = y, -x
    for i in range(3):
        J[:, i, :, 3 + i] = W
    return J.view(V, 3, B * 6)


def projection_jacobian(verts: Tensor, views: Views) -> tuple[Tensor, Tensor]:
    """uv (C, V, 2) and d uv / d x (C, V, 2, 3) of the pinhole projection of world points verts (V, 3)."""
    E = views.world_to_cam.to(verts.dtype)
    K = views.K.to(verts.dtype)
    Xc = torch.einsum("cij,vj->cvi", E[:, :3, :3], verts) + E[:, None, :3, 3]  # (C, V, 3)
    X, Y, Z = Xc.unbind(-1)
    iz = 1.0 / Z
    fx, s, cx = K[:, 0, 0, None], K[:, 0, 1, None], K[:, 0, 2, None]
    fy, cy = K[:, 1, 1, None], K[:, 1, 2, None]
    u = (fx * X + s * Y) * iz + cx
    v = fy * Y * iz + cy
    o = torch.zeros_like(X)
    du = torch.stack([fx * iz + o, s * iz + o, -(fx * X + s * Y) * iz * iz], -1)
    dv = torch.stack([o, fy * iz + o, -fy * Y * iz * iz], -1)
    D = torch.stack([du, dv], -2)  # (C, V, 2, 3) d uv / d X_cam
    return torch.stack([u, v], -1), D @ E[:, None, :3, :3]
