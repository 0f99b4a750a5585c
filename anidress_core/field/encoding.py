"""Multiresolution hash encoding (Müller, Evans, Schied, Keller, "Instant Neural Graphics
Primitives with a Multiresolution Hash Encoding", SIGGRAPH 2022), in plain torch.

A point ``x`` in the unit cube is looked up in L grids of growing resolution
``r_l = floor(r_min * b^l)``, ``b = exp((ln r_max - ln r_min) / (L - 1))``. Each grid
vertex owns a feature vector (F numbers) in a table of ``2^log2_size`` entries per level:
coarse levels whose ``(r_l + 1)^3`` vertices fit are indexed densely, finer ones through
the spatial hash of the paper, ``(i * 1) xor (j * 2654435761) xor (k * 805459861) mod T``.
The encoding is the trilinear interpolation of the 8 corner features per level,
concatenated over levels: (N, 3) -> (N, L * F).

:func:`hash_encode` runs two Warp kernels (:mod:`anidress_core.field.kernels`: the
encoding, one thread per sample and level; its backward pass, the table gradient as a
scatter-add and the input gradient from the trilinear derivative, one thread per sample),
nothing of size (N, L, 8) in memory. :func:`hash_encode_torch` is the same in batched torch
(one custom autograd function, :class:`_HashInterp`), and :func:`hash_encode_reference` the
slow, obvious version; the tests compare all three.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import warp as wp
from torch import Tensor, nn

from . import kernels

__all__ = ["HashGridConfig", "HashGrid", "hash_encode", "hash_encode_torch", "hash_encode_reference",
           "level_resolutions"]

_PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class HashGridConfig:
    """Hyper-parameters of :class:`HashGrid` (instant-ngp names in brackets)."""

    levels: int = 8
    """Number of resolution levels L."""
    features: int = 2
    """Features per level F."""
    log2_size: int = 17
    """log2 of the table rows per level T."""
    base_resolution: int = 16
    """Coarsest grid resolution r_min (cells per axis)."""
    max_resolution: int = 256
    """Finest grid resolution r_max."""

    @property
    def out_dim(self) -> int:
        return self.levels * self.features


def level_resolutions(cfg: HashGridConfig) -> list[int]:
    """Cells per axis of every level, ``floor(r_min * b^l)``."""
    if cfg.levels == 1:
        return [int(cfg.base_resolution)]
    b = math.exp((math.log(cfg.max_resolution) - math.log(cfg.base_resolution)) / (cfg.levels - 1))
    return [int(math.floor(cfg.base_resolution * b**lvl + 1e-6)) for lvl in range(cfg.levels)]


def _axis_weights(f: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-axis trilinear weights (2, L, N) = (1 - f_a, f_a) of fractions f (3, L, N)."""
    return tuple(torch.stack([1 - f[a], f[a]]) for a in range(3))  # type: ignore[return-value]


class _HashInterp(torch.autograd.Function):
    """out[l, n, :] = sum_c w_c(f[:, l, n]) table[idx[c, l, n], :] -> (L, N, F).

    f (3, L, N) cell fractions, idx (8, L, N) corner entries (corner c = 4 dx + 2 dy + dz),
    table (L * T, F) entry-major (an entry's features side by side). The backward pass is
    written out: scatter-add for the table, the trilinear derivative for f (autograd through
    the 8 weight products costs several times more on a CPU).
    """

    @staticmethod
    def forward(ctx, table: Tensor, f: Tensor, idx: Tensor) -> Tensor:
        wx, wy, wz = _axis_weights(f)
        # w[dx, dy, dz] = wx[dx] wy[dy] wz[dz]  (2, 2, 2, L, N)
        w = (wx[:, None, None] * (wy[:, None] * wz[None])[None]).reshape(8, *f.shape[1:])
        flat = idx.reshape(-1)
        ctx.save_for_backward(table, f, idx, w)
        F = table.shape[1]
        return (w[..., None] * table.index_select(0, flat).view(*w.shape, F)).sum(0)

    @staticmethod
    def backward(ctx, g: Tensor):
        table, f, idx, w = ctx.saved_tensors
        flat = idx.reshape(-1)
        grad_table = grad_f = None
        if ctx.needs_input_grad[0]:
            # grad_table[idx[c,l,n], k] += w[c,l,n] g[l,n,k]  (the transposed gather)
            grad_table = torch.zeros_like(table)
            grad_table.index_add_(0, flat, (w[..., None] * g[None]).reshape(-1, table.shape[1]))
        if ctx.needs_input_grad[1]:
            # gw[c, l, n] = <table[idx[c,l,n], :], g[l, n, :]>, then the trilinear derivative:
            # d/df_x = sum_{dy,dz} (gw[1,dy,dz] - gw[0,dy,dz]) wy[dy] wz[dz], etc.
            gw = (table.index_select(0, flat).view(*w.shape, table.shape[1]) * g[None]).sum(-1)
            gw = gw.view(2, 2, 2, *f.shape[1:])
            wx, wy, wz = _axis_weights(f)
            gx = ((gw[1] - gw[0]) * (wy[:, None] * wz[None])).sum((0, 1))
            gy = ((gw[:, 1] - gw[:, 0]) * (wx[:, None] * wz[None])).sum((0, 1))
            gz = ((gw[:, :, 1] - gw[:, :, 0]) * (wx[:, None] * wy[None])).sum((0, 1))
            grad_f = torch.stack([gx, gy, gz])
        return grad_table, grad_f, None


