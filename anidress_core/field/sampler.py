"""Sampling that skips what is empty (DESIGN.md §6, §9).

1. Rays only inside the dilated bounding box of the subject's mask
   (:func:`mask_boxes`, :func:`box_pixels`).
2. Samples only inside an occupancy grid built from the posed body and garment meshes
   of the frame (:func:`build_occupancy`): the surfaces are splatted into a per-frame,
   world-axis-aligned grid of fixed resolution and dilated by a margin (metres) per
   part, so that everything the subject can be is covered and nothing else is.
3. Joints only where they have weight: every occupied voxel stores the ``M`` joints
   of the unified pose with the largest skinning weight among the surface points that
   reach it (after dilation); the backward warp evaluates only those.

Ray marching (:func:`march`) places samples every ``step`` metres between the ray's
entry and exit of the frame's grid and keeps those in occupied voxels. When training, each
ray's samples are shifted by one random fraction of a step (the random ray offset of
instant-ngp, Müller et al. 2022), so every sample still stands for an interval of exactly one
step; rendering uses the interval midpoints. Samples come out sorted by ray, then depth, as a flat list
(``ray``, ``t``, ``x``) ready for :func:`anidress_core.field.render.composite`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import torch
from torch import Tensor

__all__ = [
    "SurfacePart",
    "OccupancyGrid",
    "build_occupancy",
    "surface_points",
    "Samples",
    "march",
    "mask_boxes",
    "box_pixels",
    "occupancy_pixels",
    "occupied_centres",
]


@dataclass
class SurfacePart:
    """One posed surface of the subject and the joints that move it."""

    verts: Tensor
    """(T, V, 3) posed vertices (world) of every frame."""
    faces: Tensor
    """(F, 3) int64 triangles."""
    weights: Tensor
    """(V, K) skinning weights over the K joints of the unified pose."""
    dilate_m: float
    """Margin around the surface that counts as occupied (metres)."""


def _bary_grid(n: int) -> Tensor:
    """Barycentric points (P, 3) of a triangle subdivided n times per edge, without the
    corners (the vertices are sampled once, not per face), plus the centroid."""
    pts = [(i / n, j / n, (n - i - j) / n) for i in range(n + 1) for j in range(n + 1 - i)
           if max(i, j, n - i - j) < n]
    pts.append((1 / 3, 1 / 3, 1 / 3))
    return torch.tensor(pts)


def surface_points(verts: Tensor, faces: Tensor, weights: Tensor, spacing: float) -> tuple[Tensor, Tensor]:
    """Points on every triangle no farther than ``spacing`` apart, with interpolated weights.

    verts (T, V, 3), faces (F, 3), weights (V, K) -> points (T, P, 3), weights (P, K).
    The vertices, and per face whose longest edge (over all frames) is e a barycentric
    grid of ceil(e / spacing) subdivisions per edge (at most 32; corners left out)
    plus its centroid.
    """
    v0, v1, v2 = verts[:, faces[:, 0]], verts[:, faces[:, 1]], verts[:, faces[:, 2]]
    e = torch.stack([(v1 - v0).norm(dim=-1), (v2 - v1).norm(dim=-1), (v0 - v2).norm(dim=-1)]).amax((0, 1))  # (F,)
    n = (e / spacing).ceil().clamp(1, 32).long()
    pts, ws = [verts], [weights]
    for k in torch.unique(n).tolist():
        sel = (n == k).nonzero()[:, 0]
        b = _bary_grid(k).to(verts.dtype)  # (P, 3)
        f = faces[sel]
        # p[t, f, q] = sum_i b[q, i] v[t, f_i]
        p = torch.einsum("qi,tfic->tfqc", b, verts[:, f])
        pts.append(p.reshape(verts.shape[0], -1, 3))
        ws.append(torch.einsum("qi,fik->fqk", b, weights[f]).reshape(-1, weights.shape[1]))
    return torch.cat(pts, 1), torch.cat(ws, 0)


@dataclass
class OccupancyGrid:
    """Per-frame occupancy and candidate joints on a (Gx, Gy, Gz) world grid.

    Voxel (i, j, k) of frame t covers ``origin[t] + [i, i+1) * voxel[t, 0]`` etc.;
    its flat index is ``(i * Gy + j) * Gz + k``.
    """

    origin: Tensor
    """(T, 3) world position of each frame's grid corner."""
    voxel: Tensor
    """(T, 3) voxel size per axis (metres)."""
    res: tuple[int, int, int]
    """(Gx, Gy, Gz) voxels per axis."""
    index: Tensor
    """(T, Gx * Gy * Gz) int32 row of each voxel in ``cand``, -1 where empty."""
    cand: Tensor
    """(N_occ, M) int16 candidate joints of every occupied voxel (M = min(max_joints, K)), K where none."""
    num_joints: int
    """K, the joints of the unified pose."""

    @property
    def num_frames(self) -> int:
        return self.origin.shape[0]

    def occupied_fraction(self) -> float:
        """Fraction of voxels that are occupied (over all frames)."""
        return float((self.index >= 0).float().mean())

    def box(self, frame: Tensor) -> tuple[Tensor, Tensor]:
        """World min and max corner (N, 3) of the grids of ``frame`` (N,)."""
        lo = self.origin[frame]
        size = torch.tensor(self.res, dtype=lo.dtype, device=lo.device)
        return lo, lo + self.voxel[frame] * size

    def lookup(self, frame: Tensor, pts: Tensor) -> tuple[Tensor, Tensor]:
        """Row into ``cand`` (N,) (-1: empty or outside) of points (N, 3) of frames (N,)."""
        G = torch.tensor(self.res, device=pts.device)
        ijk = ((pts - self.origin[frame]) / self.voxel[frame]).floor().long()
        inside = ((ijk >= 0) & (ijk < G)).all(-1)
        ijk = torch.minimum(ijk.clamp_min(0), G - 1)
        flat = (ijk[:, 0] * G[1] + ijk[:, 1]) * G[2] + ijk[:, 2]
        row = self.index[frame, flat].long()
        return torch.where(inside, row, torch.full_like(row, -1)), inside

    def to(self, device) -> "OccupancyGrid":
        return OccupancyGrid(self.origin.to(device), self.voxel.to(device), self.res, self.index.to(device),
                             self.cand.to(device), self.num_joints)


