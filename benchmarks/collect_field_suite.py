"""The field's `full` vs `body_only` novel-pose margin over a generated suite, from a pipeline run's own files.

Run after the suite went through the whole pipeline (benchmarks/fit_suite.py's module docstring):
    .venv/bin/python -m benchmarks.collect_field_suite [--suite config/field_suite.yaml] [--run-root .]
Writes benchmarks/field_suite.md and benchmarks/field_suite.csv. Not a test; nothing is recomputed.

Per scene: the pipeline's fit of the training and of the held-out sequence (results/<scene>/<seq>/fit_metrics.csv:
vertex RMSE over the rig floor's, drift = mean RMSE of the last 10 frames / the first 10), and the field's
image metrics of both variants (results/<scene>/<train seq>/<variant>/metrics_summary.json: novel pose = all
cameras on the held-out sequence, posed by its fitted garment poses; novel view = the test cameras on the
training frames), with the training time of each variant (benchmarks/runs/<scene>/<seq>/<variant>/train.tsv).
The margin is full minus body_only (the paper's "w/o G" in its novel-pose table: +0.48 dB PSNR, +1.3 IoU points;
there too the test sequences' garment poses are estimated from their images).
"""
from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import subprocess
from pathlib import Path
from statistics import median

import numpy as np
import yaml

from anidress_core.io import files
from benchmarks.benchutil import cpu_model
from benchmarks.fit_suite import FIELD_TUNING

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("full", "body_only")
METRICS = ("psnr_db", "psnr_subject_db", "psnr_garment_db", "psnr_body_db", "ssim", "ssim_subject", "iou")


