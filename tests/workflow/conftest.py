"""The tiny pipeline run shared by the workflow tests: built once per test session (a real build, the
baseline that dry runs and interrupted runs are compared against)."""
import yaml
import pytest

from tests.workflow.tiny import TINY, snakemake


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """The tiny two-scene config built from scratch once (test_workflow, test_rerun_sets, test_killed_runs)."""
    wd = tmp_path_factory.mktemp("wf")
    (wd / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    # two jobs side by side on the 2 cores of `make test`, each on one thread (the two scenes' synth, the fields'
    # renders), not one 2-thread job (synth, masks, flows, rig, fit) alone; the jobs the tests rerun with --cores 1
    # (simulate, train_field, fit) run on one thread there too
    res = snakemake(wd, "--max-threads", "1")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return wd
