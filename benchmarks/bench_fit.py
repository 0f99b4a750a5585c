"""Benchmark of the garment fit (anidress_core.fit) against the synthetic ground truth.

For each scene, sequence and number of training views, fits every loss variant named by
``--methods`` (:data:`anidress_core.fit.variants.VARIANTS`, the one list of them; default: the
paper's loss ``paper``, the pipeline's ``pipeline`` and the paper's ablations ``paper_vertex``,
``paper_no_normal_flow``, ``paper_no_flow``) with the same cues and the config's settings of
the scene (config section ``fit`` with ``scenes/<scene>/fit`` on top), then measures every
frame against the ground-truth garment (stages.fit_eval.run_fit_eval): vertex RMSE (mean, 95th
percentile, worst frame), Chamfer distance, normal consistency, temporal jitter and
acceleration error, frames per second; and the rig's floor on the same motion (RMSE of
rig.fit_transforms on the ground-truth meshes in template topology). A reference, ``sim``, is
no fit at all: the rig driven by its own simulated poses of the sequence
(``rig.transforms_of('seq-<name>')``, the cloth simulation of the template on the sequence's
body motion, paper §4.5): what fitting to the images adds over the simulator. Writes
``<out>.md`` and ``<out>.csv`` (default benchmarks/fit.md and benchmarks/fit.csv; ``--out`` a
folder: fit.md and fit.csv in it); the fitted poses go to ``--runs`` (default
benchmarks/runs/fit/, not committed). Every text of the table and its notes is generated from
VARIANTS, the settings as run and the measurements.

    .venv/bin/python -m benchmarks.bench_fit --scenes skirt --views 8,4 --cues pipeline
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import functools
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from anidress_core.config import load_config, scene_section
from anidress_core.fit import VARIANTS, FitConfig
from anidress_core.io.garment_poses import load_garment_poses
from anidress_core.io.scene import read_scene
from anidress_core.stages import setup_logging
from anidress_core.stages.fit import run_fit
from anidress_core.stages.fit_eval import run_fit_eval
from benchmarks.benchutil import git_rev

REPO = Path(__file__).resolve().parents[1]
#: how the tables' header names the command (a probe that registers variants and calls main sets its own)
PROG = ".venv/bin/python -m benchmarks.bench_fit"

# the code whose uncommitted changes the git revision of a run's table flags
CODE_PATHS = ("anidress_core/fit", "anidress_core/raster.py", "anidress_core/stages/fit.py",
              "anidress_core/stages/fit_eval.py", "anidress_core/io/fit_cues.py")

#: the loss variants fitted by default: the paper's loss, the pipeline's, the paper's ablations (Fig. 9)
DEFAULT_METHODS = ("paper", "pipeline", "paper_vertex", "paper_no_normal_flow", "paper_no_flow")
#: the methods of the suite (--suite): the pipeline, it without the garment texture, the baselines
SUITE_METHODS = ("pipeline", "pipeline_texture_anchor", "paper", "nearest")
#: issue 23's criteria on the held-out scenes (pipeline defaults): median ratio to the rig floor per views,
#: the worst at 8 views, drift on every scene
SUITE_MEDIAN = {8: 1.6, 4: 2.0}
SUITE_WORST_8, SUITE_DRIFT = 2.5, 1.3
#: the reference that is no fit: the rig driven by its simulated poses of the sequence
SIM = "sim"
SIM_DESCRIPTION = ("reference, no fit: the rig driven by its simulated poses of the sequence "
                   "(rig.transforms_of('seq-<sequence>'), the cloth simulator alone, started by simulate/cloth/"
                   "settle_frames as rule synth starts the demo scenes' truth; the suites draw their truth's start; "
                   "no fps)")
#: the reference that is no fit either: the rig driven by the stiffness ensemble's mean simulation
SIM_ENSEMBLE = "sim_ensemble"
SIM_ENSEMBLE_DESCRIPTION = ("reference, no fit: the rig driven by the mean of the simulations of the sequence at "
                            "simulate/ensemble_bend_stiffness x ensemble_settle_frames "
                            "(results/<scene>/sim_ensemble/seq-<sequence>.npz, "
                            "rig.fit_transforms of its frames: L_prior's reference; no fps)")
SIM_REFS = (SIM, SIM_ENSEMBLE)
#: the bound that is no method: the pipeline with every frame started from the rig floor (an oracle)
OPTIMUM, OPTIMUM_OF = "optimum", "pipeline"
OPTIMUM_DESCRIPTION = (f"bound, not a method: `{OPTIMUM_OF}` (the same loss and settings) with every frame started "
                       "from the rig floor (the ground truth's best rig pose): the loss's own minimum near the truth; "
                       "the method's excess over it is what its starts and optimiser leave on the table")
#: the criteria, read on these methods: vertex RMSE < RMSE_TARGET x the rig floor; >= FPS_TARGET
#: frames/s at FPS_VIEWS views
CRITERIA_METHODS = ("pipeline", "paper")
#: the baselines `pipeline` is compared with in the notes
BASELINES = ("paper", "nearest", SIM, SIM_ENSEMBLE)
RMSE_TARGET, FPS_TARGET, FPS_VIEWS = 1.5, 1.0, 8


def description(method: str) -> str:
    """The text of a method: its VARIANTS description (``sim``, ``sim_ensemble``: the simulation references)."""
    return ({SIM: SIM_DESCRIPTION, SIM_ENSEMBLE: SIM_ENSEMBLE_DESCRIPTION, OPTIMUM: OPTIMUM_DESCRIPTION}.get(method)
            or VARIANTS[method].description)


def base_of(method: str) -> str | None:
    """The variant ``method`` is an ablation of: the longest other VARIANTS name it extends
    (``paper_no_flow`` -> ``paper``, ``pipeline_no_anchor`` -> ``pipeline``); None for a base."""
    bases = [n for n in VARIANTS if method != n and method.startswith(n + "_")]
    return max(bases, key=len) if bases else None


def parse_methods(text: str, sim: bool) -> list[str]:
    """``--methods`` as a list of VARIANTS names (the references ``sim``, ``sim_ensemble`` first unless ``sim`` is
    False), checked."""
    names = [m.strip() for m in text.split(",") if m.strip()]
    bad = [m for m in names if m not in (*SIM_REFS, OPTIMUM) and m not in VARIANTS]
    if bad:
        raise SystemExit(f"--methods: unknown {bad}; choose from {[*SIM_REFS, OPTIMUM, *VARIANTS]} "
                         "(anidress_core/fit/variants.py)")
    names = [m for m in dict.fromkeys(names) if m not in SIM_REFS]
    return (list(SIM_REFS) if sim else []) + names


def weights_text(weights: dict) -> str:
    """``2 L_silhouette + 0.1 L_normal + 3 L_flow``: the nonzero weights of a loss, term by term."""
    return " + ".join(f"{w:g} L_{k}" for k, w in weights.items() if w) or "no loss term"


def settings_text(cfg: FitConfig) -> str:
    """The loss and the settings that tell variants apart, as FitConfig holds them."""
    w = dataclasses.asdict(cfg.weights)
    return (f"{weights_text(w)}; method {cfg.method}; {cfg.smooth_passes} temporal filter pass(es)"
            + (f"; L_anchor references: {cfg.anchor_reference}" if w["anchor"] else ""))


def methods_lines(methods: list[str], scene_params: dict[str, dict]) -> list[str]:
    """The methods paragraph of the .md header: each method's VARIANTS description and its
    settings as run (per scene when the scenes' settings differ)."""
    lines = ["- methods (`--methods`, the loss variants of `anidress_core.fit.variants.VARIANTS`; settings "
             "as run: config/config.yaml section `fit` with the scene's `scenes/<scene>/fit` on top, the variant "
             "applied; the loss of each row as used is the csv's `weights` column):"]
    for m in methods:
        if m in SIM_REFS:
            lines.append(f"  - `{m}`: {description(m)}")
            continue
        per = {s: settings_text(FitConfig.from_config(p, OPTIMUM_OF if m == OPTIMUM else m))
               for s, p in scene_params.items()}
        as_run = (next(iter(per.values())) if len(set(per.values())) == 1 else
                  "; ".join(f"{s}: {t}" for s, t in per.items()))
        base = base_of(m)
        lines.append(f"  - `{m}`: {description(m)}" + (f" (an ablation of `{base}`)" if base else "") +
                     f". As run: {as_run}")
    lines.append(f"- criteria, read on {', '.join(f'`{m}`' for m in CRITERIA_METHODS)}: vertex RMSE < "
                 f"{RMSE_TARGET:g} x the rig floor; >= {FPS_TARGET:g} frames/s at {FPS_VIEWS} views. The notes under "
                 "them compare `pipeline` with its baselines ("
                 f"{', '.join(f'`{m}`' for m in BASELINES)}) and each base variant with its ablations; 'better' = "
                 "lower for the first method named.")
    return lines


def cue_dirs(scene: str, seq: str, source: str) -> dict:
    if source == "ground_truth":
        return {"masks": f"data/{scene}/{seq}/gt/masks", "flows": f"data/{scene}/{seq}/gt/flows",
                "normals": f"data/{scene}/{seq}/normals", "label": "gt masks + gt flows + shipped degraded normals"}
    masks = f"results/{scene}/{seq}/masks"
    flows = f"results/{scene}/{seq}/flows"
    for d in (masks, flows):
        if not (REPO / d).is_dir():
            raise SystemExit(f"{d}: pipeline cues not found; run `snakemake --cores 2 {d}` first or use --cues "
                             "ground_truth")
    return {"masks": masks, "flows": flows, "normals": f"data/{scene}/{seq}/normals",
            "label": "pipeline masks + pipeline flows (config cues) + shipped degraded normals"}


def write_sim_poses(rig_npz: str, seq: str, frames: int, out: Path, method: str = SIM,
                    ensemble_npz: str | None = None) -> None:
    """A simulation reference as a garment_poses.npz: the rig driven by its simulated poses of ``seq``
    (``sim``) or by the stiffness ensemble's mean at ``ensemble_npz`` (``sim_ensemble``)."""
    from anidress_core.geometry import lbs
    from anidress_core.io import files
    from anidress_core.io.rig import read_rig
    from anidress_core.stages.fit import ensemble_transforms

    art = read_rig(rig_npz, dtype=torch.float64)
    name = f"seq-{seq}"
    if method == SIM_ENSEMBLE:
        G, source = ensemble_transforms(ensemble_npz, art, frames or None, "cpu")
    else:
        if name not in art.sequences:
            raise SystemExit(f"{rig_npz}: no simulated sequence {name!r} (has {sorted(art.sequences)})")
        G, source = art.transforms_of(name).double(), f"rig.transforms_of({name!r})"
        G = G[:frames] if frames else G
    T = G.shape[0]
    X = lbs(art.model.rest, art.model.weights, G)
    nan = np.full(T, np.nan)
    files.save_npz(out, {"transforms": G.float().numpy(), "verts": X.float().numpy(),
                         "faces": np.asarray(art.faces, np.int64), "loss": nan, "iterations": np.zeros(T, np.int64),
                         "wall_s": nan},
                   meta={"method": method, "loss": method, "description": description(method), "rig": rig_npz,
                         "sequence": seq, "frames": T, "fps": float("nan"), "wall_fit_s": float("nan"),
                         "cpu_fit_s": float("nan"), "torch_threads": torch.get_num_threads(),
                         "source": source})


def ensemble_npz(scene: str, seq: str) -> str:
    """The stiffness ensemble's mean simulation of ``seq`` (rule simulate_ensemble)."""
    return f"results/{scene}/sim_ensemble/seq-{seq}.npz"


#: the settings that left the fit (issue 48; they run at git d6e895a), each with the values at which a fit stored
#: before did what the fit does now (ANY: no effect once the others hold theirs); a stored fit with another value
#: is not reused
ANY = object()
RETIRED_SETTINGS = {"proposal_every": (0,), "proposal_refine": ANY, "proposal_nearest": (8,), "proposal_offsets": (2,),
                    "proposal_velocity_weight": (0.05,), "backward": (False,), "prior_information": ("uniform",),
                    "prior_member_temperature": (None,), "prior_member_window": ANY}


def without_retired(settings: dict | None) -> dict | None:
    """A stored fit's ``params`` or ``config`` without the settings that left the fit (:data:`RETIRED_SETTINGS`),
    or None when one of them held a value that made that fit unlike any fit made now."""
    out = dict(settings or {})
    for k, ok in RETIRED_SETTINGS.items():
        if k in out and ok is not ANY and out.pop(k) not in ok:
            return None
        out.pop(k, None)
    return out


def reusable(path: Path, method: str, params: dict, ensemble: str | None = None,
             inputs: Sequence[str | os.PathLike | None] = ()) -> bool:
    """Whether ``path`` holds a fit of variant ``method`` made with exactly ``params`` and the same
    settings as used (``FitConfig`` of the variant now; the header's ``config``), and, where the variant
    follows the stiffness ensemble, one with the same members as the file ``ensemble`` now and not older
    than it; and not older than any of ``inputs`` (the scene's data folder, rig, cue folders: a scene
    made again, e.g. with other ground-truth cloth, outdates its stored fits as Snakemake would). Settings that
    left the fit since are ignored at the values that did what the fit does now (:func:`without_retired`)."""
    if not path.is_file():
        return False
    made = path.stat().st_mtime_ns
    newer = lambda p: p is not None and Path(p).exists() and Path(p).stat().st_mtime_ns > made  # noqa: E731
    if any(newer(p) for p in inputs):
        return False
    from anidress_core.config import section_defaults

    meta = load_garment_poses(path)[1].get("meta", {})
    key = functools.partial(json.dumps, sort_keys=True, default=str)
    # compared with the schema's defaults filled in: a key added since (at its default) changes nothing
    full = lambda p: key(section_defaults("fit", dict(p or {})))  # noqa: E731
    oracle = method == OPTIMUM
    # and the settings as used the same as the variant's now (a default changed since changes them)
    used = dataclasses.asdict(FitConfig.from_config(params, OPTIMUM_OF if oracle else method))
    # what the fit read of the ensemble (L_prior's reference, frame 0's start) says which members it had
    read = " ".join(meta.get(k) or "" for k in ("followed_simulation", "first_frame_start"))
    from anidress_core.fit.ensemble import ENSEMBLE_NOTE_MARK, ensemble_note

    if ENSEMBLE_NOTE_MARK in read:
        from anidress_core.io.sim import read_sim

        if (ensemble is None or not Path(ensemble).is_file() or newer(ensemble)
                or ensemble_note(read_sim(ensemble, members=False).meta) not in read):
            return False
    stored_params, stored_config = without_retired(meta.get("params")), without_retired(meta.get("config"))
    if stored_params is None or stored_config is None:
        return False
    return (meta.get("loss") == (OPTIMUM_OF if oracle else method) and bool(meta.get("starts")) == oracle
            and full(stored_params) == full(params)
            and key(with_new_settings(stored_config, used)) == key(used))


#: the settings added to the fit since the first stored fits, each at the value that does what the fit did before
#: it existed (the schema holds the pipeline's values): a stored fit without one stands for a variant at that value
HISTORICAL_SETTINGS = {"prior_tangent_planes": "reference", "prior_spread_floor": None, "weights": {"stretch": 0.0}}


def with_new_settings(stored: dict, used: dict, legacy: dict = HISTORICAL_SETTINGS) -> dict:
    """``stored`` (a fit's settings as recorded) with every setting added since filled in from ``used``
    where ``used`` has it at its historical value (:data:`HISTORICAL_SETTINGS`)."""
    out = dict(stored)
    for k, v in used.items():
        if k not in out:
            if k in legacy and v == legacy[k]:
                out[k] = v
        elif isinstance(v, dict) and isinstance(out[k], dict):
            out[k] = with_new_settings(out[k], v, legacy.get(k, {}))
    return out


def floor_transforms(scene: str, seq: str, rig_npz: str, frames: int) -> torch.Tensor:
    """(T, B, 4, 4) the rig floor's poses: ``rig.fit_transforms`` on the ground truth in template topology."""
    from anidress_core.io.rig import read_rig
    from anidress_core.rig import fit_transforms
    from anidress_core.stages.fit_eval import gt_template_vertices

    art = read_rig(rig_npz, dtype=torch.float64)
    Y = gt_template_vertices(f"data/{scene}", seq, art.model.rest, frames or None)[0]
    return fit_transforms(art.model, Y).double()


@functools.lru_cache(maxsize=None)
def chamfer_bias(scene: str, seq: str, samples: int) -> float:
    """The Chamfer of the ground-truth garment of frame 0 against itself (two independent
    sample sets of ``samples`` points): what the Chamfer column reads for a perfect fit."""
    from anidress_core.metrics import mesh as MM

    d = np.load(f"data/{scene}/{seq}/gt/meshes.npz")
    V = torch.as_tensor(d["garment_vertices"][0]).double()
    F = torch.as_tensor(d["garment_faces"]).long()
    a, b = (MM.surface_samples(V, F, samples, torch.Generator().manual_seed(s)) for s in (1, 2))
    return MM.chamfer_normal(a, b).chamfer


def stats(x: np.ndarray, worst="max") -> tuple[float, float, float]:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return (float("nan"),) * 3
    return float(x.mean()), float(np.percentile(x, 95 if worst == "max" else 5)), float(x.max() if worst == "max"
                                                                                        else x.min())


def summary_row(per: list[dict], meta: dict, **key) -> dict:
    """One row of fit.csv (units in the column names) from the per-frame rows of one method in
    fit_metrics.csv and the header ``meta`` of its garment_poses.npz; ``key``: scene, sequence,
    views, method, cues."""
    col = lambda k: np.array([float(x[k]) for x in per])  # noqa: E731
    vr, fl = col("vertex_rmse_m"), col("rig_floor_rmse_m")
    row = {**key, "description": description(key["method"]),
           "weights": weights_text(meta["weights"]) if "weights" in meta else "",
           "frames": len(per), "reference": "rig floor (rig.fit_transforms on GT meshes)",
           "rig_floor_rmse_m": float(fl.mean()),
           "fps": meta["fps"], "wall_fit_s": meta["wall_fit_s"], "torch_threads": meta["torch_threads"],
           "cpu_s_per_frame": meta.get("cpu_fit_s", float("nan")) / max(len(per), 1),
           "iterations_mean": float(col("iterations").mean())}
    for k, worst in (("vertex_rmse_m", "max"), ("chamfer_m", "max"), ("normal_consistency", "min")):
        m, p, w = stats(col(k), worst)
        row[f"{k}_mean"], row[f"{k}_p95" if worst == "max" else f"{k}_p5"], row[f"{k}_worst"] = m, p, w
    row["worst_frame"] = int(np.nanargmax(vr))
    row["jitter_m"] = float(np.nanmean(col("jitter_m")))
    row["gt_jitter_m"] = float(np.nanmean(col("gt_jitter_m")))
    row["accel_error_m"] = float(np.nanmean(col("accel_error_m")))
    row["rmse_over_floor"] = row["vertex_rmse_m_mean"] / row["rig_floor_rmse_m"]
    n = min(10, len(vr) // 2) or 1  # drift: mean error of the last 10 frames over the first 10
    row["drift"] = float(np.nanmean(vr[-n:]) / np.nanmean(vr[:n]))
    row["rig_floor_chamfer_m"] = float(col("rig_floor_chamfer_m").mean())
    row["chamfer_over_floor"] = row["chamfer_m_mean"] / row["rig_floor_chamfer_m"]
    row["reprojection_px"] = float(np.nanmean(col("reprojection_px")))
    row["rig_floor_reprojection_px"] = float(np.nanmean(col("rig_floor_reprojection_px")))
    row["reprojection_over_floor"] = row["reprojection_px"] / row["rig_floor_reprojection_px"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="skirt")
    ap.add_argument("--seq", default="train", help="sequence names, or 'train' (the train-role sequence)")
    ap.add_argument("--views", default="8,4")
    ap.add_argument("--methods", default=None,
                    help=f"loss variants to fit, from {', '.join(VARIANTS)} (anidress_core/fit/variants.py); "
                         f"the references `{SIM}`, `{SIM_ENSEMBLE}` are added unless --no-sim (default: "
                         f"{','.join(DEFAULT_METHODS)})")
    ap.add_argument("--no-sim", action="store_true", help="leave out the simulation-only reference rows")
    ap.add_argument("--cues", default="pipeline", choices=["pipeline", "ground_truth"])
    ap.add_argument("--frames", type=int, default=0, help="fit only the first N frames (0: all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--out", help="output path without suffix (<out>.md, <out>.csv), or a folder (fit.md, fit.csv "
                                  "in it) (default: benchmarks/fit)")
    ap.add_argument("--runs", help="folder of the fitted poses (default: benchmarks/runs/fit)")
    ap.add_argument("--suite", metavar="OVERLAY",
                    help="the evaluation suite (benchmarks/fit_suite.py, e.g. config/fit_suite.yaml; several: "
                         "comma-separated): its scenes, "
                         f"methods {','.join(SUITE_METHODS)} unless --methods, and a summary over the scenes")
    ap.add_argument("--reuse", action="store_true",
                    help="reuse fitted poses already in --runs when made by the same variant with the same settings")
    args = ap.parse_args()
    suite = None
    if args.suite:
        import yaml

        suite = {}
        for f in args.suite.split(","):
            suite.update(yaml.safe_load(Path(f).read_text())["scenes"])
        args.scenes = ",".join(suite)
    methods = parse_methods(args.methods or ",".join(SUITE_METHODS if suite else DEFAULT_METHODS), not args.no_sim)
    # paths given are relative to the working directory, the defaults to the repository
    args.out = out_stem(args.out) if args.out else REPO / "benchmarks" / "fit"
    args.runs = Path(args.runs).absolute() if args.runs else REPO / "benchmarks" / "runs" / "fit"
    os.chdir(REPO)
    torch.set_num_threads(args.threads)
    log = setup_logging(None)
    cfg = load_config("config/config.yaml")
    load0 = os.getloadavg()
    rows, notes, scene_params = [], [], {}
    command = "  ".join([PROG] + sys.argv[1:])
    for scene in args.scenes.split(","):
        params = {k: v for k, v in scene_section(cfg, "fit", scene).items() if k not in ("ablations", "eval")}
        params["threads"] = args.threads
        scene_params[scene] = params
        info = read_scene(f"data/{scene}")
        seqs = [s["name"] for s in info["sequences"] if s.get("role") == "train"] if args.seq == "train" else \
            args.seq.split(",")
        rig = f"results/{scene}/rig.npz"
        for seq in seqs:
            dirs = cue_dirs(scene, seq, args.cues)
            for nv in (int(v) for v in args.views.split(",")):
                run_dir = Path(args.runs) / scene / seq / args.cues / f"v{nv}"
                fits, metas = {}, {}
                for method in methods:
                    out = run_dir / method / "garment_poses.npz"
                    if method in SIM_REFS:  # no fitting: cheap, always recomputed
                        write_sim_poses(rig, seq, args.frames, out, method, ensemble_npz(scene, seq))
                    else:
                        p = dict(params, views=nv)
                        if args.frames:
                            p["frames"] = args.frames
                        inputs = (f"data/{scene}", rig, dirs["masks"], dirs["flows"], dirs["normals"])
                        if not (args.reuse and reusable(out, method, p, ensemble_npz(scene, seq), inputs)):
                            t0 = time.perf_counter()
                            oracle = method == OPTIMUM
                            run_fit(f"data/{scene}", seq, rig, f"results/{scene}/template.npz", dirs["masks"],
                                    dirs["flows"], dirs["normals"], p, out,
                                    ablation=OPTIMUM_OF if oracle else method, progress=False,
                                    cue_source=dirs["label"], motions_dir=f"results/{scene}/motions",
                                    sim_ensemble_npz=ensemble_npz(scene, seq),
                                    starts=floor_transforms(scene, seq, rig, args.frames) if oracle else None)
                            log.info("bench_fit: %s %s v%d %s: %.1f s", scene, seq, nv, method,
                                     time.perf_counter() - t0)
                    fits[method], metas[method] = out, load_garment_poses(out)[1]["meta"]
                    want = OPTIMUM_OF if method == OPTIMUM else method
                    if metas[method].get("loss") != want:
                        raise SystemExit(f"{out}: header meta loss is {metas[method].get('loss')!r}, not {want!r}")
                csv_path = run_dir / "fit_metrics.csv"
                summ = run_fit_eval(f"data/{scene}", seq, rig, fits, csv_path, samples=args.samples)
                with open(csv_path) as fh:
                    per = list(csv.DictReader(fh))
                for method in fits:
                    rows.append(summary_row([x for x in per if x["method"] == method], metas[method], scene=scene,
                                            sequence=seq, views=nv, method=method, cues=args.cues))
                fitted = [m for m in fits if m not in SIM_REFS]
                cams = metas[fitted[0]]["cameras"] if fitted else "--"
                notes.append(f"{scene}/{seq}, {nv} views: template -> ground-truth correspondence distance mean "
                             f"{1e3 * summ['correspondence_mean_m']:.2f} mm, max "
                             f"{1e3 * summ['correspondence_max_m']:.2f}"
                             f" mm; Chamfer sampling bias (the ground truth of frame 0 against itself, two independent "
                             f"sample sets): {1e3 * chamfer_bias(scene, seq, args.samples):.2f} mm; "
                             f"cues: {dirs['label']}"
                             f"; cameras: {cams}")
                for m in fitted:  # a loss as used that is not the one configured (e.g. no normal maps)
                    want = weights_text(dataclasses.asdict(
                        FitConfig.from_config(params, OPTIMUM_OF if m == OPTIMUM else m).weights))
                    got = weights_text(metas[m]["weights"])
                    if got != want:
                        notes.append(f"{scene}/{seq}, {nv} views, `{m}`: ran with {got} (configured: {want})")
    load1 = os.getloadavg()
    write(rows, notes, args, command, load0, load1, methods_lines(methods, scene_params),
          suite_lines(rows, args.suite) if suite else [])


def _mm(x: float) -> str:
    return f"{1e3 * x:.2f}"


def _num(x: float) -> str:
    return f"{x:.2f}" if np.isfinite(x) else "--"


def compare(a_name: str, a: dict, b_name: str, b: dict) -> str:
    """Method ``a`` against method ``b`` (rows of fit.csv): vertex RMSE and its ratio to the rig
    floor, Chamfer and its ratio to the floor's, acceleration error, speed; 'better' = ``a`` lower."""
    def verdict(k):
        return "better" if a[k] < b[k] else "NOT better"

    speed = (f"; {_num(a['fps'])} vs {_num(b['fps'])} frames/s" if np.isfinite(a["fps"]) and np.isfinite(b["fps"])
             else "")
    return (f"`{a_name}` vs `{b_name}`: vertex RMSE {_mm(a['vertex_rmse_m_mean'])} vs {_mm(b['vertex_rmse_m_mean'])} mm"
            f" = {a['rmse_over_floor']:.2f} vs {b['rmse_over_floor']:.2f} x the rig floor -> "
            f"{verdict('vertex_rmse_m_mean')}; Chamfer {_mm(a['chamfer_m_mean'])} vs {_mm(b['chamfer_m_mean'])} mm = "
            f"{a['chamfer_over_floor']:.2f} vs {b['chamfer_over_floor']:.2f} x the rig floor's -> "
            f"{verdict('chamfer_m_mean')}; acceleration error {_mm(a['accel_error_m'])} vs {_mm(b['accel_error_m'])} "
            f"mm -> {verdict('accel_error_m')}{speed}")


def verdicts(rows: list[dict]) -> list[str]:
    """The criteria on CRITERIA_METHODS, then `pipeline` against its BASELINES and
    every base variant against its ablations, per scene, sequence, views and cues."""
    out = []
    groups: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["sequence"], r["views"], r["cues"]), {})[r["method"]] = r
    for (scene, seq, nv, cues), g in groups.items():
        out.append(f"- **{scene}/{seq}, {nv} views ({cues} cues)**")
        for m in CRITERIA_METHODS:
            if m not in g:
                continue
            r, ratio = g[m], g[m]["rmse_over_floor"]
            line = (f"  - `{m}`: vertex RMSE {_mm(r['vertex_rmse_m_mean'])} mm = {ratio:.2f} x the rig floor "
                    f"{_mm(r['rig_floor_rmse_m'])} mm -> {'MET' if ratio < RMSE_TARGET else 'NOT MET'} "
                    f"(< {RMSE_TARGET:g} x); {_num(r['fps'])} frames/s")
            if nv == FPS_VIEWS:
                line += f" -> {'MET' if r['fps'] >= FPS_TARGET else 'NOT MET'} (>= {FPS_TARGET:g} at {FPS_VIEWS} views)"
            out.append(line)
        if "pipeline" in g:
            out += [f"  - {compare('pipeline', g['pipeline'], b, g[b])}" for b in BASELINES if b in g]
        for base in dict.fromkeys(base_of(m) for m in g if m not in SIM_REFS):
            if base is not None and base in g:
                out += [f"  - {compare(base, g[base], m, g[m])}" for m in g if m not in SIM_REFS and base_of(m) == base]
    return out


