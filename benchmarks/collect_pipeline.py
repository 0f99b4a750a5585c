"""What one pipeline run cost and measured, per scene, from its own files (no recomputation).

Run after `make demo` (or `snakemake --workflow-profile profiles/default`):
    .venv/bin/python -m benchmarks.collect_pipeline [--scene skirt [--scene tight]] [--wall-s SECONDS]
Writes benchmarks/pipeline.md and benchmarks/pipeline.csv. Not a test.

Sources: Snakemake's `benchmark:` files (benchmarks/runs/<scene>/**.tsv: wall and CPU
seconds, peak memory of every job), the fit evaluation (results/<scene>/<seq>/fit_metrics.csv)
and the field evaluation (results/<scene>/<seq>/<variant>/metrics_summary.json). The times
are those of the last run of each job; jobs run two at a time on the 2 cores, so the sum of
job wall times exceeds the run's wall time (given with --wall-s when measured outside).
"""
from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import yaml

from anidress_core.io import files
from benchmarks.benchutil import cpu_model

ROOT = Path(__file__).resolve().parents[1]


FIELD_METRICS = ("psnr_db", "psnr_subject_db", "psnr_garment_db", "psnr_body_db", "ssim", "ssim_subject", "iou")


def _db(v) -> str:
    """A PSNR of metrics_summary.json as the table shows it: n/a when absent or NaN (no pixels of the region)."""
    return "n/a" if v is None or v != v else f"{float(v):.2f}"


def _tsv(path: Path) -> dict:
    with open(path) as fh:
        rows = list(csv.DictReader(fh, delimiter="\t"))
    r = rows[-1]
    return {"wall_s": float(r["s"]), "cpu_s": float(r["cpu_time"]), "max_rss_mb": float(r["max_rss"])}


def rule_of(rel: Path) -> tuple[str, str]:
    """(rule, instance) of a benchmark file path relative to benchmarks/runs/<scene>."""
    parts = rel.with_suffix("").parts
    name = parts[-1]
    if parts[0] in ("simulate", "simulate_ensemble"):
        return parts[0], name
    if name in ("synth", "template", "rig", "validate_scene"):
        return name, ""
    if len(parts) >= 3 and parts[1] in ("full", "body_only"):
        rule = {"train": "train_field", "evaluate": "evaluate_field"}.get(name, name)
        if name.startswith("render_library"):
            rule = "render_library"
        if name.startswith("render_novel_pose"):
            rule = "render_novel_pose"
        return rule, "/".join(parts[:-1]) + ("/" + name if rule != name else "")
    if parts[0] == "motions":
        return "motions", name
    return name, "/".join(parts[:-1])


