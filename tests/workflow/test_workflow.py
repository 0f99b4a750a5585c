"""End to end: the Snakemake workflow on a tiny scene, then a no-op second run."""
import numpy as np
import yaml

from tests.workflow.tiny import TINY, planned_jobs, snakemake as _snakemake

# the fixture tiny_run (conftest.py): TINY built once per session, shared with test_rerun_sets and test_killed_runs


def test_tiny_scene_layout(tiny_run):
    root = tiny_run / "data" / "tiny"
    scene = yaml.safe_load((root / "scene.yaml").read_text())
    assert len(scene["cameras"]["train"]) == 8 and len(scene["cameras"]["test"]) == 4
    cams = scene["cameras"]["train"] + scene["cameras"]["test"]
    for seq in ("walk", "jump"):
        s = root / seq
        assert (s / "intri.yml").is_file() and (s / "extri.yml").is_file()
        for cam in cams:
            assert sorted(p.name for p in (s / "images" / cam).iterdir()) == ["000000.png", "000001.png", "000002.png"]
            assert len(list((s / "gt" / "masks" / cam).iterdir())) == 3
            assert len(list((s / "gt" / "normals" / cam).iterdir())) == 3
            assert sorted(p.name for p in (s / "gt" / "flows" / cam).iterdir()) == ["000001.exr", "000002.exr"]
            assert (s / "backgrounds" / f"{cam}.png").is_file()
        assert len(list((s / "smpl").iterdir())) == 3
        meshes = np.load(s / "gt" / "meshes.npz")
        assert meshes["body_vertices"].shape[0] == 3
    assert (tiny_run / "logs" / "tiny" / "synth.log").is_file()
    # nothing half-written is left beside the scenes
    assert sorted(p.name for p in (tiny_run / "data").iterdir()) == ["tiny", "tinyskirt"]
    # a tight-clothed scene skips the garment stages (DESIGN.md §6)
    tight = tiny_run / "results" / "tiny"
    assert not [p for p in ("template.npz", "sim", "rig.npz", "walk/garment_poses.npz", "walk/flows")
                if (tight / p).exists()]


def test_garment_scene_template_and_simulations(tiny_run):
    root = tiny_run / "data" / "tinyskirt"
    scene = yaml.safe_load((root / "scene.yaml").read_text())
    assert scene["garment_template"] == "garment/template.obj" and (root / "garment" / "template.obj").is_file()
    labels = set()
    from anidress_core.io.files import read_exr, read_mask

    for cam in scene["cameras"]["train"]:
        labels |= set(np.unique(read_mask(root / "walk" / "gt" / "masks" / cam / "000003.png")).tolist())
        n = read_exr(root / "walk" / "normals" / cam / "000003.exr")  # degraded "predicted" normals
        assert np.isfinite(n).all()
    assert labels == {0, 1, 2}
    meshes = np.load(root / "walk" / "gt" / "meshes.npz")
    assert meshes["garment_vertices"].shape[:2] == (4, 600)
    res = tiny_run / "results" / "tinyskirt"
    tpl = np.load(res / "template.npz")
    assert tpl["verts"].shape == (600, 3) and tpl["band"].any()
    for motion, frames in (("seq-walk", 4), ("lib-sway", 5)):
        sim = np.load(res / "sim" / f"{motion}.npz")
        assert sim["frames"].shape == (frames, 600, 3) and np.isfinite(sim["frames"]).all()
        assert sim["nan_count"].sum() == 0
        assert (tiny_run / "logs" / "tinyskirt" / "simulate" / f"{motion}.log").is_file()


def test_every_stage_ran_to_the_report(tiny_run):
    import csv
    import json

    res = tiny_run / "results"
    assert (res / "tiny" / "scene_check.json").is_file() and (res / "tinyskirt" / "scene_check.json").is_file()
    rig = np.load(res / "tinyskirt" / "rig.npz")
    assert rig["weights"].shape == (600, 6) and sorted(rig["sequences"].tolist()) == ["lib-sway", "seq-walk"]
    assert (res / "tinyskirt" / "walk" / "flows").is_dir() and (res / "tinyskirt" / "walk" / "normals.json").is_file()
    poses = np.load(res / "tinyskirt" / "walk" / "garment_poses.npz")
    assert poses["transforms"].shape[:2] == (4, 6) and np.isfinite(poses["transforms"]).all()
    with open(res / "tinyskirt" / "walk" / "fit_metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["method"] for r in rows} == {"pipeline"} and all(np.isfinite(float(r["vertex_rmse_m"])) for r in rows)
    # the tight scene trains one field (body joints only); the garment scene both variants
    for scene, variants in (("tiny", ["full"]), ("tinyskirt", ["full", "body_only"])):
        for v in variants:
            summary = json.loads((res / scene / "walk" / v / "metrics_summary.json").read_text())
            assert summary, f"{scene}/{v}: empty metrics summary"
    assert any((res / "tinyskirt" / "walk" / "full" / "renders" / "library" / "lib-sway").iterdir())
    html = (res / "report.html").read_text()
    assert "Scene tiny (tight)" in html and "Scene tinyskirt (skirt)" in html


def test_second_run_has_nothing_to_do(tiny_run):
    res = _snakemake(tiny_run, "-n")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "Nothing to be done" in res.stdout + res.stderr


def _planned_jobs(tiny_run, cfg) -> dict:
    """Job counts of a dry run with a modified config (Snakemake's default rerun triggers): {rule: count}."""
    return planned_jobs(tiny_run, cfg)


def test_param_change_reruns_exactly_that_stage(tiny_run):
    import copy

    cfg = copy.deepcopy(TINY)
    cfg["scenes"]["tiny"]["render"]["noise_std"] = 0.01  # one scene's data: that scene downstream, not the other
    assert _planned_jobs(tiny_run, cfg) == {
        "synth": 1, "validate_scene": 1, "masks": 1, "train_field": 1, "render_novel_view": 1,
        "render_novel_pose": 1, "evaluate_field": 1, "report": 1, "all": 1}
    cfg = copy.deepcopy(TINY)
    cfg["simulate"]["cloth"]["damping"] = 0.6  # every simulation and what reads the rig; not the data, cues
    assert _planned_jobs(tiny_run, cfg) == {          # or the body-only field
        "simulate": 2, "simulate_ensemble": 1, "rig": 1, "fit": 1, "fit_eval": 1, "train_field": 1,
        "render_novel_view": 1, "render_library": 1, "evaluate_field": 1, "report": 1, "all": 1}
    cfg = copy.deepcopy(TINY)
    cfg["rig"]["bones"] = 5
    assert _planned_jobs(tiny_run, cfg) == {
        "rig": 1, "fit": 1, "fit_eval": 1, "train_field": 1, "render_novel_view": 1, "render_library": 1,
        "evaluate_field": 1, "report": 1, "all": 1}
    cfg = copy.deepcopy(TINY)
    cfg["field"]["render"]["library"] = ["twirl"]  # not simulated: refused with a message, nothing planned
    (tiny_run / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    try:
        res = _snakemake(tiny_run, "-n")
    finally:
        (tiny_run / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    assert res.returncode != 0 and "does not simulate" in res.stdout + res.stderr
