"""Image sampling for the fit: Gaussian blur, bilinear samples at vertex projections, masks.

Pixel centres at integer coordinates (:mod:`anidress_core.raster`). Shapes: C cameras, H, W
image size, V vertices, N samples.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as Fnn
from torch import Tensor

__all__ = ["gaussian_taps", "blurred", "image_features", "sample", "sample_blurred", "eroded", "pixel_ok",
           "CHROMA_EPS", "chromaticity"]


def gaussian_taps(blur: float, device=None) -> tuple[int, Tensor]:
    """Radius r = ceil(3 blur) (at least 1) and the normalised float64 taps (2r + 1,) of a
    Gaussian of ``blur`` pixels; ``blur`` 0: (0, [1])."""
    if blur <= 0:
        return 0, torch.ones(1, dtype=torch.float64, device=device)
    r = max(1, int(math.ceil(3 * blur)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64, device=device) / blur) ** 2)
    return r, k / k.sum()


def blurred(image: Tensor, blur: float) -> Tensor:
    """(C, ch, H, W) float64: the image (C, H, W, ch) (non-finite values as 0) blurred by a
    separable Gaussian of ``blur`` pixels (replicated border); ``blur`` 0: unchanged."""
    x = image.permute(0, 3, 1, 2).double()
    x = torch.where(torch.isfinite(x), x, torch.zeros_like(x))
    if blur <= 0:
        return x
    C, ch, H, W = x.shape
    r, k = gaussian_taps(blur, x.device)
    k = k.view(1, 1, -1)
    y = x.reshape(C * ch, 1, H, W)
    y = Fnn.conv2d(Fnn.pad(y, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    y = Fnn.conv2d(Fnn.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return y.view(C, ch, H, W)


def image_features(image: Tensor, blur: float) -> Tensor:
    """(C, 9, H, W): the image (C, H, W, 3) blurred by a Gaussian of ``blur`` pixels (channels
    0-2) and its derivatives along x (3-5) and y (6-8), central differences (one-sided at the
    border). L_anchor samples these bilinearly at vertex projections; the
    derivative channels are its Gauss-Newton Jacobian (smoother than the bilinear
    interpolant's own piecewise-constant derivative)."""
    x = blurred(image, blur)
    H, W = x.shape[-2:]
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    if W > 1:
        gx[..., 1:-1] = 0.5 * (x[..., 2:] - x[..., :-2])
        gx[..., 0], gx[..., -1] = x[..., 1] - x[..., 0], x[..., -1] - x[..., -2]
    if H > 1:
        gy[..., 1:-1, :] = 0.5 * (x[..., 2:, :] - x[..., :-2, :])
        gy[..., 0, :], gy[..., -1, :] = x[..., 1, :] - x[..., 0, :], x[..., -1, :] - x[..., -2, :]
    return torch.cat([x, gx, gy], 1)


def sample(feat: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples (C, V, ch) of feat (C, ch, H, W) at pixel positions uv (C, V, 2)
    (pixel centres at integer coordinates; outside: the border value)."""
    H, W = feat.shape[-2:]
    grid = torch.stack([2 * uv[..., 0] / max(W - 1, 1) - 1, 2 * uv[..., 1] / max(H - 1, 1) - 1], -1)
    grid = torch.where(torch.isfinite(grid), grid, torch.full_like(grid, -2.0))
    out = Fnn.grid_sample(feat.to(uv.dtype), grid[:, None], mode="bilinear", padding_mode="border",
                          align_corners=True)
    return out[:, :, 0].permute(0, 2, 1)


def sample_blurred(image: Tensor, cam: Tensor, uv: Tensor, blur: float) -> Tensor:
    """``sample(blurred(image, blur), uv)`` at N points only: (N, ch) for image (C, H, W, ch),
    cam (N,) and pixel positions uv (N, 2), without filtering whole images.

    The bilinear sample of the Gaussian-blurred image is one separable stencil on the
    (2r + 2)^2 pixels around the point (r = ceil(3 blur)): per axis the weights
    (1 - f) g[o] + f g[o - 1], o = -r .. r + 1, with the replicated border of both
    filters (indices clamped) and the sample position clamped to the image like
    ``grid_sample``'s border padding."""
    C, H, W, ch = image.shape
    dt = torch.float64
    r, g = gaussian_taps(blur, uv.device)
    off = torch.arange(-r, r + 2, device=uv.device)  # (S,) S = 2r + 2

    def axis(x, size):  # -> (N, S) pixel indices and weights along one axis
        x = torch.where(torch.isfinite(x), x.to(dt), torch.zeros_like(x, dtype=dt)).clamp(0, max(size - 1, 0))
        x0 = torch.floor(x)
        f = (x - x0)[:, None]
        gpad = torch.cat([g.new_zeros(1), g, g.new_zeros(1)])  # g[o] at gpad[o + r + 1]
        w = (1 - f) * gpad[off + r + 1][None] + f * gpad[off + r][None]
        return (x0.long()[:, None] + off[None]).clamp(0, size - 1), w

    cols, wc = axis(uv[:, 0], W)
    rows, wr = axis(uv[:, 1], H)
    pix = image[cam[:, None, None], rows[:, :, None], cols[:, None, :]].to(dt)  # (N, S, S, ch)
    pix = torch.where(torch.isfinite(pix), pix, torch.zeros_like(pix))
    return torch.einsum("nabc,na,nb->nc", pix, wr, wc)


def eroded(mask: Tensor, margin: int) -> Tensor:
    """(C, H, W) bool: pixels whose whole (2 margin + 1)^2 neighbourhood is garment (mask >= 1 if soft)."""
    good = mask.bool() if not mask.is_floating_point() else mask >= 1
    if margin <= 0:
        return good
    return -Fnn.max_pool2d(-good[:, None].double(), 2 * margin + 1, stride=1, padding=margin)[:, 0] > 0.5


def pixel_ok(region: Tensor, uv: Tensor) -> Tensor:
    """(C, V) bool: the pixel nearest to uv (C, V, 2) lies in the image and in region (C, H, W)."""
    C, H, W = region.shape
    finite = torch.isfinite(uv).all(-1)
    col = torch.where(finite, uv[..., 0], torch.full_like(uv[..., 0], -1.0)).round()
    row = torch.where(finite, uv[..., 1], torch.full_like(uv[..., 1], -1.0)).round()
    inside = finite & (col >= 0) & (col <= W - 1) & (row >= 0) & (row <= H - 1)
    cam = torch.arange(C, device=uv.device)[:, None].expand_as(col)
    return inside & region[cam, row.clamp(0, H - 1).long(), col.clamp(0, W - 1).long()]


#: Added to r + g + b before dividing (colours in [0, 1]): dark pixels have a chromaticity near 0
#: instead of an unstable ratio.
CHROMA_EPS = 0.05


def chromaticity(image: Tensor) -> Tensor:
    """(..., 3) -> (..., 3): rgb / (r + g + b + CHROMA_EPS), unchanged by a Lambertian shading factor
    (white light) on pixels well above black."""
    image = image.double()
    return image / (image.sum(-1, keepdim=True) + CHROMA_EPS)
