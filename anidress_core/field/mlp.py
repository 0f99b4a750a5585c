"""Canonical radiance field F_c: canonical point -> (colour, density) (AniDress §3.3).

A multiresolution hash encoding of the point in the canonical box followed by a small
MLP, as in instant-ngp (Müller et al. 2022): the first output is the log-density
(activated by a truncated exponential), the others feed a colour head (sigmoid). The
field has no view dependence (HumanNeRF's canonical MLP has none either).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from .encoding import HashGrid, HashGridConfig

__all__ = ["CanonicalField", "trunc_exp", "mlp"]


class _TruncExp(torch.autograd.Function):
    """exp(x) whose gradient is exp(min(x, 15)) (instant-ngp's truncated exponential)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15))


def trunc_exp(x: Tensor) -> Tensor:
    """Density activation: exp with a gradient clamped at exp(15)."""
    return _TruncExp.apply(x)


def mlp(d_in: int, width: int, depth: int, d_out: int) -> nn.Sequential:
    """``depth`` hidden ReLU layers of ``width`` units, linear output."""
    layers: list[nn.Module] = []
    d = d_in
    for _ in range(depth):
        layers += [nn.Linear(d, width), nn.ReLU(inplace=True)]
        d = width
    layers.append(nn.Linear(d, d_out))
    return nn.Sequential(*layers)


class CanonicalField(nn.Module):
    """F_c over an axis-aligned canonical box.

    box: (2, 3) min / max corner of the canonical box (metres, body canonical frame).
    ``forward(x (N, 3))`` returns rgb (N, 3) in [0, 1] and sigma (N,) >= 0 (1/metre);
    points outside the box get zero density.
    """

    def __init__(self, box: Tensor, grid: HashGridConfig = HashGridConfig(), width: int = 64,
                 geo_features: int = 15, density_bias: float = 3.0):
        super().__init__()
        self.register_buffer("box", torch.as_tensor(box, dtype=torch.float32).clone())
        self.encoding = HashGrid(grid)
        # density net: encoding -> (log-density, geometry features); colour net: features -> rgb
        self.density_net = mlp(grid.out_dim, width, 1, 1 + geo_features)
        self.color_net = mlp(geo_features, width, 1, 3)
        self.density_bias = float(density_bias)

    def normalise(self, x: Tensor) -> Tensor:
        """Canonical metres -> unit cube of the box."""
        return (x - self.box[0]) / (self.box[1] - self.box[0])

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        u = self.normalise(x)
        inside = ((u >= 0) & (u <= 1)).all(-1)
        h = self.density_net(self.encoding(u))
        sigma = trunc_exp(h[:, 0] + self.density_bias) * inside.to(h.dtype)
        rgb = torch.sigmoid(self.color_net(h[:, 1:]))
        return rgb, sigma
