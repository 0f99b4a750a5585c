"""Stages ``import-zju`` and ``import-easymocap``: a capture turned into a scene the pipeline reads (DESIGN.md §3).

``anidress import-easymocap SRC DST`` does the same for an EasyMocap capture folder
(``intri.yml``, ``extri.yml``, ``images/<cam>/``, ``output-smpl-3d/smpl/`` or ``smpl/``), which
the pipeline cannot read as it is: it has no scene.yaml and its body files are not in
``<seq>/smpl`` (:func:`run_import_easymocap`).

``anidress import-zju SRC DST --fps F`` reads ``SRC/annots.npy`` (cameras K, D, R, T in
millimetres, per-frame image lists), ``SRC/params/<i>.npy`` or ``SRC/new_params/<i>.npy``
(poses, Rh, Th, shapes) and the masks ``SRC/mask/`` and / or ``SRC/mask_cihp/``
(:mod:`anidress_core.io.zju`), and writes::

    DST/scene.yaml              synthetic: false, kind, fps, image_size [H, W], cameras
                                train / test, sequences (name, role, frames; no motion),
                                body_model, garment_template / garment_kind (with --garment),
                                source (format, folder)
    DST/body_model.npz          the bundled mannequin (default) or a copy of --body-model
    DST/garment/template.<ext>  a copy of --garment (and texture.png of --garment-texture)
    DST/<seq>/intri.yml         K_<cam>, dist_<cam> (k1 k2 p1 p2 k3), H_<cam>, W_<cam>
    DST/<seq>/extri.yml         R_<cam> (Rodrigues), Rot_<cam>, T_<cam> in METRES (file mm / 1000)
    DST/<seq>/images/<cam>/<frame:06d>.<ext>   the capture's images (symlink, hard link or copy)
    DST/<seq>/masks/<cam>/<frame:06d>.png      labels 0 background / 1 body / 2 garment
                                               (io.zju.zju_mask_labels; without a garment
                                               template every person pixel is body)
    DST/<seq>/smpl/<frame:06d>.json            EasyMocap body files (poses 72, Rh, Th, shapes)
    DST/<seq>/import.json                      where each camera and frame came from

Camera names: the image folders made safe for EasyMocap's files
(:func:`anidress_core.io.zju.safe_camera_names`: ``Camera (1)`` -> ``Camera_1``); frames
are numbered from 0 in the order of the chosen ``ims`` entries (``import.json`` keeps the
``ims`` index, the frame number ``i`` of ``params/<i>.npy`` and the source images).
Lens distortion is kept (``dist_<cam>``): the pipeline undistorts once (rule undistort).

Importing a second sequence into an existing DST (``--sequence novel --frames 300:``)
adds it to scene.yaml; the cameras must be the same.

Every input is checked before DST changes: a missing annots key, a camera count that
differs between fields or frames, a missing image or parameter file, a mask of another
size: one ValueError naming the file and the field. The sequence is written beside DST's
and moved in complete; scene.yaml is written last.
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from .. import __version__
from ..garment import KINDS
from ..io import cue_files, easymocap, files
from ..io.images import image_size_from_header
from ..io.motion import read_easymocap_smpl_dir, write_easymocap_smpl_dir
from ..io.scene_info import scene_config_entry
from ..io.zju import (CIHP_GARMENT_LABELS, MASK_KINDS, read_annots, read_zju_params, safe_camera_names,
                      zju_frame_number, zju_mask_labels, zju_mask_paths)

__all__ = ["parse_frames", "split_cameras", "LINK_MODES", "PARAMS_DIRS", "ZJU_FPS", "run_import_zju", "SMPL_DIRS",
           "MASK_FORMATS", "EASYMOCAP_FPS", "run_import_easymocap"]

log = logging.getLogger("anidress.import")

LINK_MODES = ("symlink", "hardlink", "copy")
"""How the capture's images reach ``DST/<seq>/images``: an absolute symbolic link (default:
no copy of gigabytes), a hard link (same file system), or a copy."""
PARAMS_DIRS = ("params", "new_params")
"""Body parameter folders of a ZJU-MoCap capture, in the order they are looked for."""
ZJU_FPS = 50.0
"""The frame rate Neural Body's ZJU-MoCap sequences are usually taken to have. ``annots.npy`` does not
store one, so the import does not assume it: ``fps`` / ``--fps`` is required (it sets the time scale of
the cloth simulation of the sequence)."""
NEURALBODY_TRAIN_VIEWS = (0, 6, 12, 18)
"""Neural Body's training cameras of a 21- or 23-camera ZJU-MoCap capture (0-based indices)."""


