"""Benchmark of the 2D cues (anidress_core.cues) against the synthetic ground truth.

Run: .venv/bin/python -m benchmarks.bench_cues [--scenes skirt,dress] [--seqs all] [--frames 60]
     [--flow-methods all] [--mask-methods all] [--max-ms-per-pair 500]
Writes benchmarks/cues.md and benchmarks/cues.csv. Not a test.

For each scene and sequence, on the scene's training cameras (the cues the fitting
uses), with one thread (so per-pair times are comparable):

* masks: every method of ``cues/masks/method`` (anidress_core.cues.masks), IoU of the
  subject, body and garment labels against ``gt/masks``; reference rows: the shape
  prior alone (posed body + skinned template, no image) and the ground truth;
* flows: every OpenCV method on the estimated masks' region (the pipeline's setting),
  end-point error on all ground-truth-valid pixels, on the subject and on the garment
  (frame t-1 labels), fraction above 3 px, time per camera pair and per frame (all
  training cameras); reference rows: the ground-truth flow (what EPE is measured
  against, 0 by definition) and the zero flow (the size of the motion); the default
  method's full-frame run shows what the region restriction saves. The default is
  the method with the lowest garment EPE x seconds per pair ("best error per second").
  Every estimator runs without the Lucas-Kanade refinement (``cues/flows/refine``); when the
  config turns it on, one more row is the configured method with it (the pipeline's flows),
  timed as the estimator's interleaved time + the refinement's own;
* normals: the shipped degraded normals against ``gt/normals`` (angular error on the
  garment and on all subject pixels; the ground truth as reference).

The scene's template is results/<scene>/template.npz when present, else one is made
from data/<scene>/garment/template.obj with the default config into a temporary folder.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from anidress_core.config import load_config
from anidress_core.cues import FLOW_METHODS, MASK_METHODS, CueErrors
from anidress_core.io import files
from anidress_core.stages import cues as sc
from anidress_core.io.scene import image_path, read_scene, scene_cameras
from benchmarks.benchutil import cpu_model, git_rev

# the code whose uncommitted changes the git revision of a run's table flags
CODE_PATHS = ("anidress_core/cues", "anidress_core/stages/cues.py")

ROOT = Path(__file__).resolve().parents[1]

COLUMNS = ["scene", "sequence", "cue", "method", "reference", "cameras", "frames", "wall_s", "per_frame_s",
           "per_pair_ms", "prior_ms_per_pair", "region_frac", "iou_subject", "iou_body", "iou_garment", "epe_all_px", "epe_subject_px",
           "epe_garment_px", "epe_garment_gt3px_frac", "epe_garment_x_s_per_pair", "normal_subject_mean_deg",
           "normal_subject_median_deg", "normal_garment_mean_deg", "normal_garment_median_deg",
           "normal_garment_within20_frac", "default", "notes"]


def machine() -> str:
    cpu = cpu_model()
    import cv2
    import torch

    return (f"{cpu}, {os.cpu_count()} logical CPUs; Python {platform.python_version()}, OpenCV {cv2.__version__}, "
            f"torch {torch.__version__}, numpy {np.__version__}")


def load() -> str:
    return " / ".join(f"{x:.2f}" for x in os.getloadavg())


def template_for(scene: str, data_root: Path, tmp: Path) -> tuple[Path, str]:
    p = ROOT / "results" / scene / "template.npz"
    if p.is_file():
        return p, str(p.relative_to(ROOT))
    from anidress_core.io.scene import load_body
    from anidress_core.stages.template import run_template

    data = data_root / scene
    info = read_scene(data)
    cfg = load_config(ROOT / "config" / "config.yaml")
    out = tmp / f"{scene}_template.npz"
    run_template(data / info["garment_template"], info["garment_kind"], load_body(data, info),
                 cfg["template"]["vertices"], tmp / f"{scene}_template.ply", out)
    return out, f"made from data/{scene}/{info['garment_template']} (template/vertices {cfg['template']['vertices']})"


def prior_iou(scene_dir: Path, seq: str, tpl: Path, frames: list[int]) -> dict:
    """IoU of the shape prior alone (no image) against the ground truth."""
    info = read_scene(scene_dir)
    names = sc.select_cameras(info, "train", scene_dir)
    cams = scene_cameras(scene_dir, seq, names, info, dtype=torch.float32)
    prior = sc.ShapePrior(scene_dir, seq, info, tpl, cams, frames)
    acc = CueErrors()
    for f in frames:
        gt = np.stack([files.read_mask(scene_dir / seq / "gt" / "masks" / c / f"{f:06d}.png") for c in names])
        acc.add_masks(prior.labels(f), gt)
    return acc.summary()


def interleaved_timing(scene_dir: Path, seq: str, names: list[str], frames: list[int], masks_dir: Path,
                       methods: list[str], margin: int, prior=None, downsample: int = 1, pairs: int = 24,
                       repeats: int = 3, full_frame: bool = False) -> dict[str, float]:
    """Median seconds per pair of each method, the methods interleaved pair by pair (and their
    order rotated) so that load changes on a shared machine hit every method alike. With
    ``prior`` (stages.cues.ShapePrior) the methods get its flow as initialisation, as in the stage."""
    from anidress_core.cues import flow as cf

    rng = np.random.default_rng(0)
    picks = [(int(rng.integers(len(names))), int(rng.integers(1, len(frames)))) for _ in range(pairs)]
    times: dict[str, list[float]] = {m: [] for m in methods}
    for k, (c, i) in enumerate(picks):
        cam, f0, f1 = names[c], frames[i - 1], frames[i]
        g0 = cf.to_gray8(files.read_image(image_path(scene_dir / seq, cam, f0)))
        g1 = cf.to_gray8(files.read_image(image_path(scene_dir / seq, cam, f1)))
        region = cf.flow_region(files.read_mask(masks_dir / cam / f"{f0:06d}.png"),
                                files.read_mask(masks_dir / cam / f"{f1:06d}.png"), margin)
        if region is None:
            continue
        init = prior.flow(f0, f1, downsample)[c] if prior is not None else None
        order = methods[k % len(methods):] + methods[: k % len(methods)]
        for _ in range(repeats):
            for m in order:
                times[m].append(cf.estimate_flow(g0, g1, m, region, init=init).compute_s)
                if full_frame:
                    times.setdefault(m + " full frame", []).append(
                        cf.estimate_flow(g0, g1, m, None, init=init).compute_s)
    return {m: float(np.median(t)) for m, t in times.items()}


def prior_flow_only(src: Path, seq: str, prior, names: list[str], frames: list[int], downsample: int,
                    out: Path) -> float:
    """Write the prior's flow alone (no image) as a flows folder; returns seconds per frame."""
    t0 = time.perf_counter()
    for i in range(1, len(frames)):
        fl = prior.flow(frames[i - 1], frames[i], downsample)
        for c, cam in enumerate(names):
            files.write_exr(out / cam / f"{frames[i]:06d}.exr",
                            np.concatenate([fl[c], np.ones(fl.shape[1:3] + (1,), np.float32)], -1),
                            ("X", "Y", "valid"))
    return (time.perf_counter() - t0) / max(1, len(frames) - 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="skirt")
    ap.add_argument("--seqs", default="", help="sequences: names, 'all', or (default) the first of each scene")
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (default: all)")
    ap.add_argument("--mask-methods", default="all")
    ap.add_argument("--flow-methods", default="all")
    ap.add_argument("--max-ms-per-pair", type=float, default=500.0,
                    help="flow methods slower than this on the first sequence are not rerun on the others")
    ap.add_argument("--data", default=str(ROOT / "data"), help="folder of the scenes (default: data/)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"))
    ap.add_argument("--render-only", action="store_true",
                    help="no measurement: rewrite cues.md from the cues.csv and cues.md of an earlier run in --out "
                         "against the current config (after setting the defaults it found); figures unchanged")
    args = ap.parse_args()
    if args.render_only:
        return render_only(args)
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    mask_methods = list(MASK_METHODS) if args.mask_methods == "all" else args.mask_methods.split(",")
    flow_methods = list(FLOW_METHODS) if args.flow_methods == "all" else args.flow_methods.split(",")
    cfg = load_config(ROOT / "config" / "config.yaml")["cues"]
    load_before = load()
    started = datetime.datetime.now().isoformat(timespec="seconds")
    rows: list[dict] = []
    notes_md: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench_cues_") as tmpdir:
        tmp = Path(tmpdir)
        for scene in args.scenes.split(","):
            scene_dir = Path(args.data) / scene
            info = read_scene(scene_dir)
            if args.seqs == "all":
                seqs = [q["name"] for q in info["sequences"]]
            else:
                seqs = args.seqs.split(",") if args.seqs else [info["sequences"][0]["name"]]
            tpl, tpl_note = template_for(scene, Path(args.data), tmp)
            notes_md.append(f"- `{scene}`: shape prior template {tpl_note}.")
            for seq in seqs:
                names = sc.select_cameras(info, "train", scene_dir)
                frames = sc.sequence_frames(scene_dir / seq, names)
                if args.frames:
                    frames = frames[: args.frames]
                # evaluate on a copy of the sequence restricted to the frames (symlinks, no copy of data)
                src = scene_dir
                if args.frames:
                    src = tmp / "scenes" / scene
                    _subset(scene_dir, src, seq, frames)
                base = {"scene": scene, "sequence": seq, "cameras": len(names), "frames": len(frames)}
                print(f"[{scene}/{seq}] {len(names)} cameras x {len(frames)} frames", flush=True)

                # ---- masks
                pr = prior_iou(src, seq, tpl, frames)
                rows.append({**base, "cue": "masks", "method": "shape prior alone", "reference": "ground truth",
                             **_pick(pr, "iou_"), "notes": "posed body + skinned template rasterised, no image"})
                default_masks = None
                for method in mask_methods:
                    mcfg = {**cfg["masks"], "method": method}
                    out = tmp / scene / seq / f"masks_{method}"
                    st = sc.run_masks(src, seq, out, mcfg, tpl, progress=False, threads=1)
                    ev = sc.evaluate_cues(src, seq, masks_dir=out)
                    is_default = method == cfg["masks"]["method"]
                    if is_default:
                        default_masks = out
                    rows.append({**base, "cue": "masks", "method": method, "reference": "ground truth",
                                 "wall_s": st["wall_s"], "per_frame_s": st["per_frame_s"], **_pick(ev, "iou_"),
                                 "default": "yes (config)" if is_default else ""})
                    print(f"  masks {method}: {_fmt_row(rows[-1])}", flush=True)
                rows.append({**base, "cue": "masks", "method": "ground truth", "reference": "ground truth",
                             "iou_subject": 1.0, "iou_body": 1.0, "iou_garment": 1.0, "notes": "by definition"})
                if default_masks is None:
                    default_masks = tmp / scene / seq / "masks_default"
                    sc.run_masks(src, seq, default_masks, cfg["masks"], tpl, progress=False, threads=1)

                # ---- flows (on the default estimated masks' region, initialised as configured)
                fcfg = cfg["flows"]
                ds = int(fcfg["prior_downsample"])
                prior = None
                if fcfg["prior"]:
                    prior = sc.ShapePrior(src, seq, info, tpl, scene_cameras(src, seq, names, info, dtype=torch.float32),
                                          frames)
                timing = interleaved_timing(src, seq, names, frames, default_masks, flow_methods, fcfg["margin_px"],
                                            prior, ds)
                prior_ms = 0.0
                if prior is not None:
                    out = tmp / scene / seq / "flows_prior_only"
                    per_frame = prior_flow_only(src, seq, prior, names, frames, ds, out)
                    prior_ms = 1e3 * per_frame / len(names)
                    ev = sc.evaluate_cues(src, seq, flows_dir=out)
                    rows.append({**base, "cue": "flows", "method": "prior flow alone", "reference": "ground-truth flow",
                                 "per_pair_ms": prior_ms, "per_frame_s": per_frame, **_pick(ev, "epe_"),
                                 "notes": f"posed body + skinned template, rasterised at 1/{ds} size, no image"})
                how = f"prior-initialised (1/{ds} size, {prior_ms:.1f} ms per pair)" if prior is not None else "plain"

                def flow_row(method: str, st: dict, ev: dict, t: float, notes: str) -> dict:
                    """A row of a region run: ``t`` the estimator's (+ refinement's) seconds per pair."""
                    total = t + prior_ms / 1e3
                    return {**base, "cue": "flows", "method": method, "reference": "ground-truth flow",
                            "wall_s": st["wall_s"], "per_pair_ms": 1e3 * t, "prior_ms_per_pair": prior_ms,
                            "per_frame_s": total * len(names), "region_frac": st["region_fraction"],
                            **_pick(ev, "epe_"), "epe_garment_x_s_per_pair": ev["epe_garment_px"] * total,
                            "notes": notes}

                flow_rows = []
                for method in list(flow_methods):
                    out = tmp / scene / seq / f"flows_{method}"
                    st = sc.run_flows(src, seq, default_masks, out, {**fcfg, "method": method, "refine": "none"}, tpl,
                                      threads=1, progress=False)
                    ev = sc.evaluate_cues(src, seq, flows_dir=out)
                    t = timing[method]
                    r = flow_row(method, st, ev, t, f"{how}; region: estimated masks, margin {fcfg['margin_px']} px; "
                                                    f"whole-sequence run {1e3 * st['compute_s_per_pair']:.1f} ms per pair")
                    rows.append(r)
                    flow_rows.append(r)
                    print(f"  flows {method}: {_fmt_row(r)}", flush=True)
                    if t * 1e3 > args.max_ms_per_pair:
                        flow_methods.remove(method)
                        notes_md.append(f"- flow method `{method}` took {t * 1e3:.0f} ms per pair on {scene}/{seq} "
                                        f"(over --max-ms-per-pair {args.max_ms_per_pair:.0f}): not rerun on the "
                                        "sequences after it.")
                    zero = {k.replace("epe_zero_", "epe_"): v for k, v in ev.items() if k.startswith("epe_zero_")}
                best = min(flow_rows, key=lambda r: r["epe_garment_x_s_per_pair"]) if flow_rows else None
                if best is not None:
                    best["default"] = best_label(best["method"], fcfg)
                    m = best["method"]
                    # the same method without the prior, and on the full frame: what each part brings
                    if prior is not None:
                        out = tmp / scene / seq / "flows_plain"
                        st = sc.run_flows(src, seq, default_masks, out,
                                          {**fcfg, "method": m, "prior": False, "refine": "none"}, tpl, threads=1,
                                          progress=False)
                        ev = sc.evaluate_cues(src, seq, flows_dir=out)
                        tp = interleaved_timing(src, seq, names, frames, default_masks, [m], fcfg["margin_px"])[m]
                        rows.append({**base, "cue": "flows", "method": m + " without prior",
                                     "reference": "ground-truth flow", "wall_s": st["wall_s"], "per_pair_ms": 1e3 * tp,
                                     "per_frame_s": tp * len(names), "region_frac": st["region_fraction"],
                                     **_pick(ev, "epe_"), "epe_garment_x_s_per_pair": ev["epe_garment_px"] * tp,
                                     "notes": "cues/flows/prior false"})
                    out = tmp / scene / seq / "flows_full"
                    st = sc.run_flows(src, seq, default_masks, out,
                                      {**fcfg, "method": m, "margin_px": 1 << 20, "refine": "none"}, tpl, threads=1,
                                      progress=False)
                    ev = sc.evaluate_cues(src, seq, flows_dir=out)
                    tt = interleaved_timing(src, seq, names, frames, default_masks, [m], fcfg["margin_px"], prior, ds,
                                            full_frame=True)
                    t_full, t_reg = tt[m + " full frame"], tt[m]
                    rows.append({**base, "cue": "flows", "method": m + " full frame",
                                 "reference": "ground-truth flow", "wall_s": st["wall_s"],
                                 "per_pair_ms": 1e3 * t_full, "prior_ms_per_pair": prior_ms,
                                 "per_frame_s": (t_full + prior_ms / 1e3) * len(names), "region_frac": 1.0,
                                 **_pick(ev, "epe_"),
                                 "notes": f"{how}; no region restriction: {t_full / t_reg:.2f}x the time of the "
                                          "region (timed interleaved with it)"})
                rm = refined_method(fcfg)
                if rm is not None and fcfg["method"] in timing:  # the pipeline's flows: the estimator + LK
                    out = tmp / scene / seq / "flows_refined"
                    st = sc.run_flows(src, seq, default_masks, out, fcfg, tpl, threads=1, progress=False)
                    ev = sc.evaluate_cues(src, seq, flows_dir=out)
                    t = timing[fcfg["method"]] + st["refine_s_per_pair"]
                    rows.append(dict(flow_row(rm, st, ev, t, f"{how}; the estimator's interleaved time + "
                                              f"{1e3 * st['refine_s_per_pair']:.1f} ms of Lucas-Kanade per pair "
                                              f"({st['refined_pixels_per_pair']:.0f} garment pixels of frame t-1)"),
                                     default="config"))
                    print(f"  flows {rm}: {_fmt_row(rows[-1])}", flush=True)
                if best is not None:
                    rows.append({**base, "cue": "flows", "method": "zero flow", "reference": "ground-truth flow",
                                 **_pick(zero, "epe_"), "notes": "no motion: the size of the motion"})
                rows.append({**base, "cue": "flows", "method": "ground-truth flow", "reference": "ground-truth flow",
                             "epe_all_px": 0.0, "epe_subject_px": 0.0, "epe_garment_px": 0.0, "notes": "by definition"})

                # ---- normals
                nd = scene_dir / seq / "normals"
                if nd.is_dir():
                    ev = sc.evaluate_cues(src, seq, normals_dir=src / seq / "normals")
                    rows.append({**base, "cue": "normals", "method": "shipped (degraded true normals)",
                                 "reference": "gt/normals", **_pick(ev, "normal_"),
                                 "notes": f"scene predicted_normals: {_pn(scene)}"})
                    rows.append({**base, "cue": "normals", "method": "ground truth", "reference": "gt/normals",
                                 "normal_subject_mean_deg": 0.0, "normal_garment_mean_deg": 0.0, "notes": "by definition"})
                    print(f"  normals: {_fmt_row(rows[-2])}", flush=True)
    notes_md += refine_note(rows, cfg["flows"])
    notes_md += overall_masks(rows, cfg["masks"]["method"])
    notes_md += overall_choice(rows, cfg["flows"]["method"])
    write(rows, args, started, load_before, notes_md)


