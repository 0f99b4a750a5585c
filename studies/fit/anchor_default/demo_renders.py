"""The demo skirt's fit and renders with each setting of L_anchor's references (issue 48 item 4).

Reads finished demo runs (results/ folders of `make demo`'s workflow, each with its overlay, e.g.
``fit: {anchor_reference: texture}`` through ``snakemake --configfile config/config.yaml OVERLAY``, which reruns
fit, fit_eval, the `full` field and its renders) and writes the table of all to OUT (markdown), each run's change
against the first:

    .venv/bin/python studies/fit/anchor_default/demo_renders.py OUT.md 'texture=DIR' 'images=DIR' --note '...'
"""
from __future__ import annotations

import csv
import json
import os
import platform
import subprocess
import statistics
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


def main(out: Path, runs: dict[str, Path], note: str) -> None:
    """The table of every run (label -> its results/ folder), each run's change against the first."""
    command = " ".join([".venv/bin/python studies/fit/anchor_default/demo_renders.py", str(out),
                        *(f"'{k}={v}'" for k, v in runs.items()), "--note", f"'{note}'"])
    lines = ["# Demo skirt: the fit and the `full` field's renders with each setting of L_anchor's references", "",
             f"- command: `{command}`",
             f"- runs: `make demo`'s workflow (config/config.yaml) with an overlay per run (fit, fit_eval, the `full` "
             f"field and its renders rerun); one machine, deterministic runs. {note}",
             f"- machine: {_cpu()}, {os.cpu_count()} logical CPUs; analysed at git {_git()}", "",
             "| run | fit walk mm (x floor) | fit dance mm (x floor) | kind | box PSNR | subject PSNR | "
             "garment PSNR | body PSNR | SSIM | subject SSIM | IoU |",
             "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, root in runs.items():
        walk, dance = fit_row(root, "walk"), fit_row(root, "dance")
        for kind, m in render_rows(root).items():
            lines.append(f"| {name} | {walk[0]:.2f} ({walk[1]:.2f}x) | {dance[0]:.2f} ({dance[1]:.2f}x) | {kind} | "
                         f"{m['psnr_db']:.2f} | {m['psnr_subject_db']:.2f} | {m['psnr_garment_db']:.2f} | "
                         f"{m['psnr_body_db']:.2f} | {m['ssim']:.4f} | {m['ssim_subject']:.4f} | {m['iou']:.4f} |")
    (ref_name, ref_root), *others = runs.items()
    b = render_rows(ref_root)
    for name, root in others:
        a = render_rows(root)
        lines += ["", f"{name} minus {ref_name}:", ""]
        for kind in a:
            d = {k: a[kind][k] - b[kind][k] for k in ("psnr_db", "psnr_subject_db", "psnr_garment_db", "iou")}
            lines.append(f"- {kind}: box {d['psnr_db']:+.2f} dB, subject {d['psnr_subject_db']:+.2f} dB, garment "
                         f"{d['psnr_garment_db']:+.2f} dB, IoU {d['iou']:+.4f}")
    out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("runs", nargs="+", help="LABEL=RESULTS_DIR, the reference first")
    ap.add_argument("--note", default="", help="what the runs are (overlays, commits)")
    args = ap.parse_args()
    main(args.out, {r.split("=", 1)[0]: Path(r.split("=", 1)[1]) for r in args.runs}, args.note)
