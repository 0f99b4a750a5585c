"""Image metrics of novel-view / novel-pose synthesis (DESIGN.md §10).

* PSNR inside the projected bounding box of the subject (Neural Body, Peng et al.
  CVPR 2021, protocol: the 3D box of the posed subject, padded 5 cm, projected; PSNR
  over the pixels it covers), :func:`subject_box_mask`, :func:`psnr`.
* SSIM (Wang, Bovik, Sheikh, Simoncelli 2004: Gaussian window 11x11, sigma 1.5,
  K1 = 0.01, K2 = 0.03, data range 1, mean over channels) on the bounding rectangle of
  that box (Neural Body crops the same way), :func:`ssim`.
* IoU of the rendered silhouette (alpha > 0.5) with the true mask, :func:`iou`.
* PSNR and SSIM inside pixel regions (the subject, garment or body of a label mask),
  pooled over images: :func:`region_stats` sums each region's squared error, pixels and
  per-pixel SSIM (:func:`ssim_map`) of one image; :class:`RegionStats` add up over images;
  :func:`region_score` turns a sum into PSNR = -10 log10(squared error / (3 pixels)) and
  SSIM = SSIM-map sum / pixels (NaN for no pixel, +inf PSNR for no error).
* LPIPS (Zhang et al. CVPR 2018, v0.1) with the AlexNet or VGG16 backbone and DISTS
  (Ding et al. TPAMI 2020) with VGG16 and L2 pooling. Both need pretrained weights:
  the backbone's torchvision ``state_dict`` (``alexnet-owt-7be5be79.pth``,
  ``vgg16-397923af.pth``), the LPIPS linear layers (the ``lpips`` package's
  ``weights/v0.1/<net>.pth``: ``lin<k>.model.1.weight``) and DISTS' ``alpha`` / ``beta``
  (``weights.pt`` of ``DISTS_pytorch``). The backbones are written here in plain torch
  with torchvision's layer indices, so those files load as they are.
  :func:`load_lpips` / :func:`load_dists` look for the files at the given paths, else in
  the torch hub cache (``$TORCH_HOME/hub/checkpoints``) and the installed packages;
  when one is missing they return :class:`Unavailable` with the reason, and the
  metric is reported as NaN with a flag -- never replaced by something else.

Images are (H, W, 3) or (B, 3, H, W) floats in [0, 1].
"""
from __future__ import annotations

import importlib.util
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "psnr",
    "ssim",
    "ssim_map",
    "RegionStats",
    "RegionScore",
    "region_stats",
    "region_score",
    "iou",
    "subject_box_mask",
    "box_rect",
    "AlexNetFeatures",
    "VGG16Features",
    "LPIPS",
    "DISTS",
    "Unavailable",
    "load_lpips",
    "load_dists",
    "BACKBONE_FILES",
]

BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
"""torchvision's file names of the ImageNet backbones (what torch.hub caches)."""


# --------------------------------------------------------------------------- pixel metrics


