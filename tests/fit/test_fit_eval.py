"""Stage fit_eval: fits of the tiny skirt scene (tests/fit/conftest.py) measured against its ground truth."""
from __future__ import annotations

import csv

import pytest
import torch

from anidress_core import fit
from tests.fit.conftest import ensemble

torch.set_num_threads(1)


def test_stage_fit_eval_on_a_tiny_scene(tiny_skirt, tmp_path):
    pytest.importorskip("warp")  # the fit's L_collision
    from anidress_core.stages.fit import run_fit
    from anidress_core.stages.fit_eval import FIT_METRIC_COLUMNS, run_fit_eval

    data, res = tiny_skirt
    seq = data / "walk"
    params = {"views": 3, "max_iters": 4, "max_iters_first": 6}
    args = (data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows")
    ens = {"sim_ensemble_npz": ensemble(res)}
    run_fit(*args, seq / "normals", params, tmp_path / "full.npz", progress=False, **ens)
    run_fit(*args, None, params, tmp_path / "no_flow.npz", ablation="paper_no_flow", progress=False, **ens)
    fits = {"full": tmp_path / "full.npz", "no_flow": tmp_path / "no_flow.npz"}
    summ = run_fit_eval(data, "walk", res / "rig.npz", fits, tmp_path / "fit_metrics.csv", samples=500)
    with open(tmp_path / "fit_metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == FIT_METRIC_COLUMNS and len(rows) == 8
    assert all(f"loss_{k}" in FIT_METRIC_COLUMNS for k in fit.TERM_NAMES)
    assert summ["correspondence_max_m"] < 0.01
    for r in rows:
        assert 0 <= float(r["vertex_rmse_m"]) < 0.1 and 0 < float(r["normal_consistency"]) <= 1
        assert float(r["rig_floor_rmse_m"]) < 0.05
        assert 0 <= float(r["rig_floor_chamfer_m"]) < 0.1
        assert 0 <= float(r["reprojection_px"]) < 50 and 0 <= float(r["rig_floor_reprojection_px"]) < 50
    # the floor's Chamfer (with its sampling bias) and reprojection error are one reference per frame,
    # the same for every method
    for col in ("rig_floor_chamfer_m", "rig_floor_reprojection_px"):
        per_frame = {}
        for r in rows:
            per_frame.setdefault(r["frame"], set()).add(r[col])
        assert all(len(v) == 1 for v in per_frame.values())
