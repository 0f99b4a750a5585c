"""Runnable only at git 5d00caa: it patches L_silhouette's internals (its old signatures, Problem.pixel_ok / mask), which the fit's one term protocol (issue 48 item 2) replaced.

Probe: a contour term with a wider basin than L_silhouette (the distance-transform silhouette energy of
model-based tracking, e.g. Gavrila & Davis 1996; Sminchisescu & Telea 2002).

L_silhouette sees a misplaced rendered outline only at the pixels it crosses (a residual of at most one per
crossing pixel). Here each crossing of L_silhouette (a visible silhouette edge between the centres of a covered
and an uncovered pixel, at fraction t) also gets the residual r = (1 - t) D(inside) + t D(outside): the signed
distance (pixels, positive outside) of the crossing point to the garment mask's boundary, D from the mask's
Euclidean distance transforms; pairs further than ``tau`` pixels from the boundary are left out. The term,
weight w, adds w sum r^2 / n_px to the loss and its Gauss-Newton rows (dr/dt = D(outside) - D(inside), dt/dx
as L_silhouette's) to the system. Registers ``contour_<w>_<tau>`` for (2, 20) and (5, 20) (the pipeline
plus the term) and runs the maintained benchmark (benchmarks/bench_fit.py) with its own arguments:

    PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/contour.py --suite <half of config/fit_suite.yaml> \\
        --views 8 --methods pipeline,contour_2_20 --no-sim --threads 1 --runs /tmp/contour --out /tmp/contour

It swaps the functions of :mod:`anidress_core.fit.terms.silhouette` in this process (a probe, not a term).
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.ndimage import distance_transform_edt  # noqa: E402

from anidress_core import raster  # noqa: E402
from anidress_core.fit import variants as V  # noqa: E402
from anidress_core.fit.terms import silhouette as S  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

SETTINGS = {f"contour_{w:g}_{tau:g}": (w, tau) for w, tau in ((2.0, 20.0), (5.0, 20.0))}
_distance: dict = {}  # id(mask) -> (mask, (C H W,) signed distance), the masks of the problems in use


def signed_distance(mask: torch.Tensor) -> torch.Tensor:
    """(C H W,) float64 distance (pixels) of each pixel centre to the garment mask (C, H, W) bool, minus its
    distance to the outside: -1 / +1 at the pixels on either side of the boundary, 0 halfway between."""
    hit = _distance.get(id(mask))
    if hit is None or hit[0] is not mask:
        m = mask.bool().cpu().numpy()
        d = np.stack([distance_transform_edt(~mi) - distance_transform_edt(mi) for mi in m])
        if len(_distance) > 64:
            _distance.clear()
        hit = _distance[id(mask)] = (mask, torch.from_numpy(d).to(torch.float64).reshape(-1).to(mask.device))
    return hit[1]


_silhouette_value, _silhouette_gauss_newton = S.value, S.gauss_newton


def value(pb, r):
    """L_silhouette (:func:`anidress_core.fit.terms.silhouette.value`) plus (w / w_silhouette) L_contour."""
    sil, data = _silhouette_value(pb, r)
    w, tau = SETTINGS.get(pb.cfg.loss, (0.0, 0.0))
    if not w > 0:
        return sil, (data, None, None, 0.0)
    nv = r.uv.shape[1]
    uvf = r.uv.reshape(-1, 2)
    t = raster.crossing_fraction(uvf[data.cam * nv + data.edge[:, 0]], uvf[data.cam * nv + data.edge[:, 1]],
                                 data.inside_xy, data.outside_xy)
    H, W = pb.mask.shape[1:]

    def flat(xy):  # pixel centres at integer coordinates (u = column, v = row)
        return data.cam * (H * W) + xy[:, 1].round().long() * W + xy[:, 0].round().long()

    inside, outside = flat(data.inside_xy), flat(data.outside_xy)
    D = signed_distance(pb.mask)
    Di, Do = D[inside], D[outside]
    ok = (Di.abs() <= tau) & (Do.abs() <= tau)
    if pb.pixel_ok is not None:
        ok &= (pb.pixel_ok[inside] > 0) & (pb.pixel_ok[outside] > 0)
    zero = torch.zeros_like(t)
    rc = torch.where(ok, (1 - t) * Di + t * Do, zero)
    slope = torch.where(ok, Do - Di, zero)
    return sil + w / pb.cfg.weights.silhouette * float((rc * rc).sum()) / pb.n_px, (data, rc, slope, w)


def gauss_newton(pb, s, uv, Puv, Jx, H, g, jdtype):
    """L_silhouette's rows (:func:`anidress_core.fit.terms.silhouette.gauss_newton`) plus the contour's, both
    from the crossings' rows (:func:`anidress_core.fit.terms.silhouette.crossing_rows`) computed once."""
    s, rc, slope, w = s
    if not (w > 0 and s.pixel.numel()):
        return _silhouette_gauss_newton(pb, s, uv, Puv, Jx, H, g, jdtype)
    Jt = S.crossing_rows(s, uv, Puv, Jx, jdtype)
    _silhouette_gauss_newton(pb, s, uv, Puv, Jx, H, g, jdtype, rows=Jt)
    Jc = slope.to(jdtype)[:, None] * Jt
    H += w / pb.n_px * (Jc.t() @ Jc).double()
    g += w / pb.n_px * (Jc.t() @ rc.to(jdtype)).double()


for name, (w, tau) in SETTINGS.items():
    V.VARIANTS[name] = V.Variant(f"the pipeline with a contour term (distance to the mask boundary), weight {w:g}, "
                                 f"pairs within {tau:g} px", lambda c: c)

if __name__ == "__main__":
    S.value, S.gauss_newton = value, gauss_newton
    bench_fit.PROG = "PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/contour.py"
    bench_fit.main()
