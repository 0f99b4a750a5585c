"""CUDA benchmark: the GPU paths of the cloth solver, the rig, the rasteriser and the field (issue 22 item 5).

Run on a machine with a CUDA GPU (one command; about 5 minutes on an H200 with 16 cores):
    python -m benchmarks.bench_cuda --workdir /tmp/cuda_work --raw OUT/raw.json
then here, from the raw results it wrote:
    .venv/bin/python -m benchmarks.bench_cuda --report OUT/raw.json [--out benchmarks]
which writes benchmarks/cuda.md and cuda.csv (scaling.md's CUDA line points to them and quotes the
speed-ups). ``--quick``: tiny sizes, CPU only (tests/test_benchmarks.py; about 15 s).

The inputs of every point (synthetic scene, garment template, library motion, masks and flows) are
made first by the pipeline's own CPU stages and not timed. Then each stage runs as the workflow's
scripts call it (``anidress_core.stages.*.run_*``), once with ``device="cuda"`` and once on the CPU of
the same machine with every core (torch threads = CPU count; the Warp CPU kernels of the cloth solver
and the rasteriser are single-threaded), in a child process forked from this one (which never
touches CUDA itself). Wall seconds per unit, after the stage's own setup:

- simulate: per simulated frame step (settle frames included); on CUDA also ``simulate_launches``, the
  same solver with its frame graph off (``graph_capture: false``: every kernel launched from Python);
- rig: per decomposition of ``RIG_FRAMES`` frames (25 bones, config ``rig``);
- fit: per frame t > 0 (the fit's own per-frame wall times; frame 0 has its own budget);
- train_field: per optimisation step (the training loop's wall time, data loading excluded);
- render: per image (median over the images of one test camera).

The first call of simulate, rig and fit on each device also pays the Warp kernel compilation (an
empty kernel cache): it is reported apart ("first call") and not in the per-unit figures. Points:
the demo scale (config/config.yaml: 8 training views of 12 cameras at 256^2, 3,000 garment
vertices) and the paper scale (8 views at 512^2, 9,000 vertices); frames are few (the per-unit costs
do not depend on them, benchmarks/scaling.md). GPU memory: torch's peak allocation
(``torch.cuda.max_memory_allocated``); Warp's own allocations (cloth solver, rig kernels) are not in it.
"""
from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import datetime
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_scaling import Plan, Runner, fork_call, hms, w_template
from benchmarks.benchutil import cpu_model, git_rev

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("simulate", "simulate_launches", "rig", "fit", "train_field", "render")
#: simulate_launches: the cloth solver on CUDA with graph capture off (kernel by kernel), the path before it
UNIT = {"simulate": "simulated frame", "simulate_launches": "simulated frame", "rig": "decomposition",
        "fit": "frame (t > 0)", "train_field": "optimisation step", "render": "image"}
#: the paper's scale, units per stage (low, high): 10K simulated frames; 400-800 frames; 600 steps
#: (config field/train/steps); 8 views x 400-800 frames rendered
#: the output compared between the devices, per stage
CHECK = {"simulate": "max stretch", "simulate_launches": "max stretch", "rig": "RMSE mm"}
PAPER_UNITS = {"simulate": (10000, 10000), "simulate_launches": (10000, 10000), "fit": (400, 800),
               "render": (3200, 6400)}


@dataclasses.dataclass(frozen=True)
class Sizes:
    points: dict            # name -> (views, image side, garment vertices)
    scene_frames: int       # frames of each scene (fit: scene_frames - 1 measured frames)
    settle: int             # cloth settle frames (ground truth and simulations)
    texture: int
    sim_frames: int         # library-walk frames simulated per point
    rig_frames: int         # frames decomposed (the simulated frames, repeated when fewer)
    bones: int
    train_steps: int
    body_vertices: int = 0  # 0: the config's


FULL = Sizes(points={"demo": (8, 256, 3000), "paper": (8, 512, 9000)}, scene_frames=3, settle=5, texture=1024,
             sim_frames=60, rig_frames=240, bones=25, train_steps=40)