def refined_method(fcfg: dict) -> str | None:
    """The row name of the configured estimator with the configured refinement (None: refinement off)."""
    if fcfg.get("refine", "none") == "none":
        return None
    return f"{fcfg['method']} + Lucas-Kanade refinement (window {int(fcfg.get('refine_window', 7))})"


def refine_note(rows: list[dict], fcfg: dict) -> list[str]:
    """One note line: the configured flows (estimator + refinement) against the estimator alone."""
    rm = refined_method(fcfg)
    if rm is None:
        return []
    pairs = []
    for key in dict.fromkeys((r["scene"], r["sequence"]) for r in rows):
        by = {r["method"]: r for r in rows if (r["scene"], r["sequence"]) == key and r["cue"] == "flows"}
        if rm in by and fcfg["method"] in by:
            pairs.append((f"{key[0]} {key[1]}", by[rm], by[fcfg["method"]]))
    if not pairs:
        return []
    dt = [r["per_pair_ms"] - b["per_pair_ms"] for _, r, b in pairs]
    return [f"- the pipeline's flows (rows marked `config`: `{fcfg['method']}` + the Lucas-Kanade refinement of the "
            f"garment's pixels, `cues/flows/refine: {fcfg['refine']}`): garment EPE "
            + " / ".join(f"{r['epe_garment_px']:.4f}" for _, r, _ in pairs) + " px against "
            + " / ".join(f"{b['epe_garment_px']:.4f}" for _, _, b in pairs)
            + f" for `{fcfg['method']}` alone (" + ", ".join(n for n, _, _ in pairs)
            + f"), at {min(dt):+.0f} to {max(dt):+.0f} ms per pair. The refinement is there for the motion the dense "
            "estimator shrinks at the fit's flow targets, which the mean EPE does not show (studies/cues/README.md)."]


