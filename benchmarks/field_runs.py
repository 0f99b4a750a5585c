"""Field runs of the benchmarks: one variant of one scene trained, rendered and scored through the
``anidress`` command line, with this checkout's code or an earlier commit's, so that two versions of
the field are measured in one run on one machine.

An earlier commit runs from a git worktree under ``benchmarks/runs/code/<rev>`` (made on first use),
put first on ``PYTHONPATH`` for the ``train`` and ``render`` commands, with that commit's own
``config/config.yaml`` under the job's overlay. Every job is scored by this checkout's ``evaluate``
(the same metrics for every version). A job whose ``row.json`` exists with the same specification is
not run again, so an interrupted benchmark resumes.

    from benchmarks.field_runs import Job, run_jobs
    rows = run_jobs([Job("new", "skirt", "full", out=...), Job("6aee398", "skirt", "full", code="6aee398", out=...)])
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
CODE_ROOT = ROOT / "benchmarks" / "runs" / "code"
#: the field before "Renders that show the garment, part 1" (issue 45): the reference of field.md
REFERENCE = "6aee398"
ANIDRESS = str(Path(sys.executable).parent / "anidress")
KINDS = ("novel_view", "novel_pose")
#: per kind, the figures of a row (metrics_summary.json names; pooled over the images where regional)
FIGURES = ("psnr_db", "psnr_subject_db", "psnr_garment_db", "psnr_body_db", "ssim", "ssim_subject", "iou")


@dataclasses.dataclass
class Job:
    """One field: ``variant`` of ``scene`` trained on its training sequence, rendered (novel view: the test
    cameras on the training frames; novel pose: every camera on the held-out sequence) and scored."""

    method: str
    """The row's label."""
    scene: str
    variant: str
    out: Path
    """Folder of the job's files (field.pt, renders, metrics, row.json)."""
    code: str = "."
    """``"."``: this checkout; else a git revision run from its worktree."""
    overlay: dict = dataclasses.field(default_factory=dict)
    """Settings merged over the code's config/config.yaml (e.g. ``{"field": {"train": {"steps": 300}}}``)."""
    poses: dict | None = None
    """{sequence: garment_poses.npz} (default: the pipeline's results/<scene>/<seq>/garment_poses.npz)."""
    rig: str | None = None
    """rig.npz (default: results/<scene>/rig.npz)."""
    masks: str | None = None
    """Training masks (default: results/<scene>/<train seq>/masks)."""
    env: dict = dataclasses.field(default_factory=dict)
    """Extra environment of the train and render commands."""
    render_stride: int = 0
    """Every n-th frame rendered (0: field/render/frame_stride of the config)."""
    oracle: str = ""
    """An oracle deformation of :mod:`benchmarks.field_oracle` (``dense_gt``) for train and render (this code only)."""
    body: dict | None = None
    """{sequence: folder of EasyMocap body files} read instead of data/<scene>/<seq>/smpl (``--body``)."""

    def spec(self) -> str:
        d = dataclasses.asdict(self)
        d.pop("out")
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


_WORKTREE_LOCK = threading.Lock()


def code_dir(rev: str) -> Path | None:
    """None for this checkout; else the worktree of ``rev`` (made when absent)."""
    if rev == ".":
        return None
    d = CODE_ROOT / rev
    with _WORKTREE_LOCK:  # the jobs of one run start side by side
        if not (d / "anidress_core").is_dir():
            CODE_ROOT.mkdir(parents=True, exist_ok=True)
            subprocess.run(["git", "worktree", "add", "--detach", "-f", str(d), rev], cwd=ROOT, check=True,
                           capture_output=True)
    return d


def _merge(a: dict, b: dict) -> dict:
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(a.get(k), dict):
            _merge(a[k], v)
        else:
            a[k] = v
    return a


def scene_sequences(scene: str) -> tuple[str, str]:
    """(training sequence, novel-pose sequence) of data/<scene>/scene.yaml."""
    info = yaml.safe_load((ROOT / "data" / scene / "scene.yaml").read_text())
    seqs = info["sequences"]
    train = [s["name"] for s in seqs if s.get("role") == "train"][0]
    pose = [s["name"] for s in seqs if s.get("role") == "novel_pose"][0]
    return train, pose


def _run(cmd: list[str], env: dict, log: Path) -> None:
    with open(log, "a") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        r = subprocess.run(cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT)
    if r.returncode:
        raise RuntimeError(f"{' '.join(cmd[:3])} failed (exit {r.returncode}); see {log}")


