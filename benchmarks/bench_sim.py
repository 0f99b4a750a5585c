"""Benchmark of the cloth solver (anidress_core.sim): time per frame and quality.

Run: .venv/bin/python benchmarks/bench_sim.py [--frames 300] [--newton-frames N]
Writes benchmarks/sim.md and benchmarks/sim.csv. Not a test.

Scene: a flared open-cone skirt with its waist ring (the band) around the
mannequin's hips, built in this script (anidress_core.garment has no skirt builder
yet), ~3K and ~8K vertices, on the procedural mannequin (6,500 vertices) doing the
library "twirl" and "walk" motions at 30 fps. Quality: edge length / rest length
(max and 99th percentile over edges, worst frame), penetration of free garment
vertices into the posed body (winding-number inside test), NaN count.
Reference: newton's SolverVBD (optional; see --newton-frames).
"""
from __future__ import annotations

import argparse
import csv
import datetime
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from anidress_core.body import make_motion, mannequin_model  # noqa: E402
from anidress_core.sim import ClothParams, edge_stretch, penetration_depth, simulate  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402


def grid_faces(rows: int, cols: int) -> np.ndarray:
    f = []
    for r in range(rows - 1):
        for c in range(cols):
            a, b = r * cols + c, r * cols + (c + 1) % cols
            d, e = a + cols, b + cols
            f += [[a, d, b], [b, d, e]] if (r + c) % 2 else [[a, d, e], [a, e, b]]
    return np.asarray(f, dtype=np.int64)


def flared_skirt(around: int, rows: int, waist_y=0.10, length=0.55, waist_r=(0.145, 0.108), hem_r=(0.40, 0.37),
                 waist_z=-0.003):
    """Open cone skirt in the mannequin's canonical space (y up): (verts, faces, band = top ring)."""
    t = np.linspace(0.0, 1.0, rows)[:, None]
    a = np.linspace(0, 2 * np.pi, around, endpoint=False)[None, :]
    rx = waist_r[0] + (hem_r[0] - waist_r[0]) * t
    rz = waist_r[1] + (hem_r[1] - waist_r[1]) * t
    v = np.stack([rx * np.cos(a), np.broadcast_to(waist_y - length * t, (rows, around)),
                  waist_z + rz * np.sin(a)], -1).reshape(-1, 3)
    band = np.zeros(len(v), bool)
    band[:around] = True
    return v, grid_faces(rows, around), band


def machine() -> str:
    cpu = platform.processor() or "?"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import torch
    import warp

    return (f"{cpu}, {os.cpu_count()} logical CPUs (Warp CPU kernels run on one thread; torch threads "
            f"{torch.get_num_threads()}); Python {platform.python_version()}, warp-lang {warp.__version__}, "
            f"torch {torch.__version__}, numpy {np.__version__}")


def quality(frames, rest, faces, band, body_verts, body_faces):
    st = edge_stretch(frames, rest, faces)
    pen = penetration_depth(frames, body_verts, body_faces)[:, ~band]
    nan = int((~np.isfinite(frames)).sum())
    return (float(np.nanmax(np.nanpercentile(st, 99, axis=1))), float(np.nanmax(st)), float(pen.max() * 1000), nan)


