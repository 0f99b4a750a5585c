"""Stage `rig`: garment rigging model from the simulated sequences (DESIGN.md §4, paper §3.1).

Reads the scene's ``template.npz`` and every ``sim/<motion>.npz``, decomposes all
simulated frames together with :func:`anidress_core.rig.ssdr` and writes ``rig.npz``
(layout: :mod:`anidress_core.io.rig`).

Also the file-to-file command of ``anidress rig-decompose`` (the Dem Bones layout:
``weights`` (B, V), ``transforms`` (T, B, 4, 4)).
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .. import rig as R
from ..io import files
from ..io.rig import DemBonesRig, RigArtifact, read_dembones_sequence, read_rig, write_dembones_rig, write_rig
from ..io.sim import read_sim
from ..io.template import read_template

__all__ = ["run_rig", "run_rig_decompose"]

log = logging.getLogger("anidress.rig")


def run_rig(template_npz: str | os.PathLike, sim_npzs: Sequence[str | os.PathLike], params: dict,
            out_npz: str | os.PathLike, device: str | None = None) -> RigArtifact:
    """Decompose every simulated frame of ``sim_npzs`` into one rig and write ``out_npz``.

    params: ``bones``, ``iters``, ``nnz``, ``smooth`` (and optional ``seed``,
    ``threads``, ``max_frames_per_sequence``: a stride so that no sequence contributes
    more frames than this to the decomposition; the transforms of every frame are still
    written, by fitting the rig to the frames left out).
    """
    t0 = time.perf_counter()
    tpl = read_template(template_npz)
    names, frames = [], []
    for p in sim_npzs:
        x = read_sim(p).frames
        if x.ndim != 3 or x.shape[1:] != tpl.verts.shape:
            raise files.ArtifactError(f"{p}: frames must be (T, {tpl.verts.shape[0]}, 3) to match "
                                      f"{template_npz}, got {x.shape}")
        if not np.isfinite(x).all():
            raise files.ArtifactError(f"{p}: frames contain NaN or inf")
        names.append(Path(p).stem)
        frames.append(x)
    if not frames:
        raise ValueError("run_rig: no simulated sequences given")
    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    dtype = torch.float32  # the simulations are float32; SSDR works in normalised coordinates
    rest = torch.as_tensor(tpl.verts, dtype=dtype, device=dev)
    faces = torch.as_tensor(tpl.faces, device=dev)
    stride_cap = int(params.get("max_frames_per_sequence") or 0)
    used = []
    for x in frames:
        step = max(1, int(np.ceil(x.shape[0] / stride_cap))) if stride_cap > 0 else 1
        used.append(torch.as_tensor(x[::step], dtype=dtype, device=dev))
    X = torch.cat(used)
    log.info("rig: %d sequences, %d of %d frames decomposed, %d vertices, B=%d, %d iterations, nnz %d",
             len(names), X.shape[0], sum(x.shape[0] for x in frames), rest.shape[0], params["bones"],
             params["iters"], params["nnz"])
    model = R.ssdr(rest, X, faces, num_bones=int(params["bones"]), iters=int(params["iters"]),
                   nnz=int(params["nnz"]), smooth=float(params.get("smooth", 1e-4)),
                   seed=int(params.get("seed", 0)), progress=True)
    # every frame of every sequence gets its transforms (frames left out by the stride are fitted)
    Ms, rm, offsets = [], [], [0]
    for name, x in zip(names, frames):
        xt = torch.as_tensor(x, dtype=dtype, device=dev)
        M = R.fit_transforms(model, xt)
        Ms.append(M)
        rm.append(R.rmse(R.reconstruct(model.rest, model.weights, M), xt))
        offsets.append(offsets[-1] + x.shape[0])
        log.info("rig: %s: %d frames, RMSE %.2f mm", name, x.shape[0], 1e3 * rm[-1])
    transforms = torch.cat(Ms)
    total = float(np.sqrt(np.sum(np.square(rm) * np.diff(offsets)) / offsets[-1]))
    wall = time.perf_counter() - t0
    meta = {"params": dict(params), "bones": model.num_bones, "frames_decomposed": int(X.shape[0]),
            "history_m": list(model.history), "wall_s": wall, "device": str(dev)}
    rest32 = torch.as_tensor(tpl.verts.astype(np.float32))
    write_rig(out_npz, RigArtifact(
        model=R.RigModel(rest=rest32, weights=model.weights, transforms=transforms, bone_centres=model.bone_centres,
                         rmse=total),
        faces=tpl.faces, sequences={n: slice(offsets[i], offsets[i + 1]) for i, n in enumerate(names)},
        rmse_per_sequence=dict(zip(names, rm)), meta=meta), config=params)
    log.info("rig: %d bones, RMSE %.2f mm over %d frames (%.1f s)", model.num_bones, 1e3 * total, offsets[-1], wall)
    return read_rig(out_npz)


def run_rig_decompose(seq_npz: str | os.PathLike, out_npz: str | os.PathLike, bones: int = 25, iters: int = 50,
                      nnz: int = 8, smooth: float = 1e-4, seed: int = 0, device: str | None = None) -> R.RigModel:
    """``anidress rig-decompose``: SEQ.npz (rest (V,3), faces (F,3), frames (T,V,3)) -> OUT.npz.

    OUT.npz holds ``weights`` (B, V) and ``transforms`` (T, B, 4, 4) with
    x[t,i] = sum_b W[b,i] (M[t,b,:3,:3] rest[i] + M[t,b,:3,3]) (Dem Bones' convention),
    plus ``rmse`` and ``bone_centres`` (B, 3).
    """
    path = Path(seq_npz)
    rest, frames, faces = read_dembones_sequence(path)
    dev = torch.device(device or "cpu")
    dtype = torch.float64 if frames.dtype == np.float64 else torch.float32
    try:
        model = R.ssdr(torch.as_tensor(rest, dtype=dtype, device=dev), torch.as_tensor(frames, dtype=dtype, device=dev),
                       None if faces is None else torch.as_tensor(faces, device=dev), num_bones=bones, iters=iters,
                       nnz=nnz, smooth=smooth, seed=seed)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e
    write_dembones_rig(out_npz, DemBonesRig(
        weights=model.weights.T.contiguous().cpu().numpy(), transforms=model.transforms.cpu().numpy(),
        bone_centres=model.bone_centres.cpu().numpy(), rmse=model.rmse))
    return model
