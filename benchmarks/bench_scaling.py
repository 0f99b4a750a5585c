"""Scaling benchmark: cost of every stage as the work grows (issue 22 item 4).

Run: .venv/bin/python -m benchmarks.bench_scaling [--quick] [--out benchmarks] [--workdir DIR]
     .venv/bin/python -m benchmarks.bench_scaling --reanalyse benchmarks/runs/scaling/raw.json
Writes <out>/scaling.md and <out>/scaling.csv, and the raw measurements to <workdir>/raw.json
(``--reanalyse`` regenerates the tables from them without measuring). Not a test
(tests/test_benchmarks.py runs ``--quick``, about 15 CPU s). The default run: about 11 CPU min.

For each stage the pipeline's own stage function (``anidress_core.stages.*.run_*``, called as the
workflow's scripts call them, one torch thread, device cpu) runs on problems that grow along one
axis at a time from the demo scale (config/config.yaml: 8 training views of 12 cameras, 256^2,
garment 3,000 vertices, 25 bones, 60-frame sequences):

- frames      simulated frames (simulate) and frames decomposed (rig);
- views       training cameras (ring of views x 3/2 cameras, as the demo's 8 of 12);
- image       pixels per image (H = W);
- vertices    garment vertices (scene garment and template);
- bones       virtual bones B of the rig (fit, train_field and render use that rig).

Every point runs in its own child process, forked from this process after it has imported the
package (so each point pays no interpreter start-up, and its peak RSS, from ``os.wait4``, is its
own: the imported modules plus the stage's work; the ``baseline`` row is a child that does nothing).
CPU seconds are process CPU time (user + system) of the stage call inside the child, turned into a
per-unit cost: synth per frame (its setup, ``build_scene``, measured in the same child and taken
off), simulate per simulated frame step (settle frames included), rig per decomposition, masks /
flows per frame (their setup included, so an upper bound), fit per frame after the first (the
CPU time of the fit apportioned by its per-frame wall times), train_field per optimisation step,
render per image. The growth exponent k of each stage and axis is the least-squares slope of
log(cost) on log(size); paper scale (8 views at 512^2, 400-800 frames, 6-9K garment vertices,
25 bones, ~10K simulated frames) is estimated as cost(demo) x prod_axis (paper / demo)^k.
"""
from __future__ import annotations

import os

if __name__ == "__main__":  # one thread everywhere, set before numpy / torch load their thread pools
    for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[_v] = "1"
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import copy  # noqa: E402
import csv  # noqa: E402
import dataclasses  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.benchutil import cpu_model, cuda_summary, git_rev  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CODE_PATHS = ("anidress_core", "benchmarks/bench_scaling.py")
STAGES = ("synth", "simulate", "rig", "masks", "flows", "fit", "train_field", "render")
AXES = ("frames", "views", "image", "vertices", "bones")
#: what one unit of each stage's cost is
UNIT = {"synth": "frame (all cameras)", "simulate": "simulated frame", "rig": "decomposition",
        "masks": "frame (training views)", "flows": "frame (training views)", "fit": "frame (t > 0)",
        "train_field": "optimisation step", "render": "image"}
#: how the size of an axis is counted (the exponent is fitted on this)
SIZE_UNIT = {"frames": "frames", "views": "training views", "image": "pixels per image",
             "vertices": "garment vertices", "bones": "bones"}


@dataclasses.dataclass(frozen=True)
class Plan:
    """The sizes run. The first entry of each axis list is the base (demo) value of that axis."""

    scene_frames: int          # frames of each rendered scene (per-frame stages)
    settle: int                # cloth settle frames of the scenes' ground truth and of the simulations
    texture: int               # procedural texture size of the scenes
    views: tuple               # training views (ring: views + views // 2 cameras)
    image: tuple               # H = W
    vertices: tuple            # garment vertices (target of make_skirt / the template)
    bones: tuple
    sim_frames: tuple          # simulate: frames of lib-walk at the base vertex count
    rig_frames_base: int       # rig vertices / bones axes: decompose this many frames
    train_steps: int
    chain_axes: tuple = ("views", "image", "vertices", "bones")  # axes of the scene chain (synth .. render)
    body_vertices: int = 0     # mannequin vertices of the scenes; 0 = the config's
    #: the paper's scale: (low, high) per axis
    paper: dict = dataclasses.field(default_factory=lambda: {
        "views": (8, 8), "image": (512 * 512, 512 * 512), "vertices": (6000, 9000), "bones": (25, 25),
        "frames": (400, 800), "sim_frames": (10000, 10000)})


DEFAULT = Plan(scene_frames=4, settle=5, texture=1024, views=(8, 12, 16, 24), image=(256, 384, 512, 768),
               vertices=(3000, 6000, 9000, 12000), bones=(25, 40, 60, 80), sim_frames=(60, 120, 240, 480),
               rig_frames_base=60, train_steps=6)
QUICK = Plan(scene_frames=3, settle=2, texture=128, views=(2, 3), image=(32, 48), vertices=(400, 600), bones=(4, 6),
             sim_frames=(3, 6), rig_frames_base=3, train_steps=1, chain_axes=("image",), body_vertices=1500)


# --------------------------------------------------------------------------- child processes