def best_label(method: str, fcfg: dict) -> str:
    """The marker of the estimator with the best error x time, against the configured one."""
    if method != fcfg["method"]:
        return f"best error x time (config has {fcfg['method']})"
    return "best error x time (= config" + (", which refines it: see below)" if refined_method(fcfg) else ")")


def overall_masks(rows: list[dict], configured: str) -> list[str]:
    """Mask methods ranked by the mean of garment and body IoU over every benchmarked sequence."""
    ms = [r for r in rows if r["cue"] == "masks" and r["method"] in MASK_METHODS]
    if not ms:
        return []
    score = {m: float(np.mean([(r["iou_garment"] + r["iou_body"]) / 2 for r in ms if r["method"] == m]))
             for m in {r["method"] for r in ms}}
    best = max(score, key=score.get)
    n = len({(r["scene"], r["sequence"]) for r in ms})
    lines = ["", f"Mask methods over all {n} benchmarked sequences (mean of garment and body IoU):", ""]
    for m, v in sorted(score.items(), key=lambda kv: -kv[1]):
        lines.append(f"- `{m}`: {v:.4f}" + (" **<- best**" if m == best else ""))
    lines.append("")
    lines.append(f"The config default `cues/masks/method` is `{configured}`"
                 + (": the best by this measure." if configured == best else
                    f"; this run finds `{best}` better by this measure."))
    return lines