def run_ours(scene, params):
    v, f, band, gw, body, posed, fps = scene
    t0 = time.perf_counter()
    res = simulate(v, f, band, gw, body.v_template, body.faces, body.weights, posed.transforms, fps, params)
    wall = time.perf_counter() - t0
    return res.frames, wall, res.stats


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--sizes", default="96x32,160x50", help="around x rows of the skirt grids")
    ap.add_argument("--motions", default="twirl,walk")
    ap.add_argument("--newton-frames", type=int, default=0, help="frames for the newton reference (0: skip)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    body = mannequin_model()
    params = ClothParams()
    rows_out = []
    for size in args.sizes.split(","):
        around, rows = map(int, size.split("x"))
        v, f, band = flared_skirt(around, rows)
        _, idx = cKDTree(body.v_template.numpy()).query(v)
        gw = body.weights.numpy()[idx]
        for motion in args.motions.split(","):
            m = make_motion(motion, args.frames)
            posed = body.pose(m.poses, m.Rh, m.Th)
            scene = (v, f, band, gw, body, posed, m.fps)
            frames, wall, stats = run_ours(scene, params)
            total = args.frames + params.settle_frames - 1  # simulated frame steps incl. settle
            q = quality(frames, v, f, band, posed.vertices, body.faces)
            row = dict(method="anidress_core.sim XPBD (Warp CPU, 30x2)", reference="no", mesh_vertices=len(v),
                       motion=motion, frames=args.frames, ms_per_frame=1000 * wall / total, stretch_p99=q[0],
                       stretch_max=q[1], penetration_max_mm=q[2], nan_count=q[3],
                       recoveries=len(stats.recoveries))
            print(row, flush=True)
            rows_out.append(row)
            if args.newton_frames > 0:
                try:
                    from bench_sim_newton import run_newton  # noqa: WPS433 (optional reference)

                    nf, nwall, nsteps = run_newton(scene, args.newton_frames)
                    nq = quality(nf, v, f, band, posed.vertices[: nf.shape[0]], body.faces)
                    row = dict(method="newton SolverVBD (CPU, 10x5)", reference="yes", mesh_vertices=len(v),
                               motion=motion, frames=nf.shape[0], ms_per_frame=1000 * nwall / nsteps,
                               stretch_p99=nq[0], stretch_max=nq[1], penetration_max_mm=nq[2], nan_count=nq[3],
                               recoveries=0)
                    print(row, flush=True)
                    rows_out.append(row)
                except Exception as exc:  # reference is optional: record why it is missing
                    print(f"newton reference failed: {exc!r}", flush=True)
    write(rows_out, args)


def write(rows, args):
    out = ROOT / "benchmarks"
    cols = ["method", "reference", "mesh_vertices", "motion", "frames", "ms_per_frame", "stretch_p99", "stretch_max",
            "penetration_max_mm", "nan_count", "recoveries"]
    with open(out / "sim.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.4f}" if isinstance(r[k], float) else r[k]) for k in cols})
    cmd = " ".join([".venv/bin/python", "benchmarks/bench_sim.py"] + sys.argv[1:])
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    except OSError:
        rev = "?"
    lines = [
        "# Cloth simulation benchmark (`anidress_core.sim`)", "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `{cmd}` (git {rev} + working tree)",
        f"- machine: {machine()}",
        "- scene: flared open-cone skirt built in `benchmarks/bench_sim.py` (no garment builder in "
        "`anidress_core.garment` yet), waist ring pinned (band) around the mannequin's hips, 0.55 m long; "
        "procedural mannequin body (6,500 vertices) from `mannequin_model()`; motions from `make_motion` at 30 fps.",
        "- ours: default `ClothParams` (substep 1/900 s -> 30 substeps/frame, 2 iterations, bend_stiffness 1e-4, "
        "thickness 4 mm) plus 30 settle frames; ms/frame = wall time of `simulate` (setup and settle included) / "
        "(frames + settle - 1).",
        "- stretch: edge length / rest length, p99 over edges of the worst frame, and the max over all; "
        "penetration: free garment vertices inside the posed body (winding number), max over frames, mm.",
        "",
        "| method | reference | V | motion | frames | ms/frame | stretch p99 | stretch max | penetration max (mm) | NaN | recoveries |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(f"| {r['method']} | {r['reference']} | {r['mesh_vertices']} | {r['motion']} | {r['frames']} | "
                     f"{r['ms_per_frame']:.1f} | {r['stretch_p99']:.3f} | {r['stretch_max']:.3f} | "
                     f"{r['penetration_max_mm']:.1f} | {r['nan_count']} | {r['recoveries']} |")
    if not any(r["reference"] == "yes" for r in rows):
        lines += ["", "Reference: newton SolverVBD was NOT run in this benchmark run (see the notes below)."]
    (out / "sim.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
