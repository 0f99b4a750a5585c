"""Runnable only at git d6e895a: it imports fit.terms.prior.member_weights, weighted_members and
stages.fit.member_scores, which left the package after that commit (issue 48; its findings:
studies/fit/README.md section 21).

Probe: L_prior's reference and frame 0's start from the stiffness ensemble's members weighted per frame by
how well each explains that frame's images (what ``fit/prior_member_temperature`` does, the variant
``pipeline_image_weights``), here with members made by members.py (``MEMBERS=<folder>``, every stiffness of the
config's ``simulate/ensemble_bend_stiffness`` with each tag of ``TAGS``, default the pipeline's own members
``settle_frames20,settle_frames40``), temperature ``ALPHA`` (default 1) and window ``SMOOTH`` (default 2).

Each member's rig poses (``rig.fit_transforms`` of its frames) are scored on every frame's cues by
L_silhouette + L_normal (the stage's ``member_scores``) and weighted by
``anidress_core.fit.terms.prior.member_weights``; the reference is their weighted mean, L_prior's weight per vertex
from their weighted spread (``weighted_members``). ``SCORES=<folder>`` keeps the scores for ``screen``;
``START=mean`` starts frame 0 from the plain mean's pose (L_prior still follows the weighted mean).

Before each fit it prints, on the scene's ground truth (a screen, not read by the fit): the vertex RMSE through the
rig over the rig floor of the plain mean, of the weighted mean at ALPHA 0, 0.5, 1, 2, and of the per-frame member
closest to the truth (an oracle). Runs bench_fit with its own arguments, e.g.

    MEMBERS=/tmp/members ALPHA=1 PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/weighted_from.py \\
        --suite <overlay> --views 8 --methods pipeline --no-sim --threads 1 --runs /tmp/w1 --out /tmp/w1
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from anidress_core import fit as FIT  # noqa: E402
from anidress_core.fit.terms.prior import member_weights, spread_scale, weighted_members  # noqa: E402
from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.rig import fit_transforms  # noqa: E402
from anidress_core.stages import fit as stage  # noqa: E402
from benchmarks import bench_fit  # noqa: E402
from members import load_members  # noqa: E402

MEMBERS = Path(os.environ["MEMBERS"])
TAGS = os.environ.get("TAGS", "settle_frames20,settle_frames40").split(",")
ALPHA = float(os.environ.get("ALPHA", "1"))
SMOOTH = int(os.environ.get("SMOOTH", "2"))
START = os.environ.get("START", "weighted")  # frame 0's start: the weighted mean's, or 'mean' the plain mean's
SCORES = Path(os.environ["SCORES"]) if os.environ.get("SCORES") else None  # the members' scores, kept and reused
BENDS = [float(b) for b in yaml.safe_load(Path("config/config.yaml").read_text())["simulate"]
         ["ensemble_bend_stiffness"]]
HINT = "members.py --vary settle_frames=20,40 makes it"
_fit_sequence = FIT.fit_sequence
_current: dict = {}  # the scene being fitted: its members and rig model


def member_transforms(path, art, frames, device):
    """Stands in for the stage's ensemble_transforms: records the scene's members; returns the mean's as usual
    (replaced in fit_sequence once the cues are there)."""
    scene, seq = Path(path).parts[-3], Path(path).stem[len("seq-"):]
    X = load_members(MEMBERS, scene, seq, BENDS, TAGS, HINT)[:, :frames]
    _current.clear()
    _current.update(scene=scene, seq=seq, model=art.model, X=torch.as_tensor(X))
    return member_transforms.__wrapped__(path, art, frames, device)


def screen(model, X: torch.Tensor, scores: torch.Tensor, grid=((0.0, 2), (0.5, 2), (1.0, 2), (2.0, 2))) -> dict:
    """The references' RMSE through the rig over the floor's, on the ground truth (printed, not used): the plain
    mean, the weighted mean at each (alpha, smooth) of ``grid``, the per-frame member closest to the truth."""
    Y = stage.gt_template_vertices(f"data/{_current['scene']}", _current["seq"], model.rest)[0][:X.shape[1]]

    def rmse(S: torch.Tensor) -> torch.Tensor:  # (T,) per frame, through the rig
        R = lbs(model.rest, model.weights, fit_transforms(model, S).double())
        return ((R - Y) ** 2).sum(-1).mean(-1).sqrt()

    floor = float(rmse(Y).mean())
    out = {"mean": float(rmse(X.mean(0)).mean()) / floor}
    for a, s in grid:
        out[f"a{a:g}/s{s}"] = float(rmse(weighted_members(X, member_weights(scores, a, s))[0]).mean()) / floor
    per = torch.stack([rmse(x) for x in X])  # (M, T)
    out["oracle_pick"] = float(per.min(0).values.mean()) / floor
    return {k: round(v, 3) for k, v in out.items()}


def fit_sequence(rig, views, num_frames, cues_of, flow_of, init, cfg=None, **kw):
    """Scores every member on every frame's cues, follows their weighted mean."""
    if kw.get("starts") is not None or kw.get("sim_transforms") is None:
        return _fit_sequence(rig, views, num_frames, cues_of, flow_of, init, cfg, **kw)
    model, X = _current["model"], _current["X"][:, :num_frames]
    cache = SCORES / f"{_current['scene']}-{_current['seq']}-{views.K.shape[0]}v.pt" if SCORES else None
    if cache is not None and cache.is_file():
        scores = torch.load(cache)
    else:
        scores = stage.member_scores(X.to(init.device), model, rig, views, cues_of, cfg)  # (M, T)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            torch.save(scores, cache)
    w = member_weights(scores, ALPHA, SMOOTH)
    ref, spread = weighted_members(X, w)
    S = fit_transforms(model, ref).double().to(init.device)
    scales = spread_scale(spread, cfg.prior_spread_floor).to(init.device) if cfg.prior_spread_floor else None
    print("weighted_from:", json.dumps({"scene": _current["scene"], "alpha": ALPHA, "smooth": SMOOTH,
                                        "weight_max_median": round(float(w.max(0).values.median()), 3),
                                        **screen(model, X, scores, ((ALPHA, SMOOTH),))}), flush=True)
    return _fit_sequence(rig, views, num_frames, cues_of, flow_of, init if START == "mean" else S[0], cfg,
                         **{**kw, "sim_transforms": S, "prior_scales": scales})


