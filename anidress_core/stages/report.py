"""Stage `report`: results/report.html, one self-contained page (DESIGN.md §11, issue 8 §1).

Reads what the pipeline wrote (nothing is recomputed here):

* per scene: ``data/<scene>/scene.yaml``, ``results/<scene>/scene_check.json``,
  ``results/<scene>/sim/*.npz`` (stability statistics), ``results/<scene>/rig.npz``
  (RMSE per simulated sequence), per sequence ``fit_metrics.csv`` and
  ``garment_poses.npz`` (loss curves), ``normals.json`` (cue skips), per training
  sequence and variant ``metrics_summary.json`` / ``metrics.csv`` and the renders;
* ``benchmarks/runs/<scene>/**.tsv``: Snakemake's per-job run time and memory (the last
  run of each job);

and, only where the caller passes them (``references``; rule ``report`` names them as its
inputs when they exist), committed *reference* tables that this run did not make:
``benchmarks/tradeoffs.csv`` (``snakemake bench``: the run-time-vs-error sweeps, shown as
Pareto plots) and ``benchmarks/rig.csv`` (the rig benchmark's bone-count sweep). Each is
labelled on the page with its file and the commit and date git reports for it
(:func:`reference_label`), or says why those are unknown.

and renders ``reports/report.html.j2`` (Jinja2) into one HTML file: tables shaped like the
paper's (novel view / novel pose, full vs body_only), fitting error per frame and per
ablation, rig RMSE per bone count, run time and memory per stage, image grids
(ground truth | render | error heat map), the trade-off plots, and "skipped and why". A captured
scene has no ground truth: the page says so, its fit is not scored, and its image metrics and grids
use the images and masks evaluate_field compared with (``metrics_summary.json`` ``sources``: the
pipeline's masks, in the working cameras of a distorted sequence).
Charts are inline SVG (:mod:`anidress_core.plots`), images inline PNG. A small script in
the page records load errors and counts the images and tables that rendered, in
``<body data-*>`` attributes a headless-browser test reads.
"""
from __future__ import annotations

import base64
import csv
import datetime
import logging
import math
import os
import subprocess
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import yaml

from .. import __version__, plots
from ..io import files
from ..io.images import frame_file
from ..io.rig import read_rig
from ..io.scene_info import cue_formats, read_scene
from ..io.sim import read_sim
from ..resources import REFERENCE_TABLES

__all__ = ["REFERENCE_TABLES", "collect_report", "reference_label", "render_report", "run_report"]

log = logging.getLogger("anidress.report")

VARIANTS = ("full", "body_only")


# --------------------------------------------------------------------------- small readers


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _num(x) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return v


def _png_data_uri(img: np.ndarray) -> str:
    """(H, W, 3) float [0, 1] or uint8 -> data:image/png;base64,..."""
    import cv2

    a = np.asarray(img)
    if a.dtype != np.uint8:
        a = (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".png", a[..., ::-1] if a.ndim == 3 else a)
    if not ok:
        raise ValueError("PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _heat(err: np.ndarray, vmax: float) -> np.ndarray:
    """Per-pixel error (H, W) -> colour heat map (H, W, 3) uint8 (OpenCV's inferno)."""
    import cv2

    u8 = (np.clip(err / max(vmax, 1e-12), 0, 1) * 255).astype(np.uint8)
    return cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO)[..., ::-1]


