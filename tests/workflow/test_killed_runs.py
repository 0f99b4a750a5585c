"""Killed runs: a run interrupted during `simulate` or `train_field` and run again ends with the same
outputs as the uninterrupted tiny run (conftest.py), bit for bit.

What happens (each case below checks it):

* SIGTERM to the run (Snakemake and its job, as Ctrl-C or a batch system's cancel): the job dies,
  Snakemake marks it failed, removes its output and releases the lock; the same command again reruns
  the job. An interrupted training resumes from ``field.pt.ckpt`` (its last checkpoint, every
  field/train/checkpoint_every steps) and ends with the same field.
* SIGKILL of the job (the python process running the rule's script, e.g. the kernel's OOM killer):
  the same, Snakemake notices the failure.
* SIGKILL of Snakemake itself: its job runs on to its end (orphaned), but Snakemake leaves its lock
  and the output marked incomplete; the same command is refused (IncompleteFilesException, then with
  ``--rerun-incomplete`` LockException) until ``snakemake --unlock`` and then the command with
  ``--rerun-incomplete`` (which reruns the job).

Each case works on a copy of the tiny run and forces one job (``-f TARGET``, ``--cores 1``).
"""
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.workflow.tiny import RERUN_TRIGGERS, copy_run, snakemake, snakemake_cmd

SIM = "results/tinyskirt/sim/seq-walk.npz"
SIM_LOG = "logs/tinyskirt/simulate/seq-walk.log"
FIELD = "results/tinyskirt/walk/full/field.pt"
FIELD_LOG = "logs/tinyskirt/walk/full/train.log"
TIMING = ("wall_s", "cpu_s", "stage_wall_s")


