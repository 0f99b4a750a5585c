"""Backward deformation: observation space -> canonical space (AniDress §3.3, eq. 2-3).

The unified pose S stacks K = 24 body joint transforms and B garment bone transforms,
all mapping the canonical (body rest) frame to the world (column vectors). A point
x_o of frame t is mapped to the canonical frame by

    x_c = sum_k w_o^k T_k^-1 x_o,     w_o^k = W_k(T_k^-1 x_o) / sum_i W_i(T_i^-1 x_o)

with W the canonical motion-weight volume (HumanNeRF's formulation): every joint
proposes its own canonical position T_k^-1 x_o, the volume says how much that joint
owns the point it proposes, and the proposals are blended. The sum of the volume
weights (before normalisation) is the foreground likelihood that gates density
(HumanNeRF multiplies alpha by it).

Joint culling (DESIGN.md §6): only the ``M`` candidate joints of a sample (from the
occupancy grid, :mod:`anidress_core.field.sampler`) are evaluated; candidate index K
means "no joint" and contributes nothing.

:func:`inverse_lbs` is the exact inverse of forward LBS for known per-point weights,
the reference the round-trip tests use.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .weights import sample_channels

__all__ = ["WarpResult", "backward_warp", "forward_lbs", "inverse_lbs"]


class WarpResult(NamedTuple):
    x_c: Tensor
    """(N, 3) canonical points."""
    fg: Tensor
    """(N,) foreground likelihood in [0, 1]: sum of the candidates' volume weights, clamped."""
    weights: Tensor
    """(N, M) volume weight of every candidate at its own canonical proposal."""


def forward_lbs(x_c: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """x_o = sum_k w_k T_k x_c for points x_c (N, 3), weights (N, K), transforms (K | N, K, 4, 4)."""
    # A[n] = sum_k w[n, k] T[(n,) k]  (blend the 3x4 matrices, then apply once)
    A = torch.einsum("nk,...kij->nij", weights, transforms[..., :3, :]) if transforms.ndim == 3 \
        else torch.einsum("nk,nkij->nij", weights, transforms[..., :3, :])
    return (A[:, :, :3] @ x_c[..., None])[..., 0] + A[:, :, 3]


def inverse_lbs(x_o: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """Exact inverse of :func:`forward_lbs`: x_c = (sum_k w_k T_k)^-1 x_o.

    x_o (N, 3), weights (N, K) the weights of the canonical point, transforms
    (K | N, K, 4, 4). The blended 3x3 part must be invertible (true for convex weights
    of rotations that are not opposite).
    """
    A = torch.einsum("nk,...kij->nij", weights, transforms[..., :3, :]) if transforms.ndim == 3 \
        else torch.einsum("nk,nkij->nij", weights, transforms[..., :3, :])
    return torch.linalg.solve(A[:, :, :3], (x_o - A[:, :, 3])[..., None])[..., 0]


def backward_warp(x_o: Tensor, frame: Tensor | None, inv_transforms: Tensor, cand: Tensor, volume: Tensor,
                  box: Tensor, eps: float = 1e-4) -> WarpResult:
    """HumanNeRF-style backward warp of observation points over candidate joints.

    x_o (N, 3) world points; frame (N,) long index of each point's frame into
    inv_transforms (T, K, 4, 4), or None with inv_transforms (K, 4, 4) for one frame:
    T_k^-1 (world -> canonical per joint); cand (N, M) long in [0, K] (K = no joint);
    volume (K + 1, D, H, W) motion weights over ``box`` (2, 3).
    """
    K = inv_transforms.shape[-3]
    N, M = cand.shape
    # 0. only (sample, candidate) pairs naming a joint are evaluated (packed)
    valid = cand < K
    n_idx, m_idx = valid.nonzero(as_tuple=True)
    c = cand[n_idx, m_idx]
    # 1. per-pair canonical proposals p = T_c^-1 x_o, from a contiguous (T * K, 12) table
    #    of the 3x4 parts
    table = inv_transforms[..., :3, :].reshape(-1, 12)
    row = c if frame is None else frame[n_idx] * K + c
    A = table[row].view(-1, 3, 4)  # (P, 3, 4)
    xo = x_o[n_idx]
    # p[q, i] = sum_j A[q, i, j] x[q, j] + A[q, i, 3]
    p = (A[:, :, :3] * xo[:, None, :]).sum(-1) + A[:, :, 3]  # (P, 3)
    # 2. volume weight of each candidate at its own proposal
    wq = sample_channels(volume, box, p[:, None], c[:, None])[:, 0]  # (P,)
    # 3. blend: x_c = sum_m w p / sum_m w ; foreground likelihood = sum_m w
    s = x_o.new_zeros(N).index_add(0, n_idx, wq)
    num = x_o.new_zeros(N, 3).index_add(0, n_idx, wq[:, None] * p)
    x_c = num / s.clamp_min(eps)[:, None]
    w = x_o.new_zeros(N, M).index_put((n_idx, m_idx), wq)
    return WarpResult(x_c=x_c, fg=s.clamp(max=1.0), weights=w)
