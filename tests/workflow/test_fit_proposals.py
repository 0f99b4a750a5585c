"""Rule fit with the proposals on (fit/proposal_every > 0): the simulated body motions of the rig's
sequences become the rule's inputs and reach the stage as its database (stages.fit.proposal_database)."""
import copy

import yaml

from anidress_core.io.garment_poses import load_garment_poses
from tests.workflow.tiny import RERUN_TRIGGERS, TINY, copy_run, planned_jobs, snakemake


def test_proposals_take_the_motions_and_run_in_the_workflow(tiny_run, tmp_path):
    wd = copy_run(tiny_run, tmp_path / "run")
    cfg = copy.deepcopy(TINY)
    cfg["fit"]["proposal_every"] = 2
    jobs = planned_jobs(wd, cfg, RERUN_TRIGGERS)
    assert jobs.get("fit") == 1 and "motions" not in jobs and "simulate" not in jobs, jobs
    (wd / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    target = "results/tinyskirt/walk/garment_poses.npz"
    res = snakemake(wd, target, "--forcerun", "fit", cores=1)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    _, header = load_garment_poses(wd / target)
    assert header["meta"]["proposal_database"], header["meta"]
    notes = header["meta"]["frame_notes"]
    kept = {t: n["proposal"]["kept"] for t, n in notes.items() if "proposal" in n}
    assert set(kept) == {"0", "2"}, notes  # keyframes 0 and 2 of 4 frames
    dry = snakemake(wd, target, "-n", *RERUN_TRIGGERS)
    assert dry.returncode == 0 and "Nothing to be done" in dry.stdout + dry.stderr


def test_nearest_baseline_runs_as_an_ablation(tiny_run, tmp_path):
    """Variant `nearest` (the database pose with the lowest loss, no fitting) through rule
    fit_ablation: the motions become its inputs; every frame records the candidate it kept."""
    wd = copy_run(tiny_run, tmp_path / "run")
    target = "results/tinyskirt/walk/fit_ablations/nearest/garment_poses.npz"
    res = snakemake(wd, target, cores=1)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    a, header = load_garment_poses(wd / target)
    notes = header["meta"]["frame_notes"]
    assert len(notes) == len(a["transforms"]) and all("nearest" in n for n in notes.values()), notes
    assert (a["iterations"] == 0).all()