def _ball_offsets(r: Sequence[int], scale: Sequence[float], d: float, device) -> Tensor:
    """Voxel offsets (O, 3) that a point in voxel 0 can reach within ``d`` metres.

    r: radius in voxels per axis, scale: voxel size per axis. Conservative: an offset is
    kept when the closest points of the two voxels are within d.
    """
    rng = [torch.arange(-ri, ri + 1, device=device) for ri in r]
    o = torch.stack(torch.meshgrid(*rng, indexing="ij"), -1).reshape(-1, 3)
    s = torch.tensor(list(scale), dtype=torch.float32, device=device)
    near = (o.abs().float() - 1).clamp_min(0) * s
    return o[near.square().sum(-1) <= d * d + 1e-12]


def _box_max(x: Tensor, r: Sequence[int]) -> Tensor:
    """Separable max filter of half-widths r (3,) over the last 3 axes of x (C, X, Y, Z), zero padded.

    Radius doubling: after k steps every cell holds the max over a forward window of up to
    2^k cells, so a half-width r costs O(log r) element-wise maxima per axis (x >= 0 assumed).
    """
    for a, ra in enumerate(r):
        if ra <= 0:
            continue
        ax = a + 1
        n = x.shape[ax]
        pad_shape = list(x.shape)
        pad_shape[ax] = ra
        # y[i] = max over the forward window [i, i + w) of x padded with r zeros in front:
        # at w = 2 r + 1, y[i] is the max of x over [i - r, i + r]
        y = torch.cat([x.new_zeros(pad_shape), x], ax)
        m = n + ra
        w, target = 1, 2 * ra + 1
        while w < target:
            step = min(w, target - w)
            shifted = torch.zeros_like(y)
            if step < m:
                shifted.narrow(ax, 0, m - step).copy_(y.narrow(ax, step, m - step))
            y = torch.maximum(y, shifted)
            w += step
        x = y.narrow(ax, 0, n).contiguous()
    return x


