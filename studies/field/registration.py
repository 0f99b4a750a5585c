"""Probe: where the field's backward warp puts the material points of the posed garment and body.

Random points on the faces of the posed surfaces that pose the field (the rig's garment with the fitted poses,
the posed body) of every 4th training frame of the demo skirt are warped back to the canonical frame with the
motion-weight volume at its start (the priors); the truth is the same barycentric point of the rest mesh.
Error: distance to the truth; spread: per point, the RMS distance of its canonical images over the frames
from their mean (what smears a texture over the frames). Warps: HumanNeRF's blend of the candidate joints'
proposals (the paper's, ``warp_iterations: 0``), then n fixed-point steps of forward skinning from the blend,
and from the most weighted candidate's proposal instead of the blend.

    PYTHONPATH=. .venv/bin/python studies/field/registration.py [SCENE]   # default skirt, after make demo
"""
from __future__ import annotations

import torch

from anidress_core.field.deform import _skinning_step, backward_warp
from anidress_core.geometry import lbs
from benchmarks.field_profile import prepare


def main(scene_name: str = "skirt") -> None:
    torch.manual_seed(0)
    model, data, _, _ = prepare(scene_name, "full")
    from benchmarks.field_profile import ROOT
    from anidress_core.io.garment_poses import read_garment_poses
    from anidress_core.io.rig import read_rig
    from anidress_core.io.scene import load_body, load_sequence_motion, read_scene
    from anidress_core.io.template import read_template

    scene = ROOT / "data" / scene_name
    info = read_scene(scene)
    seq = [q["name"] for q in info["sequences"] if q["role"] == "train"][0]
    m = load_sequence_motion(scene, seq, info["fps"], None)
    body = load_body(scene, info)
    posed = body.pose(m.poses, m.Rh, m.Th, m.shapes)
    rest_body, _ = body.shaped(m.shapes[None])
    res = ROOT / "results" / scene_name
    tpl = read_template(res / "template.npz")
    rig = read_rig(res / "rig.npz")
    G = torch.as_tensor(read_garment_poses(res / seq / "garment_poses.npz").transforms).float()
    gv = torch.as_tensor(tpl.verts).float()
    S = data.transforms
    inv = torch.linalg.inv(S)
    vol = model.weights().detach()
    box, grid, K = model.weights.box, data.grid, data.grid.num_joints

    def warp(x, fr, cand, start, n):
        if start == "blend":
            xc = backward_warp(x, fr, inv, cand, vol, box, iterations=0).x_c
        else:  # the most weighted candidate's proposal
            A = inv[fr, cand[:, 0].long().clamp(max=K - 1)]
            xc = (A[:, :3, :3] @ x[..., None])[..., 0] + A[:, :3, 3]
        n_idx, m_idx = (cand < K).nonzero(as_tuple=True)
        c = cand[n_idx, m_idx].long()
        fwd = S[fr[n_idx], c][:, :3, :]
        for _ in range(n):
            xc = _skinning_step(x, xc, n_idx, c, fwd, vol, box, 1e-4)[0]
        return xc

    surfaces = [("garment", gv, torch.as_tensor(tpl.faces).long(), lbs(gv, rig.model.weights.float(), G)),
                ("body", rest_body.reshape(-1, 3).float(), body.faces, posed.vertices.float())]
    print("| surface | warp | error median / p90 (mm) | spread over frames median / p90 (mm) |")
    print("| --- | --- | --- | --- |")
    for name, rest, faces, post in surfaces:
        f = torch.randint(faces.shape[0], (4000,))
        b = torch.rand(4000, 3)
        b = b / b.sum(1, keepdim=True)
        truth = torch.einsum("ni,nic->nc", b, rest[faces[f]])
        res: dict = {}
        for t in range(0, post.shape[0], 4):
            x = torch.einsum("ni,nic->nc", b, post[t][faces[f]])
            fr = torch.full((x.shape[0],), t)
            row, _ = grid.lookup(fr, x)
            cand = grid.cand[row.clamp_min(0)].long()
            cand[row < 0] = K
            for start, n in (("blend", 0), ("blend", 1), ("blend", 2), ("blend", 3), ("blend", 4), ("dominant", 3)):
                res.setdefault((start, n), []).append(warp(x, fr, cand, start, n))
        for (start, n), xs in res.items():
            xs = torch.stack(xs)
            err = (xs - truth).norm(dim=-1)
            spread = (xs - xs.mean(0)).norm(dim=-1).pow(2).mean(0).sqrt()
            label = "blend (the paper's)" if n == 0 else f"{start} + {n} fixed-point step{'s' if n > 1 else ''}"
            print(f"| {name} | {label} | {1e3 * err.median():.1f} / {1e3 * err.quantile(0.9):.1f} | "
                  f"{1e3 * spread.median():.1f} / {1e3 * spread.quantile(0.9):.1f} |")


if __name__ == "__main__":
    import sys

    main(*sys.argv[1:])