def fork_call(fn, log_path: Path, *args, **kwargs) -> dict:
    """Run ``fn(*args, **kwargs)`` (returns a JSON-able dict) in a forked child; its stdout/stderr go to
    ``log_path``. Returns the dict plus ``child_cpu_s`` and ``peak_rss_mb`` of the child (os.wait4)."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    r, w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # child
        code = 0
        try:
            os.close(r)
            fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.dup2(fd, 1)
            os.dup2(fd, 2)
            from anidress_core.stages import setup_logging

            setup_logging(None)
            out = {"ok": True, **fn(*args, **kwargs)}
        except BaseException:  # noqa: BLE001 -- reported to the parent
            out = {"ok": False, "error": traceback.format_exc()[-3000:]}
            code = 1
        try:
            with os.fdopen(w, "w") as fh:
                fh.write(json.dumps(out))
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r) as fh:
        text = fh.read()
    _, status, ru = os.wait4(pid, 0)
    res = json.loads(text) if text else {"ok": False, "error": f"child exited with status {status}, no result"}
    if not res.get("ok"):
        raise RuntimeError(f"{fn.__name__} failed (log {log_path}):\n{res.get('error')}")
    res["child_cpu_s"] = ru.ru_utime + ru.ru_stime
    res["peak_rss_mb"] = ru.ru_maxrss / 1024.0  # Linux: KiB
    return res


def _cpu(fn, *args, **kwargs):
    c0 = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - c0


def w_baseline() -> dict:
    return {}


def w_synth(cfg: dict, out_dir: str) -> dict:
    import torch

    from anidress_core.stages.synth import build_scene, run_synth

    torch.set_num_threads(1)
    build_scene(cfg)  # cold: first-use caches (body model, ...), as run_synth's own call below finds them warm
    _, setup = _cpu(build_scene, cfg)
    _, total = _cpu(run_synth, cfg, "bench", out_dir, threads=1, progress=False)
    T = sum(s["frames"] for s in cfg["sequences"])
    return {"stage_cpu_s": total, "setup_cpu_s": setup, "units": T, "cpu_per_unit": (total - setup) / T}


def w_template(scene_dir: str, vertices: int, out_npz: str) -> dict:
    from anidress_core.io.scene import load_body, read_scene
    from anidress_core.stages.template import run_template

    info = read_scene(scene_dir)
    run_template(Path(scene_dir) / info["garment_template"], info["garment_kind"], load_body(scene_dir, info),
                 vertices, Path(out_npz).with_suffix(".ply"), out_npz, config={"vertices": vertices})
    return {}


def w_motion(name: str, scene_dir: str, sim_cfg: dict, out_npz: str) -> dict:
    from anidress_core.stages.simulate import run_motion

    run_motion(name, scene_dir, sim_cfg, out_npz)
    return {}


def w_simulate(template: str, motion: str, scene_dir: str, cloth: dict, out_npz: str) -> dict:
    import torch

    from anidress_core.stages.simulate import run_simulate

    torch.set_num_threads(1)
    res, total = _cpu(run_simulate, template, motion, scene_dir, cloth, out_npz, progress=False)
    steps = res.frames.shape[0] + int(cloth["settle_frames"]) - 1
    return {"stage_cpu_s": total, "units": steps, "cpu_per_unit": total / steps,
            "vertices": int(res.frames.shape[1])}


def w_rig(template: str, sims: list, params: dict, out_npz: str) -> dict:
    import torch

    from anidress_core.stages.rig import run_rig

    torch.set_num_threads(1)
    art, total = _cpu(run_rig, template, sims, params, out_npz, device="cpu")
    return {"stage_cpu_s": total, "units": 1, "cpu_per_unit": total, "bones_used": int(art.model.num_bones),
            "frames": int(art.meta["frames_decomposed"]), "rmse_mm": 1e3 * float(art.model.rmse)}


def w_masks(scene_dir: str, out_dir: str, cfg: dict, template: str, frames: int) -> dict:
    from anidress_core.stages.cues import run_masks

    _, total = _cpu(run_masks, scene_dir, "walk", out_dir, cfg, template_npz=template, cameras="train", threads=1,
                    progress=False)
    return {"stage_cpu_s": total, "units": frames, "cpu_per_unit": total / frames}


def w_flows(scene_dir: str, masks_dir: str, out_dir: str, cfg: dict, template: str, frames: int) -> dict:
    from anidress_core.stages.cues import run_flows

    _, total = _cpu(run_flows, scene_dir, "walk", masks_dir, out_dir, cfg, template_npz=template, cameras="train",
                    threads=1, progress=False)
    return {"stage_cpu_s": total, "units": frames, "cpu_per_unit": total / frames}


def w_fit(scene_dir: str, rig: str, template: str, masks: str, flows: str, params: dict, out_npz: str) -> dict:
    import torch

    from anidress_core.io.garment_poses import load_garment_poses
    from anidress_core.stages.fit import run_fit

    torch.set_num_threads(1)
    normals = str(Path(scene_dir) / "walk" / "normals")
    # the rig here is decomposed from library motions only, without a simulation of walk for L_prior to
    # follow: the pipeline's loss with the frame-0 prior (the same cost per frame)
    meta, total = _cpu(run_fit, scene_dir, "walk", rig, template, masks, flows, normals,
                       params, out_npz, ablation="pipeline_no_sim_prior", progress=False, cue_source="pipeline")
    a, _ = load_garment_poses(out_npz)
    wall = np.asarray(a["wall_s"], float)
    T = len(wall)
    # the fit's CPU time apportioned by the frames' wall times: frames t > 0 (frame 0 has its own budget)
    later = meta["cpu_fit_s"] * wall[1:].sum() / wall.sum()
    return {"stage_cpu_s": total, "units": T - 1, "cpu_per_unit": later / (T - 1),
            "frame0_cpu_s": meta["cpu_fit_s"] * wall[0] / wall.sum()}


def w_train(scene_dir: str, masks: str, out_pt: str, field: dict, lpips_params: dict | None, template: str, rig: str,
            poses: str) -> dict:
    import torch

    from anidress_core.metrics.image import load_lpips
    from anidress_core.stages.field import run_train

    torch.set_num_threads(1)
    lpips = load_lpips(**lpips_params) if lpips_params else None
    out, total = _cpu(run_train, scene_dir, "walk", "full", masks, out_pt, field, template_npz=template, rig_npz=rig,
                      garment_poses_npz=poses, lpips=lpips, device="cpu", progress=False)
    return {"stage_cpu_s": total, "units": int(out["steps"]), "cpu_per_unit": out["cpu_s"] / out["steps"],
            "setup_cpu_s": total - out["cpu_s"], "lpips": str(out["lpips"])[:80]}


def w_render(field_pt: str, scene_dir: str, out_dir: str, field: dict, template: str, rig: str, poses: str,
             camera: str, frames: int) -> dict:
    import torch

    from anidress_core.stages.field import run_render

    torch.set_num_threads(1)
    s, total = _cpu(run_render, field_pt, scene_dir, out_dir, field, seq="walk", cameras=[camera],
                    garment_poses_npz=poses, template_npz=template, rig_npz=rig, frame_stride=frames, device="cpu",
                    progress=False)
    per = [p["cpu_seconds"] for p in s["per_image"]]
    return {"stage_cpu_s": total, "units": len(per), "cpu_per_unit": float(np.mean(per)),
            "samples_per_ray": s["samples_per_ray"]}


def w_warmup(scene_dir: str, template: str, motion: str, cloth: dict, work: str) -> dict:
    """Fill Warp's kernel cache (sim, rig) so that no measured point pays a compile."""
    from anidress_core.stages.rig import run_rig
    from anidress_core.stages.simulate import run_simulate

    run_simulate(template, motion, scene_dir, cloth, Path(work) / "sim.npz", progress=False)
    run_rig(template, [Path(work) / "sim.npz"], {"bones": 2, "iters": 1, "nnz": 2}, Path(work) / "rig.npz",
            device="cpu")
    return {}