def build_occupancy(parts: Sequence[SurfacePart], res: Sequence[int] = (64, 64, 64), max_joints: int = 8,
                    min_weight: float = 0.01, progress: bool = False, max_splat: float = 2e7) -> OccupancyGrid:
    """Occupancy and candidate joints of every frame from posed surfaces.

    Every part's surface, sampled densely enough (:func:`surface_points`), is splatted into
    all voxels within its ``dilate_m`` margin, carrying their top-4 skinning weights; a
    voxel keeps, per joint, the largest weight that reached it, and its ``max_joints``
    best joints with weight >= ``min_weight`` become its candidates. The grid of a
    frame spans the frame's points plus the largest margin plus two voxels. A margin whose
    ball (in voxels) times the splatted entries exceeds ``max_splat`` is dilated with a
    separable max filter instead (a box: a superset of the ball).
    """
    if not parts:
        raise ValueError("build_occupancy: no surface parts")
    K = parts[0].weights.shape[1]
    T = parts[0].verts.shape[0]
    for p in parts:
        if p.weights.shape[1] != K or p.verts.shape[0] != T:
            raise ValueError("build_occupancy: parts disagree on joints K or frames T")
    dev = parts[0].verts.device
    G = torch.tensor(list(res), device=dev)
    nvox = int(G.prod())
    topw = min(4, K)
    pre = []
    for p in parts:
        # sample spacing = the margin: every surface point then lies within the margin of a
        # sample (no margin: the smallest voxel size, roughly)
        ext = (p.verts.amax(1) - p.verts.amin(1)).amax(0)  # (3,) largest extent over frames
        spacing = float(p.dilate_m) if p.dilate_m > 0 else max(1e-4, float(ext.min()) / max(res))
        pts, pw = surface_points(p.verts.float(), p.faces, p.weights.float(), spacing)
        wv, wj = torch.topk(pw, topw, dim=1)  # (P, 4)
        pre.append((pts, wv, wj, float(p.dilate_m)))
    margin = max(x[3] for x in pre)
    origins, voxels, indices, cands = [], [], [], []
    offset = 0
    frames = range(T)
    if progress:
        from tqdm import tqdm
        frames = tqdm(frames, desc="occupancy", unit="frame")
    best = torch.zeros(nvox * K, device=dev)
    occ = torch.zeros(nvox, dtype=torch.bool, device=dev)
    for t in frames:
        allp = torch.cat([x[0][t] for x in pre])
        lo = allp.min(0).values
        hi = allp.max(0).values
        # two spare voxels beyond the margin on each side: no dilated cell leaves the grid
        vox = (hi - lo + 2 * margin) / (G.float() - 4)
        origin = lo - margin - 2 * vox
        best.zero_()
        occ.zero_()
        for pts, wv, wj, d in pre:
            # 1. splat the surface points into their own voxels: per (voxel, joint) the max weight
            ijk = ((pts[t] - origin) / vox).floor().long()
            flat = (ijk[:, 0] * G[1] + ijk[:, 1]) * G[2] + ijk[:, 2]  # (P,)
            keys, inv = torch.unique((flat[:, None] * K + wj).reshape(-1), return_inverse=True)
            vals = torch.zeros(keys.shape[0], device=dev).scatter_reduce_(0, inv, wv.reshape(-1), reduce="amax",
                                                                          include_self=False)
            sv, sj = keys // K, keys % K  # surface voxel, joint
            r = [max(0, math.ceil(d / float(vox[a]))) for a in range(3)]
            offs = _ball_offsets(r, [float(vox[a]) for a in range(3)], d, dev)  # (O, 3)
            if offs.shape[0] * sv.shape[0] <= max_splat:
                # 2a. small margin: every (voxel, joint) entry reaches the voxels of a ball
                doff = (offs[:, 0] * G[1] + offs[:, 1]) * G[2] + offs[:, 2]  # (O,) flat offsets
                cells = (torch.unique(flat)[:, None] + doff[None]).reshape(-1)
                occ[cells] = True
                dkeys = ((sv[:, None] + doff[None]) * K + sj[:, None]).reshape(-1)
                best.scatter_reduce_(0, dkeys, vals[:, None].expand(-1, doff.shape[0]).reshape(-1), reduce="amax")
            else:
                # 2b. wide margin (too many ball offsets x entries): separable max filter (a box
                #     of the margin's half-widths) over a dense grid of only this part's joints
                joints, local = torch.unique(sj, return_inverse=True)
                dense = torch.zeros(joints.shape[0], nvox, device=dev)
                dense.view(-1).scatter_reduce_(0, local * nvox + sv, vals, reduce="amax")
                dense = _box_max(dense.view(-1, *res), r).view(joints.shape[0], nvox)
                occ |= dense.max(0).values > 0
                bv = best.view(nvox, K)
                bv[:, joints] = torch.maximum(bv[:, joints], dense.T)
        rows = occ.nonzero()[:, 0]
        wv_, wj_ = torch.topk(best.view(nvox, K)[rows], min(max_joints, K), dim=1)
        cand = torch.where(wv_ >= min_weight, wj_, torch.full_like(wj_, K))  # (n_occ, min(M, K))
        index = torch.full((nvox,), -1, dtype=torch.int32, device=dev)
        index[rows] = torch.arange(offset, offset + rows.shape[0], dtype=torch.int32, device=dev)
        offset += rows.shape[0]
        origins.append(origin)
        voxels.append(vox)
        indices.append(index)
        cands.append(cand.to(torch.int16))
    return OccupancyGrid(torch.stack(origins), torch.stack(voxels), tuple(int(g) for g in res),
                         torch.stack(indices), torch.cat(cands), K)