def out_stem(text: str) -> Path:
    """``--out`` as an absolute path without suffix: a folder (existing, or written with a
    trailing slash) means ``<folder>/fit``."""
    out = Path(text).absolute()
    return out / "fit" if out.is_dir() or text.endswith(("/", os.sep)) else out


def suite_lines(rows: list[dict], overlay: str) -> list[str]:
    """The summary over the suite's scenes: per views and method the median and worst ratio to the
    rig floor and drift, frames/s; issue 23's criteria on `pipeline`; how often it beats each baseline."""
    from benchmarks.fit_suite import tuning_scenes

    tuning = tuning_scenes()
    scenes = sorted({r["scene"] for r in rows})
    tuned = [sc for sc in scenes if sc in tuning]
    held = ("none was used to choose any setting" if not tuned else
            "ALL are tuning scenes: settings were chosen on them, these are not held-out figures" if len(tuned) ==
            len(scenes) else f"settings were chosen on {', '.join(tuned)}")
    L = ["## Summary over the suite", "",
         f"Scenes: {len(scenes)} generated by `benchmarks/fit_suite.py` ({overlay}); {held} (the tuning subset: "
         f"{', '.join(tuning)}). Every scene fitted with the pipeline's defaults (no per-scene fit section). Median "
         "and worst over the scenes; drift = mean vertex RMSE of the last 10 frames / the first 10. Vertex RMSE "
         "counts material sliding along the surface, which no image cue sees on a plain fabric; the Chamfer "
         "(surface to surface) does not: both are given, each over the rig floor's. `/ optimum` = vertex RMSE over "
         f"that of `{OPTIMUM}` on the same scene (when it ran); 2D = the mean reprojection error in the training "
         "views over the rig floor's.", "",
         "| views | method | scenes | RMSE / floor median | worst (scene) | RMSE / optimum median | worst | "
         "Chamfer / floor median | worst (scene) | 2D / floor median | worst | drift median | drift worst (scene) | "
         "fps median |",
         "| --- | --- | ---: | ---: | --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | --- | ---: |"]
    by: dict[tuple, list[dict]] = {}
    for r in rows:
        by.setdefault((r["views"], r["method"]), []).append(r)
    for (nv, m), rs in sorted(by.items(), key=lambda kv: (-kv[0][0], kv[0][1])):
        ratio = np.array([r["rmse_over_floor"] for r in rs])
        drift = np.array([r["drift"] for r in rs])
        cham = np.array([r["chamfer_over_floor"] for r in rs])
        px = np.array([r["reprojection_over_floor"] for r in rs])
        opt = {r["scene"]: r["vertex_rmse_m_mean"] for r in by.get((nv, OPTIMUM), [])}
        over_opt = np.array([r["vertex_rmse_m_mean"] / opt[r["scene"]] for r in rs if r["scene"] in opt])
        w, wd, wc = rs[int(np.argmax(ratio))], rs[int(np.argmax(drift))], rs[int(np.argmax(cham))]
        fps = np.array([r["fps"] for r in rs], float)
        L.append(f"| {nv} | `{m}` | {len(rs)} | {np.median(ratio):.2f} | {w['rmse_over_floor']:.2f} ({w['scene']}) | "
                 + (f"{np.median(over_opt):.2f} | {over_opt.max():.2f} | " if over_opt.size else "-- | -- | ")
                 + f"{np.median(cham):.2f} | {wc['chamfer_over_floor']:.2f} ({wc['scene']}) | "
                 f"{np.median(px):.2f} | {px.max():.2f} | "
                 f"{np.median(drift):.2f} | {wd['drift']:.2f} ({wd['scene']}) | "
                 f"{_num(float(np.median(fps))) if np.isfinite(fps).any() else '--'} |")
    L += ["", f"Issue 23's criteria, `pipeline` on {'the held-out scenes' if not tuned else 'these scenes'}:", ""]
    for nv, target in SUITE_MEDIAN.items():
        rs = by.get((nv, "pipeline"), [])
        if not rs:
            continue
        med = float(np.median([r["rmse_over_floor"] for r in rs]))
        L.append(f"- {nv} views: median ratio to the rig floor {med:.2f} -> {'MET' if med <= target else 'NOT MET'} "
                 f"(<= {target:g})")
        if nv == 8:
            worst = max(r["rmse_over_floor"] for r in rs)
            over = [r["scene"] for r in rs if r["rmse_over_floor"] > SUITE_WORST_8]
            L.append(f"- 8 views: worst {worst:.2f} -> {'MET' if not over else 'NOT MET'} (no scene above "
                     f"{SUITE_WORST_8:g}; above: {', '.join(over) or 'none'})")
            fps = float(np.median([r["fps"] for r in rs]))
            L.append(f"- 8 views: median {fps:.2f} frames/s -> {'MET' if fps >= FPS_TARGET else 'NOT MET'} "
                     f"(>= {FPS_TARGET:g})")
        bad = [f"{r['scene']} {r['drift']:.2f}" for r in rs if r["drift"] > SUITE_DRIFT]
        L.append(f"- {nv} views: drift <= {SUITE_DRIFT:g} on every scene -> {'MET' if not bad else 'NOT MET'} "
                 f"(above: {', '.join(bad) or 'none'})")
        own = {r["scene"]: r for r in rs}
        for b in BASELINES:
            other = {r["scene"]: r for r in by.get((nv, b), [])}
            common = sorted(set(own) & set(other))
            if common:
                wins = [sc for sc in common if own[sc]["vertex_rmse_m_mean"] < other[sc]["vertex_rmse_m_mean"]]
                wins_c = [sc for sc in common if own[sc]["chamfer_m_mean"] < other[sc]["chamfer_m_mean"]]
                L.append(f"- {nv} views: `pipeline` beats `{b}` on {len(wins)} of {len(common)} scenes in vertex RMSE "
                         f"-> {'MET' if len(wins) == len(common) else 'NOT MET'} (in Chamfer: {len(wins_c)} of "
                         f"{len(common)})")
    return L + [""]