member_transforms.__wrapped__ = stage.ensemble_transforms
stage.ensemble_transforms = member_transforms
FIT.fit_sequence = fit_sequence

def screen_grid(suite: str, views: int) -> None:
    """``screen <overlay> <views>``: the screen of every scene of the overlay whose scores SCORES holds, at ALPHA
    0, 0.5, 1, 2 and SMOOTH 0, 2, 5, 10, 40 (no fit)."""
    from anidress_core.io.rig import read_rig

    grid = [(a, s) for s in (0, 2, 5, 10, 40) for a in (0.0, 0.5, 1.0, 2.0)]
    print(f"# {' '.join(sys.argv)}\n# reference RMSE through the rig over the floor; columns alpha/smooth")
    print("scene mean oracle_pick " + " ".join(f"a{a:g}/s{s}" for a, s in grid))
    for scene, sc in yaml.safe_load(Path(suite).read_text())["scenes"].items():
        seq = next(q["name"] for q in sc["sequences"] if q.get("role", "train") == "train")
        p = SCORES / f"{scene}-{seq}-{views}v.pt"
        if not p.is_file():
            continue
        scores = torch.load(p)
        art = read_rig(f"results/{scene}/rig.npz", dtype=torch.float64)
        X = torch.as_tensor(load_members(MEMBERS, scene, seq, BENDS, TAGS, HINT)[:, :scores.shape[1]])
        _current.update(scene=scene, seq=seq)
        r = screen(art.model, X, scores, grid)
        cells = " ".join(f"{r[f'a{a:g}/s{s}']:.2f}" for a, s in grid)
        print(f"{scene} {r['mean']:.2f} {r['oracle_pick']:.2f} {cells}", flush=True)


if __name__ == "__main__" and sys.argv[1:2] == ["screen"]:
    screen_grid(sys.argv[2], int(sys.argv[3]))
elif __name__ == "__main__":
    bench_fit.PROG = (f"MEMBERS={MEMBERS} TAGS={','.join(TAGS)} ALPHA={ALPHA:g} SMOOTH={SMOOTH} START={START} "
                      "PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/weighted_from.py")
    bench_fit.main()