QUICK = Sizes(points={"demo": (2, 32, 400)}, scene_frames=2, settle=2, texture=128, sim_frames=3, rig_frames=6,
              bones=4, train_steps=2, body_vertices=1500)


# --------------------------------------------------------------------------- children (forked)


def _setup(device: str) -> None:
    import torch

    torch.set_num_threads(os.cpu_count() or 1)  # every core, on both devices (CPU-side work of the GPU runs)
    if device != "cpu":
        torch.cuda.reset_peak_memory_stats()


def _sync(device: str) -> None:
    if device != "cpu":
        import torch
        import warp as wp

        torch.cuda.synchronize()
        wp.synchronize()


def _gpu_peak_mb(device: str) -> float:
    if device == "cpu":
        return float("nan")
    import torch

    return torch.cuda.max_memory_allocated() / 2 ** 20


def w_info() -> dict:
    """What the machine offers (run in a child, so that this process never initialises CUDA)."""
    import torch
    import warp as wp

    wp.config.quiet = True
    wp.init()
    cuda = torch.cuda.is_available()
    return {"cuda": cuda, "gpu": torch.cuda.get_device_name(0) if cuda else "", "torch": torch.__version__,
            "torch_cuda": str(torch.version.cuda), "warp": wp.__version__, "warp_cuda": bool(wp.is_cuda_available()),
            "numpy": np.__version__, "python": platform.python_version(), "cpu": cpu_model(),
            "cpus": os.cpu_count()}


def w_simulate(template: str, motion: str, scene_dir: str, cloth: dict, out_npz: str, device: str) -> dict:
    from anidress_core.stages.simulate import run_simulate

    _setup(device)
    t0 = time.perf_counter()
    res = run_simulate(template, motion, scene_dir, dict(cloth, device=device), out_npz, progress=False)
    _sync(device)
    wall = time.perf_counter() - t0
    steps = res.frames.shape[0] + int(cloth["settle_frames"]) - 1
    return {"wall_s": wall, "units": steps, "s_per_unit": res.stats.wall_s / steps,
            "nan": int(res.stats.nan_count.sum()), "max_stretch": float(res.stats.max_stretch.max())}


def w_rig(template: str, sims: list, params: dict, out_npz: str, device: str) -> dict:
    from anidress_core.stages.rig import run_rig

    _setup(device)
    t0 = time.perf_counter()
    art = run_rig(template, sims, params, out_npz, device=device)
    _sync(device)
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "units": 1, "s_per_unit": wall, "frames": int(art.meta["frames_decomposed"]),
            "rmse_mm": 1e3 * float(art.model.rmse), "gpu_peak_mb": _gpu_peak_mb(device)}


def w_fit(scene_dir: str, rig: str, template: str, masks: str, flows: str, params: dict, out_npz: str,
          device: str) -> dict:
    from anidress_core.io.garment_poses import load_garment_poses
    from anidress_core.stages.fit import run_fit

    _setup(device)
    t0 = time.perf_counter()
    run_fit(scene_dir, "walk", rig, template, masks, flows, str(Path(scene_dir) / "walk" / "normals"),
            dict(params, device=device, threads=0), out_npz, progress=False, cue_source="pipeline",
            ablation="pipeline_no_sim_prior")  # the rig has no simulation of walk (library motions only)
    _sync(device)
    wall = time.perf_counter() - t0
    a, _ = load_garment_poses(out_npz)
    per = np.asarray(a["wall_s"], float)
    return {"wall_s": wall, "units": len(per) - 1, "s_per_unit": float(per[1:].mean()), "frame0_s": float(per[0]),
            "gpu_peak_mb": _gpu_peak_mb(device)}