def _fit(path: Path) -> dict:
    """Mean vertex RMSE / rig floor and drift of rule fit_eval's rows for the pipeline's fit."""
    with open(path) as fh:
        rows = [r for r in csv.DictReader(fh) if r["method"] == "pipeline"]
    if not rows:
        raise SystemExit(f"{path}: no rows of method 'pipeline'")
    rmse = np.array([float(r["vertex_rmse_m"]) for r in sorted(rows, key=lambda r: int(r["frame"]))])
    floor = np.array([float(r["rig_floor_rmse_m"]) for r in rows])
    k = min(10, len(rmse) // 2) or 1
    return {"frames": len(rmse), "rmse_mm": 1e3 * rmse.mean(), "floor_mm": 1e3 * floor.mean(),
            "ratio": rmse.mean() / floor.mean(), "drift": rmse[-k:].mean() / rmse[:k].mean()}


def _field(path: Path) -> dict:
    """{kind: {psnr_db, ssim, iou, images}} of one metrics_summary.json."""
    summary = json.loads(path.read_text())
    return {m["kind"]: {**{k: float(m.get(k, float("nan"))) for k in METRICS}, "images": int(m["scored"])}
            for m in summary["metrics"]}


def _train_s(path: Path) -> float:
    with open(path) as fh:
        return float(list(csv.DictReader(fh, delimiter="\t"))[-1]["s"])


def collect(suite: dict, run: Path) -> list[dict]:
    """One row per scene of the suite overlay ``suite``, read from the run rooted at ``run``."""
    rows = []
    for name, sc in suite["scenes"].items():
        train = next(q["name"] for q in sc["sequences"] if q["role"] == "train")
        novel = next((q["name"] for q in sc["sequences"] if q["role"] == "novel_pose"), None)
        if novel is None:
            raise SystemExit(f"{name}: the suite's scene has no novel_pose sequence (fit_suite.py --novel-pose)")
        row = {"scene": name, "tuning": name in FIELD_TUNING, "kind": sc["kind"],
               "texture": sc["garment"]["texture"],
               "bend_stiffness": sc["garment"]["cloth"]["bend_stiffness"], "train": train, "novel_pose": novel}
        for role, seq in (("train", train), ("novel", novel)):
            for k, v in _fit(run / "results" / name / seq / "fit_metrics.csv").items():
                row[f"fit_{role}_{k}"] = v
        for var in VARIANTS:
            m = _field(run / "results" / name / train / var / "metrics_summary.json")
            for kind in ("novel_pose", "novel_view"):
                for k in METRICS:
                    row[f"{var}_{kind}_{k}"] = m[kind][k]
                row[f"{var}_{kind}_images"] = m[kind]["images"]
            row[f"{var}_train_s"] = _train_s(run / "benchmarks" / "runs" / name / train / var / "train.tsv")
        for kind in ("novel_pose", "novel_view"):
            for k in METRICS:
                row[f"margin_{kind}_{k}"] = row[f"full_{kind}_{k}"] - row[f"body_only_{kind}_{k}"]
        rows.append(row)
    return rows


def report(rows: list[dict], suite_path: str, run: Path, note: str = "") -> list[str]:
    """The markdown lines of benchmarks/field_suite.md."""
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=run, capture_output=True, text=True).stdout
    lines = ["# The field's full vs body_only margin on novel poses, over a generated suite", "",
             f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}; the run's git {rev.strip() or '?'}",
             f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs",
             f"- command: `.venv/bin/python -m benchmarks.collect_field_suite --suite {suite_path}"
             f"{'' if run == ROOT else f' --run-root {run}'}` after the suite "
             "went through the pipeline (`snakemake ... $(python -m benchmarks.fit_suite --seed 26 --prefix fsuite "
             "--count 6 --novel-pose --targets) --configfile config/config.yaml config/field_suite.yaml`)",
             "- scenes: generated by benchmarks/fit_suite.py; the field's settings were chosen on the tuning subset "
             "(marked), none on the others; every stage with the config's defaults (no per-scene fit or field "
             "section), the pipeline's own cues; the synthetic scenes give the exact body poses (a capture's are "
             "estimated)",
             "- fit: vertex RMSE over the rig floor's (the rig's best pose of the truth), mean over frames; drift = "
             "last 10 frames / first 10. The held-out sequence's garment poses, which pose the novel-pose renders, "
             "are the pipeline's fit of its images",
             "- field: PSNR inside the projected box of the subject (the paper's convention) and pooled inside the "
             "ground-truth subject mask and its garment label (gt/masks), SSIM on the box's rectangle, IoU of alpha > 0.5; "
             "novel pose = all 12 cameras on the held-out sequence, novel view = the 4 test cameras on the "
             "training frames (every `field/render/frame_stride`-th frame); margin = full - body_only "
             "(the paper's novel-pose table: +0.48 dB, +1.3 IoU points)"] + ([f"- run: {note}"] if note else []) + [""]
    lines += ["| scene | garment | fabric (bending J) | train -> novel pose | fit RMSE / floor train, novel (drift) "
              "| novel pose PSNR full / body_only (margin dB): box; subject; garment | SSIM full / body_only | "
              "IoU full / body_only (margin points) | novel view PSNR full / body_only: box; garment | "
              "train s full / body_only |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(
            f"| {r['scene']}{' (tuning)' if r['tuning'] else ''} | {r['kind']} | {r['texture']} "
            f"({r['bend_stiffness']:.3g}) | {r['train']} -> "
            f"{r['novel_pose']} | {r['fit_train_ratio']:.2f}x, {r['fit_novel_ratio']:.2f}x "
            f"({r['fit_train_drift']:.2f}, {r['fit_novel_drift']:.2f}) | {r['full_novel_pose_psnr_db']:.2f} / "
            f"{r['body_only_novel_pose_psnr_db']:.2f} ({r['margin_novel_pose_psnr_db']:+.2f}); "
            f"{r['full_novel_pose_psnr_subject_db']:.2f} / {r['body_only_novel_pose_psnr_subject_db']:.2f} "
            f"({r['margin_novel_pose_psnr_subject_db']:+.2f}); {r['full_novel_pose_psnr_garment_db']:.2f} / "
            f"{r['body_only_novel_pose_psnr_garment_db']:.2f} ({r['margin_novel_pose_psnr_garment_db']:+.2f}) | "
            f"{r['full_novel_pose_ssim']:.4f} / {r['body_only_novel_pose_ssim']:.4f} | "
            f"{r['full_novel_pose_iou']:.4f} / {r['body_only_novel_pose_iou']:.4f} "
            f"({100 * r['margin_novel_pose_iou']:+.2f}) | {r['full_novel_view_psnr_db']:.2f} / "
            f"{r['body_only_novel_view_psnr_db']:.2f}; {r['full_novel_view_psnr_garment_db']:.2f} / "
            f"{r['body_only_novel_view_psnr_garment_db']:.2f} | {r['full_train_s']:.0f} / {r['body_only_train_s']:.0f} |")
    held = [r for r in rows if not r["tuning"]]
    n = len(held)
    mp = [r["margin_novel_pose_psnr_db"] for r in held]
    mg = [r["margin_novel_pose_psnr_garment_db"] for r in held]
    mi = [100 * r["margin_novel_pose_iou"] for r in held]
    ms = [r["margin_novel_pose_ssim"] for r in held]
    rows = held
    lines += ["", f"## Summary over the {n} held-out scenes", "",
              f"- novel-pose PSNR margin full - body_only: median {median(mp):+.2f} dB, worst {min(mp):+.2f} dB; "
              f"full ahead on {sum(x > 0 for x in mp)} of {n} (paper +0.48 dB)",
              f"- novel-pose garment PSNR margin: median {median(mg):+.2f} dB, worst {min(mg):+.2f} dB; full ahead on "
              f"{sum(x > 0 for x in mg)} of {n}",
              f"- novel-pose IoU margin: median {median(mi):+.2f} points, worst {min(mi):+.2f}; full ahead on "
              f"{sum(x > 0 for x in mi)} of {n} (paper +1.3)",
              f"- novel-pose SSIM margin: median {median(ms):+.4f}, worst {min(ms):+.4f}; full ahead on "
              f"{sum(x > 0 for x in ms)} of {n}",
              f"- the fits that pose them: training sequence median {median(r['fit_train_ratio'] for r in rows):.2f}x "
              f"the rig floor (worst {max(r['fit_train_ratio'] for r in rows):.2f}x), held-out sequence median "
              f"{median(r['fit_novel_ratio'] for r in rows):.2f}x (worst {max(r['fit_novel_ratio'] for r in rows):.2f}x)"]
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", default="config/field_suite.yaml", help="the suite overlay (default: %(default)s)")
    ap.add_argument("--run-root", default=str(ROOT), help="the clone the pipeline ran in (default: this one)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder of field_suite.md and .csv")
    ap.add_argument("--note", default="", help="how the run was made (added to the header)")
    args = ap.parse_args()
    suite_path = Path(args.suite)
    if not suite_path.is_file():
        raise SystemExit(f"{suite_path}: no such suite overlay (benchmarks/fit_suite.py --novel-pose writes one)")
    run = Path(args.run_root).resolve()
    rows = collect(yaml.safe_load(suite_path.read_text()), run)
    lines = report(rows, args.suite, run, args.note)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "field_suite.md").write_text("\n".join(lines) + "\n")
    with files.atomic_path(out / "field_suite.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