def run_job(job: Job) -> dict:
    """Train, render and score ``job`` (or read its finished row); returns the row."""
    out = Path(job.out)
    code = code_dir(job.code)
    base = (code or ROOT) / "config" / "config.yaml"
    cfg = _merge(yaml.safe_load(base.read_text()), json.loads(json.dumps(job.overlay)))
    # the job's settings as they resolve now: a row of other settings (an edited config) is not reused
    spec = hashlib.sha256((job.spec() + json.dumps(cfg, sort_keys=True)).encode()).hexdigest()[:16]
    row_file = out / "row.json"
    if row_file.is_file():
        row = json.loads(row_file.read_text())
        if row.get("spec") == spec:
            return row
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    env = dict(os.environ, **{k: str(v) for k, v in job.env.items()})
    if code is not None:
        env["PYTHONPATH"] = str(code)
    cli = [ANIDRESS]
    if job.oracle:
        if code is not None:
            raise ValueError(f"job {job.method}: an oracle runs with this checkout's code only")
        env["ANIDRESS_ORACLE"] = job.oracle
        cli = [sys.executable, "-m", "benchmarks.field_oracle"]
    train, pose = scene_sequences(job.scene)
    res = ROOT / "results" / job.scene
    data = ROOT / "data" / job.scene
    garment = (res / "template.npz").is_file() and (data / "garment").is_dir()
    rig = job.rig or str(res / "rig.npz")
    poses = {s: (job.poses or {}).get(s, str(res / s / "garment_poses.npz")) for s in (train, pose)}
    g_args = ["--template", str(res / "template.npz")] if garment else []
    if garment and job.variant == "full":
        g_args += ["--rig", rig]
    p_args = {s: (["--poses", poses[s]] if garment and job.variant == "full" else []) for s in (train, pose)}
    stride = ["--frame-stride", str(job.render_stride)] if job.render_stride else []
    b_args = {q: (["--body", job.body[q]] if job.body and q in job.body else []) for q in (train, pose)}
    log = out / "job.log"
    log.write_text("")
    common = ["--config", str(out / "config.yaml"), "--threads", "1", "--quiet"]
    t0 = time.perf_counter()
    _run([*cli, "train", str(data), train, "--variant", job.variant, "--masks", job.masks or str(res / train / "masks"),
          *g_args, *p_args[train], *b_args[train], *common, "-o", str(out / "field.pt")], env, log)
    _run([*cli, "render", str(out / "field.pt"), str(data), "--seq", train, *p_args[train], *b_args[train], *g_args,
          "--cameras", "test", *stride, *common, "-o", str(out / "nv")], env, log)
    _run([*cli, "render", str(out / "field.pt"), str(data), "--seq", pose, *p_args[pose], *b_args[pose], *g_args,
          "--cameras", "all", *stride, *common, "-o", str(out / "np")], env, log)
    wall = time.perf_counter() - t0
    # scored by this checkout's evaluate, whichever code rendered
    _run([ANIDRESS, "evaluate", str(data), f"novel_view:{train}:{out / 'nv'}", f"novel_pose:{pose}:{out / 'np'}",
          "--config", str(ROOT / "config" / "config.yaml"), "-o", str(out / "metrics.csv"), "--quiet"],
         dict(os.environ), log)
    row = collect(job, out)
    row["spec"], row["job_wall_s"] = spec, wall
    row_file.write_text(json.dumps(row, indent=1))
    return row


def collect(job: Job, out: Path) -> dict:
    """The row of a finished job: training and rendering times, the figures of both kinds."""
    import torch

    meta = torch.load(out / "field.pt", map_location="cpu", weights_only=False)
    row = {"method": job.method, "code": job.code, "scene": job.scene, "variant": job.variant,
           "steps": int(meta["steps"]), "rays_per_step": int(meta["train_config"]["rays_per_step"]),
           "train_wall_s": float(meta["wall_s"]), "train_cpu_s": float(meta.get("cpu_s", float("nan"))),
           "train_stage_wall_s": float(meta.get("stage_wall_s", float("nan")))}
    summ = json.loads((out / "metrics_summary.json").read_text())
    for m in summ["metrics"]:
        k = "nv" if m["kind"] == "novel_view" else "np"
        row[f"{k}_images"] = m["images"]
        for f in FIGURES:
            row[f"{k}_{f}"] = m.get(f, float("nan"))
    for k in ("nv", "np"):
        r = json.loads((out / k / "render.json").read_text())
        pix = [p["rays"] for p in r["per_image"]]
        cpu = [p["cpu_seconds"] for p in r["per_image"]]
        row[f"{k}_render_cpu_s_per_image"] = r["cpu_seconds_per_image_median"]
        row[f"{k}_render_cpu_us_per_ray"] = 1e6 * sum(cpu) / max(1, sum(pix))
        row[f"{k}_samples_per_ray"] = r["samples_per_ray"]
    return row


def run_jobs(jobs: list[Job], workers: int = 2) -> list[dict]:
    """Run ``jobs`` ``workers`` at a time (one torch thread each, as profiles/default runs the demo's jobs),
    printing a line as each ends. A job that fails gives a row with its error under ``failed``."""
    def one(job: Job) -> dict:
        try:
            r = run_job(job)
        except Exception as e:  # noqa: BLE001 -- one failed job is reported in its row, the others still run
            print(f"{time.strftime('%H:%M:%S')} {job.method} {job.scene} {job.variant} FAILED: {e}", flush=True)
            return {"method": job.method, "code": job.code, "scene": job.scene, "variant": job.variant,
                    "failed": str(e)}
        print(f"{time.strftime('%H:%M:%S')} {job.method} {job.scene} {job.variant} {r['steps']} steps: train "
              f"{r['train_wall_s']:.0f} s, garment PSNR nv {r.get('nv_psnr_garment_db', float('nan')):.2f} "
              f"np {r.get('np_psnr_garment_db', float('nan')):.2f} ({job.out})", flush=True)
        return r

    with ThreadPoolExecutor(max_workers=workers) as ex:
        return list(ex.map(one, jobs))