def w_train(scene_dir: str, masks: str, out_pt: str, field: dict, template: str, rig: str, poses: str,
            device: str) -> dict:
    from anidress_core.stages.field import run_train

    _setup(device)
    t0 = time.perf_counter()
    out = run_train(scene_dir, "walk", "full", masks, out_pt, field, template_npz=template, rig_npz=rig,
                    garment_poses_npz=poses, lpips=None, device=device, progress=False)
    _sync(device)
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "units": int(out["steps"]), "s_per_unit": out["wall_s"] / out["steps"],
            "setup_s": wall - out["wall_s"], "gpu_peak_mb": _gpu_peak_mb(device)}


def w_render(field_pt: str, scene_dir: str, out_dir: str, field: dict, template: str, rig: str, poses: str,
             camera: str, device: str) -> dict:
    from anidress_core.stages.field import run_render

    _setup(device)
    t0 = time.perf_counter()
    s = run_render(field_pt, scene_dir, out_dir, field, seq="walk", cameras=[camera], garment_poses_npz=poses,
                   template_npz=template, rig_npz=rig, device=device, progress=False)
    _sync(device)
    per = [p["seconds"] for p in s["per_image"]]
    return {"wall_s": time.perf_counter() - t0, "units": len(per), "s_per_unit": float(np.median(per)),
            "gpu_peak_mb": _gpu_peak_mb(device)}


# --------------------------------------------------------------------------- the run