def _scene_sections(scene: str) -> tuple[list[str], list[dict], int, float, float]:
    """Markdown lines, CSV rows, job count, summed wall and CPU seconds of one scene's jobs."""
    runs = ROOT / "benchmarks" / "runs" / scene
    jobs = []
    for p in sorted(runs.rglob("*.tsv")):
        rule, inst = rule_of(p.relative_to(runs))
        jobs.append({"rule": rule, "instance": inst, **_tsv(p)})
    per_rule: dict[str, dict] = {}
    for j in jobs:
        d = per_rule.setdefault(j["rule"], {"jobs": 0, "wall_s": 0.0, "cpu_s": 0.0, "max_rss_mb": 0.0})
        d["jobs"] += 1
        d["wall_s"] += j["wall_s"]
        d["cpu_s"] += j["cpu_s"]
        d["max_rss_mb"] = max(d["max_rss_mb"], j["max_rss_mb"])
    tot_wall = sum(d["wall_s"] for d in per_rule.values())
    tot_cpu = sum(d["cpu_s"] for d in per_rule.values())
    lines = ["", f"## `{scene}`: time and memory per rule (jobs summed)", "",
             "| rule | jobs | wall s | CPU s | share of CPU | peak RSS (MB) |", "| --- | ---: | ---: | ---: | ---: | ---: |"]
    csv_rows = []
    for rule, d in sorted(per_rule.items(), key=lambda kv: -kv[1]["cpu_s"]):
        lines.append(f"| {rule} | {d['jobs']} | {d['wall_s']:.1f} | {d['cpu_s']:.1f} | "
                     f"{100 * d['cpu_s'] / max(tot_cpu, 1e-9):.1f} % | {d['max_rss_mb']:.0f} |")
        csv_rows.append({"section": "stage", "scene": scene, "rule": rule, "method": "", "sequence": "",
                         "kind": "", "jobs": d["jobs"], "wall_s": round(d["wall_s"], 3), "cpu_s": round(d["cpu_s"], 3),
                         "max_rss_mb": round(d["max_rss_mb"], 1), "value": "", "metric": "", "reference": ""})
    lines.append(f"| **all** | {len(jobs)} | {tot_wall:.1f} | {tot_cpu:.1f} | 100 % | |")

    scene_yaml = ROOT / "data" / scene / "scene.yaml"
    info = yaml.safe_load(scene_yaml.read_text()) if scene_yaml.is_file() else {"sequences": []}
    seqs = [s["name"] for s in info.get("sequences", [])]
    fit_lines = []
    for seq in seqs:
        p = ROOT / "results" / scene / seq / "fit_metrics.csv"
        if not p.is_file():
            continue
        with open(p) as fh:
            rows = list(csv.DictReader(fh))
        loss, main = "?", None  # main: the loss variant of rule fit, its rows' method in fit_metrics.csv
        poses = ROOT / "results" / scene / seq / "garment_poses.npz"
        if poses.is_file():  # the loss the pipeline's fit minimised (its header)
            meta = files.load_npz(poses)[1].get("meta", {})
            main = meta.get("loss")
            c = meta.get("config", {})
            an = "L_anchor"
            if meta.get("anchor_reference"):
                an += " (texture references)" if "texture" in meta["anchor_reference"] else " (image references)"
            loss = f"{meta.get('loss', '?')}: " + " + ".join(  # the weights as used (garment_poses.npz meta)
                f"{w:g} {an if name == 'anchor' else 'L_' + name}" for name, w in meta.get("weights", {}).items() if w)
            if c.get("smooth_passes", 0):
                loss += f", {c['smooth_passes']} filter pass"
        for method in dict.fromkeys(r["method"] for r in rows):
            rs = [r for r in rows if r["method"] == method]
            col = lambda k: np.array([float(r[k]) for r in rs])  # noqa: E731
            vr, fl = col("vertex_rmse_m") * 1e3, col("rig_floor_rmse_m") * 1e3
            wall = col("wall_s")
            fps = len(rs) / float(np.nansum(wall)) if np.nansum(wall) > 0 else float("nan")
            fit_lines.append(f"| {seq} | {method} | {loss if method == main else ''} | {len(rs)} | {vr.mean():.2f} | {np.percentile(vr, 95):.2f} | "
                             f"{vr.max():.2f} | {fl.mean():.2f} | {vr.mean() / fl.mean():.2f} | "
                             f"{1e3 * np.nanmean(col('chamfer_m')):.2f} | {np.nanmean(col('normal_consistency')):.3f} | "
                             f"{fps:.2f} |")
            csv_rows.append({"section": "fit", "scene": scene, "rule": "fit", "method": method, "sequence": seq,
                             "kind": "", "jobs": "", "wall_s": round(float(np.nansum(wall)), 3), "cpu_s": "",
                             "max_rss_mb": "", "value": round(float(vr.mean()), 4), "metric": "vertex_rmse_mm",
                             "reference": f"rig floor {fl.mean():.4f} mm"})
    if fit_lines:
        lines += ["", f"## `{scene}`: garment fit against the ground truth (the pipeline's own cues)", "",
                  "| sequence | method | loss | frames | vertex RMSE mean (mm) | p95 | worst | rig floor (mm) | ratio to floor | "
                  "Chamfer (mm) | normal consistency | fit fps |", "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | "
                  "---: | ---: | ---: |"] + fit_lines

    field_lines, masks_used = [], set()
    for seq in seqs:
        for variant in ("full", "body_only"):
            p = ROOT / "results" / scene / seq / variant / "metrics_summary.json"
            if not p.is_file():
                continue
            summ = json.loads(p.read_text())
            tr = runs / seq / variant / "train.tsv"
            t = _tsv(tr) if tr.is_file() else {"wall_s": float("nan"), "cpu_s": float("nan")}
            for m in summ["metrics"]:
                region = " / ".join(_db(m.get(f"psnr_{r}_db")) for r in ("subject", "garment", "body"))
                field_lines.append(f"| {seq} | {variant} | {m['kind']} ({m['sequence']}) | {m['images']} | "
                                   f"{m['psnr_db']:.2f} | {region} | {m['ssim']:.4f} | {m['iou']:.4f} | "
                                   f"{t['wall_s']:.0f} | {t['cpu_s']:.0f} |")
                masks_used.update(m.get("region_masks", []))
                for k in FIELD_METRICS:
                    if m.get(k) is None:
                        continue
                    csv_rows.append({"section": "field", "scene": scene, "rule": "evaluate_field", "method": variant,
                                     "sequence": m["sequence"], "kind": m["kind"], "jobs": "", "wall_s": "",
                                     "cpu_s": "", "max_rss_mb": "", "value": round(float(m[k]), 5), "metric": k,
                                     "reference": "body_only" if variant == "full" else ""})
    if field_lines:
        lines += ["", f"## `{scene}`: radiance field (pipeline masks; the fitted garment poses where there is a garment)", "",
                  "PSNR box: inside the subject's projected 3D box (the paper's convention); subject / garment / body: "
                  "pooled over the pixels of the ground truth's regions (masks: "
                  f"{', '.join(sorted(masks_used)) or 'n/a'}); n/a where the scene has no such pixels.", "",
                  "| trained on | variant | kind | images | PSNR box (dB) | PSNR subject / garment / body (dB) | SSIM | "
                  "IoU | train wall s | train CPU s |",
                  "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"] + field_lines
    return lines, csv_rows, len(jobs), tot_wall, tot_cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", action="append", help="a scene of the run (repeat for several; default: skirt)")
    ap.add_argument("--wall-s", type=float, default=None, help="measured wall time of the whole run")
    ap.add_argument("--note", default="", help="how the run was made (added to the header)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder of pipeline.md and pipeline.csv")
    args = ap.parse_args()
    scenes = args.scene or ["skirt"]
    sections = [_scene_sections(s) for s in scenes]
    n_jobs = sum(x[2] for x in sections)
    tot_wall, tot_cpu = sum(x[3] for x in sections), sum(x[4] for x in sections)
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    names = ", ".join(f"`{s}`" for s in scenes)
    lines = [f"# One pipeline run of {names}: cost per stage and what it measured", "",
             f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}; git {rev.strip()}",
             f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs; "
             f"load average now {' / '.join(f'{x:.2f}' for x in os.getloadavg())}",
             "- command: `.venv/bin/python -m benchmarks.collect_pipeline " + " ".join(f"--scene {s}" for s in scenes)
             + (f" --wall-s {args.wall_s:.0f}" if args.wall_s else "") + "` after the run",
             "- sources: Snakemake `benchmark:` files of the last run of each job (benchmarks/runs/<scene>/), "
             "results/<scene>/*/fit_metrics.csv, results/<scene>/*/*/metrics_summary.json"]
    if args.note:
        lines.append(f"- run: {args.note}")
    if args.wall_s:
        lines.append(f"- whole run wall time: {args.wall_s:.0f} s ({args.wall_s / 60:.1f} min); {n_jobs} jobs with "
                     f"benchmark files, summed: {tot_wall:.0f} s wall, {tot_cpu:.0f} CPU s")
    csv_rows = []
    for sec_lines, rows, *_ in sections:
        lines += sec_lines
        csv_rows += rows
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "pipeline.md").write_text("\n".join(lines) + "\n")
    fields = ["section", "scene", "rule", "method", "sequence", "kind", "jobs", "wall_s", "cpu_s", "max_rss_mb",
              "value", "metric", "reference"]
    with files.atomic_path(out / "pipeline.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields)
            w.writeheader()
            w.writerows(csv_rows)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
