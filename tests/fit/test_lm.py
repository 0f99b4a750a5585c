"""anidress_core.fit.lm: the generic Levenberg-Marquardt, and the fit's per-frame use of it."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from anidress_core import fit, raster
from anidress_core.geometry import lbs
from tests.fit.scenes import PAPER, config, exact_flow, pose, render, rmse, toy

torch.set_num_threads(1)


def rosenbrock(x):  # residuals (1 - a, 10 (b - a^2)): minimum 0 at (1, 1)
    r = torch.stack([1 - x[0], 10 * (x[1] - x[0] ** 2)])
    J = torch.stack([torch.stack([-torch.ones_like(x[0]), torch.zeros_like(x[0])]),
                     torch.stack([-20 * x[0], 10 * torch.ones_like(x[0])])])
    return r, J


def test_levenberg_marquardt_solves_a_nonlinear_least_squares_problem():
    evaluate = lambda x: SimpleNamespace(loss=float((rosenbrock(x)[0] ** 2).sum()), x=x)  # noqa: E731

    def system(ev, x):
        r, J = rosenbrock(x)
        return J.t() @ J, J.t() @ r

    res = fit.levenberg_marquardt(evaluate, system, lambda x, d: x + d, torch.tensor([-1.2, 1.0], dtype=torch.float64),
                                  max_iters=200, damping=1e-3, rel_tol=1e-12, step_tol=1e-12)
    assert res.converged and res.iterations < 200
    torch.testing.assert_close(res.x, torch.ones(2, dtype=torch.float64), rtol=0, atol=1e-6)
    assert all(b < a for a, b in zip(res.curve, res.curve[1:]))  # only accepted (lowering) steps are recorded
    assert res.evaluation.loss == res.curve[-1]
    # a non-finite start is refused; a non-finite step is rejected, never returned
    with pytest.raises(ValueError, match="not finite"):
        fit.levenberg_marquardt(lambda x: SimpleNamespace(loss=float("nan")), system, lambda x, d: x + d,
                                torch.zeros(2, dtype=torch.float64), 5, 1e-3, 1e-3, 1e-9)
    nan_far = lambda x: SimpleNamespace(loss=float("inf") if float(x.abs().max()) > 1.5 else  # noqa: E731
                                        float((rosenbrock(x)[0] ** 2).sum()))
    res = fit.levenberg_marquardt(nan_far, system, lambda x, d: x + d, torch.tensor([-1.2, 1.0], dtype=torch.float64),
                                  50, 1e-3, 1e-12, 1e-12)
    assert math.isfinite(res.evaluation.loss) and float(res.x.abs().max()) <= 1.5


def test_recovers_known_bone_transforms_from_a_perturbed_start():
    rig, views = toy(C=4, H=80, W=80)
    g = torch.Generator().manual_seed(4)
    Gt = pose(rig, g, 0.15, 0.03)
    cues, xt, _ = render(rig, views, Gt)
    G0 = pose(rig, g, 0.06, 0.015, Gt)
    x0 = lbs(rig.rest, rig.weights, G0)
    e0 = rmse(x0, xt)
    cfg = config(PAPER, max_iters=20, smooth_passes=0)
    # flow targets say where the visible vertices of the start went (as at frame t > 0)
    fr0 = raster.occlude(raster.rasterize(x0, rig.faces, views.K, views.world_to_cam, 80, 80), cues.occluder)
    ft = exact_flow(rig, views, x0, fr0, xt)
    r = fit.fit_frame(rig, views, cues, G0, cfg, flow=ft)
    assert rmse(r.verts, xt) < 0.1 * e0, (rmse(r.verts, xt), e0)  # binary masks: +-0.5 px per crossing
    assert r.converged and r.iterations <= cfg.max_iters
    Rerr = (r.transforms[:, :3, :3] @ Gt[:, :3, :3].transpose(1, 2)).diagonal(dim1=1, dim2=2).sum(-1)
    assert float(torch.arccos(((Rerr - 1) / 2).clamp(-1, 1)).max()) < 0.02  # bone rotations within ~1 degree
    # silhouettes + normals alone (the first frame) lower the loss but pin the shape only loosely:
    # at 2.3 cm per pixel many bone configurations fit 4 binary masks as well as the truth
    r0 = fit.fit_frame(rig, views, cues, G0, cfg, first=True)
    start = fit.evaluate(fit.make_problem(rig, views, cues, cfg), x0).loss
    assert r0.loss < 0.7 * start and torch.isfinite(r0.transforms).all()
    assert rmse(r0.verts, xt) < e0
