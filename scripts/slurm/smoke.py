"""Helpers of scripts/slurm-smoke.sh: node size, smoke profile, and the checks + report.

    python scripts/slurm/smoke.py node PROFILE.yaml
        -> "CPUS MEM_MB": the single node's size, large enough for every job of the profile
    python scripts/slurm/smoke.py profile PROFILE.yaml OUT_DIR
        -> OUT_DIR/config.yaml: the profile plus the few smoke settings in SMOKE_GLOBALS / SMOKE_RESOURCES
    python scripts/slurm/smoke.py check --work DIR --profile OUT_DIR/config.yaml ... --report benchmarks/slurm
        -> checks the outputs of the tiny scene and every SLURM job record (state, and the
           resources SLURM granted against the profile's runtime / mem_mb / cpus_per_task / gpu),
           writes REPORT.md and REPORT.csv, exits 1 when a check fails.

Tooling for the smoke test only (not part of the anidress_core package).
"""
from __future__ import annotations

import argparse
import copy
import csv
import datetime as dt
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

# Settings the smoke run adds to profiles/slurm (everything else is used as it is):
SMOKE_GLOBALS = {
    # no slurmdbd on the smoke cluster, so no sacct: poll with squeue (MinJobAge=3600 keeps
    # finished jobs visible)
    "slurm-status-command": "squeue",
    # first status poll after 5 s instead of 40 s (the tiny jobs take seconds to a minute)
    "slurm-init-seconds-before-status-checks": 5,
    # keep every job's SLURM log for inspection
    "slurm-keep-successful-logs": True,
    # a failure must fail the smoke test, not be hidden by a retry
    "retries": 0,
}
# One rule asks for a GPU so that the mapping gpu -> `sbatch --gpus=N` is exercised. The node
# has one fake GPU GRES (no device: torch and Warp see no CUDA and the rig runs on the CPU);
# the rig is a single job at the end of the DAG, so waiting for the one GPU delays nothing.
SMOKE_RESOURCES = {"rig": {"gpu": 1}}

RES_KEYS = ("runtime", "mem_mb", "cpus_per_task", "gpu")


# ----------------------------------------------------------------------------- profile
def load_profile(path: str | os.PathLike) -> dict:
    with open(path) as fh:
        prof = yaml.safe_load(fh)
    if not isinstance(prof, dict):
        raise SystemExit(f"{path}: not a YAML mapping")
    return prof


def expected_resources(prof: dict, rule: str) -> dict:
    """{runtime, mem_mb, cpus_per_task, gpu} the profile asks for ``rule`` (set-resources, else default-resources)."""
    default = prof.get("default-resources") or {}
    per_rule = (prof.get("set-resources") or {}).get(rule) or {}
    out = {}
    for k in RES_KEYS:
        v = per_rule.get(k, default.get(k))
        out[k] = int(v) if v is not None else (0 if k == "gpu" else None)
    return out


def node_size(prof: dict) -> tuple[int, int]:
    """CPUs and MB of the single node: the machine's, or the largest request of the profile if larger."""
    entries = [prof.get("default-resources") or {}] + list((prof.get("set-resources") or {}).values())
    cpus = max([int(e.get("cpus_per_task", 1)) for e in entries] + [os.cpu_count() or 1])
    mem = max([int(e.get("mem_mb", 0)) for e in entries] + [mem_total_mb()])
    return cpus, mem


def mem_total_mb() -> int:
    with open("/proc/meminfo") as fh:
        for line in fh:
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) // 1024
    return 0


def smoke_profile(prof: dict) -> dict:
    out = copy.deepcopy(prof)
    out.update(SMOKE_GLOBALS)
    sr = out.setdefault("set-resources", {})
    for rule, res in SMOKE_RESOURCES.items():
        sr.setdefault(rule, {}).update(res)
    return out


# ----------------------------------------------------------------------------- SLURM records
def parse_scontrol(text: str) -> list[dict]:
    """``scontrol -o show job`` (one job per line, Key=Value tokens) -> list of dicts."""
    jobs = []
    for line in text.splitlines():
        if not line.strip():
            continue
        rec, last = {}, None
        for tok in line.split(" "):
            if "=" in tok and re.match(r"^[A-Za-z][\w/:]*=", tok):
                k, v = tok.split("=", 1)
                rec[k], last = v, k
            elif last is not None and tok:
                rec[last] += " " + tok
        jobs.append(rec)
    return jobs