def psnr(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> float:
    """PSNR (dB) of images (H, W, 3) in [0, 1] over the pixels of ``mask`` (H, W) bool.

    An empty mask gives NaN; identical images give +inf.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"psnr: shapes differ, {tuple(pred.shape)} vs {tuple(gt.shape)}")
    d = (pred.double() - gt.double()) ** 2
    if mask is not None:
        if mask.shape != pred.shape[:2]:
            raise ValueError(f"psnr: mask {tuple(mask.shape)} does not match image {tuple(pred.shape)}")
        if not mask.any():
            return float("nan")
        d = d[mask]
    mse = float(d.mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def _gauss_window(size: int, sigma: float, dtype, device) -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def _ssim_valid(x: Tensor, y: Tensor, window: int, sigma: float, k1: float, k2: float,
                data_range: float) -> Tensor:
    """SSIM at every 'valid' window position: x, y (C, 1, H, W) float64 -> (C, 1, H - w + 1, W - w + 1)."""
    g = _gauss_window(window, sigma, x.dtype, x.device)

    def filt(z: Tensor) -> Tensor:  # separable Gaussian, 'valid' positions
        z = F.conv2d(z, g.view(1, 1, 1, -1))
        return F.conv2d(z, g.view(1, 1, -1, 1))

    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx * mx
    syy = filt(y * y) - my * my
    sxy = filt(x * y) - mx * my
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


def ssim(pred: Tensor, gt: Tensor, window: int = 11, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03,
         data_range: float = 1.0) -> float:
    """Mean SSIM of (H, W, 3) images (Wang et al. 2004), valid-window positions only.

    Same definition as ``skimage.metrics.structural_similarity(gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1)``.
    Images smaller than the window give NaN.
    """
    if pred.shape != gt.shape or pred.ndim != 3:
        raise ValueError(f"ssim: expects two (H, W, C) images, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    H, W, C = pred.shape
    if H < window or W < window:
        return float("nan")
    x = pred.double().permute(2, 0, 1)[:, None]  # (C, 1, H, W)
    y = gt.double().permute(2, 0, 1)[:, None]
    return float(_ssim_valid(x, y, window, sigma, k1, k2, data_range).mean())


def _mirror_index(n: int, p: int, device) -> Tensor:
    """Indices (n + 2p,) of positions -p .. n + p - 1 mirrored into 0 .. n - 1 with the edge repeated
    (``d c b a | a b c d | d c b a``, scipy.ndimage mode 'reflect'), any p (repeated mirroring)."""
    i = torch.arange(-p, n + p, device=device) % (2 * n)
    return torch.where(i < n, i, 2 * n - 1 - i)


def ssim_map(pred: Tensor, gt: Tensor, window: int = 11, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03,
             data_range: float = 1.0) -> Tensor:
    """Per-pixel SSIM (H, W) float64 of (H, W, C) images: the window centred on each pixel, mean over channels.

    The constants and Gaussian window of :func:`ssim`, whose value is the mean of this map over
    the valid positions ``[p:H-p, p:W-p]``, p = (window - 1) // 2 (equal up to rounding). Borders:
    both images are mirrored by p pixels with the edge pixel repeated (``d c b a | a b c d``,
    scipy.ndimage's 'reflect', as ``skimage.metrics.structural_similarity(full=True)``'s map; an
    image smaller than p is mirrored repeatedly) before filtering, so a window near the border
    sees the image's own content; zero padding would add black pixels that lower the local means
    and raise the variances, biasing a region that touches the border. So "SSIM in a mask" is the
    mean of this map over the mask's pixels. The window must be odd (centred).
    """
    if pred.shape != gt.shape or pred.ndim != 3:
        raise ValueError(f"ssim_map: expects two (H, W, C) images, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    if window % 2 != 1:
        raise ValueError(f"ssim_map: the window must be odd to centre it on a pixel, got {window}")
    H, W, _ = pred.shape
    p = (window - 1) // 2
    rows, cols = _mirror_index(H, p, pred.device), _mirror_index(W, p, pred.device)
    # 1. mirror-pad (H + 2p, W + 2p, C), channels first: (C, 1, H + 2p, W + 2p)
    x = pred.double()[rows][:, cols].permute(2, 0, 1)[:, None]
    y = gt.double()[rows][:, cols].permute(2, 0, 1)[:, None]
    # 2. SSIM at the valid positions of the padded images = every pixel of the image; mean over channels
    return _ssim_valid(x, y, window, sigma, k1, k2, data_range)[:, 0].mean(0)


@dataclass(frozen=True)
class RegionStats:
    """Sums over the pixels of one region of one image, or of several images (``a + b`` pools them).

    sq_err: sum over the region's pixels and the 3 channels of (pred - gt)^2; pixels: the region's
    pixel count; ssim_sum: sum of :func:`ssim_map` over the region's pixels. An empty region is
    all zeros and adds nothing to a pool.
    """

    sq_err: float = 0.0
    pixels: int = 0
    ssim_sum: float = 0.0

    def __add__(self, other: "RegionStats") -> "RegionStats":
        return RegionStats(self.sq_err + other.sq_err, self.pixels + other.pixels, self.ssim_sum + other.ssim_sum)


class RegionScore(NamedTuple):
    psnr_db: float
    ssim: float


def region_stats(pred: Tensor, gt: Tensor, masks: Mapping[str, Tensor], smap: Tensor | None = None,
                 ) -> dict[str, RegionStats]:
    """:class:`RegionStats` of (H, W, 3) images in [0, 1] for each named bool mask (H, W).

    smap: their :func:`ssim_map` (H, W) when already computed (else computed here, default window).
    """
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"region_stats: expects two (H, W, 3) images, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    for name, m in masks.items():
        if m.shape != pred.shape[:2]:
            raise ValueError(f"region_stats: mask {name!r} {tuple(m.shape)} does not match image {tuple(pred.shape)}")
        if m.dtype != torch.bool:
            raise ValueError(f"region_stats: mask {name!r} must be bool, got {m.dtype}")
    if smap is None:
        smap = ssim_map(pred, gt)
    elif smap.shape != pred.shape[:2]:
        raise ValueError(f"region_stats: SSIM map {tuple(smap.shape)} does not match image {tuple(pred.shape)}")
    sq = ((pred.double() - gt.double()) ** 2).sum(-1)  # (H, W): squared error summed over channels
    return {name: RegionStats(float(sq[m].sum()), int(m.sum()), float(smap[m].sum())) for name, m in masks.items()}


def region_score(stats: RegionStats) -> RegionScore:
    """PSNR (dB, data range 1) and SSIM of (pooled) :class:`RegionStats`.

    PSNR = -10 log10(sq_err / (3 pixels)), SSIM = ssim_sum / pixels. No pixel: both NaN. No error
    (identical pixels; a pool is identical only if every image is): PSNR +inf, kept as such (not
    clipped: a pool with any error is finite, so +inf only ever means "identical").
    """
    if stats.pixels == 0:
        return RegionScore(float("nan"), float("nan"))
    mse = stats.sq_err / (3 * stats.pixels)
    return RegionScore(float("inf") if mse == 0 else -10.0 * math.log10(mse), stats.ssim_sum / stats.pixels)


def iou(alpha: Tensor, mask: Tensor, threshold: float = 0.5) -> float:
    """Intersection over union of ``alpha > threshold`` (H, W) and a bool mask (H, W).

    Both empty: 1.0 (nothing to get wrong).
    """
    if alpha.shape != mask.shape:
        raise ValueError(f"iou: shapes differ, {tuple(alpha.shape)} vs {tuple(mask.shape)}")
    a = alpha > threshold
    m = mask.bool()
    union = int((a | m).sum())
    return 1.0 if union == 0 else int((a & m).sum()) / union


def subject_box_mask(points: Tensor, K: Tensor, world_to_cam: Tensor, height: int, width: int,
                     pad_m: float = 0.05) -> Tensor:
    """Pixels (H, W) bool covered by the projected 3D bounding box of the subject.

    points (V, 3) world (posed body and garment vertices); K (3, 3); world_to_cam (4, 4).
    Neural Body's ``mask_at_box``: the box padded by ``pad_m`` metres, its 8 corners
    projected, the convex hull filled. Corners behind the camera: the whole image.
    """
    import cv2

    lo = points.min(0).values - pad_m
    hi = points.max(0).values + pad_m
    corners = torch.stack(torch.meshgrid(*[torch.stack([lo[a], hi[a]]) for a in range(3)], indexing="ij"),
                          -1).reshape(8, 3).double()
    Xc = corners @ world_to_cam[:3, :3].double().T + world_to_cam[:3, 3].double()
    if (Xc[:, 2] <= 1e-6).any():
        return torch.ones(height, width, dtype=torch.bool)
    uv = (Xc @ K.double().T)[:, :2] / Xc[:, 2:3]
    hull = cv2.convexHull(np.round(uv.numpy()).astype(np.int32))
    m = np.zeros((height, width), np.uint8)
    cv2.fillConvexPoly(m, hull, 1)
    return torch.from_numpy(m.astype(bool))


def box_rect(mask: Tensor) -> tuple[int, int, int, int]:
    """Bounding rectangle y0, y1, x0, x1 (half-open) of a bool mask (H, W); empty -> zeros."""
    rows = mask.any(1).nonzero()[:, 0]
    cols = mask.any(0).nonzero()[:, 0]
    if rows.numel() == 0:
        return 0, 0, 0, 0
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


# --------------------------------------------------------------------------- backbones


def _alexnet_layers() -> list[nn.Module]:
    """torchvision ``alexnet().features`` (indices 0..12)."""
    return [
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=False),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=False),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=False), nn.MaxPool2d(3, 2),
    ]


def _vgg16_layers() -> list[nn.Module]:
    """torchvision ``vgg16().features`` (indices 0..30)."""
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
    layers: list[nn.Module] = []
    c = 3
    for v in cfg:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=False)]
            c = v
    return layers


class AlexNetFeatures(nn.Module):
    """AlexNet features with torchvision's parameter names (``features.<i>.weight``).

    ``forward`` returns the 5 ReLU outputs LPIPS uses (after layers 1, 4, 7, 9, 11).
    """

    channels = (64, 192, 384, 256, 256)
    taps = (1, 4, 7, 9, 11)

    def __init__(self):
        super().__init__()
        self.features = nn.Sequential(*_alexnet_layers())

    def forward(self, x: Tensor) -> list[Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
                if i == self.taps[-1]:
                    break
        return out


class VGG16Features(nn.Module):
    """VGG16 features with torchvision's parameter names (``features.<i>.weight``).

    ``forward`` returns relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (after layers 3, 8,
    15, 22, 29). With ``l2pool`` the max-pooling layers are replaced by DISTS' L2
    pooling (Hann window [0.5, 1, 0.5]^2 normalised, stride 2, padding 1).
    """

    channels = (64, 128, 256, 512, 512)
    taps = (3, 8, 15, 22, 29)

    def __init__(self, l2pool: bool = False):
        super().__init__()
        self.features = nn.Sequential(*_vgg16_layers())
        self.l2pool = l2pool
        a = torch.tensor([0.5, 1.0, 0.5])
        g = a[:, None] * a[None, :]
        self.register_buffer("hann", (g / g.sum())[None, None], persistent=False)

    def _pool(self, x: Tensor) -> Tensor:
        # DISTS L2 pooling: sqrt(hann * x^2 + 1e-12), depthwise, stride 2
        y = F.conv2d(x * x, self.hann.expand(x.shape[1], 1, 3, 3), stride=2, padding=1, groups=x.shape[1])
        return (y + 1e-12).sqrt()

    def forward(self, x: Tensor) -> list[Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = self._pool(x) if (self.l2pool and isinstance(layer, nn.MaxPool2d)) else layer(x)
            if i in self.taps:
                out.append(x)
                if i == self.taps[-1]:
                    break
        return out


# --------------------------------------------------------------------------- LPIPS / DISTS


class LPIPS(nn.Module):
    """LPIPS v0.1 distance: ``forward(x, y)`` of (B, 3, H, W) in [0, 1] -> (B,).

    Inputs are mapped to [-1, 1] and shifted / scaled by LPIPS' ScalingLayer; every
    tapped feature map is unit-normalised over channels, the squared difference is
    weighted by the non-negative 1x1 linear layer of that tap, averaged over space and
    summed over taps.
    """

    def __init__(self, net: str = "alex"):
        super().__init__()
        if net not in BACKBONE_FILES:
            raise ValueError(f"LPIPS: net must be one of {sorted(BACKBONE_FILES)}, got {net!r}")
        self.net_name = net
        self.net = AlexNetFeatures() if net == "alex" else VGG16Features()
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        # lin<k>.model.1.weight: the lpips package's NetLinLayer (Dropout, Conv2d 1x1 no bias)
        self.lins = nn.ModuleList(
            nn.Sequential(nn.Dropout(0.0), nn.Conv2d(c, 1, 1, bias=False)) for c in self.net.channels)
        for p in self.parameters():
            p.requires_grad_(False)

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        fx = self.net(((2 * x - 1) - self.shift) / self.scale)
        fy = self.net(((2 * y - 1) - self.shift) / self.scale)
        total = 0
        for a, b, lin in zip(fx, fy, self.lins):
            a = a / (a.square().sum(1, keepdim=True).sqrt() + 1e-10)
            b = b / (b.square().sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((a - b) ** 2).mean((2, 3))
        return total.view(-1)


class DISTS(nn.Module):
    """DISTS distance: ``forward(x, y)`` of (B, 3, H, W) in [0, 1] -> (B,).

    VGG16 with L2 pooling on ImageNet-normalised inputs; stages: the image itself and
    the 5 tapped ReLUs (3, 64, 128, 256, 512, 512 channels). Per channel, a structure
    term (means) weighted by alpha and a texture term (variances, covariance) weighted
    by beta, with alpha, beta normalised by their sum; distance = 1 - sum.
    """

    chns = (3, 64, 128, 256, 512, 512)

    def __init__(self):
        super().__init__()
        self.net = VGG16Features(l2pool=True)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
        self.alpha = nn.Parameter(torch.full((1, sum(self.chns), 1, 1), 0.1), requires_grad=False)
        self.beta = nn.Parameter(torch.full((1, sum(self.chns), 1, 1), 0.1), requires_grad=False)
        for p in self.parameters():
            p.requires_grad_(False)

    def _feats(self, x: Tensor) -> list[Tensor]:
        return [x] + self.net((x - self.mean) / self.std)

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        f0, f1 = self._feats(x), self._feats(y)
        c1 = c2 = 1e-6
        wsum = self.alpha.sum() + self.beta.sum()
        alpha = torch.split(self.alpha / wsum, list(self.chns), dim=1)
        beta = torch.split(self.beta / wsum, list(self.chns), dim=1)
        d1 = d2 = 0
        for k in range(len(self.chns)):
            xm = f0[k].mean((2, 3), keepdim=True)
            ym = f1[k].mean((2, 3), keepdim=True)
            s1 = (2 * xm * ym + c1) / (xm**2 + ym**2 + c1)
            d1 = d1 + (alpha[k] * s1).sum(1, keepdim=True)
            xv = ((f0[k] - xm) ** 2).mean((2, 3), keepdim=True)
            yv = ((f1[k] - ym) ** 2).mean((2, 3), keepdim=True)
            cov = (f0[k] * f1[k]).mean((2, 3), keepdim=True) - xm * ym
            s2 = (2 * cov + c2) / (xv + yv + c2)
            d2 = d2 + (beta[k] * s2).sum(1, keepdim=True)
        return (1 - (d1 + d2)).view(-1)


@dataclass(frozen=True)
class Unavailable:
    """A metric whose pretrained weights could not be found (reported as NaN + flag)."""

    metric: str
    reason: str

    def __bool__(self) -> bool:
        return False


def _hub_checkpoints() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints"


def _package_file(package: str, *parts: str) -> Path | None:
    """A file shipped inside an installed package (found without importing it), or None."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]).joinpath(*parts)


def _resolve(given: str | os.PathLike | None, candidates: list[Path | None]) -> tuple[Path | None, list[str]]:
    """The given path (must exist) or the first existing candidate; plus where it looked."""
    if given:
        p = Path(given).expanduser()
        return (p if p.is_file() else None), [str(p)]
    looked = [str(c) for c in candidates if c is not None]
    for c in candidates:
        if c is not None and c.is_file():
            return c, looked
    return None, looked


def _load_state(path: Path) -> dict:
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many kinds for a corrupt file
        raise ValueError(f"{path}: not a readable torch weights file ({e})") from e
    if not isinstance(sd, dict):
        raise ValueError(f"{path}: expected a state_dict (dict of tensors), got {type(sd).__name__}")
    return sd


def _load_backbone(module: nn.Module, path: Path) -> None:
    """Load torchvision ``features.*`` weights into ``module`` (other keys ignored)."""
    sd = _load_state(path)
    want = {k: v for k, v in module.state_dict().items() if k.startswith("features.")}
    missing = [k for k in want if k not in sd]
    if missing:
        raise ValueError(f"{path}: not a torchvision backbone state_dict for this network (missing {missing[:3]}...)")
    bad = [k for k in want if tuple(sd[k].shape) != tuple(want[k].shape)]
    if bad:
        raise ValueError(f"{path}: wrong shapes for {bad[:3]} (e.g. {tuple(sd[bad[0]].shape)} vs "
                         f"{tuple(want[bad[0]].shape)})")
    module.load_state_dict({k: sd[k] for k in want}, strict=False)


def load_lpips(net: str = "alex", backbone: str | os.PathLike | None = None,
               linear: str | os.PathLike | None = None) -> LPIPS | Unavailable:
    """LPIPS with pretrained weights, or :class:`Unavailable` saying which file is missing.

    backbone: torchvision ``state_dict`` of AlexNet / VGG16 (default: the torch hub
    cache ``<hub>/checkpoints/{alexnet-owt-7be5be79,vgg16-397923af}.pth``).
    linear: LPIPS v0.1 linear layers (default: the installed ``lpips`` package's
    ``weights/v0.1/<net>.pth``, then ``<hub>/checkpoints/lpips_v0.1_<net>.pth``).
    A file that exists but is wrong raises ValueError naming it.
    """
    if net not in BACKBONE_FILES:
        raise ValueError(f"load_lpips: net must be one of {sorted(BACKBONE_FILES)}, got {net!r}")
    bpath, blook = _resolve(backbone, [_hub_checkpoints() / BACKBONE_FILES[net]])
    if bpath is None:
        return Unavailable("lpips", f"no {net} backbone weights (looked at {', '.join(blook)})")
    lpath, llook = _resolve(linear, [_package_file("lpips", "weights", "v0.1", f"{net}.pth"),
                                     _hub_checkpoints() / f"lpips_v0.1_{net}.pth"])
    if lpath is None:
        return Unavailable("lpips", f"no LPIPS linear-layer weights (looked at {', '.join(llook)})")
    m = LPIPS(net)
    _load_backbone(m.net, bpath)
    sd = _load_state(lpath)
    lin = {}
    for k, c in enumerate(m.net.channels):
        key = f"lin{k}.model.1.weight"
        if key not in sd or tuple(sd[key].shape) != (1, c, 1, 1):
            raise ValueError(f"{lpath}: expected {key} of shape (1, {c}, 1, 1) (LPIPS v0.1 {net} linear layers)")
        lin[f"lins.{k}.1.weight"] = sd[key]
    m.load_state_dict(lin, strict=False)
    return m.eval()


def load_dists(backbone: str | os.PathLike | None = None,
               alpha_beta: str | os.PathLike | None = None) -> DISTS | Unavailable:
    """DISTS with pretrained weights, or :class:`Unavailable` saying which file is missing.

    backbone: torchvision VGG16 ``state_dict`` (default: the torch hub cache);
    alpha_beta: DISTS' ``weights.pt`` with ``alpha`` and ``beta`` (1, 1475, 1, 1)
    (default: the installed ``DISTS_pytorch`` package, then ``<hub>/checkpoints/dists_weights.pt``).
    """
    bpath, blook = _resolve(backbone, [_hub_checkpoints() / BACKBONE_FILES["vgg"]])
    if bpath is None:
        return Unavailable("dists", f"no vgg16 backbone weights (looked at {', '.join(blook)})")
    apath, alook = _resolve(alpha_beta, [_package_file("DISTS_pytorch", "weights.pt"),
                                         _hub_checkpoints() / "dists_weights.pt"])
    if apath is None:
        return Unavailable("dists", f"no DISTS alpha/beta weights (looked at {', '.join(alook)})")
    m = DISTS()
    _load_backbone(m.net, bpath)
    sd = _load_state(apath)
    n = sum(DISTS.chns)
    for key in ("alpha", "beta"):
        if key not in sd or tuple(sd[key].shape) != (1, n, 1, 1):
            raise ValueError(f"{apath}: expected {key!r} of shape (1, {n}, 1, 1) (DISTS weights.pt)")
    m.alpha.data.copy_(sd["alpha"])
    m.beta.data.copy_(sd["beta"])
    return m.eval()
