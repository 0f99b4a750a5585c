"""Benchmark of anidress_core.raster against trimesh ray casting, measured in one run.

Run from the repository root:

    .venv/bin/python -m benchmarks.bench_raster

Writes benchmarks/raster.md (table, machine, command) and benchmarks/raster.csv (one row
per configuration). Mesh: a noise-displaced UV sphere, trimesh.creation.uv_sphere(count=
(52, 50)), exactly 10,000 faces and 5,002 vertices, closed; cameras on a ring around it,
the mesh covering about 40 % of the pixels. Times are medians over --repeats runs after one
warm-up run. This is a benchmark, not a test.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from anidress_core.raster import project_vertices, rasterize, render_mesh
from benchmarks.benchutil import cpu_model

ROOT = Path(__file__).resolve().parents[1]



def bench_mesh() -> trimesh.Trimesh:
    """10,000-face closed, noise-displaced, body-proportioned sphere (deterministic)."""
    m = trimesh.creation.uv_sphere(radius=1.0, count=(52, 50))
    v = m.vertices.copy()
    rng = np.random.default_rng(0)
    th = np.arctan2(v[:, 1], v[:, 0])
    ph = np.arccos(np.clip(v[:, 2], -1, 1))
    r = 1 + 0.12 * np.sin(3 * th) * np.sin(2 * ph) + 0.015 * rng.standard_normal(len(v))
    v = v * r[:, None] * np.array([0.7, 0.6, 1.0])
    return trimesh.Trimesh(v, m.faces, process=False)


def ring_cameras(C: int, size: int, dist: float = 3.0, dtype=torch.float64):
    """C OpenCV cameras on a ring (z up), looking at the origin; K (C, 3, 3), E (C, 4, 4)."""
    Es, Ks = [], []
    f = 0.85 * size * dist / 2.0  # the mesh (about 2 high) spans ~85 % of the image height
    for c in range(C):
        a = 2 * np.pi * c / C + 0.3
        eye = np.array([dist * np.cos(a), dist * np.sin(a), 0.25 + 0.1 * np.sin(3 * a)])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        E = np.eye(4)
        E[:3, :3] = np.stack([x, y, z])
        E[:3, 3] = -E[:3, :3] @ eye
        Es.append(E)
        Ks.append([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return torch.tensor(np.array(Ks), dtype=dtype), torch.tensor(np.array(Es), dtype=dtype)


def timed(fn, repeats: int) -> tuple[float, object]:
    out = fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def reference_raycast(mesh: trimesh.Trimesh, K: torch.Tensor, E: torch.Tensor, size: int, chunk: int = 2048):
    """trimesh RayMeshIntersector (rtree) through the pixel centres of one camera."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    K, E = K.double().numpy(), E.double().numpy()
    R, t = E[:3, :3], E[:3, 3]
    Einv = np.linalg.inv(E)  # exact inverse, also if E is not quite rigid (float32 input)
    ii, jj = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    pix = np.stack([jj.ravel(), ii.ravel(), np.ones(size * size)], 1)
    dirs = (pix @ np.linalg.inv(K).T) @ Einv[:3, :3].T
    origin = np.broadcast_to(Einv[:3, 3], dirs.shape)
    fid = np.full(size * size, -1)
    depth = np.full(size * size, np.inf)
    inter = RayMeshIntersector(mesh)
    for s in range(0, size * size, chunk):  # batches of rays bound the candidate lists' memory
        tri, ray, loc = inter.intersects_id(
            origin[s : s + chunk], dirs[s : s + chunk], multiple_hits=False, return_locations=True
        )
        if len(ray):
            fid[s + ray] = tri
            depth[s + ray] = (loc @ R.T + t)[:, 2]
    return fid.reshape(size, size), depth.reshape(size, size)


