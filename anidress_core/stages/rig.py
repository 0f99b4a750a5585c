"""Stage `rig`: garment rigging model from the simulated sequences (DESIGN.md §4, paper §3.1).

Reads the scene's ``template.npz`` and every ``sim/<motion>.npz``, decomposes all
simulated frames together with :func:`anidress_core.rig.ssdr` and writes ``rig.npz``:

* ``rest`` (V, 3) float32: the template's rest vertices (body canonical frame, metres);
* ``faces`` (F, 3) int64;
* ``weights`` (V, B) float32: convex skinning weights, at most ``nnz`` non-zeros per
  row (stored dense, zeros off the support);
* ``bone_centres`` (B, 3) float32: weighted rest centroid of each bone;
* ``transforms`` (N, B, 4, 4) float32: rest -> frame transforms (column vectors) of
  every simulated frame, sequences concatenated in the order of ``sequences``;
* ``sequences`` (S,) str and ``offsets`` (S + 1,) int64: frames of sequence s are
  ``transforms[offsets[s]:offsets[s + 1]]``;
* ``rmse_per_sequence`` (S,) float64 (metres) and ``rmse`` () float64: reconstruction
  error of the rig on the simulated frames.

Also the file-to-file command of ``anidress rig-decompose`` (the Dem Bones layout:
``weights`` (B, V), ``transforms`` (T, B, 4, 4)).
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .. import rig as R
from ..io import files

__all__ = ["RigArtifact", "run_rig", "load_rig", "run_rig_decompose"]

log = logging.getLogger("anidress.rig")


@dataclass(frozen=True)
class RigArtifact:
    """``rig.npz`` as read by :func:`load_rig`."""

    model: R.RigModel
    """rest (V, 3), weights (V, B), transforms (N, B, 4, 4), bone_centres (B, 3), rmse."""
    faces: np.ndarray
    """(F, 3) int64."""
    sequences: dict[str, slice]
    """Simulated motion name -> its frames in ``model.transforms``."""
    rmse_per_sequence: dict[str, float]
    """Simulated motion name -> reconstruction RMSE (m)."""
    meta: dict
    """Header metadata (parameters, timings, iteration history)."""

    def transforms_of(self, name: str) -> torch.Tensor:
        """(T, B, 4, 4) bone transforms of simulated motion ``name``."""
        if name not in self.sequences:
            raise KeyError(f"rig has no simulated sequence {name!r} (has {sorted(self.sequences)})")
        return self.model.transforms[self.sequences[name]]


def run_rig(template_npz: str | os.PathLike, sim_npzs: Sequence[str | os.PathLike], params: dict,
            out_npz: str | os.PathLike, device: str | None = None) -> RigArtifact:
    """Decompose every simulated frame of ``sim_npzs`` into one rig and write ``out_npz``.

    params: ``bones``, ``iters``, ``nnz``, ``smooth`` (and optional ``seed``,
    ``threads``, ``max_frames_per_sequence``: a stride so that no sequence contributes
    more frames than this to the decomposition; the transforms of every frame are still
    written, by fitting the rig to the frames left out).
    """
    from .template import load_template

    t0 = time.perf_counter()
    tpl = load_template(template_npz)
    names, frames = [], []
    for p in sim_npzs:
        a, h = files.load_npz(p, required=("frames",))
        x = a["frames"]
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
    files.save_npz(out_npz, {
        "rest": tpl.verts.astype(np.float32), "faces": tpl.faces.astype(np.int64),
        "weights": model.weights.float().cpu().numpy(), "bone_centres": model.bone_centres.float().cpu().numpy(),
        "transforms": transforms.float().cpu().numpy(), "sequences": np.asarray(names),
        "offsets": np.asarray(offsets, np.int64), "rmse_per_sequence": np.asarray(rm, np.float64),
        "rmse": np.float64(total),
    }, config=params, meta=meta)
    log.info("rig: %d bones, RMSE %.2f mm over %d frames (%.1f s)", model.num_bones, 1e3 * total, offsets[-1], wall)
    return load_rig(out_npz)


def load_rig(path: str | os.PathLike, device: str | torch.device = "cpu",
             dtype: torch.dtype = torch.float32) -> RigArtifact:
    """Read ``rig.npz`` written by :func:`run_rig`."""
    a, h = files.load_npz(path, required=("rest", "faces", "weights", "bone_centres", "transforms", "sequences",
                                          "offsets", "rmse_per_sequence", "rmse"))
    V, B = a["weights"].shape
    if a["rest"].shape != (V, 3) or a["transforms"].shape[1:] != (B, 4, 4) or a["bone_centres"].shape != (B, 3):
        raise files.ArtifactError(f"{path}: inconsistent shapes: rest {a['rest'].shape}, weights "
                                  f"{a['weights'].shape}, transforms {a['transforms'].shape}")
    names = [str(n) for n in a["sequences"]]
    off = a["offsets"]
    if off.shape != (len(names) + 1,) or off[-1] != a["transforms"].shape[0]:
        raise files.ArtifactError(f"{path}: offsets {off.tolist()} do not cover {a['transforms'].shape[0]} frames")
    t = lambda k: torch.as_tensor(a[k], dtype=dtype, device=device)  # noqa: E731
    model = R.RigModel(rest=t("rest"), weights=t("weights"), transforms=t("transforms"),
                       bone_centres=t("bone_centres"), rmse=float(a["rmse"]))
    return RigArtifact(model=model, faces=a["faces"].astype(np.int64),
                       sequences={n: slice(int(off[i]), int(off[i + 1])) for i, n in enumerate(names)},
                       rmse_per_sequence={n: float(r) for n, r in zip(names, a["rmse_per_sequence"])},
                       meta=h.get("meta", {}))


def run_rig_decompose(seq_npz: str | os.PathLike, out_npz: str | os.PathLike, bones: int = 25, iters: int = 50,
                      nnz: int = 8, smooth: float = 1e-4, seed: int = 0, device: str | None = None) -> R.RigModel:
    """``anidress rig-decompose``: SEQ.npz (rest (V,3), faces (F,3), frames (T,V,3)) -> OUT.npz.

    OUT.npz holds ``weights`` (B, V) and ``transforms`` (T, B, 4, 4) with
    x[t,i] = sum_b W[b,i] (M[t,b,:3,:3] rest[i] + M[t,b,:3,3]) (Dem Bones' convention),
    plus ``rmse`` and ``bone_centres`` (B, 3).
    """
    path = Path(seq_npz)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in ("rest", "frames") if k not in z.files]
            if missing:
                raise files.ArtifactError(f"{path}: missing arrays {missing} (needs rest (V,3), frames (T,V,3), "
                                          "faces (F,3))")
            rest, frames = z["rest"], z["frames"]
            faces = z["faces"] if "faces" in z.files else None
    except (OSError, ValueError) as e:
        if isinstance(e, files.ArtifactError):
            raise
        raise files.ArtifactError(f"{path}: not a readable npz ({e})") from e
    dev = torch.device(device or "cpu")
    dtype = torch.float64 if frames.dtype == np.float64 else torch.float32
    try:
        model = R.ssdr(torch.as_tensor(rest, dtype=dtype, device=dev), torch.as_tensor(frames, dtype=dtype, device=dev),
                       None if faces is None else torch.as_tensor(faces, device=dev), num_bones=bones, iters=iters,
                       nnz=nnz, smooth=smooth, seed=seed)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e
    out = {"weights": model.weights.T.contiguous().cpu().numpy(), "transforms": model.transforms.cpu().numpy(),
           "bone_centres": model.bone_centres.cpu().numpy(), "rmse": np.float64(model.rmse)}
    with files.atomic_path(out_npz) as tmp:
        np.savez(tmp, **out)
    return model
