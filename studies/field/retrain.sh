#!/bin/bash
# Probe: retrain one field of a finished demo run with other code or settings, render its novel views and
# novel poses and score them, with the same `anidress train / render / evaluate` calls as the rules.
#
#   studies/field/retrain.sh OUT SCENE VARIANT [CODE_DIR [OVERLAY.yaml]]
#
# Run from the demo's workdir (data/, results/, config/config.yaml). SCENE: tight or skirt (trained on
# walk, novel pose dance); CODE_DIR: a checkout whose anidress_core is imported instead of the installed
# one (the probe of a code change); OVERLAY: settings merged over config/config.yaml (e.g. field/train/seed).
# Writes OUT/{field.pt, np/, nv/, metrics.csv, metrics_summary.json} and prints the PSNRs.
set -euo pipefail
out=$1; scene=$2; variant=$3; code=${4:-}; overlay=${5:-}
mkdir -p "$out"
cfg=config/config.yaml
if [ -n "$overlay" ]; then
  .venv/bin/python - "$cfg" "$overlay" "$out/config.yaml" <<'PY'
import sys, yaml
c, o = yaml.safe_load(open(sys.argv[1])), yaml.safe_load(open(sys.argv[2]))
def merge(a, b):
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(a.get(k), dict):
            merge(a[k], v)
        else:
            a[k] = v
merge(c, o)
yaml.safe_dump(c, open(sys.argv[3], "w"))
PY
  cfg=$out/config.yaml
fi
[ -n "$code" ] && export PYTHONPATH=$code  # the console script puts PYTHONPATH before the installed package
A=".venv/bin/anidress"
R=results/$scene
garment=(); walk=(); dance=()
if [ "$scene" != tight ]; then
  garment=(--template "$R/template.npz")
  if [ "$variant" = full ]; then
    garment+=(--rig "$R/rig.npz"); walk=(--poses "$R/walk/garment_poses.npz"); dance=(--poses "$R/dance/garment_poses.npz")
  fi
fi
$A train "data/$scene" walk --variant "$variant" --masks "$R/walk/masks" "${garment[@]}" "${walk[@]}" --config "$cfg" \
  --threads 1 -o "$out/field.pt" --quiet
$A render "$out/field.pt" "data/$scene" --seq dance "${dance[@]}" "${garment[@]}" --cameras all --config "$cfg" \
  --threads 1 -o "$out/np" --quiet
$A render "$out/field.pt" "data/$scene" --seq walk "${walk[@]}" "${garment[@]}" --cameras test --config "$cfg" \
  --threads 1 -o "$out/nv" --quiet
$A evaluate "data/$scene" "novel_pose:dance:$out/np" "novel_view:walk:$out/nv" --config "$cfg" -o "$out/metrics.csv" --quiet
.venv/bin/python -c "import json, sys; d = json.load(open(sys.argv[1])); print(sys.argv[2], [(m['kind'], m['images'], round(m['psnr_db'], 2)) for m in d['metrics']])" \
  "$out/metrics_summary.json" "$out"
