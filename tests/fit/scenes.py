"""Tiny fitting scenes shared by the tests of anidress_core.fit: a cone 'skirt' rig seen by ring cameras."""
from __future__ import annotations

import math

import torch

from anidress_core import fit, raster
from anidress_core.camera import ring_cameras
from anidress_core.geometry import lbs

TERM_OFF = {k: 0.0 for k in fit.TERM_NAMES}


def config(weights: dict | None = None, **kw) -> fit.FitConfig:
    """FitConfig of the config section {weights, **kw} (the rest: the schema's defaults, except ``window``:
    0, the chain alone, unless given; tests/fit/test_window.py tests the window refinement)."""
    sec = dict(kw)
    sec.setdefault("window", 0)
    if weights is not None:
        sec["weights"] = weights
    return fit.FitConfig.from_config(sec)


def only(term: str, weight: float, **kw) -> fit.FitConfig:
    """Every loss term off except ``term``."""
    return config(dict(TERM_OFF, **{term: weight}), **kw)


PAPER = dict(TERM_OFF, silhouette=2.0, normal=0.1, flow=3.0)  # the paper's weights


def cone(n_theta=32, n_h=10, r0=0.15, r1=0.35, h=0.5, z0=1.0):
    th = torch.arange(n_theta, dtype=torch.float64) / n_theta * 2 * math.pi
    s = torch.linspace(0, 1, n_h, dtype=torch.float64)
    r = r0 + (r1 - r0) * s
    v = torch.stack([r[:, None] * torch.cos(th), r[:, None] * torch.sin(th), (z0 - h * s)[:, None].expand(-1, n_theta)],
                    -1).reshape(-1, 3)
    f = []
    for i in range(n_h - 1):
        for j in range(n_theta):
            a, b = i * n_theta + j, i * n_theta + (j + 1) % n_theta
            f += [[a, a + n_theta, b], [b, a + n_theta, b + n_theta]]
    return v, torch.tensor(f)


def toy(C=4, H=64, W=64, n_theta=32, n_h=10, nb=3):
    """A cone 'skirt' with 2 nb bones (angular sectors x two bands) seen by C ring cameras."""
    v, f = cone(n_theta, n_h)
    ang = torch.atan2(v[:, 1], v[:, 0])
    a = torch.arange(nb, dtype=torch.float64) * 2 * math.pi / nb
    d = torch.cdist(torch.stack([ang.cos(), ang.sin()], -1), torch.stack([a.cos(), a.sin()], -1))
    wa = torch.softmax(-d / 0.3, -1)
    hw = ((1.0 - v[:, 2]) / 0.5).clamp(0, 1)[:, None]
    Wt = torch.cat([wa * (1 - hw), wa * hw], -1)
    centres = (Wt.t() @ v) / Wt.sum(0)[:, None]
    rig = fit.RigParts.make(v, Wt, centres, f)
    cams = ring_cameras(n=C, radius=2.0, height=1.0, target=(0, 0, 0.8), focal_px=1.1 * H, image_height=H,
                        image_width=W)
    return rig, fit.Views.from_cameras(cams)


def pose(rig, g, rot, trans, base=None):
    B = rig.weights.shape[1]
    d = torch.cat([rot * torch.randn(B, 3, generator=g, dtype=torch.float64),
                   trans * torch.randn(B, 3, generator=g, dtype=torch.float64)], -1)
    G = torch.eye(4, dtype=torch.float64).expand(B, 4, 4).clone() if base is None else base
    return fit.apply_increment(G, rig.centres, d)


def render(rig, views, G, occluder=None):
    """Exact cues of the mesh LBS(G): garment mask, face normals; and its fragments."""
    x = lbs(rig.rest, rig.weights, G)
    fr = raster.rasterize(x, rig.faces, views.K, views.world_to_cam, views.height, views.width)
    occ = torch.full(fr.depth.shape, float("inf"), dtype=torch.float64) if occluder is None else occluder
    fr = raster.occlude(fr, occ)
    n = raster.render_face_normals(x, rig.faces, views.world_to_cam, fr)
    return fit.FrameCues(fr.face_id >= 0, n, occ), x, fr


def moving(rig, views, T: int, seed: int, rot: float = 0.02, trans: float = 0.005):
    """T frames of the rig from a random pose (0.1 rad / 2 cm per bone), each moved by ``rot`` rad and
    ``trans`` m per bone from the last. Returns the generator (to go on drawing), the true poses and
    each frame's :func:`render` (cues, vertices, fragments)."""
    g = torch.Generator().manual_seed(seed)
    Gs = [pose(rig, g, 0.1, 0.02)]
    Gs += [pose(rig, g, rot, trans, Gs[-1]) for _ in range(T - 1)]
    return g, Gs, [render(rig, views, G) for G in Gs]


def exact_flow(rig, views, x_prev, fr_prev, x_next):
    """Flow targets that move the previous mesh's visible vertices to their true next positions."""
    vis = raster.visible_vertices(x_prev, views.K, views.world_to_cam, fr_prev)
    uv, _ = raster.project_vertices(x_next, views.K, views.world_to_cam)
    c, v = vis.nonzero(as_tuple=True)
    return fit.FlowTargets(c, v, uv[c, v])


def textured(rig, views, G, colour_of):
    """Exact cues of LBS(G) plus colour images: per-vertex colours colour_of(rest) (V, 3)
    interpolated with the barycentrics (background grey)."""
    cues, x, fr = render(rig, views, G)
    col = colour_of(rig.rest)
    fid = fr.face_id.clamp_min(0)
    img = (fr.bary[..., None] * col[rig.faces[fid]]).sum(-2)
    img = torch.where((fr.face_id >= 0)[..., None], img, torch.full_like(img, 0.5))
    return cues._replace(image=img), x


def cone_colour(p):
    """A smooth non-periodic colour of the cone's rest points p (V, 3) -> (V, 3) in [0, 1]."""
    th = torch.atan2(p[:, 1], p[:, 0])
    return torch.stack([0.5 + 0.4 * torch.sin(4 * th), 0.5 + 0.4 * torch.cos(3 * th + 8 * p[:, 2]),
                        0.5 + 0.3 * torch.sin(2 * th - 12 * p[:, 2])], -1)


def textured_sequence(T: int, seed: int = 7):
    """A textured cone (4 views, 64^2) over T frames of small motion and a frame-0 start 0.5 rad / 10 cm
    (per bone, random) from the truth. Returns (rig, views, frames [(cues, true verts)] per frame,
    anchor references from the texture, the true poses, the wrong start, the generator, to go on drawing)."""
    from anidress_core.fit.images import chromaticity

    rig, views = toy(C=4, H=64, W=64)
    ref = fit.AnchorRef(chromaticity(cone_colour(rig.rest)), torch.ones(rig.rest.shape[0], dtype=torch.bool))
    g = torch.Generator().manual_seed(seed)
    Gs = [pose(rig, g, 0.1, 0.02)]
    Gs += [pose(rig, g, 0.01, 0.003, Gs[-1]) for _ in range(T - 1)]
    frames = [textured(rig, views, G, cone_colour) for G in Gs]
    wrong = pose(rig, g, 0.5, 0.1, Gs[0])
    return rig, views, frames, ref, Gs, wrong, g


def rmse(a, b):
    return float(((a - b) ** 2).sum(-1).mean().sqrt())
