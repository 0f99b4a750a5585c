"""Retrain one field variant outside the workflow (another training seed, other garment poses)
and evaluate it exactly as the pipeline does: the config's field settings, the pipeline's masks,
novel view = the test cameras on every ``field/render/frame_stride``-th training frame, novel
pose = every camera on the same frames of the novel-pose sequence. Gives the spread between
trainings behind benchmarks/field.md's full vs body_only comparison. Not a test.

    .venv/bin/python benchmarks/field_retrain.py --variant full --seed 1 --poses results/skirt -o /tmp/fr/full_s1
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from anidress_core.config import load_config, scene_config  # noqa: E402
from anidress_core.metrics.image import load_dists, load_lpips  # noqa: E402
from anidress_core.stages import setup_logging  # noqa: E402
from anidress_core.stages.evaluate import run_evaluate  # noqa: E402
from anidress_core.stages.field import run_render, run_train  # noqa: E402
from anidress_core.stages.scene import read_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="skirt")
    ap.add_argument("--variant", choices=["full", "body_only"], required=True)
    ap.add_argument("--seed", type=int, default=0, help="field/train/seed")
    ap.add_argument("--poses", default="results/{scene}",
                    help="folder with <seq>/garment_poses.npz of the training and novel-pose sequences (variant full)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("-o", "--out", required=True)
    a = ap.parse_args()
    os.chdir(REPO)
    torch.set_num_threads(a.threads)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    setup_logging(str(out / "log.txt"))
    cfg = load_config(a.config)
    scene_config(cfg, a.scene)  # a clear error for an unknown scene
    fp = cfg["field"]
    fp["train"] = dict(fp["train"], seed=a.seed)
    d = Path("data") / a.scene
    info = read_scene(d)
    train = next(s["name"] for s in info["sequences"] if s["role"] == "train")
    pose_seq = next(s["name"] for s in info["sequences"] if s["role"] == "novel_pose")
    poses = Path(a.poses.format(scene=a.scene))
    kw = {"template_npz": f"results/{a.scene}/template.npz"}
    pw: dict = {}
    if a.variant == "full":
        kw["rig_npz"] = f"results/{a.scene}/rig.npz"
        pw = {s: str(poses / s / "garment_poses.npz") for s in (train, pose_seq)}
    lpips = load_lpips(**cfg["metrics"]["lpips"]) if fp["train"]["lpips_weight"] > 0 else None
    t0 = time.perf_counter()
    r = run_train(d, train, a.variant, f"results/{a.scene}/{train}/masks", out / "field.pt", fp,
                  garment_poses_npz=pw.get(train), lpips=lpips, device=fp["device"], progress=False, **kw)
    stride = fp["render"]["frame_stride"]
    nv, npose = out / "renders" / "novel_view" / train, out / "renders" / "novel_pose" / pose_seq
    run_render(out / "field.pt", d, nv, fp, seq=train, cameras=info["cameras"]["test"],
               garment_poses_npz=pw.get(train), frame_stride=stride, device=fp["device"], progress=False, **kw)
    run_render(out / "field.pt", d, npose, fp, seq=pose_seq, cameras=info["cameras"]["train"] + info["cameras"]["test"],
               garment_poses_npz=pw.get(pose_seq), frame_stride=stride, device=fp["device"], progress=False, **kw)
    m = cfg["metrics"]
    s = run_evaluate(d, [("novel_view", train, nv), ("novel_pose", pose_seq, npose)], out / "metrics.csv",
                     out / "metrics_summary.json", m, lpips=load_lpips(**m["lpips"]), dists=load_dists(**m["dists"]),
                     progress=False)
    summary = {"variant": a.variant, "seed": a.seed, "poses": pw, "train_wall_s": r.get("wall_s"),
               "train_cpu_s": r.get("cpu_s"), "total_s": time.perf_counter() - t0, "metrics": s["metrics"]}
    (out / "retrain.json").write_text(json.dumps(summary, indent=1, default=str))
    print(json.dumps(summary, default=str))


if __name__ == "__main__":
    main()
