"""How far the right axis convention of predicted normals stands from the others (anidress_core.cues.normals).

For each scene: the synthetic predicted normals (OpenCV axes) of 4 frames spread over a sequence, the 8 training
cameras, on the pixels where the body posed as the scene says is seen (the skinned garment template hides it
where it covers it): the mean cosine of every right-handed signed axis permutation (the candidates of
anidress_core.cues.normals), the best two, and for reference the mirrored x and y flips (not candidates) and
OpenGL's axes. Inputs: the scenes and templates of `make demo` and of the field suite (data/, results/).

    .venv/bin/python -m studies.cues.normal_convention   # writes studies/cues/normal_convention.md
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from anidress_core.cues import normals as cn
from anidress_core.io import files
from anidress_core.io.scene import read_scene
from anidress_core.io.scene_info import select_cameras
from anidress_core.stages.cues import ShapePrior, _cameras, sequence_frames

REPO = Path(__file__).resolve().parents[2]
SCENES = [("skirt", "walk"), ("fsuite_02", "twirl"), ("fsuite_03", "sway"), ("fsuite_05", "run")]
NAMED = {"x flip (mirrored)": np.diag([-1.0, 1, 1]), "y flip (mirrored)": np.diag([1.0, -1, 1]),
         "OpenGL (y, z flipped)": np.diag([1.0, -1, -1])}


def scores(scene: Path, seq: str, template: Path) -> tuple[np.ndarray, int, float, dict]:
    info = read_scene(scene)
    names = select_cameras(info, "train", scene)
    frames = sequence_frames(scene / seq, names)
    pick = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, 4).round().astype(int))]
    prior = ShapePrior(scene, seq, info, template, _cameras(scene / seq, names, info), pick)
    P, R, img = [], [], []
    for k, f in enumerate(pick):
        seen, nb = prior.body_normals(f)
        maps = np.stack([files.read_exr(scene / seq / "normals" / c / f"{f:06d}.exr")[..., :3] for c in names])
        sel = seen & (np.linalg.norm(maps, axis=-1) > 0.5)
        P.append(maps[sel])
        R.append(nb[sel])
        img.append(k * len(names) + np.nonzero(sel)[0])
    P, R = np.concatenate(P), np.concatenate(R)
    conv = cn.find_convention(P, R, np.concatenate(img))
    Pn = P / np.linalg.norm(P, axis=1, keepdims=True)
    Rn = R / np.linalg.norm(R, axis=1, keepdims=True)
    named = {k: float(np.mean(np.sum((Pn @ M.T) * Rn, 1))) for k, M in NAMED.items()}
    return cn.convention_scores(P, R), len(P), conv.consistency, named


def main() -> int:
    rows = []
    for name, seq in SCENES:
        s, n, won, named = scores(REPO / "data" / name, seq, REPO / "results" / name / "template.npz")
        o = np.argsort(-s)
        rows.append((f"{name}/{seq}", n, cn.describe(cn.SIGNED_PERMUTATIONS[o[0]]), s[o[0]],
                     cn.describe(cn.SIGNED_PERMUTATIONS[o[1]]), s[o[1]], won, named))
    lines = ["# The axis convention of predicted normals against the posed body", "",
             f"Command: `.venv/bin/python -m studies.cues.normal_convention` ({__doc__.splitlines()[0]})", "",
             "| scene/seq | body pixels | best | mean cos | second | mean cos | best wins in | x flip (mirrored) | "
             "y flip (mirrored) | OpenGL |", "| --- | ---: | --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.3f} | {r[4]} | {r[5]:.3f} | {r[6]:.0%} of the images | "
                     + " | ".join(f"{v:.3f}" for v in r[7].values()) + " |")
    (Path(__file__).with_suffix(".md")).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