def rig_floor_poses(scene: str, seq: str, rig_npz: str | Path, out: Path) -> Path:
    """The rig floor of ``seq``: the rig's bone transforms fitted (``anidress_core.rig.fit_transforms``) to the
    ground-truth garment meshes, mapped onto the template's vertices (nearest point of the ground truth's
    rest mesh); written as a garment_poses.npz (``out``, made when absent)."""
    import numpy as np
    import torch
    import trimesh

    from anidress_core.io import files
    from anidress_core.io.mesh import read_mesh
    from anidress_core.io.rig import read_rig
    from anidress_core.io.template import read_template
    from anidress_core.rig import fit_transforms, reconstruct, rmse

    if out.is_file():
        return out
    data = ROOT / "data" / scene
    info = yaml.safe_load((data / "scene.yaml").read_text())
    rig = read_rig(rig_npz, dtype=torch.float64)
    tpl = read_template(ROOT / "results" / scene / "template.npz")
    v, f, _ = read_mesh(data / info["garment_template"])
    mesh = trimesh.Trimesh(v, f, process=False)
    cp, _, tri = trimesh.proximity.closest_point(mesh, tpl.verts)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], cp)
    g, _ = files.load_npz(data / seq / "gt" / "meshes.npz", required=("garment_vertices",))
    mapped = torch.from_numpy(np.einsum("tvkc,vk->tvc", g["garment_vertices"][:, f[tri]], bary))
    M = fit_transforms(rig.model, mapped)
    verts = reconstruct(rig.model.rest, rig.model.weights, M)
    T = M.shape[0]
    files.save_npz(out, {"transforms": M.float().numpy(), "verts": verts.float().numpy(),
                         "faces": np.asarray(tpl.faces, np.int64), "loss": np.zeros(T), "iterations": np.zeros(T, np.int64)},
                   meta={"rig_floor": "anidress_core.rig.fit_transforms on the ground-truth garment meshes",
                         "rmse_m": rmse(verts, mapped)})
    return out


def noisy_bodies(scene: str, seq: str, cm: float, out: Path, seed: int = 0) -> Path:
    """data/<scene>/<seq>/smpl with EasyMocap-like errors of ``cm`` mean joint error (the noise of
    ``anidress export-capture``: slow drift and jitter), written as EasyMocap files under ``out/smpl`` (the layout
    ``--body`` reads, as rule refine_body writes it; when absent)."""
    import numpy as np
    import torch

    from anidress_core.io.motion import read_easymocap_smpl_dir
    from anidress_core.io.scene import load_body, read_scene
    from anidress_core.stages.export_capture import fold_root_pose, noisy_body, write_easymocap_02

    if (out / "smpl").is_dir() and any((out / "smpl").iterdir()):
        return out
    data = ROOT / "data" / scene
    info = read_scene(data)
    body = load_body(data, info)
    sm = read_easymocap_smpl_dir(data / seq / "smpl")
    _, J = body.shaped(torch.as_tensor(sm["shapes"][0], dtype=torch.float32))
    P, Rh, Th = fold_root_pose(sm["poses"], sm["Rh"], sm["Th"], J[0].double().numpy())
    nz = noisy_body(body, P, Rh, Th, sm["shapes"][0], cm, float(info["fps"]), seed)
    shapes = np.broadcast_to(np.asarray(sm["shapes"][0]), (P.shape[0], len(sm["shapes"][0])))
    for t, f in enumerate(sm["frames"]):
        write_easymocap_02(out / "smpl" / f"{f:06d}.json", nz.poses[t], nz.Rh[t], nz.Th[t], shapes[t])
    return out


def fit_anchor(scenes) -> str:
    """What L_anchor's references were in the pipeline's fits of ``scenes`` (results/<scene>/<seq>/garment_poses.npz,
    both sequences; the header's ``config``): ``images`` or ``texture``, or each scene/sequence's where they differ."""
    from anidress_core.io.garment_poses import load_garment_poses

    found = {}
    for scene in scenes:
        for seq in scene_sequences(scene):
            path = ROOT / "results" / scene / seq / "garment_poses.npz"
            if path.is_file():
                meta = load_garment_poses(path)[1].get("meta") or {}
                found[f"{scene}/{seq}"] = (meta.get("config") or {}).get("anchor_reference", "not recorded")
    kinds = sorted(set(found.values()))
    if len(kinds) == 1:
        return kinds[0]
    return "; ".join(f"{k} {v}" for k, v in found.items()) or "no fits"


def load() -> str:
    """The machine's load average (1 / 5 / 15 min)."""
    try:
        return " / ".join(open("/proc/loadavg").read().split()[:3])
    except OSError:
        return "?"