def overall_choice(rows: list[dict], configured: str) -> list[str]:
    """The flow method with the lowest mean garment EPE x mean seconds per pair over every
    benchmarked sequence it ran on (only methods run on all of them compete)."""
    flows = [r for r in rows if r["cue"] == "flows" and r["method"] in FLOW_METHODS]
    seqs = {(r["scene"], r["sequence"]) for r in flows}
    score = {}
    for m in {r["method"] for r in flows}:
        rs = [r for r in flows if r["method"] == m]
        if {(r["scene"], r["sequence"]) for r in rs} != seqs:
            continue
        epe = float(np.mean([r["epe_garment_px"] for r in rs]))
        t = float(np.mean([r["per_pair_ms"] + r.get("prior_ms_per_pair", 0.0) for r in rs])) / 1e3
        score[m] = (epe * t, epe, t)
    if not score:
        return []
    best = min(score, key=lambda m: score[m][0])
    lines = ["", f"Flow default over all {len(seqs)} benchmarked sequences (mean garment EPE x mean seconds per "
                 "pair, estimator + prior, lower is better):", ""]
    for m, (sc_, epe, t) in sorted(score.items(), key=lambda kv: kv[1][0]):
        lines.append(f"- `{m}`: {epe:.3f} px x {1e3 * t:.2f} ms = {sc_:.3g}"
                     + (" **<- best error per second**" if m == best else ""))
    lines.append("")
    lines.append(f"The config default `cues/flows/method` is `{configured}`"
                 + (": the best by this measure." if configured == best else
                    f"; this run finds `{best}` better by this measure."))
    # the prior initialisation, on vs off, for the best method
    off = [r for r in rows if r["cue"] == "flows" and r["method"] == best + " without prior"]
    on = [r for r in flows if r["method"] == best]
    if off and len(off) == len(on):
        e_on, e_off = (float(np.mean([r["epe_garment_px"] for r in x])) for x in (on, off))
        w_on, w_off = (float(np.mean([r["epe_garment_px"] for r in x])) for x in (
            [max(on, key=lambda r: r["epe_garment_px"])], [max(off, key=lambda r: r["epe_garment_px"])]))
        t_prior = float(np.mean([r.get("prior_ms_per_pair", 0.0) for r in on]))
        lines += ["", f"Prior initialisation (`cues/flows/prior`) for `{best}`: mean garment EPE {e_on:.3f} px with, "
                      f"{e_off:.3f} px without; worst sequence {w_on:.3f} vs {w_off:.3f} px; it costs "
                      f"{t_prior:.1f} ms per camera pair (the rasteriser), the same for every method. By error x "
                      f"time alone it "
                      + ("pays" if e_on * (float(np.mean([r['per_pair_ms'] for r in on])) + t_prior)
                         < e_off * float(np.mean([r['per_pair_ms'] for r in off])) else "does not pay")
                      + "; it is on by default for the error (see the twirl rows)."]
    return lines