def _corner_indices(x: Tensor, res: list[int], log2_size: int) -> tuple[Tensor, Tensor]:
    """Corner entries (8, L, N) into the flattened (L * T) table and cell fractions (3, L, N).

    Corner c = 4 * dx + 2 * dy + dz. The fractions are differentiable w.r.t. x.
    Everything is laid out with N innermost so the element-wise work runs on contiguous
    memory. Hashing is done modulo T = 2^log2_size from the start (multiplication and
    xor commute with taking the low bits), so int32 suffices.
    """
    T = 1 << log2_size
    L = len(res)
    r = torch.tensor(res, dtype=x.dtype, device=x.device)[:, None]  # (L, 1)
    # 1. continuous grid position per level, cell origin and fraction: (3, L, N)
    pos = x.t()[:, None, :] * r[None]
    i0 = torch.minimum(pos.detach().floor(), (r - 1)[None]).clamp_min(0)
    f = pos - i0
    i0 = i0.to(torch.int32)
    # 2. per-axis terms of the entry formula
    dense = torch.tensor([(q + 1) ** 3 <= T for q in res], device=x.device)[:, None]  # (L, 1)
    s = torch.tensor([q + 1 for q in res], dtype=torch.int32, device=x.device)[:, None]
    mult = [torch.where(dense, torch.ones_like(s), torch.full_like(s, _PRIMES[0] & (T - 1))),
            torch.where(dense, s, torch.full_like(s, _PRIMES[1] & (T - 1))),
            torch.where(dense, s * s, torch.full_like(s, _PRIMES[2] & (T - 1)))]
    # dense levels: i + j (r+1) + k (r+1)^2 ; hashed: (i p0 xor j p1 xor k p2) mod T
    ta = [((i0[a] * mult[a]) & (T - 1), ((i0[a] + 1) * mult[a]) & (T - 1)) for a in range(3)]
    rows = []
    for dx in (0, 1):
        for dy in (0, 1):
            sxy = ta[0][dx] + ta[1][dy]
            xxy = ta[0][dx] ^ ta[1][dy]
            for dz in (0, 1):
                rows.append(torch.where(dense, sxy + ta[2][dz], xxy ^ ta[2][dz]))
    idx = torch.stack(rows) + (torch.arange(L, dtype=torch.int32, device=x.device) * T)[None, :, None]
    return idx.long(), f


def _check(x: Tensor, table: Tensor, cfg: HashGridConfig) -> None:
    if x.ndim != 2 or x.shape[-1] != 3:
        raise ValueError(f"hash_encode: x must be (N, 3), got {tuple(x.shape)}")
    T = 1 << cfg.log2_size
    if table.shape != (cfg.levels * T, cfg.features):
        raise ValueError(f"hash_encode: table must be ({cfg.levels * T}, {cfg.features}), got {tuple(table.shape)}")


