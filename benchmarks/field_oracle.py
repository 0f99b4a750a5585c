"""Oracle deformations of the field's attribution rows (benchmarks/bench_field.py ``attribution``): a hook
module that the attribution jobs import before the ``anidress`` command runs
(``python -m benchmarks.field_oracle <command> ...``), selected by ``ANIDRESS_ORACLE``:

* ``dense_gt``: every sample nearer the ground-truth garment surface of its frame than the ground-truth body
  (and within ``ANIDRESS_ORACLE_BAND_M``, default 0.05 m) is carried to the canonical frame through that
  mesh instead of the warp: the nearest point on the posed mesh (face, barycentric coordinates) and the
  offset along its normal, put on the same face of the rest mesh (the scene's garment/template.obj, the
  ground truth's topology) with the same offset along the rest normal; its foreground likelihood is 1.
  It approximately bounds any deformation model of the garment. Where two layers of the garment
  (folds) are closer than the band, a sample may take the wrong layer; the nearest face is searched
  among the faces around the nearest vertex (exact for points whose nearest vertex is on their
  nearest face), and the count of samples whose runner-up layer is within 1 cm is logged.

The hook wraps ``anidress_core.stages.field.run_train`` / ``run_render`` to learn the scene, sequence and
frames of the command, and ``anidress_core.field.model.backward_warp`` to override the garment samples.
Library motions (no ground truth) are rendered without it.
"""
from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger("anidress.oracle")


def closest_point_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Barycentric coordinates (..., 3) of the point of triangle (a, b, c) nearest p, all (..., 3)
    (Ericson, Real-Time Collision Detection, 5.1.5: the Voronoi regions of the vertices, edges and face)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    one, zero = torch.ones_like(d1), torch.zeros_like(d1)
    eps = 1e-20
    # face interior (default)
    den = (va + vb + vc).clamp_min(eps)
    v, w = vb / den, vc / den
    bary = torch.stack([1 - v - w, v, w], -1)
    # edge bc
    wbc = ((d4 - d3) / ((d4 - d3) + (d5 - d6)).clamp_min(eps)).clamp(0, 1)
    bary = torch.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None],
                       torch.stack([zero, 1 - wbc, wbc], -1), bary)
    # edge ac
    wac = (d2 / (d2 - d6).clamp_min(eps)).clamp(0, 1)
    bary = torch.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], torch.stack([1 - wac, zero, wac], -1), bary)
    # edge ab
    vab = (d1 / (d1 - d3).clamp_min(eps)).clamp(0, 1)
    bary = torch.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], torch.stack([1 - vab, vab, zero], -1), bary)
    # vertex regions
    bary = torch.where(((d6 >= 0) & (d5 <= d6))[..., None], torch.stack([zero, zero, one], -1), bary)
    bary = torch.where(((d3 >= 0) & (d4 <= d3))[..., None], torch.stack([zero, one, zero], -1), bary)
    bary = torch.where(((d1 <= 0) & (d2 <= 0))[..., None], torch.stack([one, zero, zero], -1), bary)
    return bary