def minutes(s: str) -> float | None:
    """SLURM time ([D-]HH:MM:SS, MM:SS) -> minutes; None for UNLIMITED."""
    if s in ("UNLIMITED", "Partition_Limit", "NONE", ""):
        return None
    days = 0
    if "-" in s:
        d, s = s.split("-", 1)
        days = int(d)
    parts = [int(p) for p in s.split(":")]
    while len(parts) < 3:
        parts.insert(0, 0)
    h, m, sec = parts
    return days * 1440 + h * 60 + m + sec / 60.0


def megabytes(s: str) -> float | None:
    m = re.match(r"^([\d.]+)([KMGT]?)$", s or "")
    if not m:
        return None
    scale = {"K": 1 / 1024, "": 1, "M": 1, "G": 1024, "T": 1024 * 1024}[m.group(2)]
    return float(m.group(1)) * scale


def gpus_of(rec: dict) -> int:
    """GPUs granted to a job, from TresPerJob (gres:gpu:N, gres/gpu=N) or TRES."""
    for key in ("TresPerJob", "TresPerNode", "TRES"):
        v = rec.get(key, "")
        m = re.search(r"gres[:/]gpu(?::[\w.]+)?[:=](\d+)", v)
        if m:
            return int(m.group(1))
    return 0


def rule_of(comment: str) -> tuple[str, str] | None:
    m = re.match(r"^rule_(.+?)(?:_wildcards_(.*))?$", comment or "")
    return (m.group(1), m.group(2) or "") if m else None


def job_counts(log_text: str) -> dict[str, int]:
    """Snakemake's "Job stats" table (rule count) from a run log."""
    counts, inside = {}, False
    for line in log_text.splitlines():
        parts = line.split()
        if parts[:2] == ["job", "count"]:
            inside, counts = True, {}
            continue
        if inside:
            if len(parts) == 2 and parts[1].isdigit():
                if parts[0] == "total":
                    break
                counts[parts[0]] = int(parts[1])
            elif parts and not set(parts[0]) <= {"-"}:
                break
    return counts


