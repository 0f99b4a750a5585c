"""The demo skirt's fit and renders with L_anchor's image references (the default) against the garment texture's.

Reads two finished demo runs (results/ folders: the default, and the same run with an overlay
``fit: {anchor_reference: texture}``, i.e. ``snakemake --configfile config/config.yaml OVERLAY``, which reruns
fit, fit_eval, the `full` field and its renders) and writes the table of both to OUT (markdown):

    .venv/bin/python studies/fit/anchor_default/demo_renders.py IMAGES_RESULTS TEXTURE_RESULTS OUT.md
"""
from __future__ import annotations

import csv
import json
import os
import platform
import subprocess
import statistics
import sys
from pathlib import Path


def _cpu() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []:
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def _git() -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()


def fit_row(results: Path, seq: str) -> tuple[float, float]:
    rows = list(csv.DictReader(open(results / "skirt" / seq / "fit_metrics.csv")))
    rmse = statistics.mean(float(r["vertex_rmse_m"]) for r in rows)
    floor = statistics.mean(float(r["rig_floor_rmse_m"]) for r in rows)
    return rmse * 1e3, rmse / floor


def render_rows(results: Path) -> dict:
    summary = json.loads((results / "skirt" / "walk" / "full" / "metrics_summary.json").read_text())
    return {m["kind"]: m for m in summary["metrics"]}


def main(images: Path, texture: Path, out: Path) -> None:
    runs = {"images (default)": images, "texture": texture}
    lines = ["# Demo skirt: L_anchor on image references (the default) against the garment texture", "",
             f"- command: `.venv/bin/python studies/fit/anchor_default/demo_renders.py {images} {texture} {out}`",
             "- runs: `make demo`'s workflow (config/config.yaml), then the same with the overlay "
             "`fit: {anchor_reference: texture}` (fit, fit_eval, the `full` field and its renders rerun); one "
             "machine, deterministic runs",
             f"- machine: {_cpu()}, {os.cpu_count()} logical CPUs; analysed at git {_git()} (the runs: git 4491214)", "",
             "| references | fit walk mm (x floor) | fit dance mm (x floor) | kind | box PSNR | subject PSNR | "
             "garment PSNR | body PSNR | SSIM | subject SSIM | IoU |",
             "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, root in runs.items():
        walk, dance = fit_row(root, "walk"), fit_row(root, "dance")
        for kind, m in render_rows(root).items():
            lines.append(f"| {name} | {walk[0]:.2f} ({walk[1]:.2f}x) | {dance[0]:.2f} ({dance[1]:.2f}x) | {kind} | "
                         f"{m['psnr_db']:.2f} | {m['psnr_subject_db']:.2f} | {m['psnr_garment_db']:.2f} | "
                         f"{m['psnr_body_db']:.2f} | {m['ssim']:.4f} | {m['ssim_subject']:.4f} | {m['iou']:.4f} |")
    a, b = render_rows(images), render_rows(texture)
    lines += ["", "Image references minus texture references:", ""]
    for kind in a:
        d = {k: a[kind][k] - b[kind][k] for k in ("psnr_db", "psnr_subject_db", "psnr_garment_db", "iou")}
        lines.append(f"- {kind}: box {d['psnr_db']:+.2f} dB, subject {d['psnr_subject_db']:+.2f} dB, garment "
                     f"{d['psnr_garment_db']:+.2f} dB, IoU {d['iou']:+.4f}")
    out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