def _stats(vals) -> dict:
    v = np.asarray([x for x in vals if math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "p95": float("nan"), "worst": float("nan"), "n": 0}
    return {"mean": float(v.mean()), "p95": float(np.percentile(v, 95)), "worst": float(v.max()), "n": int(v.size)}


# --------------------------------------------------------------------------- sections


def _sims(res: Path) -> list[dict]:
    out = []
    for p in sorted((res / "sim").glob("*.npz")):
        try:
            sq = read_sim(p)
        except files.ArtifactError as e:
            out.append({"motion": p.stem, "error": str(e)})
            continue
        meta = sq.meta
        out.append({"motion": p.stem, "frames": sq.num_frames,
                    "max_stretch": float(np.max(sq.max_stretch)) if sq.max_stretch is not None else float("nan"),
                    "max_penetration_mm": 1e3 * float(np.max(sq.max_penetration_m))
                    if sq.max_penetration_m is not None else float("nan"),
                    "nan": int(np.sum(sq.nan_count)) if sq.nan_count is not None else 0,
                    "recoveries": len(meta.get("recoveries", [])), "wall_s": float(meta.get("wall_s", float("nan")))})
    return out


def _rig(res: Path) -> dict | None:
    p = res / "rig.npz"
    if not p.is_file():
        return None
    rig = read_rig(p)
    meta = rig.meta
    return {"bones": rig.model.num_bones, "vertices": int(rig.model.weights.shape[0]),
            "rmse_mm": 1e3 * rig.model.rmse, "wall_s": float(meta.get("wall_s", float("nan"))),
            "frames_decomposed": meta.get("frames_decomposed"),
            "per_sequence": [{"name": n, "rmse_mm": 1e3 * r} for n, r in rig.rmse_per_sequence.items()],
            "history_mm": [1e3 * x for x in meta.get("history_m", [])]}


def _fit(res: Path, seq: str) -> dict | None:
    p = res / seq / "fit_metrics.csv"
    if not p.is_file():
        return None
    rows = _read_csv(p)
    methods: dict[str, list[dict]] = {}
    for r in rows:
        methods.setdefault(r["method"], []).append(r)
    table, series = [], []
    for m, rs in methods.items():
        rs.sort(key=lambda r: int(r["frame"]))
        rm = [_num(r["vertex_rmse_m"]) * 1e3 for r in rs]
        wall = [_num(r.get("wall_s")) for r in rs]
        tw = float(np.nansum(wall)) if wall else float("nan")
        table.append({"method": m, "rmse_mm": _stats(rm), "floor_mm": _stats([_num(r["rig_floor_rmse_m"]) * 1e3
                                                                              for r in rs]),
                      "chamfer_mm": _stats([_num(r["chamfer_m"]) * 1e3 for r in rs]),
                      "nc": _stats([_num(r["normal_consistency"]) for r in rs]),
                      "jitter_mm": _stats([_num(r["jitter_m"]) * 1e3 for r in rs]),
                      "gt_jitter_mm": _stats([_num(r["gt_jitter_m"]) * 1e3 for r in rs]),
                      "fps": len(rs) / tw if tw > 0 else float("nan")})
        series.append((m, [int(r["frame"]) for r in rs], rm))
    chart = plots.line_chart(series, f"{seq}: garment vertex RMSE per frame", "frame", "vertex RMSE (mm)")
    curves = None
    gp = res / seq / "garment_poses.npz"
    if gp.is_file():
        a, _ = files.load_npz(gp)
        if "curve" in a:
            c = np.asarray(a["curve"], dtype=np.float64)
            pick = sorted({0, c.shape[0] // 2, c.shape[0] - 1})
            curves = plots.line_chart([(f"frame {t}", list(range(c.shape[1])), list(c[t])) for t in pick],
                                      f"{seq}: fitting loss per accepted step", "step", "weighted loss", logy=True)
    return {"table": table, "chart": chart, "curves": curves}


def _field(res: Path, data: Path, seq: str, info: dict) -> dict:
    out = {"variants": {}, "grids": []}
    for v in VARIANTS:
        p = res / seq / v / "metrics_summary.json"
        if p.is_file():
            out["variants"][v] = files.read_json(p)
    # evaluate_field's pooled region PSNRs (older summaries have none: NaN, shown n/a) and the masks of the regions
    for summ in out["variants"].values():
        for m in summ.get("metrics", []):
            for k in ("psnr_subject_db", "psnr_garment_db", "psnr_body_db"):
                m.setdefault(k, float("nan"))
    out["region_masks"] = sorted({r for summ in out["variants"].values() for m in summ.get("metrics", [])
                                  for r in m.get("region_masks", [])})
    # the images and masks evaluate_field compared with, per sequence (metrics_summary.json "sources"; older
    # summaries: the scene's images and gt/masks)
    sources = next((summ["sources"] for summ in out["variants"].values() if summ.get("sources")), {})
    # ground truth: every summary scored against gt/masks (older summaries, without the key, always were)
    out["ground_truth"] = all(summ.get("ground_truth", True) for summ in out["variants"].values())
    # image grid: reference | full | body_only | |error| of full, for one novel-view and one novel-pose image
    for kind, rel in (("novel_view", "novel_view"), *[("novel_pose", f"novel_pose/{s['name']}")
                                                      for s in info.get("sequences", []) if s["role"] == "novel_pose"]):
        folder = res / seq / "full" / "renders" / rel
        rj = folder / "render.json"
        if not rj.is_file():
            continue
        r = files.read_json(rj)
        frames, cams = r.get("frames", []), r.get("cameras", [])
        if not frames or not cams:
            continue
        f = frames[len(frames) // 2]
        gseq = seq if kind == "novel_view" else rel.split("/", 1)[1]
        if sources.get(gseq):  # paths relative to the workflow's directory (the root above results/)
            src, base = sources[gseq], res.parent.parent
        else:  # an older summary: the scene's images and gt/masks
            src, base = {"images": data / gseq / "images", "masks": data / gseq / "gt" / "masks",
                         "mask_source": "gt/masks"}, Path()
        images, masks = base / src["images"], base / src["masks"] if src.get("masks") else None
        # the first camera with a mask (a captured scene's test cameras may have none), else the first
        cam = next((c for c in cams if masks is not None and (masks / c / f"{f:06d}.png").is_file()), cams[0])
        try:
            img = files.read_image(frame_file(images / cam, f))
            mpath = None if masks is None else masks / cam / f"{f:06d}.png"
            mask = None
            if mpath is not None and (src["mask_source"] == "gt/masks" or mpath.is_file()):
                mask = files.read_mask(mpath) > 0
            if mask is not None and (src["mask_source"] == "gt/masks" or mask.any()):
                bg = np.asarray(r.get("background", [0.0, 0.0, 0.0]), dtype=np.float32)
                gt = np.where(mask[..., None], img, bg)
                label = "ground truth" if src["mask_source"] == "gt/masks" else "captured image, pipeline's mask"
            else:  # not scored (evaluate_field): the captured background is not the render's, no error map
                gt, label = None, f"captured image ({'no' if mask is None else 'empty'} mask: not scored)"
            tiles = [(label, img if gt is None else gt)]
            err = None
            for v in VARIANTS:
                pp = res / seq / v / "renders" / rel / "rgb" / cam / f"{f:06d}.png"
                if pp.is_file():
                    pred = files.read_image(pp)
                    tiles.append((v, pred))
                    if v == "full" and gt is not None:
                        err = np.abs(pred - gt).mean(-1)
            if err is not None:
                tiles.append(("|error| full (0..0.25)", _heat(err, 0.25)))
        except (FileNotFoundError, files.ArtifactError) as e:
            log.warning("report: image grid %s %s skipped: %s", seq, kind, e)
            continue
        out["grids"].append({"kind": kind, "sequence": gseq, "camera": cam, "frame": f,
                             "tiles": [{"label": lab, "src": _png_data_uri(t)} for lab, t in tiles]})
    return out


def _runtimes(root: Path, scene: str) -> list[dict]:
    """Snakemake benchmark TSVs of one scene: stage (rule dir), job, seconds, max RSS MB."""
    base = root / "benchmarks" / "runs" / scene
    out = []
    for p in sorted(base.rglob("*.tsv")) if base.is_dir() else []:
        rows = list(csv.DictReader(open(p), delimiter="\t"))
        if not rows:
            continue
        rel = p.relative_to(base).with_suffix("")
        job = str(rel)
        stage = rel.parts[-1] if len(rel.parts) == 1 else (rel.parts[0] if rel.parts[0] in
                                                            ("simulate", "motions", "masks", "flows") else rel.parts[-1])
        out.append({"stage": stage, "job": job, "s": _num(rows[-1].get("s")), "max_rss_mb": _num(rows[-1].get("max_rss")),
                    "cpu_time_s": _num(rows[-1].get("cpu_time"))})
    return out


def _git(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=30)


def reference_label(path: str | os.PathLike, shown: str | None = None) -> str:
    """Label of a committed reference table: file, commit and date, read from git.

    ``"reference figures committed in benchmarks/rig.csv (commit 1a2b3c4, 2026-12-02)"`` when
    the file is committed unchanged; otherwise the label says what is known instead: the file
    changed since its last commit, never committed, not in a git checkout, or git missing.
    ``shown``: the name printed (default: ``path`` as given).
    """
    p = Path(path).resolve()
    shown = shown or str(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: reference table not found")
    try:
        inside = _git(["rev-parse", "--is-inside-work-tree"], p.parent)
        if inside.returncode != 0:
            err = (inside.stderr.strip().splitlines() or ["no message"])[0]
            if "not a git repository" in err:
                return f"reference figures in {shown} (not in a git checkout: commit and date unknown)"
            return f"reference figures in {shown} (git failed: {err}; commit and date unknown)"
        log_ = _git(["log", "-1", "--format=%h %cs", "--", p.name], p.parent)
        status = _git(["status", "--porcelain", "--", p.name], p.parent)
    except FileNotFoundError:
        return f"reference figures in {shown} (git not installed: commit and date unknown)"
    except subprocess.TimeoutExpired:
        return f"reference figures in {shown} (git timed out: commit and date unknown)"
    if log_.returncode != 0 or not log_.stdout.strip():  # no commit at all, or none with this file
        return f"reference figures in {shown} (not committed: commit and date unknown)"
    sha, date = log_.stdout.split()[:2]
    if status.returncode != 0:
        return (f"reference figures in {shown} (last commit {sha}, {date}; git status failed, so whether "
                f"the file changed since is unknown)")
    if status.stdout.strip():
        return (f"reference figures in {shown} (changed since its last commit {sha}, {date}: "
                f"not the committed figures)")
    return f"reference figures committed in {shown} (commit {sha}, {date})"


def _reference(path: Path, root: Path) -> tuple[Path, str]:
    """Resolved path of a reference table and its label (the name shown relative to ``root``)."""
    p = path if path.is_absolute() else root / path
    try:
        shown = str(p.resolve().relative_to(root.resolve()))
    except ValueError:
        shown = str(p)
    return p, reference_label(p, shown)


def _tradeoffs(path: Path | None, root: Path) -> dict:
    """The sweeps table (benchmarks/tradeoffs.csv) -> one Pareto chart per (stage, error metric)."""
    if path is None:
        return {"available": False, "path": REFERENCE_TABLES["tradeoffs"]}
    p, label = _reference(path, root)
    rows = _read_csv(p)
    charts, verdicts = [], []
    keys = list(dict.fromkeys((r["stage"], r["error_metric"]) for r in rows))
    for stage, metric in keys:
        rs = [r for r in rows if r["stage"] == stage and r["error_metric"] == metric]
        pts = [{"x": _num(r["cpu_s"]), "y": _num(r["error"]), "label": f"{r['knob']}={r['value']}",
                "group": r["knob"], "highlight": r.get("is_default") in ("1", "True", "true")} for r in rs]
        charts.append(plots.scatter_chart(pts, f"{stage}: {metric} vs run time", "CPU time (s, log; the shared machine's wall times are noisy)",
                                          metric))
        good = [q for q in pts if math.isfinite(q["x"]) and math.isfinite(q["y"])]
        front = {good[i]["label"] for i in plots.pareto_front([(q["x"], q["y"]) for q in good])}
        for q in good:
            if q["highlight"]:
                verdicts.append({"stage": stage, "metric": metric, "default": q["label"],
                                 "on_front": q["label"] in front,
                                 "dominated_by": [o["label"] for o in good if o["x"] <= q["x"] and o["y"] <= q["y"]
                                                  and (o["x"] < q["x"] or o["y"] < q["y"])]})
    return {"available": True, "charts": charts, "verdicts": verdicts, "rows": len(rows), "label": label}


def _rig_sweep(path: Path | None, root: Path) -> dict | None:
    """The rig benchmark's bone-count sweep (benchmarks/rig.csv) -> a chart and its label."""
    if path is None:
        return None
    p, label = _reference(path, root)
    rows = [r for r in _read_csv(p) if "sweep" in r.get("method", "")]
    if not rows:
        return None
    rows.sort(key=lambda r: int(r["bones_asked"]))
    chart = plots.line_chart([("RMSE", [int(r["bones_asked"]) for r in rows],
                               [_num(r["rmse_m"]) * 1e3 for r in rows])],
                             f"rig RMSE per bone count ({rows[0]['vertices']} vertices x {rows[0]['frames']} frames)",
                             "bones B", "RMSE (mm)")
    return {"chart": chart, "label": label}


# --------------------------------------------------------------------------- collect / render


def collect_report(config: dict, root: str | os.PathLike = ".",
                   references: Mapping[str, str | os.PathLike] | None = None) -> dict:
    """Everything the page shows, from the files under ``root`` (data/, results/, benchmarks/runs/).

    ``references``: committed reference tables to show as well, by key of
    :data:`REFERENCE_TABLES` (``{"tradeoffs": "benchmarks/tradeoffs.csv"}``; relative paths
    are under ``root``). None or a missing key: that table is not shown.
    """
    root = Path(root)
    references = dict(references or {})
    unknown = set(references) - set(REFERENCE_TABLES)
    if unknown:
        raise ValueError(f"report references: unknown keys {sorted(unknown)}; known: {sorted(REFERENCE_TABLES)}")
    refs = {k: Path(v) for k, v in references.items() if v}
    scenes, skipped = [], []
    for name in config["run_scenes"]:
        scfg = config["scenes"][name]
        data, res = root / "data" / name, root / "results" / name
        info = {}
        if (data / "scene.yaml").is_file():
            info = yaml.safe_load((data / "scene.yaml").read_text()) or {}
        garment = scfg.get("kind", "tight") != "tight"
        if not garment:
            skipped.append({"scene": name, "stage": "template, simulate, rig, fit", "reason":
                            "tight-clothed scene (no garment template): the field uses body poses only "
                            "(DESIGN.md §6)"})
        check = files.read_json(res / "scene_check.json") if (res / "scene_check.json").is_file() else None
        synthetic = bool(scfg.get("synthetic", True))
        ground_truth = synthetic  # a captured scene: no ground truth (fit not scored; images under its own masks)
        seqs = []
        for s in scfg.get("sequences", []):
            seq = s["name"]
            ent = {"name": seq, "role": s["role"], "frames": s.get("frames"), "fit": None, "field": None}
            nj = res / seq / "normals.json"
            if nj.is_file():
                n = files.read_json(nj)
                if n.get("skipped"):
                    skipped.append({"scene": name, "stage": f"normals ({seq})",
                                    "reason": f"{n.get('reason', 'no normals')}: normal loss weight 0"})
                elif n.get("shipped") or n.get("source"):
                    axes = (f"; axes {n['convention_axes']}, mean cosine {n['agreement']:.2f} with the posed body"
                            if n.get("convention_axes") else "")
                    skipped.append({"scene": name, "stage": f"normal estimation ({seq})",
                                    "reason": f"normals shipped with the data ({n.get('source', '')}{axes})"})
            if (data / seq / "masks").is_dir():
                fmt = cue_formats(read_scene(data), data)["masks"] if (data / "scene.yaml").is_file() else {}
                skipped.append({"scene": name, "stage": f"mask estimation ({seq})",
                                "reason": "masks shipped with the data used as they are" if fmt.get("format") != "schp"
                                else f"a human parser's masks shipped with the data, converted to labels (SCHP "
                                     f"{fmt['label_set']})"})
            if garment:
                ent["fit"] = _fit(res, seq)
                if ent["fit"] is None and not synthetic:
                    skipped.append({"scene": name, "stage": f"fit metrics ({seq})", "reason":
                                    "no ground truth (captured scene: no true garment meshes): the fit is not scored"})
            if s["role"] == "train":
                ent["field"] = _field(res, data, seq, info or scfg)
                for v, summ in ent["field"]["variants"].items():
                    if not summ.get("ground_truth", True):
                        n = sum(m.get("images", 0) for m in summ.get("metrics", []))
                        k = sum(m.get("scored", m.get("images", 0)) for m in summ.get("metrics", []))
                        skipped.append({"scene": name, "stage": f"image metrics against ground truth ({seq}, {v})",
                                        "reason": f"no ground truth: {k} of {n} images scored against the captured "
                                                  "images under the pipeline's masks (IoU: agreement with those "
                                                  "masks); images without a mask or with an empty one not scored (n/a)"})
                    for metric in ("lpips", "dists"):
                        note = summ.get(metric, "")
                        if note and note != "available":
                            skipped.append({"scene": name, "stage": f"{metric.upper()} ({seq}, {v})",
                                            "reason": f"unavailable: {note}"})
            seqs.append(ent)
        rt = _runtimes(root, name)
        by_stage: dict[str, list[dict]] = {}
        for r in rt:
            by_stage.setdefault(r["stage"], []).append(r)
        stage_rows = [{"stage": k, "jobs": len(v), "total_s": float(np.nansum([r["s"] for r in v])),
                       "max_s": float(np.nanmax([r["s"] for r in v])),
                       "max_rss_mb": float(np.nanmax([r["max_rss_mb"] for r in v]))} for k, v in by_stage.items()]
        stage_rows.sort(key=lambda r: -r["total_s"])
        scenes.append({
            "name": name, "kind": scfg.get("kind"), "garment": garment, "info": info, "check": check,
            "synthetic": synthetic,
            "ground_truth": ground_truth and all((q["field"] or {}).get("ground_truth", True) for q in seqs),
            "sims": _sims(res) if garment else [], "rig": _rig(res) if garment else None, "sequences": seqs,
            "runtimes": stage_rows,
            "runtime_chart": plots.bar_chart([(r["stage"], r["total_s"]) for r in stage_rows],
                                             f"{name}: wall time per stage (all its jobs)", "seconds"),
        })
    return {
        "title": "AniDress pipeline report", "created": datetime.datetime.now().isoformat(timespec="seconds"),
        "code_version": __version__, "config_hash": files.config_hash(config), "scenes": scenes,
        "skipped": skipped, "tradeoffs": _tradeoffs(refs.get("tradeoffs"), root),
        "rig_sweep": _rig_sweep(refs.get("rig_sweep"), root),
    }


def _fmt(x, digits=3, inf=None):
    """A number for the page: None "–", NaN "n/a"; +inf ``inf`` when given (a PSNR of identical pixels), else "n/a"."""
    if x is None:
        return "–"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if v == math.inf and inf is not None:
        return inf
    if not math.isfinite(v):
        return "n/a"
    return f"{v:.{digits}f}"


def render_report(data: dict, template_dir: str | os.PathLike, out_html: str | os.PathLike) -> None:
    """Render ``report.html.j2`` from ``template_dir`` with ``data`` into ``out_html`` (atomic)."""
    import jinja2

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(template_dir)), autoescape=True,
                             undefined=jinja2.StrictUndefined)
    env.filters["f"] = _fmt
    html = env.get_template("report.html.j2").render(**data)
    files.write_text(out_html, html)


def run_report(config: dict, out_html: str | os.PathLike, root: str | os.PathLike = ".",
               template_dir: str | os.PathLike | None = None,
               references: Mapping[str, str | os.PathLike] | None = None) -> dict:
    """Collect and render the report; returns the collected data. ``references``: see
    :func:`collect_report`."""
    if template_dir:
        tdir = Path(template_dir)
    else:  # the checkout's reports/, or the installed package's copy (anidress_core.resources)
        from ..resources import report_template_dir

        tdir = report_template_dir()
    if not (tdir / "report.html.j2").is_file():
        raise FileNotFoundError(f"{tdir / 'report.html.j2'}: report template not found")
    data = collect_report(config, root, references)
    render_report(data, tdir, out_html)
    log.info("report: %s (%d scenes, %d skips)", out_html, len(data["scenes"]), len(data["skipped"]))
    return data
