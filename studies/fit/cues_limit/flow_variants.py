"""Probe: other settings of the flows stage on one synthetic scene, measured at L_flow's targets as in
flow_targets.py. Runs :func:`anidress_core.stages.cues.run_flows` with config.yaml's ``cues/flows`` changed by one
variant into ``<out>/<scene>_<variant>``, then prints flow_targets.py's row for those flows. Variants: ``config``,
``no_prior`` (no body/template initialisation), ``no_refine`` (no Lucas-Kanade), ``deepflow``, ``farneback``,
``lk_pyramid`` (Lucas-Kanade with 2 pyramid levels and corrections up to 6 px instead of 0 and 2).

    PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/flow_variants.py suite_03 deepflow /tmp/flow_variants
"""
from __future__ import annotations

import functools
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import flow_targets  # noqa: E402

from anidress_core.config import load_config  # noqa: E402
from anidress_core.cues import flow as cue_flow  # noqa: E402
from anidress_core.io.scene import read_scene  # noqa: E402
from anidress_core.stages.cues import run_flows  # noqa: E402

CHANGES = {"config": {}, "no_prior": {"prior": False}, "no_refine": {"refine": "none"},
           "deepflow": {"method": "deepflow"}, "farneback": {"method": "farneback"}, "lk_pyramid": {}}

if __name__ == "__main__":
    scene, variant, out = sys.argv[1], sys.argv[2], Path(sys.argv[3])
    seq = read_scene(Path("data") / scene)["sequences"][0]["name"]
    cfg = {**load_config("config/config.yaml")["cues"]["flows"], **CHANGES[variant]}
    if variant == "lk_pyramid":
        cue_flow.refine_lk = functools.partial(cue_flow.refine_lk, levels=2, max_change=6.0)
    flows = out / f"{scene}_{variant}"
    run_flows(f"data/{scene}", seq, f"results/{scene}/{seq}/masks", flows, cfg,
              template_npz=f"results/{scene}/template.npz", threads=1, progress=False)
    reader = flow_targets.CueReader
    flow_targets.CueReader = lambda cams, masks, normals, fl, *a, **k: reader(
        cams, masks, normals, flows if str(fl).startswith("results") else fl, *a, **k)
    print(flow_targets.check(scene)[1].replace("| pipeline |", f"| {variant} |"))