# =========================================================================== pure helpers
def parse_frames(spec: str | Sequence[int] | None, n: int) -> list[int]:
    """Indices into a list of ``n`` frames from a frame selection.

    spec: None or ``""`` (all), ``"START:STOP[:STEP]"`` (Python slice: ``"0:300"``,
    ``"300:"``, ``"::2"``), ``"3,5,9"`` (a list), or a sequence of ints. Indices must lie in
    [0, n) and be distinct; the order is kept. ValueError naming the spec otherwise.
    """
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        return list(range(n))
    if isinstance(spec, str):
        s = spec.strip()
        try:
            if ":" in s:
                parts = [int(p) if p.strip() else None for p in s.split(":")]
                if len(parts) > 3:
                    raise ValueError
                out = list(range(n))[slice(*parts)]
            else:
                out = [int(p) for p in s.split(",")]
        except ValueError:
            raise ValueError(f"frames {spec!r}: expected START:STOP[:STEP] or a comma-separated list of "
                             "frame indices") from None
    else:
        out = [int(x) for x in spec]
    bad = [i for i in out if not 0 <= i < n]
    if bad:
        raise ValueError(f"frames {spec!r}: indices {bad[:5]} outside the capture's {n} frames (0..{n - 1})")
    if len(set(out)) != len(out):
        raise ValueError(f"frames {spec!r}: repeated frame indices")
    if not out:
        raise ValueError(f"frames {spec!r}: selects no frame of the capture's {n}")
    return out


def _pick_cameras(spec: str | Sequence[str], names: list[str], sources: list[str], what: str) -> list[str]:
    items = [x.strip() for x in spec.split(",") if x.strip()] if isinstance(spec, str) else [str(x) for x in spec]
    out = []
    for x in items:
        if x in names:
            out.append(x)
        elif x in sources:
            out.append(names[sources.index(x)])
        elif x.isdigit() and int(x) < len(names):
            out.append(names[int(x)])
        else:
            raise ValueError(f"{what}: camera {x!r} is not a camera name ({names}), a source folder name or an "
                             f"index 0..{len(names) - 1}")
    if len(set(out)) != len(out):
        raise ValueError(f"{what}: cameras repeat: {out}")
    return out


def split_cameras(names: list[str], sources: list[str] | None = None, train: str | Sequence[str] | None = None,
                  test: str | Sequence[str] | None = None) -> tuple[list[str], list[str]]:
    """(train, test) camera names of scene.yaml.

    train / test: comma-separated (or lists of) scene camera names, source names or 0-based
    indices. Defaults: with neither given, Neural Body's protocol on a ZJU-MoCap rig of 19
    cameras or more (train 0, 6, 12, 18; test the others), else every camera but the last
    trains and the last is the test camera (one camera: train only). With only train
    given, test is every other camera; with only test, train is every other camera.
    """
    sources = list(names) if sources is None else list(sources)
    C = len(names)
    if train is None and test is None:
        if C >= 19:
            tr = [names[i] for i in NEURALBODY_TRAIN_VIEWS]
        else:
            tr = names[:-1] if C > 1 else list(names)
        return tr, [n for n in names if n not in tr]
    tr = _pick_cameras(train, names, sources, "train") if train is not None else None
    te = _pick_cameras(test, names, sources, "test") if test is not None else None
    if tr is None:
        tr = [n for n in names if n not in te]
    if te is None:
        te = [n for n in names if n not in tr]
    both = sorted(set(tr) & set(te))
    if both:
        raise ValueError(f"cameras {both} are both train and test cameras")
    if not tr:
        raise ValueError("no training camera left")
    return tr, te


# =========================================================================== scene-level files
def _is_mannequin_npz(path: Path) -> bool:
    if path.suffix != ".npz":
        return False
    with np.load(path, allow_pickle=False) as z:
        keys = set(z.files)
    return {"v_template", "faces", "weights", "joints_rest", "parents"} <= keys and "J_regressor" not in keys


