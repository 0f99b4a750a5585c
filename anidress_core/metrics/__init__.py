"""Metrics (DESIGN.md §10).

- :mod:`anidress_core.metrics.image`: PSNR (inside the projected subject box, Neural
  Body protocol), SSIM, IoU, LPIPS and DISTS (pretrained weights loaded from a path;
  reported unavailable when absent, never replaced).
- :mod:`anidress_core.metrics.mesh`: geometry against ground truth: vertex RMSE,
  Chamfer distance, normal consistency, temporal jitter.

Import the submodule you need; this package imports neither eagerly.
"""