# --------------------------------------------------------------------------- the run


class Runner:
    def __init__(self, plan: Plan, work: Path, config: dict, verbose: bool = True):
        self.plan, self.work, self.config, self.verbose = plan, work, config, verbose
        self.rows: list[dict] = []
        self.loads: list[str] = []
        self.base = {"views": plan.views[0], "image": plan.image[0], "vertices": plan.vertices[0],
                     "bones": plan.bones[0]}
        self._templates: dict[int, Path] = {}
        self._scenes: dict[tuple, Path] = {}
        self._cues: dict[tuple, tuple[Path, Path]] = {}
        self._rigs: dict[tuple, Path] = {}
        self._sims: dict[tuple, Path] = {}
        self._chain: dict[tuple, dict] = {}
        self.t0 = time.perf_counter()
        self.date = datetime.datetime.now().isoformat(timespec="seconds")
        self.git = git_rev(CODE_PATHS)
        self.reanalysed = False
        self.cmd = " ".join([".venv/bin/python", "-m", "benchmarks.bench_scaling"] + sys.argv[1:])

    def say(self, msg: str) -> None:
        if self.verbose:
            print(f"[{time.perf_counter() - self.t0:7.1f} s] {msg}", flush=True)

    def call(self, name: str, fn, *args, **kwargs) -> dict:
        res = fork_call(fn, self.work / "logs" / f"{name}.log", *args, **kwargs)
        if "cpu_per_unit" in res:
            self.say(f"{name}: {res['cpu_per_unit']:.4g} CPU s per unit, peak RSS {res['peak_rss_mb']:.0f} MB")
        return res

    def record(self, stage: str, axis: str, size: float, res: dict, **dims) -> None:
        d = {**self.base, "frames": dims.pop("frames", self.plan.scene_frames), **dims}
        self.rows.append({"stage": stage, "axis": axis, "size": size, "res": res, "dims": d})

    # inputs ----------------------------------------------------------------
    def scene_cfg(self, views: int, image: int, vertices: int) -> dict:
        p = self.plan
        cfg = copy.deepcopy(self.config["scenes"]["skirt"])
        cfg["image_size"] = [image, image]
        cfg["cameras"] = dict(cfg["cameras"], count=views + max(1, views // 2), train=views)
        cfg["garment"] = dict(cfg["garment"], vertices=vertices, cloth=dict(cfg["garment"]["cloth"],
                                                                             settle_frames=p.settle))
        cfg["render"] = dict(cfg["render"], texture_size=p.texture)
        if p.body_vertices:
            cfg["body"] = dict(cfg["body"], vertices=p.body_vertices)
        cfg["sequences"] = [{"name": "walk", "motion": "walk", "frames": p.scene_frames, "role": "train"}]
        return cfg

    def scene(self, views: int, image: int, vertices: int, axis: str | None) -> Path:
        key = (views, image, vertices)
        if key not in self._scenes:
            d = self.work / "scenes" / f"v{views}_s{image}_g{vertices}"
            res = self.call(f"synth_{d.name}", w_synth, self.scene_cfg(*key), str(d))
            self._scenes[key] = d
            self._synth_res = getattr(self, "_synth_res", {})
            self._synth_res[key] = res
        return self._scenes[key]

    def use_inputs(self, views: int, image: int, vertices: int, scene: Path, template: Path | None = None) -> None:
        """Use an existing scene (and garment template) for this point instead of making them."""
        self._scenes[(views, image, vertices)] = Path(scene)
        if template is not None:
            self._templates[vertices] = Path(template)

    def template(self, vertices: int) -> Path:
        if vertices not in self._templates:
            sd = self.scene(self.base["views"], self.base["image"], vertices, None)
            out = self.work / "templates" / f"template{vertices}.npz"
            self.call(f"template{vertices}", w_template, str(sd), vertices, str(out))
            self._templates[vertices] = out
        return self._templates[vertices]

    def sim_cfg(self) -> dict:
        s = copy.deepcopy(self.config["simulate"])
        s["cloth"] = dict(s["cloth"], settle_frames=self.plan.settle)
        return s

    def sim(self, frames: int, vertices: int) -> tuple[Path, dict]:
        key = (frames, vertices)
        if key not in self._sims:
            base_scene = self.scene(self.base["views"], self.base["image"], self.base["vertices"], None)
            mot = self.work / "motions" / f"lib-walk{frames}.npz"
            if not mot.is_file():
                cfg = dict(self.sim_cfg(), library_frames=frames)
                self.call(f"motion{frames}", w_motion, "lib-walk", str(base_scene), cfg, str(mot))
            out = self.work / "sims" / f"lib-walk{frames}_g{vertices}.npz"
            res = self.call(f"simulate_t{frames}_g{vertices}", w_simulate, str(self.template(vertices)), str(mot),
                            str(base_scene), self.sim_cfg()["cloth"], str(out))
            self._sims[key] = (out, res)
        return self._sims[key]

    def rig(self, frames: tuple, vertices: int, bones: int) -> tuple[Path, dict]:
        key = (frames, vertices, bones)
        if key not in self._rigs:
            sims = [str(self.sim(t, vertices)[0]) for t in frames]
            out = self.work / "rigs" / f"rig_t{'+'.join(map(str, frames))}_g{vertices}_b{bones}.npz"
            params = dict(self.config["rig"], bones=bones)
            res = self.call(out.stem, w_rig, str(self.template(vertices)), sims, params, str(out))
            self._rigs[key] = (out, res)
        return self._rigs[key]

    def cues(self, key: tuple) -> tuple[Path, Path, dict, dict]:
        if key not in self._cues:
            sd = self.scene(*key, None)
            tpl = str(self.template(key[2]))
            name = sd.name
            m = self.work / "cues" / name / "masks"
            f = self.work / "cues" / name / "flows"
            rm = self.call(f"masks_{name}", w_masks, str(sd), str(m), self.config["cues"]["masks"], tpl,
                           self.plan.scene_frames)
            rf = self.call(f"flows_{name}", w_flows, str(sd), str(m), str(f), self.config["cues"]["flows"], tpl,
                           self.plan.scene_frames)
            self._cues[key] = (m, f, rm, rf)
        return self._cues[key]

    def field_params(self) -> dict:
        fp = copy.deepcopy(self.config["field"])
        fp["train"] = dict(fp["train"], steps=self.plan.train_steps, checkpoint_every=10 ** 6)
        return fp

    def chain(self, axis: str, size: float, views: int, image: int, vertices: int, bones: int,
              stages=("synth", "masks", "flows", "fit", "train_field", "render")) -> None:
        """Scene -> cues -> fit -> field -> render at one point; records the asked stages."""
        p = self.plan
        key = (views, image, vertices)
        sd = self.scene(*key, axis)
        dims = dict(views=views, image=image, vertices=vertices, bones=bones)
        if "synth" in stages:
            self.record("synth", axis, size, self._synth_res[key], **dims)
        m, f, rm, rf = self.cues(key)
        if "masks" in stages:
            self.record("masks", axis, size, rm, **dims)
            self.record("flows", axis, size, rf, **dims)
        for st, res in self.fit_field(key, bones, "render" in stages).items():
            self.record(st, axis, size, res, **dims)

    def fit_field(self, key: tuple, bones: int, render: bool) -> dict:
        """fit -> train_field (-> render) of scene ``key`` with the rig of ``bones`` bones; each measured once."""
        p = self.plan
        sd = self.scene(*key, None)
        m, f, _, _ = self.cues(key)
        tpl = self.template(key[2])
        rig, _ = self.rig((p.rig_frames_base,), key[2], bones)
        name = f"{sd.name}_b{bones}"
        done = self._chain.setdefault(name, {})
        poses = self.work / "fit" / name / "garment_poses.npz"
        if "fit" not in done:
            fit_params = dict(self.config["fit"], **(self.config["scenes"]["skirt"].get("fit") or {}))
            fit_params.update(frames=p.scene_frames, threads=1, device="cpu", first_frame_init="body")
            done["fit"] = self.call(f"fit_{name}", w_fit, str(sd), str(rig), str(tpl), str(m), str(f), fit_params,
                                    str(poses))
        fp = self.field_params()
        pt = self.work / "field" / name / "field.pt"
        if "train_field" not in done:
            lp = self.config["metrics"]["lpips"] if fp["train"]["lpips_weight"] > 0 else None
            done["train_field"] = self.call(f"train_{name}", w_train, str(sd), str(m), str(pt), fp, lp, str(tpl),
                                            str(rig), str(poses))
        if render and "render" not in done:
            from anidress_core.io.scene import read_scene

            cam = read_scene(sd)["cameras"]["test"][0]
            done["render"] = self.call(f"render_{name}", w_render, str(pt), str(sd), str(self.work / "render" / name),
                                       fp, str(tpl), str(rig), str(poses), cam, p.scene_frames)
        return {k: v for k, v in done.items() if k != "render" or render}

    def run(self) -> None:
        p, b = self.plan, self.base
        self.loads.append(f"start {load()}")
        self.baseline = self.call("baseline", w_baseline)
        # warm-up: Warp kernels (the base scene and template are inputs everywhere)
        sd = self.scene(b["views"], b["image"], b["vertices"], None)
        mot = self.work / "motions" / "warmup.npz"
        self.call("motion_warmup", w_motion, "lib-walk", str(sd), dict(self.sim_cfg(), library_frames=2), str(mot))
        self.call("warmup", w_warmup, str(sd), str(self.template(b["vertices"])), str(mot), self.sim_cfg()["cloth"],
                  str(self.work / "warmup"))
        # simulate + rig: frames
        for t in p.sim_frames:
            _, res = self.sim(t, b["vertices"])
            self.record("simulate", "frames", t, res, frames=t)
        rig_sets = [(t,) for t in p.sim_frames if t >= p.rig_frames_base] + [tuple(p.sim_frames)]
        for s in rig_sets:
            _, res = self.rig(s, b["vertices"], b["bones"])
            self.record("rig", "frames", res["frames"], res, frames=res["frames"])
        self.loads.append(f"after sim/rig frames {load()}")
        # simulate + rig: vertices (the chain below uses these rigs)
        for v in p.vertices if "vertices" in p.chain_axes else ():
            _, res = self.sim(p.rig_frames_base, v)
            self.record("simulate", "vertices", res["vertices"], res, vertices=v, frames=p.rig_frames_base)
            _, res = self.rig((p.rig_frames_base,), v, b["bones"])
            self.record("rig", "vertices", v, res, vertices=v, frames=p.rig_frames_base)
        for nb in p.bones if "bones" in p.chain_axes else ():
            _, res = self.rig((p.rig_frames_base,), b["vertices"], nb)
            self.record("rig", "bones", nb, res, bones=nb, frames=p.rig_frames_base)
        self.loads.append(f"after sim/rig {load()}")
        # the scene chain
        for v in p.views if "views" in p.chain_axes else ():
            self.chain("views", v, v, b["image"], b["vertices"], b["bones"],
                       stages=("synth", "masks", "fit", "train_field"))
        self.loads.append(f"after views {load()}")
        for s in p.image if "image" in p.chain_axes else ():
            self.chain("image", s * s, b["views"], s, b["vertices"], b["bones"])
        self.loads.append(f"after image {load()}")
        for v in p.vertices if "vertices" in p.chain_axes else ():
            self.chain("vertices", v, b["views"], b["image"], v, b["bones"])
        for nb in p.bones if "bones" in p.chain_axes else ():
            self.chain("bones", nb, b["views"], b["image"], b["vertices"], nb, stages=("fit", "train_field", "render"))
        self.loads.append(f"end {load()}")


def load() -> str:
    try:
        return " / ".join(open("/proc/loadavg").read().split()[:3])
    except OSError:
        return "?"


# --------------------------------------------------------------------------- analysis


def exponent(sizes, costs) -> float:
    """Least-squares slope of log(cost) on log(size); NaN with fewer than two distinct sizes."""
    x, y = np.log(np.asarray(sizes, float)), np.log(np.asarray(costs, float))
    if len(set(x.tolist())) < 2 or not np.all(np.isfinite(y)):
        return float("nan")
    return float(np.polyfit(x, y, 1)[0])


#: exponents not measured, with the reason (per-unit costs that do not depend on the axis by construction,
#: or memory that grows as another axis does). (stage, axis) -> (cpu exponent, rss exponent or axis, reason)
ASSUMED = {
    ("synth", "frames"): (0.0, 0.0, "cost per frame; frames are rendered one at a time"),
    ("masks", "frames"): (0.0, 0.0, "cost per frame; frames are processed one at a time"),
    ("flows", "frames"): (0.0, 0.0, "cost per frame; frames are processed one at a time"),
    ("fit", "frames"): (0.0, 0.0, "cost per frame; frames are fitted one at a time"),
    ("train_field", "frames"): (0.0, "views", "cost per step (fixed rays per step); the images and masks of "
                                "all frames x views are held in memory, so memory grows as on the views axis"),
    ("render", "frames"): (0.0, 0.0, "cost per image"),
    ("render", "views"): (0.0, 0.0, "cost per image"),
    ("flows", "bones"): (0.0, 0.0, "no rig in this stage"), ("masks", "bones"): (0.0, 0.0, "no rig in this stage"),
    ("synth", "bones"): (0.0, 0.0, "no rig in this stage"), ("simulate", "bones"): (0.0, 0.0, "no rig"),
    ("simulate", "views"): (0.0, 0.0, "no images"), ("simulate", "image"): (0.0, 0.0, "no images"),
    ("rig", "views"): (0.0, 0.0, "no images"), ("rig", "image"): (0.0, 0.0, "no images"),
}

#: reasons identified for growth worse than linear in the work (printed only where the fitted exponent says so)
SUPERLINEAR_REASONS: dict[tuple[str, str], str] = {
    ("synth", "image"): "Timed alone (one process, 12 views, body only, 512^2 and 768^2), each part of a frame's "
                        "work grows close to the pixel ratio: `synth.render_views`, `synth.forward_flow`, "
                        "`synth.degrade_normals` and the PNG/EXR writes. The excess seen here is not identified; "
                        "candidates are memory traffic at this peak RSS and the shared machine's load (one run "
                        "per point).",
}


def _pts(rows, stage, axis):
    return sorted((r for r in rows if r["stage"] == stage and r["axis"] == axis), key=lambda r: r["size"])


def _rss_above(r, baseline_mb: float) -> float:
    return max(r["res"]["peak_rss_mb"] - baseline_mb, 1.0)


def end_slope(pts, value) -> float:
    """log-log slope between the two largest sizes (the trend at the end of the measured range)."""
    if len(pts) < 2:
        return float("nan")
    (s1, v1), (s2, v2) = [(p["size"], value(p)) for p in pts[-2:]]
    return math.log(v2 / v1) / math.log(s2 / s1)


def analyse(rows: list[dict], baseline_mb: float) -> dict:
    """{(stage, axis): {k_cpu, k_cpu_end, k_rss, points}} from the measured rows."""
    fits = {}
    for st in STAGES:
        for ax in AXES:
            pts = _pts(rows, st, ax)
            if not pts:
                continue
            sizes = [r["size"] for r in pts]
            k = exponent(sizes, [r["res"]["cpu_per_unit"] for r in pts])
            above = [_rss_above(r, baseline_mb) for r in pts]
            fits[(st, ax)] = {"k_cpu": k, "k_rss": exponent(sizes, above), "points": len(pts),
                              "k_cpu_end": end_slope(pts, lambda r: r["res"]["cpu_per_unit"])}
    return fits


def base_row(rows, stage):
    """The stage's measurement at the base (demo) point: the first point of its first axis."""
    for ax in AXES:
        pts = _pts(rows, stage, ax)
        if pts:
            return pts[0]
    return None


def _pair(pts, target):
    """The two measured points to interpolate / extrapolate from towards ``target`` (sorted by size)."""
    if target <= pts[1]["size"]:
        return pts[0], pts[1]
    if target >= pts[-2]["size"]:
        return pts[-2], pts[-1]
    i = max(j for j in range(len(pts) - 1) if pts[j]["size"] <= target)
    return pts[i], pts[i + 1]


def cpu_factor(pts, base, target) -> float:
    """cost(target) / cost(base) along one axis: log-log line through the two measured points nearest the
    target (interpolation inside the range; beyond it the end slope, not below 0)."""
    if len(pts) < 2 or target == base["size"]:
        return 1.0
    a, b = _pair(pts, target)
    k = math.log(b["res"]["cpu_per_unit"] / a["res"]["cpu_per_unit"]) / math.log(b["size"] / a["size"])
    if not (pts[0]["size"] <= target <= pts[-1]["size"]):
        k = max(k, 0.0)
    return a["res"]["cpu_per_unit"] * (target / a["size"]) ** k / base["res"]["cpu_per_unit"]


def rss_factor(pts, base, target, baseline_mb: float) -> float:
    """(peak RSS - baseline)(target) / (same at base): a straight line (memory adds up) through the two
    measured points nearest the target, slope not below 0."""
    if len(pts) < 2 or target == base["size"]:
        return 1.0
    a, b = _pair(pts, target)
    ya, yb = _rss_above(a, baseline_mb), _rss_above(b, baseline_mb)
    slope = max((yb - ya) / (b["size"] - a["size"]), 0.0)
    return max(ya + slope * (target - a["size"]), 1.0) / _rss_above(base, baseline_mb)


def paper_estimate(rows, fits, plan: Plan, baseline_mb: float, steps: int) -> list[dict]:
    """Per stage: CPU s per unit and peak RSS at paper scale (low / high), and the stage's total. Each axis
    contributes a factor (cpu_factor, rss_factor) from the demo point to the paper size; the factors multiply."""
    out = []
    for st in STAGES:
        b = base_row(rows, st)
        if b is None:
            continue
        est = {}
        for lh, i in (("low", 0), ("high", 1)):
            cpu, rss, notes = b["res"]["cpu_per_unit"], _rss_above(b, baseline_mb), []
            for ax in ("views", "image", "vertices", "bones", "frames"):
                pts = _pts(rows, st, ax)
                if ax == "frames":
                    target = plan.paper["sim_frames" if st in ("simulate", "rig") else "frames"][i]
                else:
                    target = plan.paper[ax][i]
                if pts:
                    base = min(pts, key=lambda r: r["size"])
                    cpu *= cpu_factor(pts, base, target)
                    rss *= rss_factor(pts, base, target, baseline_mb)
                elif (st, ax) in ASSUMED:
                    kc, kr, why = ASSUMED[(st, ax)]
                    notes.append(f"{ax}: {why}")
                    if isinstance(kr, str):  # memory grows as on axis kr, at the equivalent size
                        other = _pts(rows, st, kr)
                        if len(other) >= 2:
                            eq = other[0]["size"] * target / plan.scene_frames
                            rss *= rss_factor(other, other[0], eq, baseline_mb)
                else:
                    notes.append(f"{ax}: not measured, taken as no growth")
            units = {"synth": plan.paper["frames"][i], "masks": plan.paper["frames"][i],
                     "flows": plan.paper["frames"][i], "fit": plan.paper["frames"][i],
                     "simulate": plan.paper["sim_frames"][i], "rig": 1, "train_field": steps,
                     "render": plan.paper["views"][i] * plan.paper["frames"][i]}[st]
            est[lh] = {"cpu_per_unit": cpu, "total_cpu_s": cpu * units, "units": units, "rss_mb": baseline_mb + rss,
                       "notes": notes}
        out.append({"stage": st, **est})
    return out


# --------------------------------------------------------------------------- output


def paper_by(paper: list[dict], stage: str) -> dict:
    return next((p for p in paper if p["stage"] == stage), {"high": {"rss_mb": float("nan")}})


def fmt(x: float, nd: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    return f"{x:.{nd}g}" if abs(x) < 1e5 else f"{x:.3e}"


def hms(s: float) -> str:
    if not math.isfinite(s):
        return "n/a"
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def write(out: Path, runner: Runner, fits: dict, paper: list[dict], args, wall_s: float, cpu_s: float) -> None:
    import torch

    plan, rows = runner.plan, runner.rows
    baseline = runner.baseline["peak_rss_mb"]
    out.mkdir(parents=True, exist_ok=True)
    cols = ["kind", "stage", "axis", "size", "size_unit", "views", "image_px", "garment_vertices", "bones", "frames",
            "unit", "units_measured", "cpu_s_per_unit", "stage_cpu_s", "child_cpu_s", "peak_rss_mb",
            "rss_above_baseline_mb", "exponent_cpu", "exponent_cpu_end", "exponent_rss", "paper_cpu_s_per_unit_low",
            "paper_cpu_s_per_unit_high", "paper_total_cpu_s_low", "paper_total_cpu_s_high", "paper_rss_mb_low",
            "paper_rss_mb_high", "paper_units_low", "paper_units_high"]
    lines_csv = []
    for r in rows:
        f = fits[(r["stage"], r["axis"])]
        d, res = r["dims"], r["res"]
        lines_csv.append({
            "kind": "measured", "stage": r["stage"], "axis": r["axis"], "size": r["size"],
            "size_unit": SIZE_UNIT[r["axis"]], "views": d["views"], "image_px": d["image"],
            "garment_vertices": d["vertices"], "bones": res.get("bones_used", d["bones"]), "frames": d["frames"],
            "unit": UNIT[r["stage"]], "units_measured": res["units"], "cpu_s_per_unit": f"{res['cpu_per_unit']:.6g}",
            "stage_cpu_s": f"{res['stage_cpu_s']:.4g}", "child_cpu_s": f"{res['child_cpu_s']:.4g}",
            "peak_rss_mb": f"{res['peak_rss_mb']:.1f}", "rss_above_baseline_mb": f"{res['peak_rss_mb'] - baseline:.1f}",
            "exponent_cpu": f"{f['k_cpu']:.3f}", "exponent_cpu_end": f"{f['k_cpu_end']:.3f}",
            "exponent_rss": f"{f['k_rss']:.3f}"})
    for p in paper:
        lo, hi = p["low"], p["high"]
        lines_csv.append({
            "kind": "paper_estimate", "stage": p["stage"], "axis": "all", "unit": UNIT[p["stage"]],
            "paper_cpu_s_per_unit_low": f"{lo['cpu_per_unit']:.6g}",
            "paper_cpu_s_per_unit_high": f"{hi['cpu_per_unit']:.6g}",
            "paper_total_cpu_s_low": f"{lo['total_cpu_s']:.6g}", "paper_total_cpu_s_high": f"{hi['total_cpu_s']:.6g}",
            "paper_rss_mb_low": f"{lo['rss_mb']:.0f}", "paper_rss_mb_high": f"{hi['rss_mb']:.0f}",
            "paper_units_low": lo["units"], "paper_units_high": hi["units"]})
    with open(out / "scaling.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(lines_csv)

    cmd = runner.cmd
    cuda = torch.cuda.is_available()
    cuda_csv = ROOT / "benchmarks" / "cuda.csv"
    if cuda_csv.is_file():
        cuda_line = ("every figure here is a CPU run (device cpu). The GPU paths are timed apart, against the CPU of "
                     "the GPU machine, in [cuda.md](cuda.md) (`python -m benchmarks.bench_cuda`); CUDA speed-up per "
                     f"unit at the paper point there: {cuda_summary(cuda_csv)}.")
    elif cuda:
        cuda_line = ("a CUDA device is visible, but every figure here is a CPU run (device cpu); no CUDA time is "
                     "measured by this benchmark.")
    else:
        cuda_line = (f"untested. torch.cuda.is_available() is False here (torch {torch.__version__}) and no GPU "
                     "device was lent to the session that ran this benchmark (issue 22 item 5), so the GPU paths "
                     "of the field, the cloth solver, the rig and the rasteriser have no measured times.")
    L = [
        "# Scaling of every stage with the work (CPU)", "",
        f"- date: {runner.date}; git {runner.git}" + (f" (tables regenerated from the run's raw results with "
                                                     f"--reanalyse on {datetime.date.today()})" if runner.reanalysed
                                                     else ""),
        f"- command: `{cmd}` ("
        f"{'quick mode: tiny sizes, a smoke test, not figures to keep' if args.quick else 'default sizes'});"
        f" the whole run took {wall_s / 60:.1f} min wall, {cpu_s / 60:.1f} CPU min (children and parent)",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs; Python {platform.python_version()}, torch "
        f"{torch.__version__}, numpy {np.__version__}; every stage on one thread (torch, OpenMP, OpenCV), device cpu",
        f"- load average (1/5/15 min) during the run: {'; '.join(runner.loads)}",
        "- CUDA: " + cuda_line,
        f"- each point: a child process forked after the imports; peak RSS from os.wait4 includes the imported "
        f"modules: a child doing nothing peaks at {baseline:.0f} MB (baseline). CPU s = user + system time of the "
        f"stage call, per unit (see the table). Scenes: `scenes/skirt` of config/config.yaml with one sequence "
        f"`walk` of {plan.scene_frames} frames, ring of views x 3/2 cameras, cloth settle {plan.settle} frames, "
        f"texture {plan.texture}^2; simulate and rig: `lib-walk` on the base scene's body, settle {plan.settle} "
        f"frames; rig with config `rig` (iters {runner.config['rig']['iters']}, nnz {runner.config['rig']['nnz']}); "
        f"fit with config `fit` + `scenes/skirt/fit`, start of frame 0 from the body-skinned template; field: "
        f"variant full, config `field` with {plan.train_steps} steps; render: frame 0 of one test camera.",
        "- base (demo) point of every axis: " + ", ".join(f"{k} {v}" for k, v in runner.base.items()) +
        f"; simulate / rig base {plan.rig_frames_base} frames.", "",
        "## Growth exponents (cost ~ size^k)", "",
        "k from a least-squares line through log(cost per unit) vs log(size) of the points below; size: frames, "
        "training views, pixels per image, garment vertices, bones. k = 1: linear in the work; k = 0: independent. "
        "Memory: k of the peak RSS above the baseline.", "",
        "| stage | unit | axis | points | sizes | CPU s per unit | k (CPU) | k, last two points | peak RSS MB | "
        "k (RSS above baseline) |",
        "| --- | --- | --- | ---: | --- | --- | ---: | ---: | --- | ---: |",
    ]
    for st in STAGES:
        for ax in AXES:
            f = fits.get((st, ax))
            if f is None:
                continue
            pts = sorted((r for r in rows if r["stage"] == st and r["axis"] == ax), key=lambda r: r["size"])
            sizes = ", ".join(f"{int(r['size']) if ax != 'image' else r['dims']['image']}" for r in pts)
            if ax == "image":
                sizes += " (side)"
            L.append(f"| {st} | {UNIT[st]} | {ax} | {f['points']} | {sizes} | "
                     f"{', '.join(fmt(r['res']['cpu_per_unit']) for r in pts)} | {fmt(f['k_cpu'], 2)} | "
                     f"{fmt(f['k_cpu_end'], 2)} | "
                     f"{', '.join(str(round(r['res']['peak_rss_mb'])) for r in pts)} | "
                     f"{fmt(f['k_rss'], 2)} |")
    L += ["", "## Worse than linear in the work", ""]
    sup = [(st, ax, f) for (st, ax), f in fits.items()
           if any(math.isfinite(f[k]) and f[k] > 1.15 for k in ("k_cpu", "k_cpu_end"))]
    if not sup:
        L.append("- No stage grows faster than linearly along any measured axis (every k and every slope of the "
                 "last two points <= 1.15).")
    for st, ax, f in sup:
        pts = sorted((r for r in rows if r["stage"] == st and r["axis"] == ax), key=lambda r: r["size"])
        ratio = pts[-1]["size"] / pts[0]["size"]
        grow = pts[-1]["res"]["cpu_per_unit"] / pts[0]["res"]["cpu_per_unit"]
        reason = SUPERLINEAR_REASONS.get((st, ax), "reason not identified by this benchmark")
        a, b = pts[-2], pts[-1]
        L.append(f"- {st} / {ax}: k = {f['k_cpu']:.2f} over the range ({ratio:.3g}x the {SIZE_UNIT[ax]} costs "
                 f"{grow:.3g}x per {UNIT[st]}), {f['k_cpu_end']:.2f} between the last two points "
                 f"({b['size'] / a['size']:.3g}x costs {b['res']['cpu_per_unit'] / a['res']['cpu_per_unit']:.3g}x). "
                 f"{reason}")
    L += ["", "## Paper scale on this CPU (one thread)", "",
          "cost(demo point) x one factor per axis. CPU: the log-log line through the two measured points nearest "
          "the paper size (interpolated inside the measured range; beyond it the slope of the last two points, not "
          "below 0, so a cost that still falls as a setup is amortised is not carried further down). Memory: the "
          "peak RSS above the baseline on a straight line (memory adds up) through the same two points. "
          "Low: 400 frames, 6K garment vertices; high: 800 frames, 9K vertices; both 8 training views at 512^2, "
          "25 bones, 10K simulated frames. Carried beyond the points above: an estimate, not a measurement.", "",
          "| stage | unit | CPU s per unit (low - high) | units | CPU total (low - high) | peak RSS MB (low - high) | "
          "axes not measured (why) |",
          "| --- | --- | --- | --- | --- | --- | --- |"]
    steps = int(runner.config["field"]["train"]["steps"])
    unit_txt = {"synth": "400 - 800 frames", "masks": "400 - 800 frames", "flows": "400 - 800 frames",
                "fit": "400 - 800 frames", "simulate": "10,000 frames", "rig": "1 (10,000 frames)",
                "train_field": f"{steps} steps (config field/train/steps)",
                "render": "8 views x 400 - 800 frames"}
    tot_lo = tot_hi = 0.0
    for p in paper:
        lo, hi = p["low"], p["high"]
        tot_lo += lo["total_cpu_s"]
        tot_hi += hi["total_cpu_s"]
        L.append(f"| {p['stage']} | {UNIT[p['stage']]} | {fmt(lo['cpu_per_unit'])} - {fmt(hi['cpu_per_unit'])} | "
                 f"{unit_txt[p['stage']]} | {hms(lo['total_cpu_s'])} - {hms(hi['total_cpu_s'])} | "
                 f"{lo['rss_mb']:.0f} - {hi['rss_mb']:.0f} | {'; '.join(dict.fromkeys(lo['notes'])) or '-'} |")
    L += ["", f"- all stages above, once each: {hms(tot_lo)} - {hms(tot_hi)} CPU on one thread of this machine "
              f"(render counted for every frame of 8 views)."]
    hi_img = plan.paper["image"][1]
    data_gb = plan.paper["frames"][1] * plan.paper["views"][1] * hi_img * 4 / 1e9
    L += ["", f"- train_field holds the training images and labels of every frame and view in memory (uint8 RGB + "
              f"uint8 label, `stages.field.read_views`): {plan.paper['frames'][1]} frames x {plan.paper['views'][1]} "
              f"views x {hi_img} pixels x 4 bytes = {data_gb:.1f} GB before any tensor is built from them (the "
              f"estimate above: {fmt(paper_by(paper, 'train_field')['high']['rss_mb'] / 1024)} GB peak)."]
    L += ["", "## Notes", "",
          "- Per-unit costs of masks and flows include the stage's setup (plates, template prior) spread over "
          f"{plan.scene_frames} frames: an upper bound per frame. The fit's frame 0 (its own iteration budget) is "
          "not in its per-frame cost; synth's per-frame cost includes the ground-truth cloth simulation and the "
          "file writes, not build_scene.",
          f"- render is measured on fields trained for {plan.train_steps} steps: its cost per image depends on "
          "the field (samples kept per ray after the occupancy grid and early ray termination), so a fully trained "
          "field may render at another cost per image. train_field's per-step cost does not depend on the number "
          "of steps; its setup (occupancy grids, reading the images) is not in it.",
          "- One run per point on a machine whose cores may be shared (load averages above); the exponents of "
          "small costs (well under a second) are the least reliable."]
    (out / "scaling.md").write_text("\n".join(L) + "\n")


def finish(runner: Runner, args, wall_s: float, cpu_s: float) -> None:
    baseline = runner.baseline["peak_rss_mb"]
    fits = analyse(runner.rows, baseline)
    paper = paper_estimate(runner.rows, fits, runner.plan, baseline, int(runner.config["field"]["train"]["steps"]))
    write(Path(args.out), runner, fits, paper, args, wall_s, cpu_s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test of the script, seconds)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks"), help="folder of scaling.md and scaling.csv")
    ap.add_argument("--workdir", default=None,
                    help="scratch folder of the scenes and stage outputs (emptied first; default "
                         "benchmarks/runs/scaling, with --quick <out>/scaling_work)")
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--reanalyse", metavar="RAW_JSON",
                    help="no run: regenerate scaling.md/.csv from the raw results of an earlier run "
                         "(<workdir>/raw.json, written by every run)")
    args = ap.parse_args()
    if args.reanalyse:
        raw = json.loads(Path(args.reanalyse).read_text())
        runner = Runner(Plan(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw["plan"].items()}),
                        Path(args.reanalyse).parent, raw["config"], verbose=False)
        for k in ("rows", "loads", "baseline", "date", "git", "base", "cmd"):
            setattr(runner, k, raw[k])
        runner.reanalysed = True
        args.quick = raw["quick"]
        finish(runner, args, raw["wall_s"], raw["cpu_s"])
        return
    import torch

    from anidress_core.config import load_config

    torch.set_num_threads(1)
    # import what the children run, once, here (each child is a fork of this process)
    import anidress_core.stages.cues  # noqa: F401
    import anidress_core.stages.field  # noqa: F401
    import anidress_core.stages.fit  # noqa: F401
    import anidress_core.stages.rig  # noqa: F401
    import anidress_core.stages.simulate  # noqa: F401
    import anidress_core.stages.synth  # noqa: F401
    import anidress_core.stages.template  # noqa: F401

    plan = QUICK if args.quick else DEFAULT
    out = Path(args.out)
    work = Path(args.workdir) if args.workdir else (out / "scaling_work" if args.quick else
                                                    ROOT / "benchmarks" / "runs" / "scaling")
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    config = load_config(args.config)
    t0, c0 = time.perf_counter(), time.process_time()
    runner = Runner(plan, work, config)
    runner.run()
    ru = __import__("resource").getrusage(__import__("resource").RUSAGE_CHILDREN)
    cpu = time.process_time() - c0 + ru.ru_utime + ru.ru_stime
    wall = time.perf_counter() - t0
    raw = {"plan": dataclasses.asdict(plan), "config": config, "quick": bool(args.quick), "wall_s": wall, "cpu_s": cpu,
           **{k: getattr(runner, k) for k in ("rows", "loads", "baseline", "date", "git", "base", "cmd")}}
    (work / "raw.json").write_text(json.dumps(raw))
    finish(runner, args, wall, cpu)
    if args.quick and not args.workdir:
        shutil.rmtree(work, ignore_errors=True)
    print(f"wrote {out / 'scaling.md'} and {out / 'scaling.csv'}")


if __name__ == "__main__":
    main()