def _write_body_model(dst: Path, body_model: str | os.PathLike | None, height: float) -> dict:
    """body_model entry of scene.yaml; writes the file into ``dst``."""
    if body_model is None:
        from ..body.model import mannequin_model

        b = mannequin_model(height)
        files.save_npz(dst / "body_model.npz", {
            "v_template": b.v_template.numpy(), "faces": b.faces.numpy(), "weights": b.weights.numpy(),
            "joints_rest": b.joints_rest.numpy(), "parents": b.parents.numpy(), "face_uv": b.face_uv.numpy(),
            "vertex_part": b.vertex_part.numpy(), "part_names": np.array(b.part_names)},
            meta={"written_by": "anidress import", "height_m": height})
        log.info("body model: the bundled mannequin (%.2f m; it has no shape space: the capture's SMPL 'shapes' "
                 "do not change it; pass --body-model with a SMPL model file you own for the captured shape)", height)
        return {"type": "mannequin", "file": "body_model.npz", "height_m": float(height)}
    src = Path(body_model)
    if not src.is_file():
        raise FileNotFoundError(f"{src}: body model file not found (--body-model)")
    kind = "mannequin" if _is_mannequin_npz(src) else "smpl"
    name = f"body_model{src.suffix}"
    shutil.copyfile(src, dst / name)
    return {"type": kind, "file": name}


def _write_garment(dst: Path, garment: str | os.PathLike | None, kind: str | None,
                   texture: str | os.PathLike | None) -> dict:
    if garment is None:
        if kind not in (None, "tight"):
            raise ValueError(f"garment kind {kind!r} given without a garment template (--garment)")
        if texture is not None:
            raise ValueError("a garment texture given without a garment template (--garment)")
        return {}
    src = Path(garment)
    if not src.is_file():
        raise FileNotFoundError(f"{src}: garment template not found (--garment)")
    if kind not in KINDS:
        raise ValueError(f"--garment-kind must be one of {list(KINDS)} with a garment template, got {kind!r}")
    (dst / "garment").mkdir(parents=True, exist_ok=True)
    rel = f"garment/template{src.suffix.lower()}"
    shutil.copyfile(src, dst / rel)
    out = {"garment_template": rel, "garment_kind": kind}
    if texture is not None:
        t = Path(texture)
        if not t.is_file():
            raise FileNotFoundError(f"{t}: garment texture not found (--garment-texture)")
        shutil.copyfile(t, dst / "garment" / f"texture{t.suffix.lower()}")
        out["garment_texture"] = f"garment/texture{t.suffix.lower()}"
    return out


def _place(src: Path, dst: Path, link: str) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if link == "symlink":
        os.symlink(src.resolve(), dst)
    elif link == "hardlink":
        os.link(src, dst)
    else:
        shutil.copyfile(src, dst)


def _check_addition(dst: Path, existing: dict | None, names: list[str], size: tuple[int, int],
                    garment, body_model) -> None:
    """A sequence added to an existing scene must have its cameras and image size."""
    if existing is None:
        return
    if garment is not None or body_model is not None:
        raise ValueError(f"{dst / 'scene.yaml'}: the scene exists; its body model and garment stay "
                         "(no --garment / --body-model when adding a sequence)")
    old = existing.get("cameras") or {}
    if set(old.get("train") or []) | set(old.get("test") or []) != set(names):
        raise ValueError(f"{dst / 'scene.yaml'}: cameras {old} differ from the capture's {names}")
    if list(existing.get("image_size") or size) != list(size):
        raise ValueError(f"{dst / 'scene.yaml'}: image_size {existing.get('image_size')} differs from the "
                         f"capture's {list(size)}")


