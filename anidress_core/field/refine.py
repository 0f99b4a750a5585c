"""Photometric refinement of joint transforms through the field's image loss (Animatable NeRF and HumanNeRF
refine body poses this way; AniDress's garment poses come from its fit alone).

A :class:`PoseRefiner` holds a rigid correction per frame and joint of a subset of the unified pose (the
garment bones): an axis-angle rotation ``omega`` about the joint's posed centre ``c`` and a translation ``tau``,

    S'_tk = [R(omega_tk) | c_tk - R(omega_tk) c_tk + tau_tk] S_tk,

zero at the start (S' = S, the fit's poses). The corrections are optimised with the field and pulled back
towards zero by :meth:`PoseRefiner.regulariser` (the fit stays the reference). Rotating about the posed
centre keeps a small rotation from swinging the bone's far side across the scene (a rotation about the
world origin would).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ..geometry import axis_angle_to_matrix

__all__ = ["PoseRefiner", "corrected_pose"]


def corrected_pose(S: Tensor, delta: Tensor, first: int, centres: Tensor) -> Tensor:
    """S (T, K, 4, 4) with joints ``first``..``first + J - 1`` corrected by delta (T, J, 6) (axis-angle,
    translation in metres) about centres (T, J, 3): returns (T, K, 4, 4), differentiable w.r.t. delta and S."""
    T, J = delta.shape[:2]
    R = axis_angle_to_matrix(delta[..., :3].reshape(-1, 3)).view(T, J, 3, 3)
    t = centres - (R @ centres[..., None])[..., 0] + delta[..., 3:]
    C = torch.zeros(T, J, 4, 4, dtype=S.dtype, device=S.device)
    C[..., :3, :3] = R
    C[..., :3, 3] = t
    C[..., 3, 3] = 1
    part = C @ S[:, first:first + J]
    return torch.cat([S[:, :first], part, S[:, first + J:]], 1)


class PoseRefiner(nn.Module):
    """Per-frame rigid corrections of joints ``first``..``first + J - 1`` of the unified pose.

    centres (T, J, 3): the joints' posed centres (e.g. the garment bones' weighted rest vertices, posed by
    the fit). ``forward(S (T, K, 4, 4)) -> (T, K, 4, 4)``.
    """

    def __init__(self, centres: Tensor, first: int):
        super().__init__()
        self.first = int(first)
        self.register_buffer("centres", centres.detach().float().clone())
        self.delta = nn.Parameter(torch.zeros(*centres.shape[:2], 6))

    def forward(self, S: Tensor) -> Tensor:
        return corrected_pose(S, self.delta.to(S.dtype), self.first, self.centres.to(S.dtype))

    def regulariser(self, radius_m: float = 0.1) -> Tensor:
        """Mean squared correction, the rotation as the displacement it gives at ``radius_m`` from the centre
        (metres^2): 0 at the fit's poses."""
        return (self.delta[..., :3].square().sum(-1) * radius_m ** 2 + self.delta[..., 3:].square().sum(-1)).mean()
