"""Cloth simulation of a garment template on a moving skinned body (stage ``simulate``).

XPBD in Warp kernels (CPU by default, CUDA when available): stretch and bending
(cross-edge) distance constraints solved Gauss–Seidel over a graph colouring, long-range
attachments to the band, collision with the skinned body mesh, settle phase from the
T-pose, per-frame blow-up detection with substep refinement. Modules: :mod:`.solver`
(driver, :func:`simulate`), :mod:`.kernels` (Warp kernels), :mod:`.setup` (one-time
preprocessing), :mod:`.metrics` (edge stretch, penetration depth).
"""
from .metrics import edge_stretch, penetration_depth
from .solver import ClothParams, SimResult, SimStats, SimulationError, simulate

__all__ = ["ClothParams", "SimResult", "SimStats", "SimulationError", "simulate", "edge_stretch",
           "penetration_depth"]