class CudaRun:
    def __init__(self, sizes: Sizes, work: Path, config: dict, raw_path: Path, devices: tuple, git: str):
        self.s, self.work, self.config, self.raw_path, self.devices = sizes, work, config, raw_path, devices
        plan = Plan(scene_frames=sizes.scene_frames, settle=sizes.settle, texture=sizes.texture, views=(8,),
                    image=(256,), vertices=(3000,), bones=(sizes.bones,), sim_frames=(sizes.sim_frames,),
                    rig_frames_base=sizes.sim_frames, train_steps=sizes.train_steps,
                    body_vertices=sizes.body_vertices)
        self.inputs = Runner(plan, work, config)  # scene / cue helpers of the scaling benchmark
        self.raw = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "git": git,
                    "cmd": " ".join(["python", "-m", "benchmarks.bench_cuda"] + sys.argv[1:]),
                    "sizes": dataclasses.asdict(sizes), "devices": list(devices), "rows": [], "errors": []}

    def save(self) -> None:
        self.raw_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.raw_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.raw, indent=1))
        tmp.replace(self.raw_path)

    def measure(self, stage: str, point: str, device: str, fn, *args, first: bool = False) -> dict | None:
        name = f"{stage}_{point}_{device}" + ("_first" if first else "")
        try:
            res = fork_call(fn, self.work / "logs" / f"{name}.log", *args, device)
        except RuntimeError as e:  # recorded, and the run goes on: one failed stage should not lose the others
            print(f"FAILED {name}: {e}", flush=True)
            self.raw["errors"].append({"stage": stage, "point": point, "device": device, "error": str(e)[-2000:]})
            self.save()
            return None
        row = {"stage": stage, "point": point, "device": device, "first_call": first, **res}
        self.raw["rows"].append(row)
        self.save()
        print(f"[{time.perf_counter() - self.t0:6.1f} s] {name}: {res['s_per_unit']:.4g} s per {UNIT[stage]} "
              f"({res['wall_s']:.1f} s)", flush=True)
        return res

    def make_inputs(self, point: str, root: Path) -> dict:
        """The scene, garment template and library motion of ``point`` under ``root`` (made here if absent)."""
        views, image, vertices = self.s.points[point]
        r = self.inputs
        sd = root / "scenes" / f"v{views}_s{image}_g{vertices}"
        if not sd.is_dir():
            sd = r.scene(views, image, vertices, None)  # synth into the work folder (= root when preparing)
        tpl = root / "templates" / f"{point}.npz"
        if not tpl.is_file():
            fork_call(w_template, self.work / "logs" / f"template_{point}.log", str(sd), vertices, str(tpl))
        r.use_inputs(views, image, vertices, sd, tpl)
        mot = root / "motions" / f"lib-walk{self.s.sim_frames}.npz"
        if not mot.is_file():
            from benchmarks.bench_scaling import w_motion

            cfg = dict(r.sim_cfg(), library_frames=self.s.sim_frames)
            fork_call(w_motion, self.work / "logs" / "motion.log", "lib-walk", str(sd), cfg, str(mot))
        return {"scene": sd, "template": tpl, "motion": mot}

    def prepare(self, point: str, inputs: Path | None) -> dict:
        """Inputs of ``point`` (from ``inputs`` when given, else made in the work folder) and its cues."""
        inp = self.make_inputs(point, inputs or self.work)
        m, f, _, _ = self.inputs.cues(self.s.points[point])
        return dict(inp, masks=m, flows=f)

    def run(self, inputs: Path | None = None) -> None:
        self.t0 = time.perf_counter()
        self.raw["info"] = fork_call(w_info, self.work / "logs" / "info.log")
        self.save()
        if "cuda" in self.devices and not self.raw["info"]["cuda"]:
            raise SystemExit("bench_cuda: no CUDA device visible to torch (use --quick for the CPU smoke test)")
        inputs = {p: self.prepare(p, inputs) for p in self.s.points}
        self.raw["prepare_s"] = time.perf_counter() - self.t0
        self.save()
        cfg = self.config
        cloth = dict(self.inputs.sim_cfg()["cloth"])
        rig_params = dict(cfg["rig"], bones=self.s.bones)
        fit_params = dict(cfg["fit"], **(cfg["scenes"]["skirt"].get("fit") or {}))
        fit_params.update(frames=self.s.scene_frames, first_frame_init="body")
        field = copy.deepcopy(cfg["field"])
        field["train"] = dict(field["train"], steps=self.s.train_steps, checkpoint_every=10 ** 6, lpips_weight=0.0)
        from anidress_core.io.scene import read_scene

        for dev in self.devices:
            for i, (p, inp) in enumerate(inputs.items()):
                o = self.work / dev / p
                sim = o / "sim.npz"
                args = (str(inp["template"]), str(inp["motion"]), str(inp["scene"]), cloth)
                if i == 0:  # Warp compiles the solver's kernels for this device on the first call
                    self.measure("simulate", p, dev, w_simulate, *args, str(o / "sim_first.npz"), first=True)
                ok = self.measure("simulate", p, dev, w_simulate, *args, str(sim)) is not None
                if dev == "cuda":
                    eager = (*args[:3], dict(cloth, graph_capture=False))  # the same call, graph off
                    ok = self.measure("simulate_launches", p, dev, w_simulate, *eager,
                                      str(sim if not ok else o / "sim_launches.npz")) is not None or ok
                if not ok:
                    continue
                reps = max(1, self.s.rig_frames // self.s.sim_frames)  # copies: the rig keys sequences by name
                sims = [str(sim)] + [str(shutil.copy(sim, o / f"sim_copy{k}.npz")) for k in range(1, reps)]
                rig_args = (str(inp["template"]), sims, rig_params, str(o / "rig.npz"))
                if i == 0:
                    self.measure("rig", p, dev, w_rig, *rig_args[:3], str(o / "rig_first.npz"), first=True)
                if self.measure("rig", p, dev, w_rig, *rig_args) is None:
                    continue
                fit_args = (str(inp["scene"]), str(o / "rig.npz"), str(inp["template"]), str(inp["masks"]),
                            str(inp["flows"]), fit_params)
                if i == 0:
                    self.measure("fit", p, dev, w_fit, *fit_args, str(o / "fit_first.npz"), first=True)
                poses = o / "garment_poses.npz"
                if self.measure("fit", p, dev, w_fit, *fit_args, str(poses)) is None:
                    continue
                pt = o / "field.pt"
                tr = (str(inp["scene"]), str(inp["masks"]), str(pt), field, str(inp["template"]),
                      str(o / "rig.npz"), str(poses))
                if self.measure("train_field", p, dev, w_train, *tr) is None:
                    continue
                cam = read_scene(inp["scene"])["cameras"]["test"][0]
                self.measure("render", p, dev, w_render, str(pt), str(inp["scene"]), str(o / "render"), field,
                             str(inp["template"]), str(o / "rig.npz"), str(poses), cam)
        self.raw["wall_s"] = time.perf_counter() - self.t0
        self.save()


# --------------------------------------------------------------------------- report


def _fmt(x: float) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x:.3g}" if abs(x) < 1000 else f"{x:,.0f}"


