"""Rule fit_ablation with the nearest baseline: the simulated body motions of the rig's sequences are the
rule's inputs and reach the stage as its database (stages.fit.simulation_database)."""
from anidress_core.io.garment_poses import load_garment_poses
from tests.workflow.tiny import copy_run, snakemake


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
    assert header["meta"]["simulation_database"], header["meta"]