class Samples(NamedTuple):
    """Samples along rays, sorted by ray then depth."""

    ray: Tensor
    """(S,) long index of the ray of each sample."""
    t: Tensor
    """(S,) distance along the (unit) ray direction (metres)."""
    x: Tensor
    """(S, 3) world position."""
    cand: Tensor
    """(S, M) int16 candidate joints (K = none), as the occupancy grid stores them."""
    considered: int
    """Samples the marcher looked at (inside the grid box) before the occupancy test."""


def _ray_box(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Slab intersection: entry and exit distance (N,), exit < entry where the ray misses."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    tmin = torch.minimum(t0, t1).max(-1).values.clamp_min(0)
    tmax = torch.maximum(t0, t1).min(-1).values
    return tmin, tmax


def _march_warp(origins: Tensor, dirs: Tensor, frame: Tensor, grid: OccupancyGrid, step: float,
                u: Tensor) -> tuple[Tensor, Tensor, Tensor, int]:
    """Occupied samples (ray (S,) long, t (S,), row (S,) long) and the considered count, by the Warp
    kernel ``march_count`` (:mod:`anidress_core.field.kernels`): a counting pass, offsets, a filling pass."""
    from . import kernels

    dev, dt = origins.device, origins.dtype
    R = origins.shape[0]
    wdev, stream = kernels.device_of(origins, "march")
    A = kernels.array
    G = torch.tensor(grid.res, dtype=torch.int32, device=dev)
    common = [A(origins), A(dirs), A(frame.to(torch.int32)), A(u), float(step), A(grid.origin.to(dt)),
              A(grid.voxel.to(dt)), A(G), A(grid.index)]
    count = torch.zeros(R, dtype=torch.int32, device=dev)
    seen = torch.zeros(R, dtype=torch.int32, device=dev)
    empty_i, empty_t = torch.zeros(1, dtype=torch.int32, device=dev), torch.zeros(1, dtype=dt, device=dev)
    kernels.wp.launch(kernels.march_count, R, inputs=[*common, 0, A(count), A(count), A(seen),
                                                      A(torch.zeros(1, dtype=torch.int64, device=dev)), A(empty_t),
                                                      A(empty_i)], device=wdev, stream=stream)
    offset = (torch.cumsum(count, 0) - count).to(torch.int32)
    S = int(count.sum())
    ray = torch.empty(S, dtype=torch.int64, device=dev)
    t = torch.empty(S, dtype=dt, device=dev)
    row = torch.empty(S, dtype=torch.int32, device=dev)
    if S:
        kernels.wp.launch(kernels.march_count, R, inputs=[*common, 1, A(offset), A(count), A(seen),
                                                          kernels.wp.from_torch(ray), kernels.wp.from_torch(t),
                                                          kernels.wp.from_torch(row)], device=wdev, stream=stream)
    return ray, t, row.long(), int(seen.sum())


def march(origins: Tensor, dirs: Tensor, frame: Tensor, grid: OccupancyGrid, step: float,
          generator: torch.Generator | None = None, jitter: bool = False, use_occupancy: bool = True,
          cull_joints: bool = True, chunk: int = 4096, backend: str = "warp") -> Samples:
    """Samples every ``step`` metres inside each ray's frame grid, kept where occupied.

    origins, dirs (R, 3) (unit directions), frame (R,) long. With ``jitter`` each ray's
    samples are shifted by one offset, uniform in [0, step) from ``generator`` (without it:
    the midpoints of the steps).
    Ablations (what the skipping saves is measured against them):
    ``use_occupancy=False`` keeps every sample inside the grid box, with all K joints
    as candidates where the grid has none; ``cull_joints=False`` makes every joint a
    candidate of every sample (M = K).
    ``backend``: ``"warp"`` marches in one Warp kernel (with the occupancy grid; the
    ablation ``use_occupancy=False`` runs in torch), ``"torch"`` in batched torch (``chunk``
    rays at a time), the reference.
    """
    dev, dt = origins.device, origins.dtype
    K = grid.num_joints
    if backend not in ("warp", "torch"):
        raise ValueError(f"march: backend must be 'warp' or 'torch', got {backend!r}")
    if backend == "warp" and use_occupancy:
        R = origins.shape[0]
        u = torch.rand(R, generator=generator, dtype=dt).to(dev) if jitter else torch.full((R,), 0.5, dtype=dt,
                                                                                              device=dev)
        r_all, t_all, row, considered = _march_warp(origins, dirs, frame, grid, step, u)
        x_all = origins[r_all] + t_all[:, None] * dirs[r_all]
        cand = grid.cand[row] if cull_joints else \
            torch.arange(K, dtype=torch.int16, device=dev)[None].expand(r_all.shape[0], K)
        return Samples(r_all, t_all, x_all, cand, considered)
    lo, hi = grid.box(frame)
    tmin, tmax = _ray_box(origins, dirs, lo, hi)
    n = ((tmax - tmin) / step).ceil().clamp_min(0).long()  # samples per ray
    out_r, out_t, out_row = [], [], []
    considered = 0
    for s in range(0, origins.shape[0], chunk):
        sl = slice(s, s + chunk)
        nmax = int(n[sl].max()) if n[sl].numel() else 0
        if nmax == 0:
            continue
        i = torch.arange(nmax, device=dev, dtype=dt)
        shape = (n[sl].shape[0], nmax)
        # one offset per ray (the whole grid of its samples shifted): samples stay exactly a step
        # apart, as the compositing assumes (each stands for an interval of ``step``). Drawn from
        # the (CPU) generator, then moved: one random stream on any device
        u = torch.rand((shape[0], 1), generator=generator, dtype=dt).to(dev).expand(shape) if jitter \
            else torch.full(shape, 0.5, device=dev, dtype=dt)
        t = tmin[sl, None] + (i[None] + u) * step  # (r, nmax)
        keep = (i[None] < n[sl, None]) & (t < tmax[sl, None])
        considered += int(keep.sum())
        r_idx = torch.arange(s, s + shape[0], device=dev)[:, None].expand(shape)[keep]
        tt = t[keep]
        row, inside = grid.lookup(frame[r_idx], origins[r_idx] + tt[:, None] * dirs[r_idx])
        sel = row >= 0 if use_occupancy else inside
        out_r.append(r_idx[sel])
        out_t.append(tt[sel])
        out_row.append(row[sel])
    if not out_r:
        r_all = torch.zeros(0, dtype=torch.long, device=dev)
        t_all = origins.new_zeros(0)
        row = torch.zeros(0, dtype=torch.long, device=dev)
    else:
        r_all, t_all, row = torch.cat(out_r), torch.cat(out_t), torch.cat(out_row)
    x_all = origins[r_all] + t_all[:, None] * dirs[r_all]
    if not cull_joints:
        cand = torch.arange(K, dtype=torch.int16, device=dev)[None].expand(r_all.shape[0], K)
    elif use_occupancy:
        cand = grid.cand[row]
    else:
        M = grid.cand.shape[1]
        cand = torch.arange(K, dtype=torch.int16, device=dev)[None].repeat(r_all.shape[0], 1)
        occ = row >= 0
        cand[occ] = torch.cat([grid.cand[row[occ]],
                               torch.full((int(occ.sum()), K - M), K, device=dev, dtype=torch.int16)], 1)
    return Samples(r_all, t_all, x_all, cand, considered)


def mask_boxes(masks: Tensor, dilate_px: int) -> Tensor:
    """Dilated bounding box of every mask: masks (N, H, W) bool -> (N, 4) long y0, y1, x0, x1.

    Half-open (rows y0..y1-1, cols x0..x1-1), clipped to the image; an empty mask gives
    an empty box (y0 = y1 = 0).
    """
    N, H, W = masks.shape
    rows = masks.any(2)  # (N, H)
    cols = masks.any(1)  # (N, W)
    ar_h = torch.arange(H, device=masks.device)
    ar_w = torch.arange(W, device=masks.device)
    big = 1 << 30
    y0 = torch.where(rows, ar_h, big).min(1).values
    y1 = torch.where(rows, ar_h, -1).max(1).values + 1
    x0 = torch.where(cols, ar_w, big).min(1).values
    x1 = torch.where(cols, ar_w, -1).max(1).values + 1
    empty = ~rows.any(1)
    box = torch.stack([(y0 - dilate_px).clamp(0, H), (y1 + dilate_px).clamp(0, H),
                       (x0 - dilate_px).clamp(0, W), (x1 + dilate_px).clamp(0, W)], -1)
    return torch.where(empty[:, None], torch.zeros_like(box), box)


def box_pixels(box: Tensor) -> tuple[Tensor, Tensor]:
    """Row and column (n,) of every pixel in one box (4,) y0, y1, x0, x1, row-major."""
    y0, y1, x0, x1 = (int(v) for v in box)
    yy, xx = torch.meshgrid(torch.arange(y0, y1), torch.arange(x0, x1), indexing="ij")
    return yy.reshape(-1), xx.reshape(-1)


def occupied_centres(grid: OccupancyGrid, frame: int) -> Tensor:
    """World centres (n, 3) of the occupied voxels of ``frame``."""
    G = torch.tensor(grid.res, device=grid.index.device)
    occ = (grid.index[frame] >= 0).nonzero()[:, 0]
    ijk = torch.stack([occ // (G[1] * G[2]), (occ // G[2]) % G[1], occ % G[2]], -1).to(grid.voxel.dtype)
    return grid.origin[frame] + (ijk + 0.5) * grid.voxel[frame]


def occupancy_pixels(uv: Tensor, depth: Tensor, radius_px: Tensor, height: int, width: int) -> Tensor:
    """Pixels (C, H, W) bool whose rays can meet an occupied voxel.

    uv (C, n, 2), depth (C, n): the occupied voxel centres projected into C cameras
    (:func:`occupied_centres`, then the camera model, distortion included);
    radius_px (C,): a voxel's half-diagonal in pixels at the nearest depth (conservative
    growth of every hit). A centre behind a camera marks its whole image.
    """
    C = uv.shape[0]
    out = torch.zeros(C, height, width, dtype=torch.bool, device=uv.device)
    for c in range(C):  # C cameras: a loop over images, not over pixels
        if uv.shape[1] == 0:
            continue
        if (depth[c] <= 1e-6).any():
            out[c] = True
            continue
        r = int(radius_px[c]) + 1
        px = uv[c].round().long()
        ok = (px[:, 0] >= -r) & (px[:, 0] < width + r) & (px[:, 1] >= -r) & (px[:, 1] < height + r)
        px = px[ok]
        m = torch.zeros(height + 2 * r, width + 2 * r, dtype=torch.float32, device=uv.device)
        m[px[:, 1] + r, px[:, 0] + r] = 1
        m = torch.nn.functional.max_pool2d(m[None, None], 2 * r + 1, stride=1, padding=r)[0, 0]
        out[c] = m[r:r + height, r:r + width] > 0
    return out