def table(raw: dict) -> list[dict]:
    """One row per (stage, point): per-unit seconds on each device, the speed-up, first-call seconds."""
    by = {(r["stage"], r["point"], r["device"], r["first_call"]): r for r in raw["rows"]}
    out = []
    for st in STAGES:
        for p in raw["sizes"]["points"]:
            cpu, gpu = by.get((st, p, "cpu", False)), by.get((st, p, "cuda", False))
            if cpu is None and gpu is None:
                continue
            first = {d: by.get((st, p, d, True)) for d in ("cpu", "cuda")}
            row = {"stage": st, "point": p, "unit": UNIT[st],
                   "cpu_s_per_unit": cpu["s_per_unit"] if cpu else float("nan"),
                   "cuda_s_per_unit": gpu["s_per_unit"] if gpu else float("nan"),
                   "units_measured": (gpu or cpu)["units"],
                   "cpu_first_call_s": first["cpu"]["wall_s"] if first["cpu"] else float("nan"),
                   "cuda_first_call_s": first["cuda"]["wall_s"] if first["cuda"] else float("nan"),
                   "cuda_peak_mb_torch": gpu.get("gpu_peak_mb", float("nan")) if gpu else float("nan")}
            row["speedup"] = row["cpu_s_per_unit"] / row["cuda_s_per_unit"]
            # the same result on both devices? (float atomics and summation order differ)
            key = {"simulate": "max_stretch", "simulate_launches": "max_stretch", "rig": "rmse_mm"}.get(st)
            row["check"] = (f"{CHECK[st]} {_fmt(cpu[key]) if cpu else '-'} / {_fmt(gpu[key]) if gpu else '-'}"
                            if key else "")
            if st == "train_field":
                lo = hi = int(raw.get("train_steps_config", 600))
            elif st == "rig":  # measured at RIG_FRAMES frames, not at the paper's 10K: no total
                lo = hi = float("nan")
            else:
                lo, hi = PAPER_UNITS[st]
            row["units_paper"] = "-" if np.isnan(lo) else (f"{lo}" if lo == hi else f"{lo}-{hi}")
            row["cuda_total_paper_s_low"] = row["cuda_s_per_unit"] * lo
            row["cuda_total_paper_s_high"] = row["cuda_s_per_unit"] * hi
            out.append(row)
    return out


def growth(rows: list[dict]) -> dict:
    """stage -> {device: per-unit time at the paper point / at the demo point} where both were measured."""
    by = {(r["stage"], r["point"]): r for r in rows}
    out = {}
    for st in STAGES:
        d, p = by.get((st, "demo")), by.get((st, "paper"))
        if d and p:
            out[st] = {dev: p[f"{dev}_s_per_unit"] / d[f"{dev}_s_per_unit"] for dev in ("cpu", "cuda")}
    return out