def _pn(scene: str) -> str:
    scenes = load_config(ROOT / "config" / "config.yaml")["scenes"]
    if scene not in scenes:
        return "?"
    cfg = scenes[scene]["predicted_normals"]
    return ", ".join(f"{k} {v}" for k, v in cfg.items())


def _subset(scene_dir: Path, dst: Path, seq: str, frames: list[int]) -> None:
    """A view of one sequence restricted to ``frames``: symlinks to the files (nothing copied)."""
    if dst.exists():
        return
    dst.mkdir(parents=True)
    for p in scene_dir.iterdir():
        if p.name != seq:
            os.symlink(p, dst / p.name)
    keep = {f"{f:06d}" for f in frames}
    for root, dirs, fnames in os.walk(scene_dir / seq):
        rel = Path(root).relative_to(scene_dir)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for fn in fnames:
            stem = Path(fn).stem
            if stem.isdigit() and len(stem) == 6 and stem not in keep:
                continue
            os.symlink(Path(root) / fn, dst / rel / fn)


def _pick(d: dict, prefix: str) -> dict:
    return {k: v for k, v in d.items() if k.startswith(prefix) and k in COLUMNS}


def _fmt_row(r: dict) -> str:
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()
                     if k not in ("scene", "sequence", "cue", "method", "reference", "notes", "cameras", "frames"))