def _job_pid(workdir: Path, script: str) -> int | None:
    """pid of the python process running rule script ``script`` (``.snakemake/scripts/tmp*.<script>``) in workdir."""
    marker = str(workdir / ".snakemake" / "scripts").encode()
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            argv = Path(f"/proc/{d}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(a.startswith(marker) and a.endswith(b"." + script.encode()) for a in argv):
            return int(d)
    return None


def _wait(cond, timeout: float, what: str):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = cond()
        if v:
            return v
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _interrupted_run(workdir: Path, target: str, script: str, ready, victim: str, sig: int) -> tuple[int, int]:
    """Start ``snakemake -f target`` in its own process group, wait for the job's script process and
    ``ready()``, then send ``sig`` to ``victim`` (run: the whole process group; job: the script process;
    snakemake: Snakemake alone). Returns (Snakemake's exit status, job pid)."""
    log = open(workdir / "interrupted.log", "w")
    proc = subprocess.Popen(snakemake_cmd(workdir, target, "-f", *RERUN_TRIGGERS, cores=1), stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        pid = _wait(lambda: _job_pid(workdir, script), 300, f"the {script} job")
        _wait(ready, 300, f"the {script} job to be under way")
        if victim == "run":
            os.killpg(proc.pid, sig)
        elif victim == "job":
            os.kill(pid, sig)
        else:
            os.kill(proc.pid, sig)
        rc = proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        log.close()
    return rc, pid


def _sim_arrays(path: Path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files if k != "__anidress_header__"}


def _same_sim(a: Path, b: Path):
    x, y = _sim_arrays(a), _sim_arrays(b)
    assert sorted(x) == sorted(y)
    for k in x:
        assert np.array_equal(x[k], y[k]), f"{b}: {k} differs from the uninterrupted run"


def _same_field(a: Path, b: Path):
    x, y = torch.load(a, weights_only=False), torch.load(b, weights_only=False)
    sx, sy = x.pop("state_dict"), y.pop("state_dict")
    assert sorted(sx) == sorted(sy)
    for k in sx:
        assert torch.equal(sx[k], sy[k]), f"{b}: {k} differs from the uninterrupted run"
    strip = lambda d: {k: ([{kk: vv for kk, vv in h.items() if kk not in TIMING} for h in v] if k == "history" else v)
                       for k, v in d.items() if k not in TIMING}
    assert strip(x) == strip(y)


def _log_has(workdir: Path, log: str, text: str):
    return lambda: (workdir / log).is_file() and text in (workdir / log).read_text()


CASES = [  # (target, victim, signal): both ways to stop the run on the training, the kill of the job on simulate too
    ("simulate", "job", signal.SIGKILL),
    ("train_field", "run", signal.SIGTERM),
    ("train_field", "job", signal.SIGKILL),
]


@pytest.mark.parametrize("rule, victim, sig", CASES, ids=[f"{r}-{v}-{s.name}" for r, v, s in CASES])
def test_interrupted_job_reruns_to_the_same_output(tiny_run, tmp_path, rule, victim, sig):
    wd = copy_run(tiny_run, tmp_path / "run")
    if rule == "simulate":
        target, script, log = SIM, "simulate.py", SIM_LOG
        ready = _log_has(wd, log, "simulating seq-walk")  # logged just before the solver starts
    else:
        target, script, log = FIELD, "train.py", FIELD_LOG
        ready = lambda: (wd / (FIELD + ".ckpt")).is_file()  # the checkpoint of step 10 of 20
    rc, pid = _interrupted_run(wd, target, script, ready, victim, sig)
    # 1. the run failed, the job is gone, nothing half-made is left as the output, no lock
    assert rc != 0, (wd / "interrupted.log").read_text()[-3000:]
    _wait(lambda: not Path(f"/proc/{pid}").exists(), 30, "the job process to end")
    assert not (wd / target).exists()
    assert not list((wd / ".snakemake" / "locks").glob("*"))
    if rule == "train_field":
        assert (wd / (FIELD + ".ckpt")).is_file()
    # 2. the same command again: the job reruns (a training resumes) to the uninterrupted output
    res = snakemake(wd, target, *RERUN_TRIGGERS, cores=1)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    if rule == "simulate":
        _same_sim(tiny_run / SIM, wd / SIM)
    else:
        assert "resuming from results/tinyskirt/walk/full/field.pt.ckpt at step 10" in (wd / log).read_text()
        assert not (wd / (FIELD + ".ckpt")).exists()
        _same_field(tiny_run / FIELD, wd / FIELD)


def test_killed_snakemake_needs_unlock_and_rerun_incomplete(tiny_run, tmp_path):
    wd = copy_run(tiny_run, tmp_path / "run")
    rc, pid = _interrupted_run(wd, FIELD, "train.py", lambda: (wd / (FIELD + ".ckpt")).is_file(), "snakemake",
                               signal.SIGKILL)
    assert rc == -signal.SIGKILL
    # 1. the job runs on to its end without Snakemake; the lock and the incomplete mark stay
    _wait(lambda: not Path(f"/proc/{pid}").exists(), 120, "the orphaned job to end")
    assert (wd / FIELD).is_file() and list((wd / ".snakemake" / "locks").glob("*"))
    # 2. the same command is refused: the output is incomplete; with --rerun-incomplete: the lock
    res = snakemake(wd, FIELD, *RERUN_TRIGGERS, cores=1)
    assert res.returncode != 0 and "IncompleteFilesException" in res.stdout + res.stderr
    res = snakemake(wd, FIELD, "--rerun-incomplete", *RERUN_TRIGGERS, cores=1)
    assert res.returncode != 0 and "LockException" in res.stdout + res.stderr
    # 3. --unlock, then --rerun-incomplete trains again, to the uninterrupted field
    assert snakemake(wd, "--unlock").returncode == 0
    res = snakemake(wd, FIELD, "--rerun-incomplete", *RERUN_TRIGGERS, cores=1)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert not (wd / (FIELD + ".ckpt")).exists()
    _same_field(tiny_run / FIELD, wd / FIELD)
