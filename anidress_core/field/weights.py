"""Motion-weight volume W in canonical space (AniDress §3.3, supplementary "Pose-driven
Rendering Network"; HumanNeRF, Weng et al. CVPR 2022, §4 "Skeletal motion").

One volume over the canonical box holds K + 1 channels: one per joint of the unified
pose S = 24 body joints (+) B garment bones, plus a background channel. It is decoded
by a 3D CNN from a fixed random latent code and added, in log space, to a prior:

    W(x) = softmax_k( CNN(z)_k(x) + log P_k(x) )

so the network learns the residue of the prior (HumanNeRF initialises with Gaussian
bone volumes the same way). The priors:

* body: one Gaussian ellipsoid per body joint around the bone it moves, fitted to the
  rest-pose body vertices that the joint dominates (mean and covariance, widened by
  ``scale``): :func:`body_bone_priors`;
* garment: the skinning weights around the garment T-pose vertices (AniDress Tab.
  "vertices prior": better than priors around the virtual bones, which do not lie on
  the garment): a proximity ``g(x) = exp(-d(x)^2 / 2 s^2)`` to the nearest garment
  vertex times the Gaussian-kernel average of the nearest vertices' weights:
  :func:`vertex_priors`;
* combination (:func:`combine_priors`): body channels ``(1 - g) P_body``, garment
  channels ``g W_garment``, background ``max(0, 1 - sum)``. In the ``body_only``
  variant there are no garment channels and the garment region carries the body
  skinning weights of the garment vertices instead.

Volume layout: (K + 1, D, H, W) with depth along canonical z, height along y, width
along x (``grid_sample`` order); voxel centres span the box corners (align_corners).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "grid_points",
    "body_bone_priors",
    "vertex_priors",
    "combine_priors",
    "sample_channels",
    "sample_channels_reference",
    "MotionWeightVolume",
]


def grid_points(box: Tensor, res: tuple[int, int, int]) -> Tensor:
    """Voxel centres (D, H, W, 3) of a (D, H, W) = (z, y, x) grid spanning ``box`` (2, 3)."""
    D, H, W = res
    zs = torch.linspace(float(box[0, 2]), float(box[1, 2]), D, dtype=box.dtype)
    ys = torch.linspace(float(box[0, 1]), float(box[1, 1]), H, dtype=box.dtype)
    xs = torch.linspace(float(box[0, 0]), float(box[1, 0]), W, dtype=box.dtype)
    z, y, x = torch.meshgrid(zs, ys, xs, indexing="ij")
    return torch.stack([x, y, z], -1)


def body_bone_priors(verts: Tensor, weights: Tensor, joints: Tensor, pts: Tensor, scale: float = 1.5,
                     min_std: float = 0.02) -> Tensor:
    """Gaussian ellipsoid of every body joint evaluated at ``pts`` (P, 3) -> (J, P) in [0, 1].

    verts (V, 3) rest body, weights (V, J) its skinning weights, joints (J, 3) rest
    joints. Ellipsoid of joint j: mean and covariance of the vertices whose largest
    weight is j, each axis std widened by ``scale`` and at least ``min_std`` metres;
    a joint that dominates fewer than 4 vertices gets a sphere of std ``3 min_std`` at
    the joint. Value ``exp(-0.5 (x - mu)^T S^-1 (x - mu))``.
    """
    J = weights.shape[1]
    owner = weights.argmax(1)
    mus, covs = [], []
    eye = torch.eye(3, dtype=verts.dtype, device=verts.device)
    for j in range(J):  # J = 24: a loop over joints, not over points
        v = verts[owner == j]
        if v.shape[0] < 4:
            mus.append(joints[j])
            covs.append(eye * (3 * min_std) ** 2)
            continue
        mu = v.mean(0)
        C = (v - mu).T @ (v - mu) / v.shape[0]
        evals, evecs = torch.linalg.eigh(C)
        std = (evals.clamp_min(0).sqrt() * scale).clamp_min(min_std)
        mus.append(mu)
        covs.append(evecs @ torch.diag(std**2) @ evecs.T)
    mu = torch.stack(mus)  # (J, 3)
    prec = torch.linalg.inv(torch.stack(covs))  # (J, 3, 3)
    d = pts[None] - mu[:, None]  # (J, P, 3)
    # m[j, p] = d[j,p]^T prec[j] d[j,p]
    m = torch.einsum("jpa,jab,jpb->jp", d, prec, d)
    return torch.exp(-0.5 * m)


def vertex_priors(verts: Tensor, weights: Tensor, pts: Tensor, sigma: float, k: int = 4,
                  chunk: int = 8192) -> tuple[Tensor, Tensor]:
    """Skinning weights around mesh vertices, evaluated at ``pts`` (P, 3).

    verts (V, 3), weights (V, K). Returns proximity (P,) = exp(-d^2 / 2 sigma^2) with d
    the distance to the nearest vertex, and weights (K, P): the average of the ``k``
    nearest vertices' weights with Gaussian kernel exp(-d_i^2 / 2 sigma^2) (relative to
    the nearest, so it stays defined far from the mesh), rows normalised to sum 1.
    """
    k = min(k, verts.shape[0])
    prox, wout = [], []
    for s in range(0, pts.shape[0], chunk):
        d2 = torch.cdist(pts[s:s + chunk], verts).square()  # (p, V)
        dk, ik = torch.topk(d2, k, dim=1, largest=False)  # (p, k)
        prox.append(torch.exp(-0.5 * dk[:, 0] / sigma**2))
        kern = torch.exp(-0.5 * (dk - dk[:, :1]) / sigma**2)  # (p, k), 1 for the nearest
        w = (kern[..., None] * weights[ik]).sum(1)  # (p, K)
        wout.append(w / w.sum(-1, keepdim=True).clamp_min(1e-12))
    return torch.cat(prox), torch.cat(wout).T


def combine_priors(body: Tensor, garment_prox: Tensor | None = None, garment_weights: Tensor | None = None,
                   garment_body_weights: Tensor | None = None) -> Tensor:
    """Prior volume (K + 1, P) with the background channel last.

    body (J, P) ellipsoids; garment_prox (P,) proximity to the garment; either
    garment_weights (B, P) (variant ``full``: channels J..J+B-1) or
    garment_body_weights (J, P) (variant ``body_only``: added to the body channels).
    Without a garment (tight clothes) the prior is the body ellipsoids alone.
    """
    if garment_prox is None:
        chans = body
    else:
        g = garment_prox[None]
        if garment_weights is not None:
            chans = torch.cat([(1 - g) * body, g * garment_weights], 0)
        elif garment_body_weights is not None:
            chans = (1 - g) * body + g * garment_body_weights
        else:
            raise ValueError("combine_priors: garment_prox needs garment_weights or garment_body_weights")
    bg = (1 - chans.sum(0, keepdim=True)).clamp(0, 1)
    return torch.cat([chans, bg], 0)


def _voxel_coords(pts: Tensor, box: Tensor, res: tuple[int, int, int]) -> Tensor:
    """Continuous voxel coordinates (..., 3) in (x, y, z) = (W, H, D) index units."""
    size = torch.tensor([res[2] - 1, res[1] - 1, res[0] - 1], dtype=pts.dtype, device=pts.device)
    return (pts - box[0]) / (box[1] - box[0]) * size


class _TrilinearTake(torch.autograd.Function):
    """out[n] = trilinear value of the flat volume at voxel coordinates u[n] in channel base[n].

    flat (C * D * H * W,), u (..., 3) continuous (x, y, z) voxel coordinates, base (...)
    channel offsets ``c * D * H * W``; corners outside the grid read 0. The backward pass
    is written out (scatter-add for the volume, the trilinear derivative for u), which
    on a CPU is several times cheaper than autograd through the 8-corner expression.
    """

    @staticmethod
    def forward(ctx, flat: Tensor, u: Tensor, base: Tensor, dhw: tuple[int, int, int]) -> Tensor:
        D, H, W = dhw
        i0 = u.floor()
        f = u - i0
        i0 = i0.long()
        hi = (W - 1, H - 1, D - 1)
        # per-axis corner index (clamped), in-range flag and weight: index 0 -> i0, 1 -> i0 + 1
        ax = []
        for a in range(3):
            i = torch.stack([i0[..., a], i0[..., a] + 1])  # (2, ...)
            ok = (i >= 0) & (i <= hi[a])
            ax.append((i.clamp(0, hi[a]), ok, torch.stack([1 - f[..., a], f[..., a]])))
        (ix, okx, wx), (iy, oky, wy), (iz, okz, wz) = ax
        # corner (dx, dy, dz) -> tensors of shape (2, 2, 2, ...)
        idx = base + (iz[None, None] * H + iy[None, :, None]) * W + ix[:, None, None]
        ok = okx[:, None, None] & oky[None, :, None] & okz[None, None]
        vals = flat.take(idx) * ok.to(flat.dtype)
        wyz = wy[:, None] * wz[None]  # (2, 2, ...)
        w = wx[:, None, None] * wyz[None]
        ctx.save_for_backward(idx, vals, w, wx, wy, wz)
        ctx.numel = flat.numel()
        ctx.ok = ok
        return (w * vals).sum((0, 1, 2))

    @staticmethod
    def backward(ctx, g: Tensor):
        idx, vals, w, wx, wy, wz = ctx.saved_tensors
        grad_flat = grad_u = None
        if ctx.needs_input_grad[0]:
            contrib = (w * g * ctx.ok.to(g.dtype)).reshape(-1)
            grad_flat = torch.zeros(ctx.numel, dtype=g.dtype, device=g.device).index_add_(0, idx.reshape(-1), contrib)
        if ctx.needs_input_grad[1]:
            # d out / d f_x = sum_{dy,dz} (v[1,dy,dz] - v[0,dy,dz]) wy[dy] wz[dz], etc.
            dvx = vals[1] - vals[0]  # (2, 2, ...)
            dvy = vals[:, 1] - vals[:, 0]  # (2, 2, ...) over (dx, dz)
            dvz = vals[:, :, 1] - vals[:, :, 0]  # (2, 2, ...) over (dx, dy)
            gx = (dvx * (wy[:, None] * wz[None])).sum((0, 1))
            gy = (dvy * (wx[:, None] * wz[None])).sum((0, 1))
            gz = (dvz * (wx[:, None] * wy[None])).sum((0, 1))
            grad_u = torch.stack([gx, gy, gz], -1) * g[..., None]
        return grad_flat, grad_u, None, None


def sample_channels(volume: Tensor, box: Tensor, pts: Tensor, chans: Tensor) -> Tensor:
    """Trilinear value of channel ``chans[n, m]`` at ``pts[n, m]``: (N, M, 3), (N, M) -> (N, M).

    volume (C, D, H, W); points outside the box read 0 (zero padding, as grid_sample).
    Differentiable w.r.t. ``volume`` and ``pts``.
    """
    C, D, H, W = volume.shape
    u = _voxel_coords(pts, box, (D, H, W))  # (N, M, 3)
    # keep far-away points finite in integer arithmetic (they read zeros either way)
    u = u.clamp(-2, max(D, H, W) + 1)
    return _TrilinearTake.apply(volume.reshape(-1), u, chans * (D * H * W), (D, H, W))


def sample_channels_reference(volume: Tensor, box: Tensor, pts: Tensor, chans: Tensor) -> Tensor:
    """Slow reference of :func:`sample_channels` through ``F.grid_sample`` of every channel."""
    g = (pts - box[0]) / (box[1] - box[0]) * 2 - 1  # (N, M, 3) in [-1, 1], (x, y, z)
    allc = F.grid_sample(volume[None], g[None, :, :, None].to(volume.dtype), mode="bilinear",
                         padding_mode="zeros", align_corners=True)[0, :, :, :, 0]  # (C, N, M)
    return allc.gather(0, chans[None]).squeeze(0)


class MotionWeightVolume(nn.Module):
    """W = softmax(CNN(z) + log P) over the canonical box (HumanNeRF's motion-weight volume).

    prior: (K + 1, D, H, W) with D = H = W = 4 * 2^n; box (2, 3). The decoder maps a fixed
    random latent (``latent`` numbers, a buffer: the paper's "fixed random latent code")
    through a linear layer to a 4^3 volume of ``width`` channels, then n transposed
    convolutions (kernel 4, stride 2) halving the channels, the last one giving the K + 1
    residue channels. The last layer starts at zero, so W starts as the normalised prior.
    """

    def __init__(self, prior: Tensor, box: Tensor, latent: int = 256, width: int = 64,
                 generator: torch.Generator | None = None):
        super().__init__()
        C, D, H, W = prior.shape
        if not (D == H == W) or D < 8 or D & (D - 1):
            raise ValueError(f"MotionWeightVolume: prior must be (K+1, R, R, R) with R = 4 * 2^n >= 8, "
                             f"got {tuple(prior.shape)}")
        self.register_buffer("box", torch.as_tensor(box, dtype=torch.float32).clone())
        self.register_buffer("log_prior", torch.log(prior.float().clamp_min(1e-8)))
        self.register_buffer("latent", torch.randn(latent, generator=generator))
        n = D.bit_length() - 3  # 4 * 2^n = D
        self.width = width
        self.fc = nn.Linear(latent, width * 64)
        layers: list[nn.Module] = []
        c = width
        for i in range(n):
            last = i == n - 1
            out = C if last else max(8, c // 2)
            layers.append(nn.ConvTranspose3d(c, out, 4, stride=2, padding=1))
            if not last:
                layers.append(nn.LeakyReLU(0.2, inplace=True))
            c = out
        self.decoder = nn.Sequential(*layers)
        nn.init.zeros_(self.decoder[-1].weight)
        nn.init.zeros_(self.decoder[-1].bias)

    @property
    def num_channels(self) -> int:
        return self.log_prior.shape[0]

    def residue(self) -> Tensor:
        """CNN(z): (K + 1, D, H, W)."""
        h = F.leaky_relu(self.fc(self.latent), 0.2).view(1, self.width, 4, 4, 4)
        return self.decoder(h)[0]

    def forward(self) -> Tensor:
        """The weight volume (K + 1, D, H, W), softmax over channels."""
        return torch.softmax(self.residue() + self.log_prior, dim=0)
