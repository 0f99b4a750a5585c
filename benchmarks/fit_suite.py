"""The garment fit's evaluation suites (issue 23): generated synthetic scenes, a tuning and a held-out one.

The fit's settings were chosen on the tuning subset: the demo scenes `skirt` and `dress`, and the
suite of ``--seed 23`` (config/fit_suite.yaml; L_prior's weight and form, studies/fit). The
headline suite is ``--seed 24 --prefix heldout`` (config/fit_heldout.yaml), drawn after those
choices, on which nothing is tuned. Scenes are drawn here, deterministically from ``--seed``, and
written as a config overlay; none has a `fit` section, so each is fitted with the pipeline's
defaults. They vary what the issue names:
garment (skirt, dress), fabric (plain one-colour fabrics in at least a third of them, plaid,
denim, floral), the training motion (every library motion, run, jump and twirl included), the
scene seed, the ground-truth fabric's bending stiffness (log-uniform 3e-4 .. 1e-2 J, so the
truth is not the rig's own soft material, 1e-4 J) and the normal degradation (blur 1-3 px,
noise 0.03-0.08). The truth's other cloth settings are drawn too (:data:`TRUTH_CLOTH`), from a
stream of their own: its damping, its friction against the body and its state at frame 0 (the
settle length), which a capture does not share with the pipeline's simulations (solver defaults
0.5 1/s, 0.3, 30 frames).

    .venv/bin/python -m benchmarks.fit_suite --seed 24 --prefix heldout --out config/fit_heldout.yaml
    snakemake --workflow-profile profiles/default \\
        $(.venv/bin/python -m benchmarks.fit_suite --seed 24 --prefix heldout --targets) \\
        --configfile config/config.yaml config/fit_heldout.yaml  # scenes, rigs, ensembles, cues
    .venv/bin/python -m benchmarks.bench_fit --suite config/fit_heldout.yaml              # benchmarks/fit.md

The field suite (config/field_suite.yaml: ``--seed 26 --prefix fsuite --count 6 --novel-pose``) adds a
held-out sequence to each scene and is run through the whole pipeline (its targets include the fit
evaluation and both field variants' metrics); ``benchmarks/collect_field_suite.py`` tabulates it. The
field's settings were chosen on :data:`FIELD_TUNING`; the other four are its held-out scenes.
"""
from __future__ import annotations

import argparse
import math
import random
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "config" / "fit_suite.yaml"
#: the scenes every fit setting was chosen on (config/config.yaml): the demo scenes and the suite of
#: --seed 23 (config/fit_suite.yaml); reported apart, never in the headline (config/fit_heldout.yaml, --seed 24)
TUNING = ("skirt", "dress")
TUNING_SUITE = ROOT / "config" / "fit_suite.yaml"
#: the field suite (config/field_suite.yaml: --seed 26 --prefix fsuite --count 6 --novel-pose) and the scenes of it the
#: field's settings were chosen on (a plain skirt and a denim dress); the others are held out
FIELD_SUITE = ROOT / "config" / "field_suite.yaml"
FIELD_TUNING = ("fsuite_00", "fsuite_01")
MOTIONS = ("walk", "run", "twirl", "sway", "dance", "arms_up", "jump")
FABRICS = ("plain", "floral", "plaid", "denim")
FRAMES = 40
#: ranges of the ground truth's cloth settings drawn per scene besides the stiffness (anidress_core.sim.ClothParams):
#: damping 1/s (log-uniform), friction against the body (uniform), settle frames (uniform integer: how the garment
#: starts the sequence). The pipeline simulates with the solver's 0.5, 0.3 and 30 (its ensemble: 20 and 40 frames).
TRUTH_CLOTH = {"damping": (0.2, 2.0), "friction": (0.1, 0.6), "settle_frames": (15, 60)}