def edge_distance(mesh, K, E, fid) -> np.ndarray:
    """Pixel distance of each pixel centre to the boundary of face fid (inf where -1)."""
    uv = project_vertices(torch.tensor(mesh.vertices), K.double(), E.double())[0][0].numpy()
    out = np.full(fid.shape, np.inf)
    ii, jj = np.nonzero(fid >= 0)
    tri = uv[mesh.faces[fid[ii, jj]]]
    p = np.stack([jj, ii], 1).astype(np.float64)
    d = np.full(len(p), np.inf)
    for k in range(3):
        a, b = tri[:, k], tri[:, (k + 1) % 3]
        ab = b - a
        s = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-300), 0, 1)
        d = np.minimum(d, np.linalg.norm(a + s[:, None] * ab - p, axis=1))
    out[ii, jj] = d
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--frames", type=int, default=60, help="frames of the demo-scale sweep")
    ap.add_argument("--threads", default="", help="comma-separated torch thread counts to time (default: torch's)")
    ap.add_argument("--no-reference", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder of raster.md and raster.csv")
    args = ap.parse_args()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    thread_counts = [int(x) for x in args.threads.split(",") if x.strip()]
    command = " ".join([".venv/bin/python", "-m", "benchmarks.bench_raster", *sys.argv[1:]])
    mesh = bench_mesh()
    V = torch.tensor(mesh.vertices, dtype=torch.float32)
    Fc = torch.tensor(mesh.faces)
    nF = Fc.shape[0]
    load_before = os.getloadavg()
    rows: list[dict] = []

    def row(method, reference, res, C, wall, frames=1, **kw):
        r = dict(
            method=method, reference=reference, resolution=f"{res}x{res}", cameras=C, frames=frames, faces=nF,
            threads=torch.get_num_threads(), wall_s=wall, mpix_per_s=res * res * C * frames / wall / 1e6,
            face_agreement_pct="", depth_err_max_m="", depth_err_median_m="", notes="",
        )
        r.update(kw)
        rows.append(r)
        print({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()}, flush=True)
        return r

    default_threads = torch.get_num_threads()
    for nt in thread_counts or [default_threads]:
        torch.set_num_threads(nt)
        # 1. rasterize: 512^2, one camera and a batch of 8; both backends (warp: the default)
        for res, C in ((512, 1), (512, 8), (256, 12)):
            K, E = ring_cameras(C, res, dtype=torch.float32)
            for bary in (True, False):
                wall_t, fr_t = timed(lambda: rasterize(V, Fc, K, E, res, res, backend="torch", with_bary=bary),
                                     args.repeats)
                wall_w, fr_w = timed(lambda: rasterize(V, Fc, K, E, res, res, backend="warp", with_bary=bary),
                                     args.repeats)
                cov = (fr_w.face_id >= 0).float().mean().item()
                same = 100 * (fr_w.face_id == fr_t.face_id).double().mean().item()
                tag = "" if bary else ", with_bary=False"
                row(f"rasterize (torch){tag}", "", res, C, wall_t)
                row(f"rasterize (warp){tag}", "rasterize (torch)", res, C, wall_w, face_agreement_pct=same,
                    notes=f"{wall_t / wall_w:.2f}x the torch backend's speed; coverage {100 * cov:.0f} % of pixels")
            if res == 512 and C == 1:
                for be in ("torch", "warp"):
                    wall_c, _ = timed(lambda: rasterize(V, Fc, K, E, res, res, cull_backfaces=True, backend=be),
                                      args.repeats)
                    row(f"rasterize ({be}) cull_backfaces", "", res, C, wall_c)

        # 2. render_mesh end to end (texture, 2 lights, ambient)
        g = torch.Generator().manual_seed(0)
        face_uv = torch.rand(nF, 3, 2, generator=g)
        tex = torch.rand(256, 256, 3, generator=g)
        lights = dict(
            light_dirs=torch.tensor([[0.3, -0.5, 0.8], [-0.6, 0.4, 0.2]]),
            light_colors=torch.tensor([[0.8, 0.8, 0.75], [0.3, 0.3, 0.35]]),
            ambient=torch.tensor([0.15, 0.15, 0.15]),
        )
        for res, C in ((512, 1), (512, 8), (256, 12)):
            K, E = ring_cameras(C, res, dtype=torch.float32)
            wall, _ = timed(
                lambda: render_mesh(V, Fc, K, E, res, res, face_uv=face_uv, texture=tex, **lights), args.repeats
            )
            row("render_mesh textured+lit", "", res, C, wall)

        # 3. demo scale: 12 cameras x F frames at 256^2, a deforming mesh, render_mesh
        K, E = ring_cameras(12, 256, dtype=torch.float32)
        t = torch.linspace(0, 1, args.frames)
        Vs = [V * (1 + 0.05 * torch.sin(6.28 * ti + 3 * V[:, 2:3])) for ti in t]
        render_mesh(Vs[0], Fc, K, E, 256, 256, face_uv=face_uv, texture=tex, **lights)
        t0 = time.perf_counter()
        for Vt in Vs:
            render_mesh(Vt, Fc, K, E, 256, 256, face_uv=face_uv, texture=tex, **lights)
        wall = time.perf_counter() - t0
        row("render_mesh textured+lit, deforming mesh", "", 256, 12, wall, frames=args.frames,
            notes=f"total for {args.frames} frames x 12 cameras (one run)")
    torch.set_num_threads(default_threads)

    # 4. agreement with trimesh ray casting at 512^2, one camera (the reference is timed
    #    once: it is slow), for float64 and float32 input
    if not args.no_reference:
        K, E = ring_cameras(1, 512)
        t0 = time.perf_counter()
        ref_fid, ref_depth = reference_raycast(mesh, K[0], E[0], 512)
        ref_wall = time.perf_counter() - t0
        row("trimesh RayMeshIntersector (rtree)", "", 512, 1, ref_wall,
            notes="the slow reference, float64, rays in batches of 2048, one run")
        for dtype, be in ((torch.float64, "warp"), (torch.float32, "warp"), (torch.float64, "torch")):
            Vd, Kd, Ed = torch.tensor(mesh.vertices, dtype=dtype), K.to(dtype), E.to(dtype)
            wall, frags = timed(lambda: rasterize(Vd, Fc, Kd, Ed, 512, 512, backend=be), args.repeats)
            fid = frags.face_id[0].numpy()
            agree = fid == ref_fid
            both = agree & (fid >= 0)
            err = np.abs(frags.depth[0].double().numpy()[both] - ref_depth[both])
            d_edge = np.minimum(edge_distance(mesh, K[0], E[0], fid), edge_distance(mesh, K[0], E[0], ref_fid))
            worst = float(d_edge[~agree].max()) if (~agree).any() else 0.0
            row(
                f"rasterize ({be}, {str(dtype)[6:]} input)", "trimesh RayMeshIntersector", 512, 1, wall,
                face_agreement_pct=100 * agree.mean(), depth_err_max_m=float(err.max()),
                depth_err_median_m=float(np.median(err)),
                notes=f"{int((~agree).sum())} of {agree.size} pixels differ, all within {worst:.2g} px of a "
                f"face edge; depth error over the {int(both.sum())} pixels hitting the same face; "
                f"{ref_wall / wall:.0f}x faster than the reference",
            )

    # 5. write the files
    fields = [
        "method", "reference", "resolution", "cameras", "frames", "faces", "threads", "wall_s", "mpix_per_s",
        "face_agreement_pct", "depth_err_max_m", "depth_err_median_m", "notes",
    ]
    with open(out_dir / "raster.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})

    def fmt(v, spec):
        return "" if v == "" else format(v, spec)

    lines = [
        "# Rasteriser benchmark (`anidress_core.raster`)",
        "",
        f"Command: `{command}`  ",
        f"Date: {datetime.datetime.now().isoformat(timespec='seconds')}  ",
        f"Machine: {cpu_model()}, {os.cpu_count()} logical CPUs, torch {torch.__version__}, "
        f"torch default threads {torch.get_num_threads()} (the `threads` column is what each row ran with), "
        f"Python {platform.python_version()}  ",
        f"Load average before the run (1, 5, 15 min): {', '.join(f'{x:.2f}' for x in load_before)}; "
        f"after: {', '.join(f'{x:.2f}' for x in os.getloadavg())}  ",
        f"Mesh: noise-displaced `trimesh.creation.uv_sphere(count=(52, 50))`, {nF} faces, "
        f"{V.shape[0]} vertices, closed (so about half the faces face away and are rasterised "
        f"too unless culled); cameras on a ring; float32 unless stated. Times: median of "
        f"{args.repeats} runs after a warm-up; Mpix/s = H * W * cameras * frames / wall time.",
        "",
        "| method | reference | resolution | cameras | frames | threads | wall (s) | Mpix/s "
        "| face agreement (%) | depth err max (m) | depth err median (m) | notes |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['reference']} | {r['resolution']} | {r['cameras']} | {r['frames']} "
            f"| {r['threads']} | "
            f"{r['wall_s']:.4f} | {r['mpix_per_s']:.2f} | {fmt(r['face_agreement_pct'], '.3f')} | "
            f"{fmt(r['depth_err_max_m'], '.2e')} | {fmt(r['depth_err_median_m'], '.2e')} | {r['notes']} |"
        )
    lines += [
        "",
        "Backends: `warp` (the default) is one Warp kernel thread per (camera, face) walking its pixel box",
        "(`anidress_core/raster_kernels.py`; on the CPU Warp runs it on ONE thread whatever the `threads`",
        "column says); `torch` is the batched tile code, which uses torch's threads. Both give the same",
        "face ids (the agreement column) and quantised depths to a unit in the last place. On a many-core",
        "CPU the torch backend may catch up (`rasterize(..., backend='torch')`).",
        "",
        "The machine is shared: other jobs running at the same time slow torch's parallel",
        "regions down a lot (see the load average above); rerun when it is idle to compare versions.",
    ]
    (out_dir / "raster.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out_dir / 'raster.md'} and {out_dir / 'raster.csv'}")


if __name__ == "__main__":
    main()