def _write_sequence(dst: Path, seq: str, role: str, existing: dict | None, cam_dict: dict, images: list[list[Path]],
                    labels, body: dict, record: dict, link: str, scene: dict, threads: int = 2) -> int:
    """Write ``dst/<seq>`` (cameras, images T x C placed as ``<cam>/<k:06d>``, masks from ``labels(k, c)``
    when given, ``threads`` files at a time; smpl/, import.json) beside ``dst`` and move it in; then the
    scene-level files of a new scene (garment, body model) and scene.yaml last. Returns the number of
    masks written."""
    names = list(cam_dict)
    dst.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{seq}.partial-", dir=dst))
    n_masks = 0
    try:
        easymocap.write_camera(tmp / "intri.yml", tmp / "extri.yml", cam_dict)
        def one(k: int, c: int) -> int:
            n, p = names[c], images[k][c]
            _place(p, tmp / "images" / n / f"{k:06d}{p.suffix.lower()}", link)
            if labels is None:
                return 0
            files.write_mask(tmp / "masks" / n / f"{k:06d}.png", labels(k, c))
            return 1

        with ThreadPoolExecutor(max_workers=max(1, int(threads))) as pool:  # the first failure (in order) raises
            jobs = [pool.submit(one, k, c) for k in range(len(images)) for c in range(len(names))]
            n_masks = sum(j.result() for j in jobs)
        write_easymocap_smpl_dir(tmp / "smpl", body["poses"], body["Rh"], body["Th"], body["shapes"])
        files.write_json(tmp / "import.json", record)
        if existing is None:
            tr, te = scene["split"]
            size = scene["size"]
            info = {"name": dst.name, "synthetic": False,
                    "kind": scene["garment_kind"] if scene["garment"] is not None else "tight",
                    "fps": float(scene["fps"]), "units": "metres", "image_size": [int(size[0]), int(size[1])],
                    "cameras": {"train": tr, "test": te}, "sequences": []}
            info.update(_write_garment(dst, scene["garment"], scene["garment_kind"], scene["garment_texture"]))
            info["body_model"] = _write_body_model(dst, scene["body_model"], scene["height"])
            info["source"] = scene["source"]
        else:
            info = existing
        info["sequences"] = [s for s in info.get("sequences") or [] if s.get("name") != seq]
        info["sequences"].append({"name": seq, "role": role, "frames": len(images)})
        if (dst / seq).exists():
            shutil.rmtree(dst / seq)
        os.replace(tmp, dst / seq)
        files.write_text(dst / "scene.yaml", yaml.safe_dump(info, sort_keys=False))
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return n_masks


# =========================================================================== ZJU-MoCap
def _zju_params_dir(src: Path, params: str | os.PathLike | None) -> Path:
    if params is not None:
        p = Path(params)
        d = p if p.is_absolute() or p.is_dir() else src / p
        if not d.is_dir():
            raise FileNotFoundError(f"{d}: body parameter folder not found (--params)")
        return d
    for name in PARAMS_DIRS:
        if (src / name).is_dir():
            return src / name
    raise FileNotFoundError(f"{src}: no body parameter folder ({' or '.join(f'{n}/' for n in PARAMS_DIRS)})")


def _zju_mask_kinds(src: Path, masks: str) -> tuple[str, ...]:
    choices = {"auto": tuple(k for k in MASK_KINDS if (src / k).is_dir()), "none": (), "both": MASK_KINDS,
               "mask": ("mask",), "mask_cihp": ("mask_cihp",)}
    if masks not in choices:
        raise ValueError(f"masks must be one of {list(choices)}, got {masks!r}")
    kinds = choices[masks]
    for k in kinds:
        if not (src / k).is_dir():
            raise FileNotFoundError(f"{src / k}: mask folder not found (masks={masks!r})")
    return kinds


def _check_images(src: Path, annots: Path, ims: list[list[str]], picked: list[int], size: tuple[int, int]) -> None:
    for t in picked:
        for c, rel in enumerate(ims[t]):
            p = src / rel
            if not p.is_file():
                raise ValueError(f"{annots}: 'ims[{t}]' image {c} ({rel}) is missing: {p} not found")
            hw = image_size_from_header(p)
            if hw != size:
                raise ValueError(f"{p}: image is {hw[1]}x{hw[0]} (WxH), the capture's first image is "
                                 f"{size[1]}x{size[0]}")


def _read_labels(src: Path, rel: str, kinds: tuple[str, ...], size: tuple[int, int],
                 garment_labels: Sequence[int]) -> np.ndarray:
    paths = zju_mask_paths(src, rel)
    arrays = {}
    for k in kinds:
        p = paths[k]
        if not p.is_file():
            raise ValueError(f"{p}: missing: the {k}/ file of image {rel}")
        a = files.read_mask(p)
        if a.shape != size:
            raise ValueError(f"{p}: mask is {a.shape[1]}x{a.shape[0]} (WxH), the image {rel} is {size[1]}x{size[0]}")
        arrays[k] = a
    try:
        return zju_mask_labels(arrays.get("mask"), arrays.get("mask_cihp"), garment_labels)
    except ValueError as e:
        raise ValueError(f"{paths['mask_cihp']}: {e}") from e


def _existing_scene(dst: Path) -> dict | None:
    if not (dst / "scene.yaml").is_file():
        if dst.exists() and any(dst.iterdir()):
            raise ValueError(f"{dst}: exists, is not empty and has no scene.yaml: not a scene to add a sequence to")
        return None
    info = yaml.safe_load((dst / "scene.yaml").read_text()) or {}
    if info.get("synthetic", True) is not False:
        raise ValueError(f"{dst / 'scene.yaml'}: not a captured scene (synthetic: false): import into a new folder")
    return info