def report(raw: dict, out: Path) -> None:
    rows = table(raw)
    out.mkdir(parents=True, exist_ok=True)
    cols = ["stage", "point", "unit", "units_measured", "cpu_s_per_unit", "cuda_s_per_unit", "speedup",
            "cpu_first_call_s", "cuda_first_call_s", "cuda_peak_mb_torch", "check", "units_paper",
            "cuda_total_paper_s_low", "cuda_total_paper_s_high"]
    with open(out / "cuda.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    info, s = raw["info"], raw["sizes"]
    pts = "; ".join(f"{k}: {v[0]} training views at {v[1]}^2, {v[2]:,} garment vertices"
                    for k, v in s["points"].items())
    L = ["# CUDA against the CPU of the same machine", "",
         f"- date: {raw['date']}; git {raw['git']}; command: `{raw['cmd']}`, tables by "
         f"`.venv/bin/python -m benchmarks.bench_cuda --report <raw.json>`",
         f"- machine: {info['gpu'] or 'no GPU'}; {info['cpu']}, {info['cpus']} logical CPUs; Python {info['python']}, "
         f"torch {info['torch']} (CUDA {info['torch_cuda']}), Warp {info['warp']}, numpy {info['numpy']}. The "
         f"project pins torch 2.13.0 (CPU build); this run used the GPU machine's own torch.",
         f"- points: {pts}; {s['scene_frames']} frames per scene, simulate {s['sim_frames']} library-walk frames "
         f"+ {s['settle']} settle, rig {s['bones']} bones over {s['rig_frames']} frames (the simulated frames "
         f"repeated), field variant full for {s['train_steps']} steps, render every frame of one test camera.",
         f"- CPU: every core (torch threads = {info['cpus']}); the Warp CPU kernels of the cloth solver and the "
         "rasteriser run on one thread. Wall seconds per unit after the stage's setup; first call: the whole "
         "first call on that device, Warp kernel compilation included. One run per point.",
         *([f"- tests: {raw['tests']}"] if raw.get("tests") else []),
         f"- the run took {raw.get('wall_s', float('nan')) / 60:.1f} min (cues of the inputs "
         f"{raw.get('prepare_s', float('nan')):.0f} s, not timed per stage)"
         + ("; the scenes, templates and motion were made beforehand by `--prepare` (ground truth and the test "
            "cameras' images left out) on a machine with pymeshlab." if "--inputs" in raw["cmd"] else "."), "",
         "| stage | point | unit | CPU s per unit | CUDA s per unit | CUDA speed-up | first call CPU / CUDA (s) | "
         "CUDA peak MB (torch) | result CPU / CUDA | paper-scale units | paper-scale CUDA total |",
         "| --- | --- | --- | ---: | ---: | ---: | --- | ---: | --- | --- | --- |"]
    for r in rows:
        lo, hi = r["cuda_total_paper_s_low"], r["cuda_total_paper_s_high"]
        tot = "-" if not np.isfinite(lo) else (hms(lo) if lo == hi else f"{hms(lo)} - {hms(hi)}")
        paper = r["point"] == "paper"
        L.append(f"| {r['stage']} | {r['point']} | {r['unit']} | {_fmt(r['cpu_s_per_unit'])} | "
                 f"{_fmt(r['cuda_s_per_unit'])} | {_fmt(r['speedup']) + 'x' if np.isfinite(r['speedup']) else '-'} | "
                 f"{_fmt(r['cpu_first_call_s'])} / "
                 f"{_fmt(r['cuda_first_call_s'])} | {_fmt(r['cuda_peak_mb_torch'])} | {r['check'] or '-'} | "
                 f"{r['units_paper'] if paper else '-'} | {tot if paper else '-'} |")
    grow = growth(rows)
    if grow:
        L += ["", "Per-unit time at the paper point over the demo point (3x the garment vertices, 4x the pixels):", ""]
        L += [f"- {st}: " + ", ".join(f"{dev.upper() if dev == 'cpu' else 'CUDA'} {v:.2f}x" for dev, v in g.items()
                                      if np.isfinite(v)) for st, g in grow.items()]
        flat = [st for st, g in grow.items() if g["cuda"] < 1.2]
        if flat:
            L += ["", f"- CUDA time per unit grows by less than 1.2x with the work for {', '.join(flat)}: bound by "
                      "per-call work on the host (launches, copies, Python), not by the GPU."]
    by = {(r["stage"], r["point"]): r for r in rows}
    for p in raw["sizes"]["points"]:
        g, e = by.get(("simulate", p)), by.get(("simulate_launches", p))
        if g and e:
            L.append(f"- cloth solver, {p} point: the frame graph (default) against kernel-by-kernel launches: "
                     f"{e['cuda_s_per_unit']:.3g} -> {g['cuda_s_per_unit']:.3g} s per frame "
                     f"({e['cuda_s_per_unit'] / g['cuda_s_per_unit']:.2f}x).")
    if raw["errors"]:
        L += ["", "## Failed", ""] + [f"- {e['stage']} / {e['point']} / {e['device']}: "
                                      f"`{e['error'].strip().splitlines()[-1][:300]}`" for e in raw["errors"]]
    L += ["", "- paper-scale CUDA total: the paper point's per-unit time x the paper's units (10K simulated "
              "frames; one rig; 400-800 fitted frames; 600 training steps, config field/train/steps; 8 views x "
              "400-800 rendered images). The rig is measured at the frames above, not at 10K frames.", ""]
    (out / "cuda.md").write_text("\n".join(L))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes, CPU only (a smoke test of the script)")
    ap.add_argument("--workdir", default=None, help="scratch folder (emptied first; default benchmarks/runs/cuda)")
    ap.add_argument("--raw", default=None, help="raw results json, written after every measurement "
                                                "(default <workdir>/raw.json)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder of cuda.md and cuda.csv")
    ap.add_argument("--git", default=None, help="the commit measured (default: git here)")
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--devices", nargs="+", choices=("cuda", "cpu"), default=None,
                    help="devices measured (default: cuda cpu; --quick: cpu)")
    ap.add_argument("--points", nargs="+", default=None, help="points measured (default: all of the sizes)")
    ap.add_argument("--prepare", metavar="DIR", help="no measurement: make the scenes, templates and motion "
                    "of every point into DIR (their ground truth left out), for a GPU machine that lacks pymeshlab")
    ap.add_argument("--inputs", metavar="DIR", help="the inputs made by --prepare (default: made in the workdir)")
    ap.add_argument("--report", metavar="RAW_JSON", help="no run: write cuda.md / cuda.csv from a raw json")
    args = ap.parse_args()
    if args.report:
        report(json.loads(Path(args.report).read_text()), Path(args.out))
        print(f"wrote {Path(args.out) / 'cuda.md'} and {Path(args.out) / 'cuda.csv'}")
        return
    # import what the children run, once, here (each child is a fork of this process); no CUDA call here
    import anidress_core.stages.cues  # noqa: F401
    import anidress_core.stages.field  # noqa: F401
    import anidress_core.stages.fit  # noqa: F401
    import anidress_core.stages.rig  # noqa: F401
    import anidress_core.stages.simulate  # noqa: F401
    import anidress_core.stages.synth  # noqa: F401
    import anidress_core.stages.template  # noqa: F401
    from anidress_core.config import load_config

    work = Path(args.workdir) if args.workdir else ROOT / "benchmarks" / "runs" / "cuda"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    config = load_config(args.config)
    sizes = QUICK if args.quick else FULL
    if args.points:
        unknown = sorted(set(args.points) - set(sizes.points))
        if unknown:
            raise SystemExit(f"bench_cuda: unknown points {unknown}; known: {sorted(sizes.points)}")
        sizes = dataclasses.replace(sizes, points={k: v for k, v in sizes.points.items() if k in args.points})
    devices = tuple(args.devices or (("cpu",) if args.quick else ("cuda", "cpu")))
    run = CudaRun(sizes, work, config, Path(args.raw) if args.raw else work / "raw.json", devices,
                  args.git or git_rev(("anidress_core",)))
    if args.prepare:
        for p in sizes.points:
            run.make_inputs(p, work)
        for gt in work.glob("scenes/*/*/gt"):
            shutil.rmtree(gt)
        shutil.copytree(work, args.prepare, dirs_exist_ok=True, ignore=shutil.ignore_patterns("logs"))
        print(f"wrote the inputs to {args.prepare}")
        return
    run.raw["train_steps_config"] = int(config["field"]["train"]["steps"])
    run.run(Path(args.inputs) if args.inputs else None)
    print(f"wrote {run.raw_path}")
    if args.quick:
        report(run.raw, Path(args.out))


if __name__ == "__main__":
    main()
