"""Probe: the observed motion of suite scenes simulated at several bending stiffnesses; each member's and the
members' mean's vertex RMSE against the ground truth through the rig (``rig.fit_transforms`` of the frames, as
the fit's L_prior sees a simulation), over the rig floor's, mean over frames. The other cloth parameters are
config/config.yaml's ``simulate/cloth`` (the pipeline's). ``--true`` adds the scene's own stiffness (an oracle:
the suite file's ``garment/cloth/bend_stiffness``). ``--vary NAME=V1,V2`` simulates every stiffness again with
the cloth parameter NAME at each value (e.g. ``damping``, ``friction``, ``settle_frames``: members that differ in
more than the stiffness; ``NAME=V1,V2:NAME2=W1,W2`` at every combination, tagged ``NAMEv-NAME2w``) and adds the
mean over the stiffnesses at each value ('mean@NAMEvalue'), at all the values ('mean@<spec>') and at them and the
config's value ('mean+<spec>'). ``--subset NAME=TAG1,TAG2`` adds the mean of members already in ``--out`` with
those tags at every stiffness ('' = the config's cloth), as ensemble_from.py's ``TAGS``. Members are written to
``--out`` and reused.

    PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/members.py --suite config/fit_suite.yaml \\
        --bend 1e-4,3e-4,1e-3,3e-3,1e-2 --true --out /tmp/members suite_00 suite_03 > members.txt
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.io.rig import read_rig  # noqa: E402
from anidress_core.rig import fit_transforms  # noqa: E402
from anidress_core.stages.fit_eval import gt_template_vertices  # noqa: E402
from anidress_core.stages.simulate import run_simulate  # noqa: E402


def member_path(out: Path, scene: str, seq: str, bend: float, tag: str = "") -> Path:
    """A member's file: ``tag`` names what differs from the config's cloth ('' none; see :func:`tag_of`)."""
    return out / f"{scene}-{seq}-{bend:g}{'-' + tag if tag else ''}.npz"


def load_members(out: Path, scene: str, seq: str, bends: list[float], tags: list[str], hint: str) -> np.ndarray:
    """(M, T, V, 3) float64 the members at every stiffness of ``bends`` with each tag of ``tags``, in that order;
    a missing one stops the probe, naming its file and ``hint`` (how to make it)."""
    X = []
    for b in bends:
        for tag in tags:
            p = member_path(out, scene, seq, b, tag)
            if not p.is_file():
                raise SystemExit(f"{p}: no such member ({hint})")
            X.append(np.load(p)["frames"].astype(np.float64))
    return np.stack(X)


def tag_of(combo: tuple[tuple[str, float], ...]) -> str:
    """((NAME, v), (NAME2, w)) -> ``NAMEv-NAME2w``, the tag of a member's file and of its mean's column."""
    return "-".join(f"{name}{val:g}" for name, val in combo)


def combinations(spec: str) -> list[tuple[tuple[str, float], ...]]:
    """``NAME=V1,V2[:NAME2=W1,W2]`` -> every combination of the values, as ((NAME, v), (NAME2, w)) tuples."""
    combos: list[tuple[tuple[str, float], ...]] = [()]
    for part in spec.split(":"):
        name, vals = part.split("=")
        combos = [c + ((name, float(v)),) for c in combos for v in vals.split(",")]
    return combos


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", required=True, help="the suite's config overlay (its scenes' true stiffness)")
    ap.add_argument("--bend", default="1e-4,3e-4,1e-3,3e-3,1e-2", help="the members' bending stiffnesses (J)")
    ap.add_argument("--true", action="store_true", help="also simulate at the scene's own stiffness (oracle)")
    ap.add_argument("--out", required=True, help="folder of the members (<scene>-<seq>-<bend>.npz)")
    ap.add_argument("--vary", action="append", default=[],
                    help="NAME=V1,V2[:NAME2=W1,W2]: every stiffness also at these values of cloth parameter NAME "
                         "(at every combination with NAME2's; repeatable)")
    ap.add_argument("--subset", action="append", default=[],
                    help="NAME=TAG1,TAG2: the mean of the stored members with these tags (repeatable)")
    ap.add_argument("scenes", nargs="+")
    a = ap.parse_args()
    suite = yaml.safe_load(Path(a.suite).read_text())["scenes"]
    cloth = yaml.safe_load(Path("config/config.yaml").read_text())["simulate"]["cloth"]
    bends = [float(b) for b in a.bend.split(",")]
    out = Path(a.out)
    print(f"# {' '.join(sys.argv)}")
    print("# vertex RMSE through the rig / rig floor, mean over frames: each member (bending stiffness, J), the "
          "members' mean ('mean'), the scene's own stiffness ('true', not in the mean)")
    for scene in a.scenes:
        seq = next(s["name"] for s in suite[scene]["sequences"] if s.get("role", "train") == "train")
        true = float(suite[scene]["garment"]["cloth"]["bend_stiffness"])
        art = read_rig(f"results/{scene}/rig.npz", dtype=torch.float64)
        Y = gt_template_vertices(f"data/{scene}", seq, art.model.rest)[0]  # (T, V, 3)
        T = Y.shape[0]

        def rmse(S: torch.Tensor) -> float:  # S (>= T, V, 3) through the rig, against Y, mean over frames
            X = lbs(art.model.rest, art.model.weights, fit_transforms(art.model, S[:T]).double())
            return float(((X - Y) ** 2).sum(-1).mean(-1).sqrt().mean())

        floor = rmse(Y)

        def ratio(S: torch.Tensor) -> float:
            return rmse(S) / floor

        frames = {}
        for b in bends + ([true] if a.true else []):
            p = member_path(out, scene, seq, b)
            if not p.is_file():
                run_simulate(f"results/{scene}/template.npz", f"results/{scene}/motions/seq-{seq}.npz",
                             f"data/{scene}", {**cloth, "bend_stiffness": b}, p, progress=False)
            frames[b] = torch.as_tensor(np.load(p)["frames"]).double()
        mean = torch.stack([frames[b] for b in bends]).mean(0)
        cells = [f"{b:g}: {ratio(frames[b]):.2f}" for b in bends] + [f"mean: {ratio(mean):.2f}"]
        for v in a.vary:
            extra = []
            for combo in combinations(v):
                at = []
                for b in bends:
                    p = member_path(out, scene, seq, b, tag_of(combo))
                    if not p.is_file():
                        params = {name: int(val) if name == "settle_frames" else val for name, val in combo}
                        run_simulate(f"results/{scene}/template.npz", f"results/{scene}/motions/seq-{seq}.npz",
                                     f"data/{scene}", {**cloth, "bend_stiffness": b, **params}, p, progress=False)
                    at.append(torch.as_tensor(np.load(p)["frames"]).double())
                cells.append(f"mean@{tag_of(combo)}: {ratio(torch.stack(at).mean(0)):.2f}")
                extra += at
            every = torch.stack([frames[b] for b in bends] + extra).mean(0)
            cells.append(f"mean@{v}: {ratio(torch.stack(extra).mean(0)):.2f}")
            cells.append(f"mean+{v}: {ratio(every):.2f}")
        for spec in a.subset:
            name, tags = spec.split("=")
            at = [torch.as_tensor(np.load(member_path(out, scene, seq, b, t))["frames"]).double()
                  for b in bends for t in tags.split(",")]
            cells.append(f"{name}: {ratio(torch.stack(at).mean(0)):.2f}")
        if a.true:
            cells.append(f"true {true:g}: {ratio(frames[true]):.2f}")
        print(f"{scene}/{seq}  " + "  ".join(cells), flush=True)


if __name__ == "__main__":
    main()