def run_import_zju(src: str | os.PathLike, dst: str | os.PathLike, sequence: str | None = None,
                   frames: str | Sequence[int] | None = None, garment: str | os.PathLike | None = None,
                   garment_kind: str | None = None, garment_texture: str | os.PathLike | None = None,
                   garment_labels: Sequence[int] = CIHP_GARMENT_LABELS, body_model: str | os.PathLike | None = None,
                   params: str | os.PathLike | None = None, masks: str = "auto",
                   train: str | Sequence[str] | None = None, test: str | Sequence[str] | None = None,
                   role: str = "train", fps: float | None = None, link: str = "symlink", height: float = 1.7,
                   threads: int = 2) -> dict:
    """Convert the ZJU-MoCap capture ``src`` into (or add a sequence to) the scene ``dst``; see the module doc.

    fps: the capture's frame rate (frames/s), required: ZJU-MoCap's files do not store it.

    sequence: the sequence name (default: ``src``'s folder name made safe); frames: which
    ``ims`` entries (:func:`parse_frames`); garment / garment_kind / garment_texture: the
    garment template (none: a tight-clothed scene); garment_labels: CIHP values that are
    garment; body_model: a SMPL model file or mannequin npz (default: the bundled
    mannequin of ``height`` metres); params: ``params`` / ``new_params`` / a folder
    (default: the first of :data:`PARAMS_DIRS` present); masks: auto (every mask folder
    present), mask, mask_cihp, both or none; train / test: :func:`split_cameras`; role: the
    sequence's role (train, novel_pose); link: :data:`LINK_MODES`; threads: files placed and masks
    converted at a time (a ZJU-MoCap sequence: 23 cameras x ~1,000 frames of 1024 x 1024 masks).

    Returns the import record (also ``dst/<seq>/import.json``).
    """
    t0 = time.perf_counter()
    src, dst = Path(src), Path(dst)
    annots = src / "annots.npy"
    if link not in LINK_MODES:
        raise ValueError(f"link must be one of {list(LINK_MODES)}, got {link!r}")
    if fps is None:
        raise ValueError(f"{annots}: ZJU-MoCap's files do not store the frame rate: give the capture's (fps / --fps; "
                         f"Neural Body's ZJU-MoCap sequences are usually taken as {ZJU_FPS:g} frames/s)")
    if not (isinstance(fps, (int, float)) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    seq = sequence or safe_camera_names([src.resolve().name])[0]
    if not seq or not all(ch.isalnum() or ch in "_-" for ch in seq):
        raise ValueError(f"sequence name {seq!r}: letters, digits, _ or - only")
    # 1. read and check everything before writing anything
    a = read_annots(annots)
    cams, ims = a["cameras"], a["ims"]
    sources = list(cams.names)
    names = safe_camera_names(sources)
    size = (cams.height, cams.width)
    picked = parse_frames(frames, len(ims))
    numbers = []
    for t in picked:
        nums = set()
        for rel in ims[t]:
            try:
                nums.add(zju_frame_number(rel))
            except ValueError as e:
                raise ValueError(f"{annots}: 'ims[{t}]': {e}") from None
        if len(nums) != 1:
            raise ValueError(f"{annots}: 'ims[{t}]' images have different frame numbers {sorted(nums)}: {ims[t]}")
        numbers.append(nums.pop())
    _check_images(src, annots, ims, picked, size)
    pdir = _zju_params_dir(src, params)
    body = read_zju_params(pdir, numbers)
    kinds = _zju_mask_kinds(src, masks)
    existing = _existing_scene(dst)
    _check_addition(dst, existing, names, size, garment, body_model)
    has_garment = (existing or {}).get("garment_template") or garment is not None
    labels_garment = tuple(garment_labels) if has_garment else ()
    cam_dict = {n: {"K": cams.K[c].numpy(), "dist": cams.dist[c].numpy(), "R": cams.R[c].numpy(),
                    "T": cams.T[c].numpy(), "H": size[0], "W": size[1]} for c, n in enumerate(names)}
    record = {
        "format": "zju-mocap", "source": str(src.resolve()), "annots": str(annots.resolve()),
        "params": str(pdir.resolve()), "masks": list(kinds), "garment_labels": list(labels_garment),
        "link": link, "cameras": dict(zip(names, sources)),
        "frames": [{"frame": k, "ims_index": t, "params": f"{i}.npy", "images": ims[t]}
                   for k, (t, i) in enumerate(zip(picked, numbers))],
        "code_version": __version__,
    }
    images = [[src / rel for rel in ims[t]] for t in picked]
    labels = (lambda k, c: _read_labels(src, ims[picked[k]][c], kinds, size, labels_garment)) if kinds else None
    n_masks = _write_sequence(dst, seq, role, existing, cam_dict, images, labels, body, record, link, dict(
        fps=fps, size=size, split=split_cameras(names, sources, train, test), garment=garment,
        garment_kind=garment_kind, garment_texture=garment_texture, body_model=body_model, height=height,
        source={"format": "zju-mocap", "path": str(src.resolve())}), threads)
    info = yaml.safe_load((dst / "scene.yaml").read_text())
    record.update(scene_dir=str(dst), sequence=seq, wall_s=round(time.perf_counter() - t0, 3),
                  masks_written=n_masks, config_entry=scene_config_entry(info))
    log.info("import-zju %s -> %s/%s: %d cameras x %d frames (%s images), masks from %s, body parameters from %s "
             "(%.1f s)", src, dst, seq, len(names), len(picked), link, ", ".join(kinds) or "none", pdir.name,
             record["wall_s"])
    return record


# =========================================================================== EasyMocap
SMPL_DIRS = ("smpl", "output-smpl-3d/smpl", "output/smpl")
"""Where an EasyMocap capture keeps its body files, in the order they are looked for: ``smpl/``, the
output of EasyMocap >= 0.2's ``apps/demo/mocap.py`` (``output-smpl-3d/smpl``), 0.1's ``output/smpl``."""
MASK_FORMATS = ("person", "cihp", "labels", "schp")
"""What a capture's mask files hold: ``person`` (0 background, non-zero person: body), ``cihp`` (CIHP
part labels, garment from ``garment_labels``), ``labels`` (the pipeline's 0 / 1 / 2), ``schp`` (EasyMocap's
``mask-schp``: a 0 / 255 silhouette per person ``<frame>_<i>.png`` with SCHP's CIHP part labels in the sibling
``mask-schp-parsing/``, or SCHP's CIHP palette PNGs; :func:`anidress_core.io.cue_files.read_schp_indices`)."""
EASYMOCAP_FPS = 30.0
"""Frame rate written to scene.yaml when none is given (EasyMocap's files store none: an
assumption; pass the capture's real rate)."""


def _frame_files(folder: Path) -> dict[int, Path]:
    out = {}
    for p in folder.iterdir() if folder.is_dir() else []:
        if p.suffix.lower() in (".png", ".jpg", ".jpeg") and p.stem.isdigit():
            out[int(p.stem)] = p
    return out


def _easymocap_labels(path: Path, size: tuple[int, int], fmt: str, garment_labels: Sequence[int]) -> np.ndarray:
    if not path.is_file():
        raise ValueError(f"{path}: missing: the mask of this image frame")
    m = files.read_mask(path)
    if m.shape != size:
        raise ValueError(f"{path}: mask is {m.shape[1]}x{m.shape[0]} (WxH), the images are {size[1]}x{size[0]}")
    if fmt == "labels":
        if m.max() > 2:
            raise ValueError(f"{path}: labels must be 0 background, 1 body, 2 garment; found {int(m.max())}")
        return np.where(m == 2, 2 if garment_labels else 1, m).astype(np.uint8)
    try:
        return zju_mask_labels(m if fmt == "person" else None, m if fmt == "cihp" else None, garment_labels)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e


def run_import_easymocap(src: str | os.PathLike, dst: str | os.PathLike, sequence: str | None = None,
                         frames: str | Sequence[int] | None = None, smpl: str | os.PathLike | None = None,
                         person_id: int | None = None, max_gap: int = 0, cameras: str | Sequence[str] | None = None,
                         masks: str | os.PathLike | None = None, mask_format: str = "person",
                         garment: str | os.PathLike | None = None, garment_kind: str | None = None,
                         garment_texture: str | os.PathLike | None = None,
                         garment_labels: Sequence[int] = CIHP_GARMENT_LABELS,
                         body_model: str | os.PathLike | None = None, train: str | Sequence[str] | None = None,
                         test: str | Sequence[str] | None = None, role: str = "train", fps: float = EASYMOCAP_FPS,
                         link: str = "symlink", height: float = 1.7, threads: int = 2) -> dict:
    """Convert the EasyMocap capture ``src`` into (or add a sequence to) the scene ``dst``.

    ``src`` as EasyMocap lays out a capture: ``intri.yml``, ``extri.yml`` (any of the
    layouts :mod:`anidress_core.io.easymocap` reads: no H_/W_, ``D_`` for ``dist_``, unquoted
    names), ``images/<cam>/<frame:06d>.jpg`` and the body files in one of :data:`SMPL_DIRS`
    (or ``smpl``: a folder) of any layout :mod:`anidress_core.io.motion` reads (poses 72 / 69
    / 63, ``{"annots": [...]}``, several people: ``person_id``; short gaps: ``max_gap``).
    cameras: a subset of intri.yml's (names or 0-based indices; default all); masks: a folder
    (relative to ``src`` or absolute) of ``<cam>/<frame:06d>.png`` in ``mask_format``
    (:data:`MASK_FORMATS`). The other arguments and the written scene are those of
    :func:`run_import_zju`. Image frames are matched to body files by number; frames (an
    index range over the image frames, :func:`parse_frames`) are renumbered from 0.
    Returns the import record (also ``dst/<seq>/import.json``).
    """
    t0 = time.perf_counter()
    src, dst = Path(src), Path(dst)
    if link not in LINK_MODES:
        raise ValueError(f"link must be one of {list(LINK_MODES)}, got {link!r}")
    if mask_format not in MASK_FORMATS:
        raise ValueError(f"mask_format must be one of {list(MASK_FORMATS)}, got {mask_format!r}")
    if not (isinstance(fps, (int, float)) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    seq = sequence or safe_camera_names([src.resolve().name])[0]
    # 1. cameras
    all_names = easymocap.read_names(src / "intri.yml")
    posed = easymocap.extrinsic_names(src / "extri.yml", all_names)  # intri.yml may list more (trackmesh_gui)
    if cameras is not None:
        sources = _pick_cameras(cameras, all_names, all_names, "cameras")
        unposed = [c for c in sources if c not in posed]
        if unposed:
            raise ValueError(f"{src / 'extri.yml'}: cameras {unposed} (asked for by cameras) have intrinsics in "
                             f"intri.yml but no pose here (Rot_<cam> or R_<cam>, and T_<cam>); cameras with both: "
                             f"{posed}")
    else:
        sources = posed
        skipped = [c for c in all_names if c not in posed]
        if not sources:
            raise ValueError(f"{src / 'extri.yml'}: none of the cameras of {src / 'intri.yml'} ({all_names}) has a "
                             f"pose here (Rot_<cam> or R_<cam>, and T_<cam>)")
        if skipped:
            log.warning("%s: %d of %d cameras have intrinsics but no pose in extri.yml, skipped: %s",
                        src / "intri.yml", len(skipped), len(all_names), ", ".join(skipped))
    raw = easymocap.read_camera(src / "intri.yml", src / "extri.yml", sources)
    names = safe_camera_names(sources)
    # 2. image frames: the same numbers in every camera folder
    per = {}
    for cam in sources:
        d = src / "images" / cam
        if not d.is_dir():
            raise ValueError(f"{d}: image folder of camera '{cam}' (listed in {src / 'intri.yml'}) not found")
        per[cam] = _frame_files(d)
        if not per[cam]:
            raise ValueError(f"{d}: no <frame:06d>.jpg / .png images")
    ref = sources[0]
    for cam in sources[1:]:
        if set(per[cam]) != set(per[ref]):
            diff = sorted(set(per[cam]) ^ set(per[ref]))
            raise ValueError(f"{src / 'images' / cam}: camera '{cam}' has {len(per[cam])} frames, camera '{ref}' "
                             f"{len(per[ref])} (frames {diff[:5]} are in only one of them)")
    numbers = sorted(per[ref])
    picked = [numbers[i] for i in parse_frames(frames, len(numbers))]
    size = image_size_from_header(per[ref][picked[0]])
    for f in picked:
        for cam in sources:
            hw = image_size_from_header(per[cam][f])
            if hw != size:
                raise ValueError(f"{per[cam][f]}: image is {hw[1]}x{hw[0]} (WxH), {per[ref][picked[0]]} is "
                                 f"{size[1]}x{size[0]}")
    for cam in sources:
        for k, v in (("H", size[0]), ("W", size[1])):
            if k in raw[cam] and raw[cam][k] != v:
                raise ValueError(f"{src / 'intri.yml'}: camera '{cam}': '{k}_{cam}' is {raw[cam][k]} but the "
                                 f"images are {size[1]}x{size[0]} (WxH)")
    # 3. body parameters of the picked frames
    if smpl is not None:
        sdir = Path(smpl) if Path(smpl).is_absolute() or Path(smpl).is_dir() else src / smpl
        if not sdir.is_dir():
            raise FileNotFoundError(f"{sdir}: body parameter folder not found (--smpl)")
    else:
        sdir = next((src / d for d in SMPL_DIRS if (src / d).is_dir()), None)
        if sdir is None:
            raise FileNotFoundError(f"{src}: no body parameter folder ({', '.join(d + '/' for d in SMPL_DIRS)})")
    params = read_easymocap_smpl_dir(sdir, person_id=person_id, max_gap=max_gap)
    index = {f: i for i, f in enumerate(params["frames"])}
    missing = [f for f in picked if f not in index]
    if missing:
        raise ValueError(f"{sdir / f'{missing[0]:06d}.json'}: missing: no body parameters for image frame "
                         f"{missing[0]}" + (f" ({len(missing)} frames lack them)" if len(missing) > 1 else ""))
    sel = [index[f] for f in picked]
    body = {k: params[k][sel] for k in ("poses", "Rh", "Th", "shapes")}
    # 4. masks
    mdir = None
    if masks is not None:
        mdir = Path(masks) if Path(masks).is_absolute() or Path(masks).is_dir() else src / masks
        if not mdir.is_dir():
            raise FileNotFoundError(f"{mdir}: mask folder not found (--masks)")
    existing = _existing_scene(dst)
    _check_addition(dst, existing, names, size, garment, body_model)
    has_garment = (existing or {}).get("garment_template") or garment is not None
    labels_garment = tuple(garment_labels) if has_garment else ()
    cam_dict = {n: {"K": raw[s]["K"], "dist": raw[s]["dist"], "R": raw[s]["R"], "T": raw[s]["T"], "H": size[0],
                    "W": size[1]} for n, s in zip(names, sources)}
    record = {
        "format": "easymocap", "source": str(src.resolve()), "smpl": str(sdir.resolve()),
        "person_id": person_id, "interpolated": [f for f in params["interpolated"] if f in set(picked)],
        "masks": str(mdir.resolve()) if mdir else None, "mask_format": mask_format if mdir else None,
        "garment_labels": list(labels_garment), "link": link, "cameras": dict(zip(names, sources)),
        "frames": [{"frame": k, "source_frame": f} for k, f in enumerate(picked)], "code_version": __version__,
    }
    images = [[per[cam][f] for cam in sources] for f in picked]
    labels = None
    if mdir is not None and mask_format == "schp":
        def labels(k: int, c: int) -> np.ndarray:
            idx, path = cue_files.read_schp_indices(mdir, sources[c], picked[k])
            if idx.shape != size:
                raise ValueError(f"{path}: mask is {idx.shape[1]}x{idx.shape[0]} (WxH), the images are "
                                 f"{size[1]}x{size[0]}")
            try:
                return zju_mask_labels(None, idx, labels_garment)
            except ValueError as e:
                raise ValueError(f"{path}: {e}") from e
    elif mdir is not None:
        def labels(k: int, c: int) -> np.ndarray:
            return _easymocap_labels(mdir / sources[c] / f"{picked[k]:06d}.png", size, mask_format, labels_garment)
    n_masks = _write_sequence(dst, seq, role, existing, cam_dict, images, labels, body, record, link, dict(
        fps=fps, size=size, split=split_cameras(names, sources, train, test), garment=garment,
        garment_kind=garment_kind, garment_texture=garment_texture, body_model=body_model, height=height,
        source={"format": "easymocap", "path": str(src.resolve())}), threads)
    record.update(scene_dir=str(dst), sequence=seq, wall_s=round(time.perf_counter() - t0, 3), masks_written=n_masks,
                  config_entry=scene_config_entry(yaml.safe_load((dst / "scene.yaml").read_text())))
    log.info("import-easymocap %s -> %s/%s: %d cameras x %d frames (%s images), body parameters from %s, masks %s "
             "(%.1f s)", src, dst, seq, len(names), len(picked), link, sdir, mdir or "none", record["wall_s"])
    return record