# ----------------------------------------------------------------------------- outputs
def check_outputs(work: Path, scene: str, ran: set[tuple[str, str]]) -> list[tuple[str, bool, str]]:
    """The contract of what the run's jobs ``ran`` ({(rule, wildcards)}) made for ``scene``:
    dataset (synth), template, simulations, rig, and each job's log and benchmark TSV."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    res: list[tuple[str, bool, str]] = []

    def add(name, ok, detail=""):
        res.append((name, bool(ok), detail))

    rules = {r for r, wc in ran if wc == scene or wc.startswith(scene + "_")}
    cfg = yaml.safe_load((work / "tiny.yaml").read_text())
    scfg = cfg["scenes"][scene]
    V = int(cfg["template"]["vertices"])
    data = work / "data" / scene
    sims = [("seq-" + s["name"], int(s["frames"])) for s in scfg["sequences"]]
    sims += [("lib-" + m, int(cfg["simulate"]["library_frames"])) for m in cfg["simulate"]["library"]]
    ran_sims = [(n, T) for n, T in sims if ("simulate", f"{scene}_{n}") in ran]
    if "synth" in rules:
        try:
            meta = yaml.safe_load((data / "scene.yaml").read_text())
            cams = list(meta["cameras"]["train"]) + list(meta["cameras"]["test"])
            for seq in scfg["sequences"]:
                n = int(seq["frames"])
                counts = {c: len(list((data / seq["name"] / "images" / c).glob("*.png"))) for c in cams}
                add(f"data/{scene}/{seq['name']}/images: {n} frames x {len(cams)} cameras",
                    all(v == n for v in counts.values()), f"per camera: {sorted(set(counts.values()))}")
        except Exception as e:  # noqa: BLE001 - reported as a failed check
            add(f"data/{scene}/scene.yaml", False, repr(e))
    if "template" in rules:
        try:
            from anidress_core.io.template import read_template

            t = read_template(work / "results" / scene / "template.npz")
            add(f"results/{scene}/template.npz verts ({V}, 3)", t.verts.shape == (V, 3), str(t.verts.shape))
        except Exception as e:  # noqa: BLE001
            add(f"results/{scene}/template.npz", False, repr(e))
    for name, T in ran_sims:
        try:
            from anidress_core.io.sim import read_sim

            s = read_sim(work / "results" / scene / "sim" / f"{name}.npz")
            ok = s.frames.shape == (T, V, 3) and np.isfinite(s.frames).all() and s.nan_count.sum() == 0
            add(f"results/{scene}/sim/{name}.npz frames ({T}, {V}, 3), finite", ok, str(s.frames.shape))
        except Exception as e:  # noqa: BLE001
            add(f"results/{scene}/sim/{name}.npz", False, repr(e))
    if "rig" in rules:
        try:
            from anidress_core.io.rig import read_rig

            rig = read_rig(work / "results" / scene / "rig.npz")
            T_all = sum(T for _, T in sims)
            ok = (rig.model.weights.shape[0] == V and rig.model.transforms.shape[0] == T_all
                  and sorted(rig.sequences) == sorted(n for n, _ in sims) and np.isfinite(rig.model.rmse))
            add(f"results/{scene}/rig.npz ({V} vertices, {T_all} frames, every sequence)", ok,
                f"B={rig.model.weights.shape[1]}, rmse={rig.model.rmse * 1000:.2f} mm")
        except Exception as e:  # noqa: BLE001
            add(f"results/{scene}/rig.npz", False, repr(e))
    logs, bench = [], []
    for rule in ("synth", "template", "rig"):
        if rule in rules:
            logs.append(f"logs/{scene}/{rule}.log")
            bench.append(f"benchmarks/runs/{scene}/{rule}.tsv")
    for rule, wc in sorted(ran):
        if rule in ("motions", "simulate") and wc.startswith(scene + "_"):
            logs.append(f"logs/{scene}/{rule}/{wc[len(scene) + 1:]}.log")
            if rule == "simulate":
                bench.append(f"benchmarks/runs/{scene}/simulate/{wc[len(scene) + 1:]}.tsv")
    for kind, paths in (("stage logs under logs/", logs), ("benchmark TSVs under benchmarks/runs/", bench)):
        if paths:
            missing = [p for p in paths if not (work / p).is_file()]
            add(f"{len(paths)} {kind}{scene}/", not missing, "missing: " + ", ".join(missing) if missing else "")
    other = sorted(r for r in rules if r not in ("synth", "template", "motions", "simulate", "rig"))
    if other:
        add(f"outputs of {', '.join(other)}: not checked here (only their SLURM job state above)", True)
    return res


def compare_to_reference(work: Path, ref: Path, scene: str) -> list[tuple[str, float]]:
    """Largest absolute difference of each array between the SLURM run and the local run."""
    out = []
    pairs = [(f"data/{scene}/{seq}/gt/meshes.npz", "garment_vertices") for seq in
             sorted(p.parent.parent.name for p in (work / "data" / scene).glob("*/gt/meshes.npz"))]
    pairs += [(f"results/{scene}/template.npz", "verts")]
    pairs += [(f"results/{scene}/sim/{p.name}", "frames") for p in sorted((work / "results" / scene / "sim").glob("*.npz"))]
    pairs += [(f"results/{scene}/rig.npz", "rmse")]
    for rel, key in pairs:
        try:
            a, b = np.load(work / rel)[key], np.load(ref / rel)[key]
            out.append((f"{rel}[{key}]", float(np.abs(a.astype(np.float64) - b).max()) if a.shape == b.shape else float("nan")))
        except Exception:  # noqa: BLE001 - a missing reference file shows as nan
            out.append((f"{rel}[{key}]", float("nan")))
    return out


# ----------------------------------------------------------------------------- report
def _cmd(*args: str) -> str:
    try:
        return subprocess.run(args, capture_output=True, text=True, timeout=30).stdout.strip()
    except Exception:  # noqa: BLE001
        return ""


def _pip_version(name: str) -> str:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def check(args) -> int:
    work = Path(args.work)
    prof = load_profile(args.profile)
    repo = Path(__file__).resolve().parents[2]
    log_text = (work / "snakemake-slurm.log").read_text()
    planned = job_counts(log_text)
    planned.pop("all", None)
    recs = [r for r in parse_scontrol(Path(args.scontrol).read_text()) if rule_of(r.get("Comment", ""))]

    job_rows, ok_all = [], True
    seen: dict[str, int] = {}
    for r in sorted(recs, key=lambda r: int(r["JobId"])):
        rule, wc = rule_of(r["Comment"])
        seen[rule] = seen.get(rule, 0) + 1
        exp = expected_resources(prof, rule)
        got = {"runtime": minutes(r.get("TimeLimit", "")), "mem_mb": megabytes(r.get("MinMemoryNode", "")),
               "cpus_per_task": int(r.get("CPUs/Task", "0") or 0), "gpu": gpus_of(r)}
        res_ok = all(got[k] is not None and exp[k] is not None and abs(got[k] - exp[k]) < 1e-6 for k in RES_KEYS)
        state_ok = r.get("JobState") == "COMPLETED" and r.get("ExitCode") == "0:0"
        ok_all &= res_ok and state_ok
        job_rows.append({
            "rule": rule, "wildcards": wc, "slurm_job": r["JobId"], "state": f"{r.get('JobState')} {r.get('ExitCode')}",
            "run_time": r.get("RunTime", ""),
            "runtime_min": f"{exp['runtime']} -> {r.get('TimeLimit')}",
            "mem_mb": f"{exp['mem_mb']} -> {r.get('MinMemoryNode')}",
            "cpus_per_task": f"{exp['cpus_per_task']} -> {r.get('CPUs/Task')}",
            "gpu": f"{exp['gpu']} -> {got['gpu']}",
            "ok": "yes" if (res_ok and state_ok) else "NO",
        })
    counts_ok = bool(planned) and seen == planned
    # time the jobs ran (summed) and the span from the first start to the last end
    t = [(dt.datetime.fromisoformat(r["StartTime"]), dt.datetime.fromisoformat(r["EndTime"])) for r in recs
         if re.match(r"^\d{4}-", r.get("StartTime", "")) and re.match(r"^\d{4}-", r.get("EndTime", ""))]
    busy_s = sum((b - a).total_seconds() for a, b in t)
    union_s, end = 0.0, None  # seconds in which at least one job ran
    for a, b in sorted(t):
        if end is None or a > end:
            union_s, end = union_s + (b - a).total_seconds(), b
        elif b > end:
            union_s, end = union_s + (b - end).total_seconds(), b
    ok_all &= counts_ok
    outputs = check_outputs(work, args.scene, {rule_of(r["Comment"]) for r in recs})
    ok_all &= all(ok for _, ok, _ in outputs)
    diffs = compare_to_reference(work, Path(args.reference), args.scene) if args.reference else []

    # ------------------------------------------------------------------ write the report
    report = Path(args.report)
    report.parent.mkdir(parents=True, exist_ok=True)
    rev = _cmd("git", "-C", str(repo), "rev-parse", "--short", "HEAD")
    dirty = len([ln for ln in _cmd("git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no").splitlines() if ln])
    slurm_v = _cmd("sinfo", "--version") or "?"
    runs = [("slurm", "snakemake --profile <smoke profile> (executor slurm)", args.wall_slurm, sum(planned.values()))]
    if args.reference:
        runs.append(("local", "snakemake --workflow-profile profiles/default --cores "
                     f"{os.cpu_count()} (reference)", args.wall_local, sum(planned.values())))
    ref_wall = args.wall_local if args.reference else None
    tmp = report.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["method", "executor", "targets", "jobs", "wall_s", "reference", "reference_wall_s",
                    "ratio_to_reference", "checks_passed"])
        for method, executor, wall, n in runs:
            w.writerow([method, executor, " ".join(args.targets), n, f"{wall:.1f}",
                        "local" if ref_wall else "", f"{ref_wall:.1f}" if ref_wall else "",
                        f"{wall / ref_wall:.2f}" if ref_wall else "", int(ok_all) if method == "slurm" else ""])
    os.replace(tmp, report.with_suffix(".csv"))

    L = []
    L.append("# SLURM smoke test (scripts/slurm-smoke.sh)\n")
    L.append(f"**Result: {'PASS' if ok_all else 'FAIL'}** — the tiny garment scene through "
             "`snakemake --executor slurm` with profiles/slurm on a single-node SLURM cluster "
             "started on this machine.\n")
    L.append(f"- date: {dt.datetime.now().astimezone().isoformat(timespec='seconds')}")
    L.append(f"- machine: {platform.node()}, {os.cpu_count()} CPUs, {mem_total_mb()} MB RAM, "
             f"{platform.system()} {platform.release()}; {slurm_v} (Debian packages slurmctld, slurmd, "
             "slurm-client, munge); one node declared with "
             f"CPUs={args.node_cpus} RealMemory={args.node_mem} (SlurmdParameters=config_overrides) and one fake GPU GRES")
    L.append(f"- plugins: snakemake {_pip_version('snakemake')}, snakemake-executor-plugin-slurm "
             f"{_pip_version('snakemake-executor-plugin-slurm')}, snakemake-executor-plugin-slurm-jobstep "
             f"{_pip_version('snakemake-executor-plugin-slurm-jobstep')}")
    L.append(f"- git revision: {rev}" + (f" (working tree: {dirty} tracked files modified)" if dirty else ""))
    L.append(f"- command: `{args.command}`")
    L.append(f"- scene: scripts/slurm/tiny.yaml (scene `{args.scene}`); targets: `{' '.join(args.targets)}`")
    L.append("- smoke settings added to the profile: " + ", ".join(f"`{k}: {v}`" for k, v in SMOKE_GLOBALS.items())
             + ", " + ", ".join(f"`{r}: {v}`" for r, v in SMOKE_RESOURCES.items()) + "\n")
    L.append("## Wall time (one run each, same invocation)\n")
    L.append("| method | executor | jobs | wall_s | ratio to local |")
    L.append("| --- | --- | ---: | ---: | ---: |")
    for method, executor, wall, n in runs:
        L.append(f"| {method} | {executor} | {n} | {wall:.1f} | {wall / ref_wall:.2f} |" if ref_wall
                 else f"| {method} | {executor} | {n} | {wall:.1f} | (no reference run) |")
    L.append("")
    L.append(f"In the SLURM run at least one job was running during {union_s:.0f} s of the {args.wall_slurm:.0f} s "
             f"wall time (jobs summed: {busy_s:.0f} s; each includes the start-up of Snakemake inside its "
             f"allocation). The other {args.wall_slurm - union_s:.0f} s are DAG building, submission and, mostly, "
             "the plugin's status polling: a finished job is noticed at the next squeue poll (first poll 5 s "
             "after a submission, each poll that finds no job finished waits 10 s longer), and its dependants "
             "are submitted only then. The machine is shared, so both times vary with its load.\n")
    L.append("## SLURM jobs: state and granted resources (profile -> SLURM)\n")
    L.append(f"Planned by Snakemake: {planned}; SLURM jobs found: {seen} — "
             f"{'match' if counts_ok else 'MISMATCH'}.\n")
    L.append("| rule | wildcards | job | state exit | run time | runtime (min) -> TimeLimit | mem_mb -> MinMemoryNode "
             "| cpus_per_task -> CPUs/Task | gpu -> GRES gpu | ok |")
    L.append("| --- | --- | ---: | --- | --- | --- | --- | --- | --- | --- |")
    for j in job_rows:
        L.append("| " + " | ".join(str(j[k]) for k in ("rule", "wildcards", "slurm_job", "state", "run_time",
                                                       "runtime_min", "mem_mb", "cpus_per_task", "gpu", "ok")) + " |")
    L.append("")
    L.append("## Outputs\n")
    L.append("| check | ok | detail |")
    L.append("| --- | --- | --- |")
    for name, ok, detail in outputs:
        L.append(f"| {name} | {'yes' if ok else 'NO'} | {detail} |")
    L.append("")
    if diffs:
        L.append("## Agreement with the local reference run\n")
        L.append("Largest absolute difference between the arrays of the SLURM run and of the local run "
                 "(same config; jobs on SLURM get the slurm profile's thread counts, locally the default profile's):\n")
        L.append("| array | max abs diff |")
        L.append("| --- | ---: |")
        for name, d in diffs:
            L.append(f"| {name} | {d:.3g} |")
        L.append("")
    report.with_suffix(".md.tmp").write_text("\n".join(L) + "\n")
    os.replace(report.with_suffix(".md.tmp"), report.with_suffix(".md"))
    print("\n".join(L))
    return 0 if ok_all else 1


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("node")
    a.add_argument("profile")
    a = sub.add_parser("profile")
    a.add_argument("profile")
    a.add_argument("out_dir")
    a = sub.add_parser("check")
    a.add_argument("--work", required=True, help="workdir of the SLURM run (holds tiny.yaml, snakemake-slurm.log)")
    a.add_argument("--reference", default="", help="workdir of the local reference run (optional)")
    a.add_argument("--profile", required=True, help="the smoke profile the run used")
    a.add_argument("--scontrol", required=True, help="file with `scontrol -o show job` after the run")
    a.add_argument("--scene", default="tinyskirt")
    a.add_argument("--targets", nargs="+", required=True)
    a.add_argument("--wall-slurm", type=float, required=True)
    a.add_argument("--wall-local", type=float, default=0.0)
    a.add_argument("--node-cpus", type=int, required=True)
    a.add_argument("--node-mem", type=int, required=True)
    a.add_argument("--command", default="scripts/slurm-smoke.sh")
    a.add_argument("--report", required=True, help="path without suffix: writes .md and .csv")
    args = p.parse_args(argv)
    if args.cmd == "node":
        cpus, mem = node_size(load_profile(args.profile))
        print(cpus, mem)
        return 0
    if args.cmd == "profile":
        out = Path(args.out_dir)
        out.mkdir(parents=True, exist_ok=True)
        text = ("# Generated by scripts/slurm/smoke.py from " + args.profile + " plus the smoke settings.\n"
                + yaml.safe_dump(smoke_profile(load_profile(args.profile)), sort_keys=False))
        (out / "config.yaml").write_text(text)
        return 0
    return check(args)


if __name__ == "__main__":
    sys.exit(main())
