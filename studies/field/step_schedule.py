"""Probe: train a field with a coarse-to-fine ray-marching step (the first part of the steps at
field/sampler/step_m, the rest at a finer step), for the tight scene of a finished demo run.

    python studies/field/step_schedule.py OUT.pt SWITCH_FRACTION FINE_STEP_M [STEPS]

Run from a workdir holding a demo run (data/tight, results/tight/walk/masks); the training settings are
config/config.yaml's. Score it by copying OUT.pt onto results/tight/walk/full/field.pt and rerunning
only the renders and the scores (`snakemake results/tight/walk/full/metrics_summary.json --rerun-triggers
mtime -R render_novel_pose render_novel_view`, with an overlay setting field/sampler/step_m to render
at another step). The step schedule is applied by wrapping the training loop's render call: a probe,
not a pipeline option.
"""
import sys

import torch
import yaml

import anidress_core.field.train as T
from anidress_core.stages.field import run_train

torch.set_num_threads(1)
out, frac, fine = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
steps = int(sys.argv[4]) if len(sys.argv) > 4 else 600
f = yaml.safe_load(open("config/config.yaml"))["field"]
sampler = {k: v for k, v in f["sampler"].items() if k != "body_only_garment_dilate_m"}
params = {"model": f["model"], "priors": f["priors"], "sampler": sampler,
          "train": dict(f["train"], steps=steps, checkpoint_every=0),
          "render": {"background": f["render"]["background"]}, "device": f["device"]}
switch, calls, render_rays = int(frac * steps), [0], T.render_rays


def scheduled(model, o, d, fr, inv, grid, step, *a, **kw):
    calls[0] += 1  # one call per optimiser step
    return render_rays(model, o, d, fr, inv, grid, fine if calls[0] > switch else step, *a, **kw)


T.render_rays = scheduled
rec = run_train("data/tight", "walk", "full", "results/tight/walk/masks", out, params, progress=False)
print(out, f"switch at step {switch} to {fine} m", {k: rec[k] for k in ("wall_s", "cpu_s") if k in rec})