def write(rows, notes, args, command, load0, load1, methods_paragraph: list[str], suite: list[str] = ()) -> None:
    """Write ``<args.out>.csv`` (the rows) and ``<args.out>.md`` (header, table, criteria, notes)."""
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cols = list(rows[0].keys()) if rows else []
    with open(out.with_suffix(".csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    lines = [
        "# Garment fitting benchmark (`anidress_core.fit`) against the synthetic ground truth",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `{command}` (git {git_rev(CODE_PATHS)})",
        f"- machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, torch "
        f"{torch.__version__} ({args.threads} threads), Python {platform.python_version()}; shared machine, load "
        f"average (1/5/15 min) at start {load0[0]:.2f}/{load0[1]:.2f}/{load0[2]:.2f}, at end "
        f"{load1[0]:.2f}/{load1[1]:.2f}/{load1[2]:.2f}",
        "- reference (measured in the same run): the rig floor = RMSE of `rig.fit_transforms` on the ground-truth "
        "garment meshes carried onto the template's vertices (the best the rig can express); every method is "
        "measured against the same ground truth, on the same frames and cues.",
        "- metrics per frame: vertex RMSE vs ground truth in template topology; Chamfer = symmetric mean nearest-"
        f"neighbour distance between {args.samples} area-uniform surface samples of each mesh; normal consistency "
        "= mean |cos| between nearest samples' face normals (1 best); jitter = mean |x[t+1] - 2x[t] + x[t-1]| "
        "(fit and ground truth); acceleration error = the same of (fit - ground truth), the jitter a fit adds; "
        "rig floor Chamfer = the Chamfer of the rig floor's meshes (the surface error the rig cannot avoid; unlike the "
        "vertex RMSE, the Chamfer does not count material sliding along the surface, which images cannot see at "
        "frame 0: studies/fit/fit_frame0.md). "
        "Columns give mean / 95th percentile / worst frame (normal consistency: mean / 5th percentile / worst).",
        "- fps = frames / wall time of the fitting loop (cue loading and body occluder rasterisation included, "
        "rig and camera loading excluded); CPU s/frame = process CPU time of that loop per frame (all threads; "
        "less sensitive to other jobs on the machine than the wall time).",
        *methods_paragraph,
        "",
        *suite,
        *(["## Per scene", ""] if suite else []),
        "| scene/seq | views | method | frames | vertex RMSE mm mean / p95 / worst (frame) | rig floor mm "
        "| RMSE / floor "
        "| Chamfer mm mean / p95 / worst | rig floor Chamfer mm | Chamfer / floor | 2D error px (rig floor) "
        "| 2D / floor "
        "| normal consistency mean / p5 / worst | jitter mm (GT) | acceleration error mm | drift | fps | CPU s/frame "
        "| iterations/frame |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- "
        "| --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']}/{r['sequence']} | {r['views']} | `{r['method']}` | {r['frames']} | "
            f"{_mm(r['vertex_rmse_m_mean'])} / {_mm(r['vertex_rmse_m_p95'])} / {_mm(r['vertex_rmse_m_worst'])} "
            f"({r['worst_frame']}) | {_mm(r['rig_floor_rmse_m'])} | {r['rmse_over_floor']:.2f} | "
            f"{_mm(r['chamfer_m_mean'])} / {_mm(r['chamfer_m_p95'])} / {_mm(r['chamfer_m_worst'])} | "
            f"{_mm(r['rig_floor_chamfer_m'])} | {r['chamfer_over_floor']:.2f} | "
            f"{_num(r['reprojection_px'])} ({_num(r['rig_floor_reprojection_px'])}) | "
            f"{_num(r['reprojection_over_floor'])} | "
            f"{r['normal_consistency_mean']:.4f} / {r['normal_consistency_p5']:.4f} / "
            f"{r['normal_consistency_worst']:.4f}"
            f" | {_mm(r['jitter_m'])} ({_mm(r['gt_jitter_m'])}) | {_mm(r['accel_error_m'])} | {_num(r['drift'])} | "
            f"{_num(r['fps'])} | "
            f"{_num(r['cpu_s_per_frame'])} | {r['iterations_mean']:.1f} |")
    lines += ["", "## Criteria", ""] + verdicts(rows) + ["", "## Notes", ""] + [f"- {n}" for n in notes]
    (out.with_suffix(".md")).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