class _HashWarp(torch.autograd.Function):
    """:func:`hash_encode` through the Warp kernels ``hash_fwd`` / ``hash_bwd``; the forward pass also
    keeps d out / d x (N, L F, 3) when x needs a gradient (the corners' features are in cache then)."""

    @staticmethod
    def forward(ctx, table: Tensor, x: Tensor, res: Tensor, dense: Tensor, log2_size: int) -> Tensor:
        dev, stream = kernels.device_of(x, "hash_encode")
        N, L, F = x.shape[0], res.shape[0], table.shape[1]
        want_dx = ctx.needs_input_grad[1]
        out = x.new_empty(N, L * F)
        dout = x.new_empty(N, L * F, 3) if want_dx else x.new_empty(1, 1, 3)
        wp.launch(kernels.hash_fwd, N * L,
                  inputs=[kernels.array(x), kernels.array(table), kernels.array(res), kernels.array(dense), log2_size,
                          int(want_dx), wp.from_torch(out), wp.from_torch(dout)],
                  device=dev, stream=stream)
        ctx.save_for_backward(x, res, dense, dout)
        ctx.log2_size, ctx.table_shape = log2_size, table.shape
        return out

    @staticmethod
    def backward(ctx, g: Tensor):
        x, res, dense, dout = ctx.saved_tensors
        g = g.contiguous()
        grad_table = grad_x = None
        if ctx.needs_input_grad[0]:
            grad_table = g.new_zeros(ctx.table_shape)
            dev, stream = kernels.device_of(x, "hash_encode")
            wp.launch(kernels.hash_bwd, x.shape[0] * res.shape[0],
                      inputs=[kernels.array(x), kernels.array(g), kernels.array(res), kernels.array(dense),
                              ctx.log2_size, wp.from_torch(grad_table)],
                      device=dev, stream=stream)
        if ctx.needs_input_grad[1]:
            # grad_x[n, a] = sum_j g[n, j] dout[n, j, a]
            grad_x = torch.bmm(g[:, None, :], dout)[:, 0]
        return grad_table, grad_x, None, None, None


def hash_encode(x: Tensor, table: Tensor, cfg: HashGridConfig) -> Tensor:
    """Encode points x (N, 3) in [0, 1]^3 (clamped) with ``table`` (L * T, F) -> (N, L * F).

    Differentiable w.r.t. ``table`` and ``x`` (zero where x was clamped); float32 or float64
    (x is cast to the table's type). Warp kernels; :func:`hash_encode_torch` is the same in torch.
    """
    _check(x, table, cfg)
    if x.shape[0] == 0:
        return x.new_zeros(0, cfg.out_dim, dtype=table.dtype)
    res = level_resolutions(cfg)
    T = 1 << cfg.log2_size
    r = torch.tensor(res, dtype=torch.int32, device=x.device)
    dense = torch.tensor([int((q + 1) ** 3 <= T) for q in res], dtype=torch.int32, device=x.device)
    return _HashWarp.apply(table.contiguous(), x.to(table.dtype).contiguous(), r, dense, cfg.log2_size)


def hash_encode_torch(x: Tensor, table: Tensor, cfg: HashGridConfig) -> Tensor:
    """:func:`hash_encode` in batched torch (one custom autograd function; the kernels' reference)."""
    _check(x, table, cfg)
    if x.shape[0] == 0:
        return x.new_zeros(0, cfg.out_dim, dtype=table.dtype)
    idx, f = _corner_indices(x.clamp(0, 1), level_resolutions(cfg), cfg.log2_size)
    out = _HashInterp.apply(table, f.to(table.dtype), idx)  # (L, N, F)
    return out.permute(1, 0, 2).reshape(x.shape[0], -1)


def hash_encode_reference(x: Tensor, table: Tensor, cfg: HashGridConfig) -> Tensor:
    """Slow reference of :func:`hash_encode`: loops over levels and corners, plain indexing."""
    T = 1 << cfg.log2_size
    x = x.clamp(0, 1)
    out = []
    for lvl, r in enumerate(level_resolutions(cfg)):
        pos = x * r
        i0 = torch.minimum(pos.detach().floor(), torch.full_like(pos, r - 1)).clamp_min(0)
        f = pos - i0
        i0 = i0.long()
        acc = 0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    i, j, k = i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz
                    if (r + 1) ** 3 <= T:
                        row = i + j * (r + 1) + k * (r + 1) ** 2
                    else:
                        row = (i * _PRIMES[0] ^ j * _PRIMES[1] ^ k * _PRIMES[2]) % T
                    wgt = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) \
                        * (f[:, 2] if dz else 1 - f[:, 2])
                    acc = acc + wgt[:, None] * table[lvl * T + row]
        out.append(acc)
    return torch.cat(out, -1)


class HashGrid(nn.Module):
    """Stores the hash table (L * T, F); ``forward(x (N, 3) in [0,1]^3) -> (N, L * F)``."""

    def __init__(self, cfg: HashGridConfig = HashGridConfig(), generator: torch.Generator | None = None):
        super().__init__()
        self.cfg = cfg
        rows = cfg.levels * (1 << cfg.log2_size)
        # instant-ngp: table initialised uniformly in [-1e-4, 1e-4]
        self.table = nn.Parameter(torch.rand(rows, cfg.features, generator=generator) * 2e-4 - 1e-4)

    @property
    def out_dim(self) -> int:
        return self.cfg.out_dim

    def forward(self, x: Tensor) -> Tensor:
        return hash_encode(x, self.table, self.cfg)
