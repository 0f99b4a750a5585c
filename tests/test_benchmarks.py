"""The maintained benchmark scripts (benchmarks/, run as ``python -m benchmarks.<name>``) import
and parse their arguments: a change of the package's API that breaks one shows here, not at its
next (long) run. The runs themselves are not tests."""
from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: every script with a command line: the per-stage benchmarks, the collectors of pipeline runs and the suite
#: generator (bench_sim_newton is bench_sim's reference, called from it)
SCRIPTS = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py")
                 if p.stem.startswith(("bench_", "collect_")) and p.stem != "bench_sim_newton") + ["fit_suite"]


def test_every_stage_has_a_benchmark():
    stages = {"raster", "sim", "rig", "cues", "fit", "field", "validate"}
    assert {f"bench_{s}" for s in stages} <= set(SCRIPTS)


@pytest.mark.parametrize("name", SCRIPTS)
def test_benchmark_parses_help(name, monkeypatch, capsys):
    mod = importlib.import_module(f"benchmarks.{name}")
    monkeypatch.setattr("sys.argv", [f"benchmarks.{name}", "--help"])
    with pytest.raises(SystemExit) as exit_:
        mod.main()
    assert exit_.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_sim_reference_imports():
    mod = importlib.import_module("benchmarks.bench_sim_newton")
    assert callable(mod.run_newton)


def test_scaling_quick(tmp_path):
    """``bench_scaling --quick`` runs every stage at tiny sizes and writes a csv with finite, positive
    per-unit costs and peak memory, the fitted exponents and a paper-scale estimate per stage."""
    import csv
    import math
    import os
    import subprocess
    import sys

    from benchmarks.bench_scaling import STAGES

    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-m", "benchmarks.bench_scaling", "--quick", "--out", str(tmp_path)],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    rows = list(csv.DictReader(open(tmp_path / "scaling.csv")))
    measured = [r for r in rows if r["kind"] == "measured"]
    assert {r["stage"] for r in measured} == set(STAGES)
    for r in measured:
        for col in ("cpu_s_per_unit", "peak_rss_mb", "size"):
            assert math.isfinite(float(r[col])) and float(r[col]) > 0, (r["stage"], r["axis"], col, r[col])
        assert math.isfinite(float(r["exponent_cpu"])), (r["stage"], r["axis"])
    paper = {r["stage"]: r for r in rows if r["kind"] == "paper_estimate"}
    assert set(paper) == set(STAGES)
    for r in paper.values():
        for col in ("paper_total_cpu_s_low", "paper_total_cpu_s_high", "paper_rss_mb_high"):
            assert math.isfinite(float(r[col])) and float(r[col]) > 0, (r["stage"], col, r[col])
    md = (tmp_path / "scaling.md").read_text()
    assert "CUDA" in md and "## Growth exponents" in md
    assert not (tmp_path / "scaling_work").exists()  # the quick run's scratch folder is removed


