"""Probe: the field trained with other settings beside its defaults, on the scenes named, through
benchmarks/field_runs.py as bench_field does (the pipeline's masks, rig and fits under results/; one torch
thread per job). Meant for tuning scenes (the demo skirt, fsuite_00, fsuite_01); a row that helps there is
then measured on the held-out scenes by ``bench_field options``.

    PYTHONPATH=. .venv/bin/python studies/field/rows.py [--scenes skirt fsuite_00 fsuite_01] \
        [--variants full body_only] [--rows default every1 ...] [--workers 2]

Prints one line per field and a table of garment / subject PSNR (novel view, novel pose) and training time.
Fields are kept under benchmarks/runs/field/study_rows/<scene>/<variant>/<row>/ and reused.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.field_runs import Job, run_jobs

ROOT = Path(__file__).resolve().parents[2]
WORK = ROOT / "benchmarks" / "runs" / "field" / "study_rows"


def _train(**kw) -> dict:
    return {"field": {"train": kw}}


#: name -> (label, config overlay)
ROWS = {
    "default": ("defaults (decoder stepped every 4th batch, lr_weights 1e-3)", {}),
    # the weight volume's decoder takes one Adam step per block of weights_every (4) batches
    "every1": ("decoder stepped every batch (weights_every 1)", _train(weights_every=1)),
    "lr4x": ("every 4th batch, lr_weights 4e-3", _train(lr_weights=4e-3)),
    "blend": ("warp: HumanNeRF blend (warp_iterations 0)", {"field": {"model": {"warp_iterations": 0}}}),
    # garment poses refined through the images: rate and pull towards the fit
    "refine": ("refine_garment, its defaults (refine_lr 1e-3, refine_weight 1)", _train(refine_garment=True)),
    "refine_lr3": ("refine_garment, refine_lr 3e-3", _train(refine_garment=True, refine_lr=3e-3)),
    "refine_lr10": ("refine_garment, refine_lr 1e-2", _train(refine_garment=True, refine_lr=1e-2)),
    "refine_w01": ("refine_garment, refine_weight 0.1", _train(refine_garment=True, refine_weight=0.1)),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["skirt", "fsuite_00", "fsuite_01"])
    ap.add_argument("--variants", nargs="+", default=["full", "body_only"])
    ap.add_argument("--rows", nargs="+", default=["default", "every1", "lr4x"], choices=sorted(ROWS))
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    jobs = [Job(ROWS[name][0], scene, variant, WORK / scene / variant / name, overlay=ROWS[name][1])
            for scene in args.scenes for variant in args.variants for name in args.rows]
    rows = run_jobs(jobs, args.workers)
    print("| scene | variant | row | train wall s | nv garment / subject | np garment / subject |")
    print("| --- | --- | --- | ---: | --- | --- |")
    for r in rows:
        if "failed" in r:
            print(f"| {r['scene']} | {r['variant']} | {r['method']} | failed | | |")
            continue
        print(f"| {r['scene']} | {r['variant']} | {r['method']} | {r['train_wall_s']:.0f} | "
              f"{r.get('nv_psnr_garment_db', float('nan')):.2f} / {r['nv_psnr_subject_db']:.2f} | "
              f"{r.get('np_psnr_garment_db', float('nan')):.2f} / {r['np_psnr_subject_db']:.2f} |")


if __name__ == "__main__":
    main()
