"""Do the masks stage's thresholds hold when a capture's images (and plates) are JPEG? (issue 47 item 1)

The demo skirt's walk (8 training cameras x 60 frames, 256x256) is copied with its images and background
plates re-encoded as JPEG at several qualities (OpenCV's encoder, 4:2:0 chroma), then rule masks' stage
runs on each copy with the pipeline's settings and template; the labels are scored against the ground truth
(IoU of the subject, labels > 0, and of the garment, label 2, pooled over all pixels of the sequence).
The PNG row is the same run on the scene as it is. Needs `make demo` first (data/skirt, results/skirt).

    PYTHONPATH=. .venv/bin/python studies/cues/jpeg_masks.py [--qualities 95,85,75] [--out studies/cues]
"""
from __future__ import annotations

import argparse
import csv
import datetime
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from anidress_core.io import files

ROOT = Path(__file__).resolve().parents[2]


def reencode(src: Path, dst: Path, quality: int | None) -> None:
    """A copy of scene ``src`` whose walk images and plates are JPEG of ``quality`` (None: links, PNG as is)."""
    dst.mkdir(parents=True)
    for p in src.iterdir():
        if p.name != "walk":
            (dst / p.name).symlink_to(p.resolve())
    for p in (src / "walk").iterdir():
        if p.name not in ("images", "backgrounds") or quality is None:
            (dst / "walk" / p.name).parent.mkdir(parents=True, exist_ok=True)
            (dst / "walk" / p.name).symlink_to(p.resolve())
            continue
        for f in p.rglob("*.png"):
            out = (dst / "walk" / f.relative_to(src / "walk")).with_suffix(".jpg")
            out.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out), cv2.imread(str(f), cv2.IMREAD_COLOR), [cv2.IMWRITE_JPEG_QUALITY, quality])


def score(masks: Path, gt: Path) -> dict:
    """Pooled IoU of the subject (labels > 0) and the garment (== 2) over every mask of ``masks``."""
    inter = {"subject": 0, "garment": 0}
    union = {"subject": 0, "garment": 0}
    for p in sorted(masks.rglob("*.png")):
        a, b = files.read_mask(p), files.read_mask(gt / p.relative_to(masks))
        for name, fn in (("subject", lambda m: m > 0), ("garment", lambda m: m == 2)):
            inter[name] += int((fn(a) & fn(b)).sum())
            union[name] += int((fn(a) | fn(b)).sum())
    return {f"iou_{k}": inter[k] / max(1, union[k]) for k in inter}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--qualities", default="95,85,75")
    ap.add_argument("--out", default=str(ROOT / "studies" / "cues"))
    args = ap.parse_args()
    scene, res = ROOT / "data" / "skirt", ROOT / "results" / "skirt"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for q in [None] + [int(x) for x in args.qualities.split(",")]:
            name = "png" if q is None else f"jpeg_q{q}"
            d = Path(tmp) / name / "skirt"
            reencode(scene, d, q)
            out = Path(tmp) / name / "masks"
            subprocess.run([str(Path(sys.executable).parent / "anidress"), "masks", str(d), "walk", "-o", str(out),
                            "--template", str(res / "template.npz"), "--config", str(ROOT / "config" / "config.yaml"),
                            "--threads", "2", "--quiet"], check=True, cwd=ROOT)
            r = {"images": name, **score(out, scene / "walk" / "gt" / "masks")}
            print(r, flush=True)
            rows.append(r)
    base = rows[0]
    head = ["images", "iou_subject", "iou_garment"]
    out = Path(args.out)
    with open(out / "jpeg_masks.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=head, lineterminator="\n")
        w.writeheader()
        w.writerows({k: (f"{v:.5f}" if isinstance(v, float) else v) for k, v in r.items()} for r in rows)
    git = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                         text=True).stdout.strip()
    L = ["# The masks stage on JPEG images (demo skirt, walk, 8 cameras x 60 frames, 256x256)", "",
         f"- command: `PYTHONPATH=. .venv/bin/python studies/cues/jpeg_masks.py --qualities {args.qualities}` "
         f"(git {git}, {datetime.datetime.now().isoformat(timespec='seconds')})",
         "- images and background plates re-encoded by OpenCV at each JPEG quality; the pipeline's mask settings "
         "(config/config.yaml cues/masks) and template; IoU pooled over every pixel of the sequence against the "
         "ground-truth labels", "",
         "| images | subject IoU | garment IoU | subject IoU - PNG's | garment IoU - PNG's |",
         "| --- | --- | --- | --- | --- |"]
    for r in rows:
        L.append(f"| {r['images']} | {r['iou_subject']:.4f} | {r['iou_garment']:.4f} | "
                 f"{r['iou_subject'] - base['iou_subject']:+.4f} | {r['iou_garment'] - base['iou_garment']:+.4f} |")
    (out / "jpeg_masks.md").write_text("\n".join(L) + "\n")
    print(out / "jpeg_masks.md")


if __name__ == "__main__":
    main()
