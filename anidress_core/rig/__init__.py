"""Garment rigging model (paper §3.1): SSDR skinning decomposition and transforms-from-mesh fitting.

:mod:`anidress_core.rig.decompose` holds the math (batched torch), :mod:`anidress_core.rig.kernels`
the Warp kernel of the per-bone rigid fit.
"""
from .decompose import RigModel, fit_transforms, reconstruct, rmse, ssdr

__all__ = ["RigModel", "ssdr", "fit_transforms", "reconstruct", "rmse"]
