"""The axis convention of a normal predictor's maps, found against normals the pipeline knows.

Normal predictors write camera-space normals in their own axes: Sapiens and ICON / ECON
render with y up and z towards the viewer (OpenGL), the pipeline uses OpenCV's (x right,
y down, z forward). The body is known (its poses are an input), so the convention is
measured rather than assumed: on the pixels where the posed body is seen, every signed
axis permutation ``M`` that keeps the frame right-handed (24 of them) turns the predicted
normals ``n`` into ``M n``, and
the one whose mean cosine with the body's rendered normals is highest wins, provided it
agrees (mean cosine at least :data:`AGREEMENT`) and stands out (it beats the second best
in at least a fraction :data:`CONSISTENCY` of the images). Pure functions: arrays in, arrays out.

Why these thresholds (studies/cues/normal_convention.md: the synthetic predicted normals of
the demo skirt and three suite scenes, against the body posed as the scene says, the
skinned garment template hiding the body where it covers it): the right convention
agrees at a mean cosine of 0.92 to 0.97, the best other rotation at 0.61 to 0.66 (a quarter
turn about z; OpenGL's axes, y and z flipped, at -0.57 to -0.48). A mean of 0.5 leaves
room for a body estimate a few centimetres off and a smoothing predictor. The mirrored y
flip, not a candidate, would come second at 0.69 to 0.78 there and within 0.005 of the right
one on a tiny scene of the tests; the win in 90% of the images is asked for on top of the mean.
"""
from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

__all__ = ["SIGNED_PERMUTATIONS", "AGREEMENT", "CONSISTENCY", "Convention", "convention_scores", "find_convention",
           "describe"]

AGREEMENT = 0.5
"""Least mean cosine between the converted predicted normals and the body's for a convention to agree."""
CONSISTENCY = 0.9
"""Least fraction of the images in which the best convention beats the second best."""


def _signed_permutations() -> np.ndarray:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs)):
                M[row, col] = s
            if np.linalg.det(M) > 0:  # right-handed frames only
                out.append(M)
    out.sort(key=lambda M: (not np.array_equal(M, np.eye(3)),))  # the identity first
    return np.stack(out)


SIGNED_PERMUTATIONS = _signed_permutations()
"""(24, 3, 3) every signed axis permutation that keeps a frame right-handed (a rotation), the identity first: a
map ``n -> M n``. Camera frames are right-handed in every convention in use (OpenCV; OpenGL / Blender, y up and
z towards the viewer; PyTorch3D, x left and y up); a mirrored frame (one axis flipped alone) is not a
candidate, so that the y flip, which an upright body's mostly horizontal normals hardly tell apart, never
competes with the right convention."""


class Convention(NamedTuple):
    """The convention found: ``matrix`` (3, 3) maps the file's normals into the pipeline's axes."""

    matrix: np.ndarray
    score: float
    """Mean cosine of the converted normals with the body's."""
    runner_up: float
    """The best mean cosine of any other signed permutation."""
    pixels: int
    consistency: float
    """The fraction of the images in which it beats the second best."""


def convention_scores(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Mean cosine of ``M pred`` with ``ref`` for each M of :data:`SIGNED_PERMUTATIONS`.

    pred, ref: (N, 3) unit (or zero-free) normals -> (24,) float64.
    """
    pred = np.asarray(pred, np.float64)
    ref = np.asarray(ref, np.float64)
    if pred.ndim != 2 or pred.shape[-1] != 3 or pred.shape != ref.shape:
        raise ValueError(f"convention_scores: pred and ref must be (N, 3) alike, got {pred.shape}, {ref.shape}")
    pred = pred / np.maximum(np.linalg.norm(pred, axis=-1, keepdims=True), 1e-12)
    ref = ref / np.maximum(np.linalg.norm(ref, axis=-1, keepdims=True), 1e-12)
    C = pred.T @ ref / max(1, len(pred))  # C[j, k] = mean pred_j ref_k
    # cos(M pred, ref) = sum_k ref_k sum_j M_kj pred_j -> mean = sum_kj M_kj C[j, k]
    return np.einsum("mkj,jk->m", SIGNED_PERMUTATIONS, C)


def describe(M: np.ndarray) -> str:
    """The convention as the file's axes seen from the pipeline's: e.g. ``x, -y, -z`` for OpenGL's."""
    names = []
    for row in np.asarray(M):
        j = int(np.argmax(np.abs(row)))
        names.append(("-" if row[j] < 0 else "") + "xyz"[j])
    return ", ".join(names)


def find_convention(pred: np.ndarray, ref: np.ndarray, image: np.ndarray | None = None,
                    agreement: float = AGREEMENT, consistency: float = CONSISTENCY, min_pixels: int = 100,
                    where: str = "normals") -> Convention:
    """The signed axis permutation that turns predicted normals ``pred`` into the body's ``ref``.

    pred, ref: (N, 3) normals at the same pixels (body pixels where the prediction is non-zero); image:
    (N,) int, the image (camera and frame) of each pixel (None: one image). The best permutation by mean
    cosine must reach ``agreement`` and beat the second best in at least a fraction ``consistency`` of the
    images (with 20 or more of the pixels each): a sign that only some pixels decide (the y axis of an
    upright body, whose normals are mostly horizontal) is then still told apart when every image agrees.
    Raises ValueError naming ``where`` when there are fewer than ``min_pixels`` pixels, when no permutation
    agrees or when the images disagree on the best.
    """
    n = len(pred)
    if n < min_pixels:
        raise ValueError(f"{where}: only {n} body pixels with a normal to check the axis convention on "
                         f"(need {min_pixels}); are the normals zero where the body is?")
    image = np.zeros(n, np.int64) if image is None else np.asarray(image)
    s = convention_scores(pred, ref)
    order = np.argsort(-s)
    best, second = float(s[order[0]]), float(s[order[1]])
    M, M2 = SIGNED_PERMUTATIONS[order[0]], SIGNED_PERMUTATIONS[order[1]]
    if best < agreement:
        raise ValueError(f"{where}: no axis convention of the normal maps agrees with the posed body's normals: the "
                         f"best signed axis permutation ({describe(M)}) reaches a mean cosine of {best:.3f} over "
                         f"{n} body pixels, {agreement:g} is needed. Are these camera-space normals of these images "
                         "(not world-space, not of another camera or frame), is the body pose right?")
    # the lead of the best over the second best, image by image
    lead = np.sum((pred @ (M - M2).T) * ref, -1)
    ids, inv, counts = np.unique(image, return_inverse=True, return_counts=True)
    per = np.bincount(inv, weights=lead) / counts
    used = counts >= 20
    won = float((per[used] > 0).mean()) if used.any() else 0.0
    if won < consistency:
        raise ValueError(f"{where}: the axis convention of the normal maps is ambiguous: {describe(M)} (mean cosine "
                         f"{best:.3f}) beats {describe(M2)} ({second:.3f}) in {won:.0%} of {int(used.sum())} images "
                         f"with 20 or more body pixels ({consistency:.0%} needed)")
    return Convention(M, best, second, n, won)
