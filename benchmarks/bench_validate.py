"""How long the scene check (anidress_core.stages.validate.validate_scene) takes on the demo scenes.

Run: .venv/bin/python -m benchmarks.bench_validate [--scenes skirt,tight,dress] [--repeats 3]
Writes benchmarks/validate.md and benchmarks/validate.csv. Not a test.

Methods, per scene folder data/<scene> (skipped when absent):
* ``ends_cli``: ``python -m anidress_core.cli validate data/<scene>`` in a fresh process:
  what the Snakemake job costs (imports of torch, scipy, pymeshlab included);
* ``ends``: ``validate_scene(images="ends")`` in a warm process (every image header,
  first and last frame of each camera decoded): the check itself;
* reference ``all``: ``validate_scene(images="all")``, every image decoded, measured in
  the same run: what a check that decodes everything would cost.
One thread (torch.set_num_threads(1), OMP_NUM_THREADS=1); medians of ``--repeats``,
the methods interleaved.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV1 = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="skirt,tight,dress")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder of validate.md and validate.csv")
    args = ap.parse_args()
    os.environ.update(ENV1)
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from anidress_core.stages.validate import validate_scene

    load_start = os.getloadavg()[0]
    rows = []
    for scene in args.scenes.split(","):
        d = ROOT / "data" / scene
        if not (d / "scene.yaml").is_file():
            print(f"skip {scene}: {d} not there")
            continue
        t_cli, t_ends, t_all = [], [], []
        s_ends = s_all = None
        for r in range(args.repeats):
            t0 = time.perf_counter()
            res = subprocess.run([sys.executable, "-m", "anidress_core.cli", "validate", f"data/{scene}"], cwd=ROOT,
                                 capture_output=True, text=True, env={**os.environ, **ENV1})
            t_cli.append(time.perf_counter() - t0)
            if res.returncode != 0:
                raise SystemExit(f"validate data/{scene} failed: {res.stderr[-2000:]}")
            t0 = time.perf_counter()
            s_ends = validate_scene(d, images="ends")
            t_ends.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            s_all = validate_scene(d, images="all")
            t_all.append(time.perf_counter() - t0)
            print(f"{scene} repeat {r}: cli {t_cli[-1]:.2f} s, ends {t_ends[-1]:.2f} s, all {t_all[-1]:.2f} s")
        images = sum(q["images"] for q in s_ends["sequences"].values())
        ref = statistics.median(t_all)
        for method, ts, s in (("ends_cli", t_cli, s_ends), ("ends", t_ends, s_ends), ("all", t_all, s_all)):
            rows.append({
                "scene": scene, "method": method, "reference": "all",
                "cameras": len(s["cameras"]["train"]) + len(s["cameras"]["test"]),
                "frames": sum(q["frames"] for q in s["sequences"].values()),
                "image_size": "x".join(map(str, s["image_size"])), "images": images,
                "images_decoded": sum(q["images_decoded"] for q in s["sequences"].values()),
                "garment_faces": (s["garment_template"] or {}).get("faces", 0),
                "wall_s": round(statistics.median(ts), 3), "wall_s_min": round(min(ts), 3),
                "ref_wall_s": round(ref, 3), "ratio_to_ref": round(statistics.median(ts) / ref, 3),
                "repeats": len(ts),
            })
    if not rows:
        raise SystemExit("no scene found under data/")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "validate.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "anidress_core/stages/validate.py"], cwd=ROOT,
                           capture_output=True, text=True).stdout.strip()
    lines = [
        "# Scene check (validate_scene) run time",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- machine: {platform.node()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs "
        f"(shared with other jobs; load average {load_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end), "
        "one thread",
        f"- command: `.venv/bin/python -m benchmarks.bench_validate --scenes {args.scenes} --repeats {args.repeats}`",
        f"- git revision: {rev}{' (validate.py modified)' if dirty else ''}",
        "- methods: `ends_cli` = `python -m anidress_core.cli validate data/<scene>` in a fresh process (imports "
        "included: the Snakemake job's cost); `ends` = `validate_scene(images=\"ends\")` in a warm process (every "
        "image header, first and last frame of each camera decoded); reference `all` = every image decoded, same run",
        "",
        "| scene | method | cameras | frames | images | decoded | garment faces | wall s (median) | min s | x reference |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['method']} | {r['cameras']} | {r['frames']} | {r['images']} "
                     f"({r['image_size']}) | {r['images_decoded']} | {r['garment_faces']} | {r['wall_s']:.2f} | "
                     f"{r['wall_s_min']:.2f} | {r['ratio_to_ref']:.2f} |")
    lines.append("")
    (out / "validate.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