def draw(count: int = 10, seed: int = 23, prefix: str = "suite", novel_pose: bool = False) -> dict:
    """``count`` scene sections ``<prefix>_00`` ..: every library motion at least once (for count >= 7),
    garments alternating, plain fabric on every third scene, the rest drawn. The truth's damping,
    friction and settle length (:data:`TRUTH_CLOTH`) come from a stream of their own, so the rest of
    a scene is what the same seed drew before they were. ``novel_pose``: each scene also gets a
    held-out sequence of another library motion (role novel_pose, for the field), drawn from a
    separate stream so the scenes are otherwise those drawn without it."""
    rng = random.Random(seed)
    rng_novel = random.Random(seed + 7919)
    rng_cloth = random.Random(seed + 104729)
    motions = list(MOTIONS) + [rng.choice(MOTIONS) for _ in range(max(0, count - len(MOTIONS)))]
    rng.shuffle(motions)
    (d0, d1), (f0, f1), (s0, s1) = (TRUTH_CLOTH[k] for k in ("damping", "friction", "settle_frames"))
    scenes = {}
    for i in range(count):
        fabric = "plain" if i % 3 == 0 else rng.choice(FABRICS[1:])
        bend = math.exp(rng.uniform(math.log(3e-4), math.log(1e-2)))
        cloth = {"bend_stiffness": float(f"{bend:.3g}"),
                 "damping": float(f"{math.exp(rng_cloth.uniform(math.log(d0), math.log(d1))):.3g}"),
                 "friction": round(rng_cloth.uniform(f0, f1), 2), "settle_frames": rng_cloth.randint(s0, s1)}
        scenes[f"{prefix}_{i:02d}"] = {
            "synthetic": True,
            "kind": ("skirt", "dress")[i % 2],
            "seed": 1000 + seed * 100 + i,
            "image_size": [256, 256],
            "sequences": [{"name": motions[i], "motion": motions[i], "frames": FRAMES, "role": "train"}],
            "garment": {"vertices": 3000, "texture": fabric, "cloth": cloth},
            "predicted_normals": {"blur_px": round(rng.uniform(1.0, 3.0), 2),
                                  "noise_std": round(rng.uniform(0.03, 0.08), 3)},
        }
        if novel_pose:
            other = rng_novel.choice([m for m in MOTIONS if m != motions[i]])
            scenes[f"{prefix}_{i:02d}"]["sequences"].append(
                {"name": other, "motion": other, "frames": FRAMES, "role": "novel_pose"})
    return scenes


def tuning_scenes() -> list[str]:
    """The names of every scene a fit setting was chosen on: :data:`TUNING` and :data:`TUNING_SUITE`'s."""
    return [*TUNING, *yaml.safe_load(TUNING_SUITE.read_text())["scenes"]]


def overlay(scenes: dict, seed: int, prefix: str = "suite", novel_pose: bool = False) -> str:
    head = (f"# An evaluation suite: {len(scenes)} generated scenes (benchmarks/fit_suite.py, --seed {seed} "
            f"--prefix {prefix}{' --novel-pose' if novel_pose else ''}).\n"
            "# Written by that script; none has a fit section. The tuning subset (settings chosen on it) is\n"
            "# config/fit_suite.yaml (--seed 23) with the demo scenes; the held-out suite is --seed 24.\n"
            + (f"# The field's settings were chosen on {', '.join(FIELD_TUNING)} of config/field_suite.yaml.\n"
               if novel_pose else "")
            + "# Use: snakemake --configfile config/config.yaml <this file> (after config/config.yaml).\n")
    return head + yaml.safe_dump({"run_scenes": list(scenes), "scenes": scenes}, sort_keys=False)


def targets(scenes: dict) -> list[str]:
    """What bench_fit reads of each scene: the rig (with the simulation of its sequence), the simulation
    ensemble's mean of the sequence (L_prior's reference) and the cues;
    for a scene with a novel-pose sequence also what benchmarks/collect_field_suite.py reads: the
    pipeline's fit evaluation of every sequence and the field's metrics of both variants."""
    out = []
    for name, s in scenes.items():
        seq = s["sequences"][0]["name"]
        out += [f"results/{name}/rig.npz", f"results/{name}/sim_ensemble/seq-{seq}.npz",
                f"results/{name}/{seq}/masks", f"results/{name}/{seq}/flows"]
        if len(s["sequences"]) > 1:
            out += [f"results/{name}/{q['name']}/fit_metrics.csv" for q in s["sequences"]]
            out += [f"results/{name}/{seq}/{v}/metrics_summary.json" for v in ("full", "body_only")]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=10)
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--prefix", default="suite", help="scene names <prefix>_00 .. (default: %(default)s)")
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="the overlay written (default: %(default)s)")
    ap.add_argument("--novel-pose", action="store_true",
                    help="add a held-out sequence of another motion to each scene (the field's novel poses)")
    ap.add_argument("--targets", action="store_true", help="print the Snakemake targets of the suite instead")
    args = ap.parse_args()
    scenes = draw(args.count, args.seed, args.prefix, args.novel_pose)
    if args.targets:
        print(" ".join(targets(scenes)))
        return
    Path(args.out).write_text(overlay(scenes, args.seed, args.prefix, args.novel_pose))
    print(f"wrote {args.out}: {', '.join(scenes)}")


if __name__ == "__main__":
    main()
