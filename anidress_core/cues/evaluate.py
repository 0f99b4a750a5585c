"""Cue errors against ground truth: mask IoU, flow end-point error, normal angular error.

Each function returns sums and counts (not means) so per-frame results add up to
sequence totals exactly; :class:`CueErrors` accumulates them. Pure functions.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["iou_counts", "epe_sums", "angle_sums", "CueErrors"]

BODY, GARMENT = 1, 2


def iou_counts(pred: np.ndarray, gt: np.ndarray, label: int | None) -> tuple[int, int]:
    """(intersection, union) pixel counts of one label; ``label=None``: the subject (> 0).

    pred, gt: (..., H, W) integer label maps of the same shape.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"iou_counts: shapes differ, {pred.shape} vs {gt.shape}")
    a, b = (pred > 0, gt > 0) if label is None else (pred == label, gt == label)
    return int((a & b).sum()), int((a | b).sum())


def epe_sums(flow: np.ndarray, gt_flow: np.ndarray, select: np.ndarray) -> tuple[float, int, int]:
    """(sum of end-point errors, count, count with error > 3 px) over ``select``.

    flow, gt_flow: (..., H, W, 2) pixels; select: (..., H, W) bool.
    """
    if flow.shape != gt_flow.shape or flow.shape[:-1] != select.shape:
        raise ValueError(f"epe_sums: shapes {flow.shape}, {gt_flow.shape}, {select.shape} do not match")
    e = np.linalg.norm((flow - gt_flow)[select], axis=-1)
    return float(e.sum(dtype=np.float64)), int(e.size), int((e > 3.0).sum())


def angle_sums(normals: np.ndarray, gt_normals: np.ndarray, select: np.ndarray) -> tuple[float, int, np.ndarray]:
    """(sum of angular errors in degrees, count, the errors) over ``select``.

    normals, gt_normals: (..., H, W, 3), normalised here; select: (..., H, W) bool.
    Pixels where either normal is zero count as 90 degrees (the predictor gave nothing).
    """
    if normals.shape != gt_normals.shape or normals.shape[:-1] != select.shape:
        raise ValueError(f"angle_sums: shapes {normals.shape}, {gt_normals.shape}, {select.shape} do not match")
    a, b = normals[select].astype(np.float64), gt_normals[select].astype(np.float64)
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    cos = (a * b).sum(-1) / np.maximum(na * nb, 1e-12)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ang = np.where((na < 1e-6) | (nb < 1e-6), 90.0, ang)
    return float(ang.sum()), int(ang.size), ang.astype(np.float32)


@dataclass
class CueErrors:
    """Running totals of cue errors over many (camera, frame) pairs."""

    iou: dict = field(default_factory=dict)  # name -> [intersection, union]
    epe: dict = field(default_factory=dict)  # name -> [sum, count, outliers]
    angle: dict = field(default_factory=dict)  # name -> list of error arrays

    def add_masks(self, pred: np.ndarray, gt: np.ndarray) -> None:
        for name, label in (("subject", None), ("body", BODY), ("garment", GARMENT)):
            i, u = iou_counts(pred, gt, label)
            acc = self.iou.setdefault(name, [0, 0])
            acc[0] += i
            acc[1] += u

    def add_flow(self, flow: np.ndarray, gt_flow: np.ndarray, gt_valid: np.ndarray, gt_labels0: np.ndarray,
                 tag: str = "") -> None:
        """Flow of one pair; ``gt_labels0``: ground-truth labels of frame t-1 (where the flow lives).

        Regions: ``all`` every pixel where the ground truth is valid (visible in both
        frames; flow outside the processed region counts as 0, right for the static
        background), ``subject`` and ``garment`` those of the subject / garment.
        """
        for name, sel in (("all", gt_valid), ("subject", gt_valid & (gt_labels0 > 0)),
                          ("garment", gt_valid & (gt_labels0 == GARMENT))):
            s, n, o = epe_sums(flow, gt_flow, sel)
            acc = self.epe.setdefault(tag + name, [0.0, 0, 0])
            acc[0] += s
            acc[1] += n
            acc[2] += o

    def add_normals(self, normals: np.ndarray, gt_normals: np.ndarray, gt_labels: np.ndarray) -> None:
        for name, sel in (("subject", gt_labels > 0), ("garment", gt_labels == GARMENT)):
            self.angle.setdefault(name, []).append(angle_sums(normals, gt_normals, sel)[2])

    def summary(self) -> dict[str, float]:
        """Flat dict: ``iou_<name>``, ``epe_<name>_px``, ``epe_<name>_gt3px_frac``,
        ``normal_<name>_mean_deg`` / ``_median_deg`` / ``_within20_frac``, ``*_pixels``."""
        out: dict[str, float] = {}
        for name, (i, u) in self.iou.items():
            out[f"iou_{name}"] = i / u if u else float("nan")
        for name, (s, n, o) in self.epe.items():
            out[f"epe_{name}_px"] = s / n if n else float("nan")
            out[f"epe_{name}_gt3px_frac"] = o / n if n else float("nan")
            out[f"epe_{name}_pixels"] = n
        for name, parts in self.angle.items():
            a = np.concatenate(parts) if parts else np.zeros(0, np.float32)
            out[f"normal_{name}_mean_deg"] = float(a.mean()) if a.size else float("nan")
            out[f"normal_{name}_median_deg"] = float(np.median(a)) if a.size else float("nan")
            out[f"normal_{name}_within20_frac"] = float((a < 20).mean()) if a.size else float("nan")
            out[f"normal_{name}_pixels"] = int(a.size)
        return out
