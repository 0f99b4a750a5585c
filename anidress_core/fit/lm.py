"""A generic Levenberg-Marquardt for sums of squared residuals over a list of terms.

Marquardt's diagonal scaling and Nielsen's damping update: the step solves
(H + mu diag(H)) delta = -g for the system (H, g) of the current point (L(d) ~ L + 2 g.d + d.H d),
is accepted when it lowers the loss (mu shrinks by max(1/3, 1 - (2 rho - 1)^3), rho the gain
over the predicted gain), else mu grows by nu (doubling). Stops when an accepted step lowers
the loss by less than ``rel_tol`` (relative), when the step is below ``step_tol``, or after
``max_iters`` evaluations. The loss, its system and the update of the unknowns are callables:
the garment fit (:func:`anidress_core.fit.sequence.fit_frame`) evaluates its terms
(:mod:`anidress_core.fit.terms`) at bone transforms and composes bone increments.
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import torch
from torch import Tensor

__all__ = ["LMResult", "levenberg_marquardt"]


class LMResult(NamedTuple):
    x: Tensor  # the unknowns at the result
    evaluation: object  # evaluate(x) at the result (has .loss)
    iterations: int  # evaluations spent (accepted + rejected steps)
    converged: bool  # stopped by a tolerance rather than by the iteration limit
    curve: list  # loss after each accepted step (index 0: the start)


def levenberg_marquardt(evaluate: Callable[[Tensor], object], system: Callable[[object, Tensor], tuple[Tensor, Tensor]],
                        update: Callable[[Tensor, Tensor], Tensor], x0: Tensor, max_iters: int, damping: float,
                        rel_tol: float, step_tol: float) -> LMResult:
    """Minimise ``evaluate(x).loss`` from ``x0``.

    evaluate(x) -> an object with ``.loss`` (float; non-finite: the step is rejected);
    system(ev, x) -> (H (P, P), g (P,)) float64 at that evaluation; update(x, delta (P,)) -> the
    new unknowns. damping: initial mu relative to the largest diagonal entry of H.
    """
    x = x0
    ev = evaluate(x)
    if not math.isfinite(ev.loss):
        raise ValueError("fit: the loss at the starting pose is not finite (check the cues and the start pose)")
    curve = [ev.loss]
    H, g = system(ev, x)
    mu, nu = None, 2.0
    it, converged = 0, False
    while it < max_iters:
        d = H.diagonal()
        dscale = d.clamp_min(1e-9 * float(d.max().clamp_min(1e-30)))
        if mu is None:
            mu = damping * float(d.max().clamp_min(1e-30))
        if float(g.abs().max()) == 0.0:
            converged = True
            break
        A = H + mu * torch.diag(dscale)
        delta, info = torch.linalg.solve_ex(A, -g)
        it += 1
        if int(info) != 0 or not bool(torch.isfinite(delta).all()):
            mu *= nu
            nu *= 2
            continue
        pred = -float(2 * g @ delta + delta @ H @ delta)
        x_new = update(x, delta)
        ev_new = evaluate(x_new)
        gain = ev.loss - ev_new.loss
        if math.isfinite(ev_new.loss) and gain > 0:
            rho = gain / pred if pred > 0 else 1.0
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            small = gain < rel_tol * ev.loss or float(delta.abs().max()) < step_tol
            x, ev = x_new, ev_new
            curve.append(ev.loss)
            if small:
                converged = True
                break
            H, g = system(ev, x)
        else:
            if float(delta.abs().max()) < step_tol:
                converged = True
                break
            mu *= nu
            nu *= 2
    return LMResult(x, ev, it, converged, curve)