class DenseGT:
    """Ground-truth garment meshes of one sequence and the rest mesh, with per-frame vertex trees."""

    def __init__(self, scene_dir: Path, seq: str, frames: list[int], band_m: float):
        from scipy.spatial import cKDTree

        from anidress_core.io.mesh import read_mesh

        a = np.load(scene_dir / seq / "gt" / "meshes.npz")
        self.g = torch.from_numpy(a["garment_vertices"][frames]).float()  # (T, V, 3)
        self.faces = torch.from_numpy(a["garment_faces"]).long()
        body = a["body_vertices"][frames]
        rest, faces, _ = read_mesh(scene_dir / "garment" / "template.obj")
        if rest.shape[0] != self.g.shape[1] or not np.array_equal(faces, a["garment_faces"]):
            raise SystemExit(f"{scene_dir}/garment/template.obj is not the topology of {seq}/gt/meshes.npz")
        self.rest = torch.from_numpy(rest).float()
        self.band = band_m
        self.gtree = [cKDTree(g) for g in a["garment_vertices"][frames]]
        self.btree = [cKDTree(b) for b in body]
        # 1-ring faces of every vertex, padded with -1
        V, F = self.rest.shape[0], self.faces.shape[0]
        inc = [[] for _ in range(V)]
        for f, tri in enumerate(self.faces.tolist()):
            for v in tri:
                inc[v].append(f)
        deg = max(len(x) for x in inc)
        self.ring = torch.full((V, deg), -1, dtype=torch.long)
        for v, fs in enumerate(inc):
            self.ring[v, :len(fs)] = torch.tensor(fs)
        self.near_layers = 0
        self.garment_samples = 0

    def warp(self, x: torch.Tensor, frame: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(x_c (N, 3), mask (N,) bool of the samples carried through the garment mesh)."""
        x_c = torch.zeros_like(x)
        mask = torch.zeros(x.shape[0], dtype=torch.bool)
        xn = x.detach().cpu().numpy()
        for t in torch.unique(frame).tolist():
            sel = (frame == t).nonzero()[:, 0]
            dg, vg = self.gtree[t].query(xn[sel.numpy()], k=8)
            db, _ = self.btree[t].query(xn[sel.numpy()])
            near = torch.from_numpy((dg[:, 0] < db) & (dg[:, 0] < self.band))
            if not near.any():
                continue
            s = sel[near]
            v = torch.from_numpy(vg[near.numpy(), 0]).long()
            ring = self.ring[v]  # (n, D)
            ok = ring >= 0
            fi = self.faces[ring.clamp_min(0)]  # (n, D, 3)
            P = self.g[t]
            p = x[s].float()[:, None].expand(-1, ring.shape[1], 3)
            bary = closest_point_on_triangles(p, P[fi[..., 0]], P[fi[..., 1]], P[fi[..., 2]])
            q = (bary[..., None] * P[fi]).sum(-2)
            d = (p - q).norm(dim=-1).masked_fill(~ok, float("inf"))
            best = d.argmin(1)
            ar = torch.arange(s.shape[0])
            f, b, qb = fi[ar, best], bary[ar, best], q[ar, best]
            n_pose = torch.linalg.cross(P[f[:, 1]] - P[f[:, 0]], P[f[:, 2]] - P[f[:, 0]])
            n_pose = n_pose / n_pose.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            h = ((x[s].float() - qb) * n_pose).sum(-1)
            R = self.rest
            n_rest = torch.linalg.cross(R[f[:, 1]] - R[f[:, 0]], R[f[:, 2]] - R[f[:, 0]])
            n_rest = n_rest / n_rest.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            x_c[s] = ((b[..., None] * R[f]).sum(-2) + h[:, None] * n_rest).to(x.dtype)
            mask[s] = True
            # another layer within 1 cm: one of the 8 nearest posed vertices lies more than 3 cm from the nearest
            # on the rest mesh (another part of the garment), yet within 1 cm of the nearest one's distance
            self.garment_samples += int(s.shape[0])
            vk = torch.from_numpy(vg[near.numpy()]).long()
            far = (self.rest[vk] - self.rest[vk[:, :1]]).norm(dim=-1) > 0.03
            close = torch.from_numpy(dg[near.numpy()] - dg[near.numpy(), :1] < 0.01)
            self.near_layers += int((far & close).any(1).sum())
        return x_c, mask


_CTX: dict = {}


def _install() -> None:
    from anidress_core.field import model as M
    from anidress_core.stages import field as SF

    kind = os.environ.get("ANIDRESS_ORACLE", "")
    if kind != "dense_gt":
        raise SystemExit(f"ANIDRESS_ORACLE: unknown oracle {kind!r} (dense_gt)")
    band = float(os.environ.get("ANIDRESS_ORACLE_BAND_M", "0.05"))
    warp0, train0, render0 = M.backward_warp, SF.run_train, SF.run_render

    def warp(x_o, frame, *a, **kw):
        r = warp0(x_o, frame, *a, **kw)
        oracle = _CTX.get("oracle")
        if oracle is None or frame is None:
            return r
        x_c, m = oracle.warp(x_o, frame.cpu())
        m = m.to(x_o.device)
        return r._replace(x_c=torch.where(m[:, None], x_c.to(r.x_c), r.x_c),
                          fg=torch.where(m, torch.ones_like(r.fg), r.fg))

    def frames_of(scene_dir, seq, stride):
        from anidress_core.io.scene import load_sequence_motion, read_scene

        info = read_scene(Path(scene_dir))
        T = load_sequence_motion(Path(scene_dir), seq, info["fps"], None).poses.shape[0]
        return list(range(0, T, max(1, int(stride))))

    def run_train(scene_dir, seq, variant, masks_dir, out_pt, params, **kw):
        stride = int(params.get("train", {}).get("frame_stride", 1))
        _CTX["oracle"] = DenseGT(Path(scene_dir), seq, frames_of(scene_dir, seq, stride), band)
        try:
            return train0(scene_dir, seq, variant, masks_dir, out_pt, params, **kw)
        finally:
            _report()

    def run_render(field_pt, scene_dir, out_dir, params, seq=None, **kw):
        _CTX["oracle"] = None
        if seq is not None and kw.get("library_motion_npz") is None:
            _CTX["oracle"] = DenseGT(Path(scene_dir), seq, frames_of(scene_dir, seq, kw.get("frame_stride", 1)), band)
        try:
            return render0(field_pt, scene_dir, out_dir, params, seq=seq, **kw)
        finally:
            _report()

    M.backward_warp, SF.run_train, SF.run_render = warp, run_train, run_render


def _report() -> None:
    o = _CTX.get("oracle")
    if o is not None and o.garment_samples:
        log.info("dense_gt oracle: %d garment samples, %.1f%% with another layer within 1 cm", o.garment_samples,
                 100 * o.near_layers / o.garment_samples)


if __name__ == "__main__":
    _install()
    from anidress_core import cli

    sys.argv = ["anidress", *sys.argv[1:]]
    cli.main()