def test_cuda_quick(tmp_path):
    """``bench_cuda --quick`` (CPU only, tiny sizes) measures every stage it times on a GPU and writes
    cuda.md / cuda.csv with finite, positive per-unit seconds; ``--report`` rewrites them from its raw json."""
    import csv
    import math
    import os
    import subprocess
    import sys

    from benchmarks.bench_cuda import STAGES

    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    work, out = tmp_path / "work", tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "benchmarks.bench_cuda", "--quick", "--workdir", str(work), "--out",
                          str(out)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    rows = list(csv.DictReader(open(out / "cuda.csv")))
    assert {r["stage"] for r in rows} == set(STAGES) - {"simulate_launches"}  # that one is CUDA only
    for r in rows:
        assert math.isfinite(float(r["cpu_s_per_unit"])) and float(r["cpu_s_per_unit"]) > 0, r
        assert r["cuda_s_per_unit"] == "nan"  # no CUDA run in quick mode: nothing is filled in
    first = (out / "cuda.md").read_text()
    (out / "cuda.md").unlink()
    rep = subprocess.run([sys.executable, "-m", "benchmarks.bench_cuda", "--report", str(work / "raw.json"), "--out",
                          str(out)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert rep.returncode == 0, rep.stderr[-2000:]
    assert (out / "cuda.md").read_text() == first


def test_fit_suite_novel_pose_adds_a_held_out_sequence_and_changes_nothing_else():
    from benchmarks.fit_suite import draw, targets

    plain, novel = draw(5, seed=31), draw(5, seed=31, novel_pose=True)
    for name, sc in novel.items():
        train, held = sc["sequences"]
        assert held["role"] == "novel_pose" and held["motion"] != train["motion"]
        assert {**sc, "sequences": [train]} == plain[name]
    out = targets(novel)
    assert f"results/{name}/{held['name']}/fit_metrics.csv" in out
    assert f"results/{name}/{train['name']}/body_only/metrics_summary.json" in out
    assert f"results/{name}/sim_ensemble/seq-{train['name']}.npz" in out  # L_prior's reference


def test_fit_suite_draws_the_truths_cloth_apart_from_the_solvers_and_the_schema_takes_it():
    import dataclasses

    import yaml

    from anidress_core.config import default_schema_path, validate_config
    from anidress_core.sim import ClothParams
    from benchmarks.fit_suite import TRUTH_CLOTH, draw

    scenes = draw(10, seed=31)
    solver = ClothParams()
    for key, (lo, hi) in TRUTH_CLOTH.items():
        values = [sc["garment"]["cloth"][key] for sc in scenes.values()]
        assert all(lo <= v <= hi for v in values), (key, values)
        assert len(set(values)) > 5 and any(v != getattr(solver, key) for v in values)  # drawn, not the solver's
    assert all(isinstance(sc["garment"]["cloth"]["settle_frames"], int) for sc in scenes.values())
    assert draw(10, seed=31) == scenes and draw(10, seed=32) != scenes  # deterministic in the seed
    schema = yaml.safe_load(default_schema_path().read_text())
    filled = validate_config({"run_scenes": list(scenes), "scenes": scenes}, schema)
    cloth = filled["scenes"]["suite_00"]["garment"]["cloth"]
    assert {k: cloth[k] for k in TRUTH_CLOTH} == {k: scenes["suite_00"]["garment"]["cloth"][k] for k in TRUTH_CLOTH}
    assert set(TRUTH_CLOTH) <= {f.name for f in dataclasses.fields(ClothParams)}


def _field_run(root: Path, scene: str, train: str, novel: str, psnr: dict) -> None:
    for seq, rmse in ((train, [2.0] * 10 + [3.0] * 10), (novel, [4.0] * 20)):
        d = root / "results" / scene / seq
        d.mkdir(parents=True)
        rows = ["method,frame,vertex_rmse_m,rig_floor_rmse_m"]
        rows += [f"pipeline,{i},{r},1.0" for i, r in enumerate(rmse)] + ["sim,0,9.0,1.0"]
        (d / "fit_metrics.csv").write_text("\n".join(rows) + "\n")
    for v, p in psnr.items():
        d = root / "results" / scene / train / v
        d.mkdir(parents=True)
        (d / "metrics_summary.json").write_text(json.dumps({"metrics": [
            {"kind": k, "scored": 4, "psnr_db": p + dk, "ssim": 0.9, "iou": 0.95 if v == "full" else 0.93}
            for k, dk in (("novel_pose", 0.0), ("novel_view", 1.0))]}))
        t = root / "benchmarks" / "runs" / scene / train / v
        t.mkdir(parents=True)
        (t / "train.tsv").write_text("s\tcpu_time\n12.5\t10.0\n")


def test_collect_field_suite_reads_a_run(tmp_path):
    from benchmarks.collect_field_suite import collect

    suite = {"scenes": {"a": {"kind": "skirt", "garment": {"texture": "plain", "cloth": {"bend_stiffness": 1e-3}},
                              "sequences": [{"name": "walk", "role": "train"}, {"name": "run", "role": "novel_pose"}]}}}
    _field_run(tmp_path, "a", "walk", "run", {"full": 26.0, "body_only": 25.5})
    (row,) = collect(suite, tmp_path)
    assert row["fit_train_ratio"] == pytest.approx(2.5) and row["fit_train_drift"] == pytest.approx(1.5)
    assert row["fit_novel_ratio"] == pytest.approx(4.0) and row["fit_train_frames"] == 20
    assert row["margin_novel_pose_psnr_db"] == pytest.approx(0.5)
    assert row["margin_novel_pose_iou"] == pytest.approx(0.02)
    assert row["full_novel_view_psnr_db"] == pytest.approx(27.0) and row["body_only_train_s"] == 12.5
    suite["scenes"]["a"]["sequences"].pop()
    with pytest.raises(SystemExit, match="a: the suite's scene has no novel_pose"):
        collect(suite, tmp_path)


def test_fit_reuse_fills_a_setting_added_since_only_at_its_legacy_value():
    """bench_fit --reuse: a stored fit without L_stretch (made before it existed) stands for a variant that has
    it off (its legacy 0), never for one that has it at the pipeline's weight."""
    import dataclasses

    from anidress_core.fit import FitConfig
    from benchmarks.bench_fit import with_new_settings

    def stored_before(cfg):  # the settings as a fit recorded them before fit/weights/stretch existed
        d = dataclasses.asdict(cfg)
        del d["weights"]["stretch"]
        return d

    for name, off in (("pipeline_no_stretch", True), ("paper", True), ("pipeline", False)):
        used = dataclasses.asdict(FitConfig.from_config({}, name))
        assert (with_new_settings(stored_before(FitConfig.from_config({}, name)), used) == used) is off, name


def test_fit_reuse_needs_the_same_ensemble_members(tmp_path, monkeypatch):
    """bench_fit --reuse: a stored fit that followed the stiffness ensemble stands for the variant only while the
    ensemble file has the same members (a change of simulate/ensemble_* remakes the file, not the fit's settings)."""
    import dataclasses

    import numpy as np

    import benchmarks.bench_fit as bf
    from anidress_core.fit import FitConfig
    from anidress_core.fit.ensemble import ensemble_note
    from anidress_core.io.sim import SimSequence, write_sim

    def members(settles):
        return {"members": [{"bend_stiffness": k, "settle_frames": n} for k in (1e-4, 1e-3) for n in settles]}

    ens = tmp_path / "seq-walk.npz"
    write_sim(ens, SimSequence(frames=np.zeros((2, 3, 3), np.float32), meta=members([30])))
    cfg = dataclasses.asdict(FitConfig.from_config({}, "pipeline"))
    stored = {"loss": "pipeline", "params": {}, "config": cfg, "starts": None,
              "followed_simulation": f"{ens}: {ensemble_note(members([30]))}, rig transforms fitted to it"}
    fit = tmp_path / "garment_poses.npz"
    fit.write_bytes(b"")
    monkeypatch.setattr(bf, "load_garment_poses", lambda path: (None, {"meta": stored}))
    assert bf.reusable(fit, "pipeline", {}, str(ens))
    write_sim(ens, SimSequence(frames=np.zeros((2, 3, 3), np.float32), meta=members([20, 40])))
    assert not bf.reusable(fit, "pipeline", {}, str(ens))
    assert not bf.reusable(fit, "pipeline", {}, None)


def test_fit_reuse_ignores_the_settings_that_left_the_fit_at_their_off_values(tmp_path, monkeypatch):
    """bench_fit --reuse: a fit stored before issue 48 records the settings that left the fit since; at the values
    that did what the fit does now (proposals and the backward pass off, a uniform prior, the plain ensemble mean)
    it stands for the variant, with one of them on it does not."""
    import dataclasses

    import benchmarks.bench_fit as bf
    from anidress_core.fit import FitConfig

    old = {"proposal_every": 0, "proposal_nearest": 8, "proposal_offsets": 2, "proposal_refine": 2,
           "proposal_velocity_weight": 0.05, "backward": False, "prior_information": "uniform",
           "prior_member_temperature": None, "prior_member_window": 5}
    cfg = {**dataclasses.asdict(FitConfig.from_config({}, "pipeline_no_sim_prior")), **old}
    stored = {"loss": "pipeline_no_sim_prior", "params": dict(old), "starts": None, "config": cfg}
    monkeypatch.setattr(bf, "load_garment_poses", lambda path: (None, {"meta": stored}))
    fit = tmp_path / "garment_poses.npz"
    fit.write_bytes(b"")
    assert bf.reusable(fit, "pipeline_no_sim_prior", {})
    for k, on in (("proposal_every", 5), ("backward", True), ("prior_information", "anchor"),
                  ("prior_member_temperature", 1.0)):
        stored.update(params=dict(old, **{k: on}), config=dict(cfg, **{k: on}))
        assert not bf.reusable(fit, "pipeline_no_sim_prior", {}), k
        stored.update(params=dict(old), config=dict(cfg, **{k: on}))
        assert not bf.reusable(fit, "pipeline_no_sim_prior", {}), k


def test_fit_reuse_refuses_a_fit_older_than_its_scene(tmp_path, monkeypatch):
    """bench_fit --reuse: a scene made again (other ground-truth cloth, new cues or rig) outdates its stored fits,
    as Snakemake would; the ensemble outdates only the fits that followed it."""
    import dataclasses
    import os

    import benchmarks.bench_fit as bf
    from anidress_core.fit import FitConfig

    stored = {"loss": "pipeline_no_sim_prior", "params": {}, "starts": None,
              "config": dataclasses.asdict(FitConfig.from_config({}, "pipeline_no_sim_prior"))}
    monkeypatch.setattr(bf, "load_garment_poses", lambda path: (None, {"meta": stored}))
    data, masks, ens, fit = (tmp_path / n for n in ("data", "masks", "seq-walk.npz", "garment_poses.npz"))
    data.mkdir(), masks.mkdir(), ens.write_bytes(b""), fit.write_bytes(b"")
    for p, t in ((data, 100), (masks, 100), (ens, 300), (fit, 200)):
        os.utime(p, ns=(t * 10**9, t * 10**9))
    inputs = (str(data), str(masks), None, str(tmp_path / "absent"))
    assert bf.reusable(fit, "pipeline_no_sim_prior", {}, str(ens), inputs)  # a newer ensemble it did not read
    os.utime(masks, ns=(250 * 10**9, 250 * 10**9))
    assert not bf.reusable(fit, "pipeline_no_sim_prior", {}, str(ens), inputs)


def test_collect_pipeline_names_the_rule_of_each_benchmark_file():
    """benchmarks/runs/<scene>/...: the rule of a benchmark file from its path (the ensemble's jobs under their rule,
    not under their sequence's name)."""
    from pathlib import Path

    from benchmarks.collect_pipeline import rule_of

    assert rule_of(Path("simulate/seq-walk.tsv")) == ("simulate", "seq-walk")
    assert rule_of(Path("simulate_ensemble/seq-walk.tsv")) == ("simulate_ensemble", "seq-walk")
    assert rule_of(Path("rig.tsv")) == ("rig", "")
    assert rule_of(Path("walk/full/train.tsv")) == ("train_field", "walk/full/train")