def _table(rows: list[dict], cols: list[tuple[str, str, str]]) -> str:
    head = "| " + " | ".join(c[1] for c in cols) + " |"
    sep = "| " + " | ".join("---" for _ in cols) + " |"
    lines = [head, sep]
    for r in rows:
        cells = []
        for key, _, spec in cols:
            v = r.get(key, "")
            cells.append(format(v, spec) if isinstance(v, (float, int)) and not isinstance(v, bool) and spec else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render_only(args) -> None:
    """Rewrite cues.md from an earlier run's cues.csv (+ its md header) with the current config's defaults."""
    out = Path(args.out)
    cfg = load_config(ROOT / "config" / "config.yaml")["cues"]
    rows = []
    with open(out / "cues.csv", newline="") as fh:
        for r in csv.DictReader(fh):
            row = {}
            for k, v in r.items():
                if v == "":
                    continue
                try:
                    row[k] = float(v) if k not in ("scene", "sequence", "cue", "method", "reference", "default",
                                                   "notes") else v
                except ValueError:
                    row[k] = v
            rows.append(row)
    old = (out / "cues.md").read_text().splitlines()
    header = {k: next((ln for ln in old if ln.startswith(k)), f"{k} ?") for k in
              ("Command:", "Date:", "Git revision:", "Machine:", "Load average")}
    start = next(i for i, ln in enumerate(old) if ln.startswith("Cameras:"))
    stop = next((i for i, ln in enumerate(old) if ln.startswith("Mask methods over") or ln.startswith("## Masks")),
                len(old))
    notes = [ln for ln in old[start + 1: stop] if ln.startswith("- ") and not ln.startswith("- the pipeline's flows")]
    # the default markers against the current config
    for r in rows:
        r.pop("default", None)
        if r["cue"] == "masks" and r["method"] == cfg["masks"]["method"]:
            r["default"] = "yes (config)"
    rm = refined_method(cfg["flows"])
    for r in rows:
        if r["cue"] == "flows" and r["method"] == rm:
            r["default"] = "config"
    for key in {(r["scene"], r["sequence"]) for r in rows}:
        cand = [r for r in rows if (r["scene"], r["sequence"]) == key and r["cue"] == "flows"
                and r["method"] in FLOW_METHODS and "epe_garment_x_s_per_pair" in r]
        if cand:
            best = min(cand, key=lambda r: r["epe_garment_x_s_per_pair"])
            best["default"] = best_label(best["method"], cfg["flows"])
    notes += refine_note(rows, cfg["flows"])
    notes += overall_masks(rows, cfg["masks"]["method"]) + overall_choice(rows, cfg["flows"]["method"])
    rerender = (f"Re-rendered by `.venv/bin/python -m benchmarks.bench_cues --render-only` on "
                f"{datetime.datetime.now().isoformat(timespec='seconds')} against the config's current defaults; "
                "every figure is that of the run above.  ")
    write(rows, args, None, None, notes, header={**header, "rerender": rerender})


def write(rows: list[dict], args, started: str | None, load_before: str | None, notes_md: list[str],
          header: dict | None = None) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with files.atomic_path(out / "cues.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    cmd = ".venv/bin/python -m benchmarks.bench_cues " + " ".join(sys.argv[1:])
    if header is None:
        head = [f"Command: `{cmd.strip()}`  ", f"Date: {started}  ", f"Git revision: {git_rev(CODE_PATHS)}  ",
                f"Machine: {machine()}; torch and OpenCV set to 1 thread  ",
                f"Load average (1, 5, 15 min) before the run: {load_before}; after: {load()}  "]
    else:
        head = [header[k] for k in ("Command:", "Date:", "Git revision:", "Machine:", "Load average")]
        head.append(header["rerender"])
    md = [
        "# 2D cues benchmark (`anidress_core.cues`)",
        "",
        *head,
        "Cameras: each scene's training cameras (what the fitting uses). Ground truth: data/<scene>/<seq>/gt "
        "(masks and flows at pixel centres; the images are 2x2 supersampled, so a silhouette pixel whose "
        "centre is in the subject can be half covered: about a quarter of the silhouette pixels are ambiguous).",
        "",
        *notes_md,
        "",
        "## Masks (IoU against gt/masks; 0 background, 1 body, 2 garment)",
        "",
        _table([r for r in rows if r["cue"] == "masks"], [
            ("scene", "scene", ""), ("sequence", "seq", ""), ("method", "method", ""), ("reference", "reference", ""),
            ("iou_subject", "IoU subject", ".4f"), ("iou_body", "IoU body", ".4f"), ("iou_garment", "IoU garment", ".4f"),
            ("per_frame_s", "s per frame (all cameras)", ".3f"), ("default", "default", ""), ("notes", "notes", "")]),
        "",
        "## Optical flow (end-point error against gt/flows, pixels)",
        "",
        "EPE *all*: every pixel where the ground truth is valid (visible in both frames; outside the processed "
        "region the estimate is 0, right for the static background); *subject* / *garment*: those pixels of "
        "frame t-1's subject / garment. The methods are initialised by the flow of the posed body + skinned "
        "garment template (`cues/flows/prior`; its own error is the row *prior flow alone*, and the default "
        "method without it is shown too). Times: the estimator call (with the prior's warp and composition) on "
        "one thread, median over 24 camera pairs x 3 repeats with the methods interleaved (robust to the load of "
        "a shared machine), plus the prior's rasterisation per pair (the same for every method); per frame = all "
        "training cameras. The default is the lowest garment EPE x (estimator + prior) seconds per pair.",
        "",
        _table([r for r in rows if r["cue"] == "flows"], [
            ("scene", "scene", ""), ("sequence", "seq", ""), ("method", "method", ""), ("reference", "reference", ""),
            ("epe_all_px", "EPE all", ".4f"), ("epe_subject_px", "EPE subject", ".4f"),
            ("epe_garment_px", "EPE garment", ".4f"), ("epe_garment_gt3px_frac", "garment >3 px", ".4f"),
            ("per_pair_ms", "ms per pair", ".2f"), ("prior_ms_per_pair", "+ prior ms per pair", ".1f"),
            ("per_frame_s", "s per frame", ".3f"),
            ("region_frac", "pixels processed", ".3f"), ("epe_garment_x_s_per_pair", "EPE x s", ".3g"),
            ("default", "default", ""), ("notes", "notes", "")]),
        "",
        "## Normals (angular error against gt/normals, degrees)",
        "",
        _table([r for r in rows if r["cue"] == "normals"], [
            ("scene", "scene", ""), ("sequence", "seq", ""), ("method", "method", ""), ("reference", "reference", ""),
            ("normal_garment_mean_deg", "garment mean", ".2f"), ("normal_garment_median_deg", "garment median", ".2f"),
            ("normal_garment_within20_frac", "garment < 20 deg", ".3f"),
            ("normal_subject_mean_deg", "subject mean", ".2f"), ("normal_subject_median_deg", "subject median", ".2f"),
            ("notes", "notes", "")]),
        "",
    ]
    files.write_text(out / "cues.md", "\n".join(md))
    print(f"wrote {out / 'cues.md'} and {out / 'cues.csv'}")


if __name__ == "__main__":
    import signal

    # a terminated run still removes its temporary folder (TemporaryDirectory's cleanup)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    main()
