"""Stage `validate_scene`: check a scene folder cheaply, before any long computation.

A malformed scene (DESIGN.md §3 layout) stops here with ONE :class:`SceneError`
(a ValueError) whose message names the file and the problem, e.g.::

    data/x/walk/extri.yml: camera '03' listed in intri.yml has no extrinsics (no T_03 / R_03 / Rot_03)

instead of minutes into a simulation or a training run. Nothing is written unless the
whole scene passes; then the summary goes to ``results/<scene>/scene_check.json``.

What is checked (in this order; the first problem found is the error):

1. ``scene.yaml``: readable; ``fps`` > 0; ``units`` metres (if given); ``sequences``
   (unique names); ``cameras/train`` (and ``test``) lists of camera-name strings;
   ``body_model`` (type, file); ``garment_template`` / ``garment_kind``.
2. Body model (:func:`anidress_core.io.scene.load_body`): readable, finite, and in
   metres: the rest vertices and the rest joints must span a person (0.3-3 m and
   0.2-3 m); a 1000x error (1.7 m read as 1700 m or 1.7 mm) says "looks like
   millimetres" / "kilometres".
3. Garment template (when scene.yaml names one): readable
   (:func:`anidress_core.io.mesh.read_mesh`), units and placement against the body
   (:func:`anidress_core.garment.check_placement`), then
   :func:`anidress_core.garment_mesh.mesh_defects`:
   degenerate or duplicate faces are repairable by the template stage's cleaning
   unless they are more than 10% of the faces (then the file is not the mesh it
   claims to be: a broken export, wrong index base); any edge shared by more than
   two faces is an error (the cleaning would delete the faces around it: the
   garment would silently lose pieces); self-intersecting faces are an error above
   :data:`SELF_INTERSECTION_TOLERANCE` (see there why a pair is tolerated).
4. Per sequence: ``intri.yml`` / ``extri.yml`` exist and list the same cameras, and
   every camera of scene.yaml's train/test lists is in them; intrinsics positive and
   rotations proper; ``images/<cam>/`` for every listed camera with the same frames
   (a camera whose count differs is named with both counts); every image has a
   valid PNG/JPEG header and end marker and the image size (header only); the first
   and last frame of each camera are decoded fully (``images="all"``: every frame);
   ``smpl/`` has one ``<frame>.json`` per image frame, all finite (the file and key
   are named); the body root lies in front of and inside the view of at least half
   the cameras at the first, middle and last frame and 0.2-200 m from them (a
   camera or body file in millimetres, or inverted extrinsics, fail here);
   optional ``masks/`` and ``normals/`` folders cover the same frames (every training
   camera, and every camera that has a folder), headers checked, ends decoded.

Cost: header reads for every image, a few decodes per camera, one self-intersection
query on the garment (pymeshlab): about a second on the demo scene.
"""
from __future__ import annotations

import logging
import math
import os
import re
import time
from collections import Counter
from pathlib import Path
from typing import NoReturn

import cv2
import numpy as np

from .. import __version__, garment
from ..garment import KINDS
from ..garment_mesh import mesh_defects
from ..io import cue_files, files, shipped_cues
from ..io.easymocap import read_extri, read_intri, read_names
from ..io.files import SceneError
from ..io.images import check_exr_magic, image_size_from_header
from ..io.mesh import read_mesh
from ..io.motion import read_easymocap_smpl_dir, smpl_selection
from ..camera import scale_calibration
from ..io.scene_info import cue_formats
from ..io.scene import DIST_EPS, IMAGE_EXTS, camera_scale, garment_texture_path, load_body, read_scene

__all__ = [
    "SceneError",
    "unit_guess",
    "validate_scene",
    "run_validate",
    "format_summary",
]

log = logging.getLogger("anidress.validate")

PERSON_EXTENT_M = (0.3, 3.0)
"""Largest bounding-box side of the body's rest vertices: a person from a small child to a tall adult in T-pose."""
JOINT_EXTENT_M = (0.2, 3.0)
"""Largest bounding-box side of the rest joints (1.7 m mannequin: 1.54 m wrist to wrist)."""
CAMERA_DISTANCE_M = (0.2, 200.0)
"""Median distance between the body root and the camera centres of a capture."""
MAX_REPAIRABLE_FRACTION = 0.10
"""Degenerate + duplicate faces above this fraction of the faces: not a repairable template."""
SELF_INTERSECTION_TOLERANCE = 2
"""Self-intersecting faces tolerated in a garment template: one pair. A single pair of
faces touching through round-off (at a seam or where a strap crosses) is what an
export from cloth CAD occasionally has, and it is harmless here: the cloth solver has
no self-collision to lock on it and the renderers do not care. A surface cutting
through the garment shows up as a chain of crossing faces along the cut (3 or more),
and the remesher (which reprojects onto the input surface) would carry it into the
rig, the fitting and the radiance field's garment prior. Procedural and simulated
templates have none."""
_TYPICAL_BODY_M = 1.7
_TYPICAL_JOINTS_M = 1.5
_UNITS = {1000.0: "millimetres", 100.0: "centimetres", 10.0: "decimetres", 1e-3: "kilometres"}
_NAME_RE = re.compile(r"^[A-Za-z0-9_-]+$")


def _fail(path: str | os.PathLike, problem: str) -> NoReturn:
    raise SceneError(f"{path}: {problem}")


def _wrap(fn, *args, **kwargs):
    """Call a reader; its errors (which name the file) become SceneError."""
    try:
        return fn(*args, **kwargs)
    except SceneError:
        raise
    except (ValueError, OSError) as e:  # ArtifactError is a ValueError, FileNotFoundError an OSError
        raise SceneError(str(e)) from e


def unit_guess(ratio: float) -> str:
    """The unit a length in metres was probably written in, from ``ratio`` = value / expected value.

    >>> unit_guess(1000.0), unit_guess(0.001), unit_guess(98.0)
    ('millimetres', 'kilometres', 'centimetres')
    """
    k = min(_UNITS, key=lambda f: abs(math.log10(max(ratio, 1e-30)) - math.log10(f)))
    return _UNITS[k]


def _units_problem(what: str, extent: float, bounds: tuple[float, float], typical: float) -> str | None:
    """None when ``extent`` (metres) lies within ``bounds``, else the sentence saying what it looks like."""
    lo, hi = bounds
    if np.isfinite(extent) and lo <= extent <= hi:
        return None
    ratio = extent / typical
    scale = "too large" if ratio > 1 else "too small"
    return (f"{what} spans {extent:.4g} m (largest bounding-box side; a person is {lo:g}-{hi:g} m): "
            f"it looks like {unit_guess(ratio)} ({ratio:.4g}x {scale}); the pipeline works in metres")


# =========================================================================== scene.yaml
def _check_scene_yaml(scene_dir: Path, checks: list[str]) -> dict:
    if not scene_dir.is_dir():
        _fail(scene_dir, "scene folder not found")
    path = scene_dir / "scene.yaml"
    info = _wrap(read_scene, scene_dir)
    if not isinstance(info, dict):
        _fail(path, f"expected a mapping of keys, got {type(info).__name__}")
    fps = info["fps"]
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not np.isfinite(fps) or fps <= 0:
        _fail(path, f"'fps' must be a positive number, got {fps!r}")
    units = info.get("units")
    if units is not None and str(units).lower() not in ("metres", "meters", "metre", "meter", "m"):
        _fail(path, f"'units' is {units!r}: the pipeline works in metres (convert the cameras, body and garment)")
    seqs = info["sequences"]
    if not isinstance(seqs, list) or not seqs:
        _fail(path, "'sequences' must be a non-empty list of {name: ...} entries")
    names = []
    for i, s in enumerate(seqs):
        name = s.get("name") if isinstance(s, dict) else None
        if not isinstance(name, str) or not _NAME_RE.match(name):
            _fail(path, f"sequences item {i} needs a 'name' (letters, digits, _ or -), got {s!r}")
        if "frames" in s and (isinstance(s["frames"], bool) or not isinstance(s["frames"], int) or s["frames"] < 1):
            _fail(path, f"sequence '{name}': 'frames' must be a positive integer, got {s['frames']!r}")
        names.append(name)
    dup = sorted(n for n, c in Counter(names).items() if c > 1)
    if dup:
        _fail(path, f"sequence names repeat: {dup}")
    cams = info.get("cameras")
    if not isinstance(cams, dict) or not cams.get("train"):
        _fail(path, "missing key 'cameras/train' (the training camera names; 'cameras/test' the held-out ones)")
    for role in ("train", "test"):
        lst = cams.get(role) or []
        if not isinstance(lst, list):
            _fail(path, f"'cameras/{role}' must be a list of camera names, got {lst!r}")
        for c in lst:
            if not isinstance(c, str):
                _fail(path, f"'cameras/{role}' item {c!r} is not a string: quote camera names ('01'); "
                            "YAML reads an unquoted 01 as the number 1")
    both = sorted(set(cams.get("train") or []) & set(cams.get("test") or []))
    if both:
        _fail(path, f"cameras {both} are listed in both cameras/train and cameras/test")
    bm = info["body_model"]
    if not isinstance(bm, dict) or bm.get("type") not in ("mannequin", "smpl") or not isinstance(bm.get("file"), str):
        _fail(path, f"'body_model' needs type (mannequin | smpl) and file, got {bm!r}")
    size = info.get("image_size")
    if size is not None and (not isinstance(size, list) or len(size) != 2
                             or not all(isinstance(x, int) and x > 0 for x in size)):
        _fail(path, f"'image_size' must be [H, W] positive integers, got {size!r}")
    if info.get("garment_template"):
        if not isinstance(info["garment_template"], str):
            _fail(path, f"'garment_template' must be a path relative to the scene, got {info['garment_template']!r}")
        if info.get("garment_kind") not in KINDS:
            _fail(path, f"'garment_kind' must be one of {list(KINDS)} when a garment_template is given, "
                        f"got {info.get('garment_kind')!r}")
    checks.append("scene.yaml keys")
    return info


# =========================================================================== body model
def _check_body(scene_dir: Path, info: dict, checks: list[str]):
    spec = info["body_model"]
    path = scene_dir / spec["file"]
    if not path.is_file():
        _fail(path, "body model file not found (scene.yaml body_model/file)")
    body = _wrap(load_body, scene_dir, info)
    v = body.v_template.detach().double().numpy()
    J = body.joints_rest.detach().double().numpy()
    jkey = "joints_rest" if spec["type"] == "mannequin" else "joints (J_regressor @ v_template)"
    for key, a in (("v_template", v), (jkey, J), ("weights", body.weights.detach().double().numpy())):
        if not np.isfinite(a).all():
            _fail(path, f"'{key}' has NaN or inf values")
    for key, a, bounds, typical in (("v_template", v, PERSON_EXTENT_M, _TYPICAL_BODY_M),
                                    (jkey, J, JOINT_EXTENT_M, _TYPICAL_JOINTS_M)):
        problem = _units_problem(f"body model '{key}'", float((a.max(0) - a.min(0)).max()), bounds, typical)
        if problem:
            _fail(path, problem)
    checks.append("body model: readable, finite, in metres")
    ext = v.max(0) - v.min(0)
    return body, {"type": spec["type"], "file": str(path), "vertices": int(v.shape[0]),
                  "extent_m": [round(float(x), 4) for x in ext]}


# =========================================================================== garment
def _check_fit_texture(scene_dir: Path, info: dict, fit_texture: dict, checks: list[str]) -> None:
    """The garment texture a fit's L_anchor samples at the template's UVs (fit/anchor_reference: texture)."""
    tex = garment_texture_path(scene_dir, info)
    setting = fit_texture.get("setting", "fit/anchor_reference")
    if not tex.is_file():
        _fail(tex, f"{setting} is 'texture' (the garment texture at the template's UVs is L_anchor's reference "
                   f"in the fit's loss {', '.join(fit_texture.get('losses') or ['pipeline'])}) but the garment has no "
                   f"texture: add one (scene.yaml garment_texture, or texture.png beside the template) or set "
                   f"{setting}: images")
    checks.append("garment texture for the fit's L_anchor (anchor_reference texture)")


def _check_mask_plates(scene_dir: Path, mask_plates: dict, checks: list[str]) -> None:
    """The background plates rule masks reads (cues/masks/background: plate) for sequences without masks."""
    setting = mask_plates.get("setting", "cues/masks/background")
    for seq in mask_plates.get("sequences") or []:
        plates = scene_dir / seq / "backgrounds"
        if not plates.is_dir():
            _fail(plates, f"{setting} is 'plate' (masks are estimated against a background plate per camera, "
                          f"backgrounds/<cam>.png) but sequence '{seq}' ships neither masks nor background plates: "
                          f"add them, or set {setting}: temporal_median (a median of the frames as the plate)")
    checks.append("background plates for the estimated masks (cues/masks/background plate)")


def _check_garment(scene_dir: Path, info: dict, body, checks: list[str], warnings: list[str]) -> dict | None:
    rel = info.get("garment_template")
    if not rel:
        return None
    path = scene_dir / rel
    if not path.is_file():
        _fail(path, "garment template not found (scene.yaml garment_template)")
    v, f, face_uv = _wrap(read_mesh, path)
    checks.append("garment template readable")
    tex = garment_texture_path(scene_dir, info)
    texture = None
    if info.get("garment_texture") and not tex.is_file():
        _fail(tex, "garment texture not found (scene.yaml garment_texture)")
    if tex.is_file():  # optional; fit/anchor_reference: texture samples it at the template's UVs
        th, tw = _wrap(image_size_from_header, tex)
        texture = {"file": str(tex), "size": [th, tw]}
        if face_uv is None:
            warnings.append(f"{tex}: the garment has a texture but {path} has no UVs (vt) on every face; "
                            "fit/anchor_reference: texture cannot use it")
        checks.append("garment texture readable")
    try:
        garment.check_placement(v, body)
    except ValueError as e:
        _fail(path, str(e))
    checks.append("garment units and placement against the body")
    d = mesh_defects(v, f)
    F = len(f)
    if d.repairable_faces > MAX_REPAIRABLE_FRACTION * F:
        _fail(path, f"{len(d.degenerate_faces)} degenerate and {len(d.duplicate_faces)} duplicate faces out of {F} "
                    f"(more than {MAX_REPAIRABLE_FRACTION:.0%}): not a usable garment surface (a broken export? "
                    "wrong face index base?)")
    if d.repairable_faces:
        warnings.append(f"{path}: {len(d.degenerate_faces)} degenerate and {len(d.duplicate_faces)} duplicate faces; "
                        "the template stage's cleaning removes them")
    checks.append("garment degenerate/duplicate faces")
    if len(d.non_manifold_edges):
        a, b = (int(x) + 1 for x in d.non_manifold_edges[0])
        _fail(path, f"non-manifold: {len(d.non_manifold_edges)} edge(s) shared by more than two faces "
                    f"(e.g. the edge between vertices {a} and {b}, 1-based as in OBJ, has "
                    f"{int(d.non_manifold_counts[0])} faces); a garment must be a manifold surface "
                    "(cleaning would delete the faces around such edges)")
    checks.append("garment manifold edges")
    n_int = len(d.self_intersecting_faces)
    if n_int > SELF_INTERSECTION_TOLERANCE:
        eg = ", ".join(str(int(i) + 1) for i in d.self_intersecting_faces[:5])
        _fail(path, f"self-intersecting: {n_int} of {F} triangles cross other triangles of the garment (e.g. triangles {eg}, "
                    f"1-based in file order; at most {SELF_INTERSECTION_TOLERANCE} are tolerated): the surface passes "
                    "through itself")
    if n_int:
        warnings.append(f"{path}: {n_int} self-intersecting faces (tolerated: at most {SELF_INTERSECTION_TOLERANCE})")
    checks.append("garment self-intersections")
    return {"file": str(path), "kind": info["garment_kind"], "vertices": int(len(v)), "faces": int(F),
            "merged_vertices": d.merged_vertices, "degenerate_faces": int(len(d.degenerate_faces)),
            "duplicate_faces": int(len(d.duplicate_faces)), "non_manifold_edges": 0,
            "self_intersecting_faces": int(n_int), "texture": texture,
            "extent_m": [round(float(x), 4) for x in (v.max(0) - v.min(0))]}


# =========================================================================== cameras
def _check_cameras(sdir: Path, info: dict, checks: list[str]) -> tuple[list[str], dict, tuple | None]:
    """-> (cameras used, {cam: K, dist, R, T}, expected (H, W) or None)."""
    intri_p, extri_p = sdir / "intri.yml", sdir / "extri.yml"
    for p, what in ((intri_p, "intrinsics"), (extri_p, "extrinsics")):
        if not p.is_file():
            _fail(p, f"camera file missing (EasyMocap {what}; every sequence needs intri.yml and extri.yml)")
    intri = _wrap(read_intri, intri_p)
    if not intri:
        _fail(intri_p, "lists no cameras")
    scale = _wrap(camera_scale, info, sdir.parent)
    if scale is not None:  # the images are `scale` times the calibration's size (scene.yaml cameras/scale)
        _wrap(scale_calibration, intri, scale, intri_p)
    # 1. the same cameras in both files: presence of keys, by OpenCV's own parser
    try:
        fs = cv2.FileStorage(str(extri_p), cv2.FILE_STORAGE_READ)
        ok = fs.isOpened()
    except Exception:  # noqa: BLE001 - cv2.error / SystemError on parse errors
        ok = False
    if not ok:
        _fail(extri_p, "not a readable OpenCV YAML file")
    try:
        def has(k: str) -> bool:
            n = fs.getNode(k)
            return not (n.empty() or n.isNone())

        yaml_cams = info["cameras"]  # extrinsics are needed only for the cameras scene.yaml uses
        used_set = set(yaml_cams.get("train") or []) | set(yaml_cams.get("test") or [])
        for cam in (c for c in intri if c in used_set):
            if not has(f"T_{cam}") and not has(f"R_{cam}") and not has(f"Rot_{cam}"):
                _fail(extri_p, f"camera '{cam}' listed in intri.yml has no extrinsics (no T_{cam} / R_{cam} / Rot_{cam})")
        # the names as the readers spell them (an unquoted 01 takes the keys' spelling "01")
        extra = [n for n in _wrap(read_names, extri_p) if n not in intri] if fs.getNode("names").isSeq() else []
        if extra:
            _fail(intri_p, f"camera(s) {extra} listed in extri.yml have no intrinsics")
    finally:
        fs.release()
    extri = _wrap(read_extri, extri_p, [c for c in intri if c in used_set])
    checks.append("camera files list the same cameras")
    cams = info["cameras"]
    used = list(dict.fromkeys(list(cams.get("train") or []) + list(cams.get("test") or [])))
    for role in ("train", "test"):
        for c in cams.get(role) or []:
            if c not in intri:
                _fail(intri_p, f"camera '{c}' of scene.yaml cameras/{role} is not listed (cameras: {list(intri)})")
    # 2. intrinsics and rotations
    raw = {}
    for c in used:
        K, R = intri[c]["K"], extri[c]["R"]
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            _fail(intri_p, f"camera '{c}': focal lengths must be positive, got fx={K[0, 0]:g} fy={K[1, 1]:g}")
        err = float(np.abs(R @ R.T - np.eye(3)).max())
        det = float(np.linalg.det(R))
        if err > 1e-3 or det < 0:
            _fail(extri_p, f"camera '{c}': not a rotation matrix (det {det:.4g}, max |R R^T - I| {err:.2g})")
        raw[c] = {**intri[c], **extri[c]}
    checks.append("camera intrinsics and rotations")
    # 3. image size: files' H_/W_ and scene.yaml's image_size agree
    sizes = {(raw[c]["H"], raw[c]["W"]) for c in used if "H" in raw[c] and "W" in raw[c]}
    if len(sizes) > 1:
        _fail(intri_p, f"cameras have different image sizes H_/W_ {sorted(sizes)}")
    size = tuple(info["image_size"]) if info.get("image_size") else None
    if sizes:
        (hw,) = sizes
        if size is not None and hw != size:
            _fail(intri_p, f"image size H_/W_ is {hw[0]}x{hw[1]} but scene.yaml image_size is {size[0]}x{size[1]}"
                  + _size_factor_hint(size, hw))
        size = hw
    return used, raw, size


def _size_factor_hint(images: tuple, calib: tuple) -> str:
    """': the images are f times ... set cameras/scale: f' when both sides differ by one factor f, else ''."""
    fy, fx = images[0] / calib[0], images[1] / calib[1]
    if abs(fy - fx) > 1e-9 * max(fx, fy):
        return ""
    return (f"; the images are {fx:.6g}x the calibration's size: if the calibration is right for the images at "
            f"full size, set scene.yaml cameras/scale: {fx:.6g}")


#: the principal point must lie within this fraction of the image size from its centre, on both axes
CENTRE_BAND = 0.15
#: image-size factors a calibration is commonly off by (resized images), tried when the principal point is not
#: near the centre
SIZE_FACTORS = (1 / 4, 1 / 3, 1 / 2, 2 / 3, 3 / 4, 4 / 3, 3 / 2, 2, 3, 4)


def _check_principal_points(intri_p: Path, info: dict, raw: dict, used: list[str], size: tuple,
                            checks: list[str]) -> None:
    """Each camera's principal point near the centre of the images (|c / size - 0.5| <= CENTRE_BAND): a
    calibration made for another image size puts it elsewhere. The error names the factor that would fit
    (scene.yaml cameras/scale); ``cameras/off_centre: true`` skips the check (a lens whose axis is off-centre)."""
    if (info.get("cameras") or {}).get("off_centre") is True:
        checks.append("principal points not checked (scene.yaml cameras/off_centre: true)")
        return
    H, W = size
    for c in used:
        cx, cy = float(raw[c]["K"][0, 2]), float(raw[c]["K"][1, 2])
        rx, ry = (cx + 0.5) / W, (cy + 0.5) / H
        if abs(rx - 0.5) <= CENTRE_BAND and abs(ry - 0.5) <= CENTRE_BAND:
            continue
        fits = sorted((max(abs((f * (cx + 0.5)) / W - 0.5), abs((f * (cy + 0.5)) / H - 0.5)), f)
                      for f in SIZE_FACTORS)
        dev, f = fits[0]
        scale = camera_scale(info) or 1.0
        hint = (f"the calibration looks made for images {1 / f:.3g}x this size: set scene.yaml cameras/scale: "
                f"{scale * f:.6g} (K scaled about the pixel centres), " if dev <= CENTRE_BAND else "")
        _fail(intri_p, f"camera '{c}': principal point ({cx:.1f}, {cy:.1f}) lies at ({rx:.2f}, {ry:.2f}) of the "
                       f"{W}x{H} images, not within {CENTRE_BAND} of their centre: {hint}or, for a lens whose axis "
                       f"is off-centre, scene.yaml cameras/off_centre: true")
    checks.append(f"principal points within {CENTRE_BAND} of the image centre")


# =========================================================================== frames and images
def _frames_of(d: Path, exts: tuple[str, ...]) -> dict[int, Path]:
    """{frame: path} of ``<frame digits>.<ext>`` files in a folder (other files ignored)."""
    out: dict[int, Path] = {}
    for p in d.iterdir():
        if p.suffix.lower() in exts and p.stem.isdigit():
            fr = int(p.stem)
            if fr in out:
                _fail(d, f"frame {p.stem} is there twice ({out[fr].name} and {p.name})")
            out[fr] = p
    return out


def _fmt_frames(frames, ext: str, n: int = 3) -> str:
    fr = sorted(frames)
    s = ", ".join(f"{f:06d}{ext}" for f in fr[:n])
    return s + (f" and {len(fr) - n} more" if len(fr) > n else "")


def _same_frames(folders: dict[str, Path], ext_name: str, exts: tuple[str, ...], what: str) -> tuple[list[int], dict]:
    """Frames common to all camera folders; the camera whose count differs is the error."""
    per = {}
    for cam, d in folders.items():
        if not d.is_dir():
            _fail(d, f"{what} folder of camera '{cam}' not found")
        per[cam] = _frames_of(d, exts)
        if not per[cam]:
            _fail(d, f"no <frame>{ext_name} files")
    counts = Counter(len(v) for v in per.values())
    majority = max(counts, key=lambda n: (counts[n], n))
    ref = next(c for c in per if len(per[c]) == majority)
    ref_set = set(per[ref])
    for cam, fr in per.items():
        if len(fr) != majority:
            missing, extra = ref_set - set(fr), set(fr) - ref_set
            detail = (f"missing {_fmt_frames(missing, ext_name)}" if missing else "") + \
                     ("; " if missing and extra else "") + (f"extra {_fmt_frames(extra, ext_name)}" if extra else "")
            _fail(folders[cam], f"camera '{cam}' has {len(fr)} frames but camera '{ref}' has {majority} ({detail})")
        if set(fr) != ref_set:
            _fail(folders[cam], f"camera '{cam}' has other frame numbers than camera '{ref}' "
                                f"(e.g. {_fmt_frames(set(fr) ^ ref_set, ext_name)})")
    return sorted(ref_set), per


def _check_images(sdir: Path, used: list[str], size: tuple | None, images: str, checks: list[str]):
    folders = {c: sdir / "images" / c for c in used}
    frames, per = _same_frames(folders, ".png", IMAGE_EXTS, "image")
    # headers of every image: valid PNG/JPEG, the same size everywhere
    expect = size
    for cam in used:
        for fr in frames:
            p = per[cam][fr]
            hw = _wrap(image_size_from_header, p)
            if expect is None:
                expect = hw
            elif hw != tuple(expect):
                src = "camera files / scene.yaml image_size" if size is not None else f"as {per[used[0]][frames[0]]}"
                _fail(p, f"image is {hw[1]}x{hw[0]} (WxH), expected {expect[1]}x{expect[0]} ({src})"
                         + _size_factor_hint(hw, expect))
    checks.append("image headers and sizes (every frame)")
    # full decodes: the first and last frame of each camera, or all
    pick = frames if images == "all" else sorted({frames[0], frames[-1]})
    for cam in used:
        for fr in pick:
            img = _wrap(files.read_image, per[cam][fr])
            if img.shape[:2] != tuple(expect):
                _fail(per[cam][fr], f"decoded image is {img.shape[1]}x{img.shape[0]}, expected {expect[1]}x{expect[0]}")
    checks.append("image decode (" + ("every frame" if images == "all" else "first and last frame") + ")")
    return frames, tuple(int(x) for x in expect), len(pick) * len(used)


def _check_optional(sdir: Path, sub: str, used: list[str], train: list[str], frames: list[int], size: tuple,
                    checks: list[str], fmts: dict) -> bool:
    """Shipped ``masks/``, ``normals/`` or ``flows/`` in scene.yaml's ``cues`` format: same frames (flows: all but
    the first), PNG headers / EXR magic, the first and last files decoded."""
    root = sdir / sub
    if not root.is_dir():
        return False
    fmt = fmts[sub]["format"]
    cams = [c for c in used if c in train or (root / c).is_dir()]
    folders = {c: root / c for c in cams}
    for c, d in folders.items():
        if not d.is_dir():
            _fail(d, f"{sub} folder of training camera '{c}' not found (shipped {sub} must cover every training camera)")
    want = set(frames[1:] if sub == "flows" else frames)
    ext = shipped_cues.CUE_SUFFIX[(sub, fmt)]
    crops = None
    if sub == "normals" and fmt == "icon":
        crops = _wrap(cue_files.read_crops, root / shipped_cues.CROPS_FILE)
    for c, d in folders.items():
        have = shipped_cues.cue_frames(d, sub, fmt)
        if set(have) != want:
            missing, extra = want - set(have), set(have) - want
            _fail(d, f"{len(have)} {sub} ({fmt}) for {len(want)} " + ("image frames after the first" if sub == "flows"
                                                                      else "image frames") + f" of camera '{c}'"
                     + (f" (missing {_fmt_frames(missing, ext)})" if missing else "")
                     + (f" (extra {_fmt_frames(extra, ext)})" if extra else "")
                     + (f"; scene.yaml cues/{sub}/format is {fmt!r}" if not have else ""))
        for fr in sorted(want):
            suffix = have[fr].suffix.lower()
            if suffix == ".png" and fmt != "icon":
                hw = _wrap(image_size_from_header, have[fr])
                if hw != size:
                    _fail(have[fr], f"{sub[:-1]} is {hw[1]}x{hw[0]} (WxH), the images are {size[1]}x{size[0]}")
            elif suffix == ".exr":
                _wrap(check_exr_magic, have[fr])
        for fr in sorted({min(want), max(want)}):
            if sub == "masks":
                _wrap(shipped_cues.read_mask_labels, root, c, fr, fmts["masks"], size)
            elif sub == "normals":
                _wrap(shipped_cues.read_normals, root, c, fr, fmt, size, crops)
            else:
                _wrap(shipped_cues.read_flow, root, c, fr, fmt, size)
    checks.append(f"{sub} ({fmt}): same frames, headers, first/last decoded")
    return True


# =========================================================================== body parameters
def _check_smpl(sdir: Path, frames: list[int], checks: list[str]) -> dict:
    d = sdir / "smpl"
    if not d.is_dir():
        _fail(d, "body parameter folder not found (EasyMocap smpl/<frame>.json)")
    have = {int(p.stem) for p in d.iterdir() if p.suffix == ".json" and p.stem.isdigit()}
    want = set(frames)
    if have != want:
        missing, extra = want - have, have - want
        _fail(d, f"{len(have)} body parameter files for {len(want)} image frames per camera"
                 + (f" (missing {_fmt_frames(missing, '.json')})" if missing else "")
                 + (f" (extra {_fmt_frames(extra, '.json')})" if extra else ""))
    sel = _wrap(smpl_selection, read_scene(sdir.parent), sdir.name, sdir.parent / "scene.yaml")
    params = _wrap(read_easymocap_smpl_dir, d, **sel)  # scene.yaml person_id / max_missing_frames
    checks.append("body parameters: one per frame, finite")
    return params


def _check_body_in_view(sdir: Path, params: dict, body, raw: dict, used: list[str], size: tuple,
                        checks: list[str]) -> dict:
    """The body root (R(Rh) J_0 + Th, EasyMocap's world placement) seen by the cameras at 0.2-200 m."""
    H, W = size
    J0 = body.joints_rest[0].detach().double().numpy()
    T = len(params["frames"])
    K = np.stack([raw[c]["K"] for c in used])
    R = np.stack([raw[c]["R"] for c in used])
    Tc = np.stack([raw[c]["T"] for c in used])
    centres = -np.einsum("cji,cj->ci", R, Tc)  # C = -R^T T
    dists = []
    for t in sorted({0, T // 2, T - 1}):
        root = cv2.Rodrigues(params["Rh"][t].reshape(3, 1))[0] @ J0 + params["Th"][t]
        jpath = sdir / "smpl" / f"{params['frames'][t]:06d}.json"
        d = np.linalg.norm(centres - root, axis=1)
        med = float(np.median(d))
        dists.append(med)
        lo, hi = CAMERA_DISTANCE_M
        if not lo <= med <= hi:
            cam_far, body_far = float(np.median(np.linalg.norm(centres, axis=1))), float(np.linalg.norm(root))
            if cam_far > hi and body_far < hi:
                _fail(sdir / "extri.yml", f"the cameras are {cam_far:.4g} m from the world origin and {med:.4g} m from "
                                          f"the body: T looks like {unit_guess(med / 3.0)}; the pipeline works in metres")
            if body_far > hi and cam_far < hi:
                _fail(jpath, f"'Th' puts the body {body_far:.4g} m from the world origin and {med:.4g} m from the "
                             f"cameras: it looks like {unit_guess(body_far / 1.0)}; the pipeline works in metres")
            _fail(jpath, f"the body is {med:.4g} m from the cameras of {sdir / 'extri.yml'} (median; expected "
                         f"{lo:g}-{hi:g} m): the cameras and the body parameters are not in the same units")
        # X_cam = R X + T; in view: in front and within the image (+10% margin), pinhole
        xc = np.einsum("cij,j->ci", R, root) + Tc
        z = xc[:, 2]
        uv = np.einsum("cij,cj->ci", K, xc / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None])[:, :2]
        seen = (z > 0) & (uv[:, 0] > -0.1 * W) & (uv[:, 0] < 1.1 * W) & (uv[:, 1] > -0.1 * H) & (uv[:, 1] < 1.1 * H)
        if seen.sum() * 2 < len(used):
            blind = [c for c, s in zip(used, seen) if not s]
            _fail(jpath, f"the body (root at {np.round(root, 3).tolist()} m) is behind or outside the image of "
                         f"{len(blind)} of {len(used)} cameras ({blind[:6]}) of {sdir / 'extri.yml'}: cameras and "
                         "body parameters are not in the same world frame (extri.yml must map world to camera, "
                         "X_cam = R X_world + T, metres)")
    checks.append("cameras see the body (same world frame and units)")
    return {"camera_distance_m": round(min(dists), 3)}


# =========================================================================== the stage
def validate_scene(scene_dir: str | os.PathLike, images: str = "ends", fit_texture: dict | None = None,
                   mask_plates: dict | None = None) -> dict:
    """Check a scene folder (DESIGN.md §3) and return a summary; raise SceneError on the first problem.

    images: 'ends' (every image's header; first and last frame of each camera decoded)
    or 'all' (every image decoded; ~5 ms per 256x256 PNG).
    fit_texture: ``{"losses": [...], "setting": "fit/anchor_reference"}`` when a garment fit of the
    scene samples the garment texture (L_anchor with anchor_reference 'texture', for those loss
    variants; the workflow passes it when the scene has no texture): the texture must exist, else a
    SceneError naming it and the setting, before any long stage (rule fit would stop after template,
    simulate, rig and the cues ran). None: no fit needs it.
    mask_plates: ``{"sequences": [...], "setting": "cues/masks/background"}``, the sequences whose
    masks rule masks estimates against background plates (the workflow passes the captured scene's
    sequences without shipped masks when the setting is 'plate'): each must ship ``backgrounds/``,
    else a SceneError naming the folder and the setting (rule masks would stop on the first plate).
    Returns dict(scene, scene_dir, cameras {train, test}, image_size [H, W], sequences
    {name: {frames, first_frame, last_frame, cameras, images, images_decoded, masks,
    normals, camera_distance_m}}, garment (bool), garment_template (dict | None),
    body (dict), checks [str], warnings [str], notes [str] (what the pipeline will do about
    the scene, e.g. undistort its images), images, wall_s, code_version); per sequence also
    ``distorted_cameras`` (the cameras with lens distortion, undistorted by rule undistort).
    """
    if images not in ("ends", "all"):
        raise ValueError(f"validate_scene: images must be 'ends' or 'all', got {images!r}")
    t0 = time.perf_counter()
    scene_dir = Path(scene_dir)
    checks: list[str] = []
    warnings: list[str] = []
    notes: list[str] = []
    info = _check_scene_yaml(scene_dir, checks)
    fmts = _wrap(cue_formats, info, scene_dir)
    body, body_sum = _check_body(scene_dir, info, checks)
    g = _check_garment(scene_dir, info, body, checks, warnings)
    if fit_texture and g is not None:
        _check_fit_texture(scene_dir, info, fit_texture, checks)
    if mask_plates:
        _check_mask_plates(scene_dir, mask_plates, checks)
    seqs = {}
    size_all = None
    train = list(info["cameras"]["train"])
    for s in info["sequences"]:
        name = s["name"]
        sdir = scene_dir / name
        if not sdir.is_dir():
            _fail(sdir, f"sequence folder of '{name}' (scene.yaml sequences) not found")
        used, raw, size = _check_cameras(sdir, info, checks)
        distorted = [c for c in used if np.any(np.abs(np.asarray(raw[c]["dist"], np.float64)) > DIST_EPS)]
        if distorted:
            notes.append(f"{sdir / 'intri.yml'}: cameras {', '.join(distorted)} have lens distortion: images, masks "
                         "and normals will be undistorted to pinhole working cameras by rule undistort "
                         f"(results/<scene>/{name}/undistorted), which every later stage reads")
        frames, size, decoded = _check_images(sdir, used, size, images, checks)
        _check_principal_points(sdir / "intri.yml", info, raw, used, size, checks)
        if "frames" in s and s["frames"] != len(frames):
            _fail(scene_dir / "scene.yaml", f"sequence '{name}' has frames: {s['frames']} but {sdir / 'images'} "
                                            f"holds {len(frames)} per camera")
        params = _check_smpl(sdir, frames, checks)
        view = _check_body_in_view(sdir, params, body, raw, used, size, checks)
        masks = _check_optional(sdir, "masks", used, train, frames, size, checks, fmts)
        normals = _check_optional(sdir, "normals", used, train, frames, size, checks, fmts)
        flows = _check_optional(sdir, "flows", used, train, frames, size, checks, fmts)
        if size_all is not None and size != size_all:
            warnings.append(f"{sdir}: images are {size[1]}x{size[0]}, other sequences {size_all[1]}x{size_all[0]}")
        size_all = size_all or size
        seqs[name] = {"frames": len(frames), "first_frame": frames[0], "last_frame": frames[-1],
                      "cameras": len(used), "images": len(frames) * len(used), "images_decoded": decoded,
                      "masks": masks, "normals": normals, "flows": flows, "distorted_cameras": distorted, **view}
        log.info("validate %s/%s: %d cameras x %d frames, masks %s, normals %s", scene_dir.name, name, len(used),
                 len(frames), "yes" if masks else "no", "yes" if normals else "no")
    for w in warnings:
        log.warning("%s", w)
    for n in notes:
        log.info("%s", n)
    return {
        "scene": str(info.get("name") or scene_dir.name), "scene_dir": str(scene_dir),
        "cameras": {"train": train, "test": list(info["cameras"].get("test") or [])},
        "image_size": list(size_all), "sequences": seqs, "garment": g is not None, "garment_template": g,
        "body": body_sum, "checks": list(dict.fromkeys(checks)), "warnings": warnings, "notes": notes,
        "images": images,
        "wall_s": round(time.perf_counter() - t0, 3), "code_version": __version__,
    }


def run_validate(scene_dir: str | os.PathLike, out_json: str | os.PathLike | None = None,
                 images: str = "ends", fit_texture: dict | None = None, mask_plates: dict | None = None) -> dict:
    """:func:`validate_scene`, then (only when the scene passes) write the summary to ``out_json`` atomically."""
    summary = validate_scene(scene_dir, images=images, fit_texture=fit_texture, mask_plates=mask_plates)
    if out_json is not None:
        files.write_json(out_json, summary)
    log.info("validate %s: OK (%d checks, %.2f s)%s", scene_dir, len(summary["checks"]), summary["wall_s"],
             f" -> {out_json}" if out_json else "")
    return summary


def format_summary(s: dict) -> str:
    """A few human lines for the command line."""
    h, w = s["image_size"]
    lines = [f"{s['scene_dir']}: OK ({len(s['cameras']['train'])} train + {len(s['cameras']['test'])} test "
             f"cameras, {w}x{h} images; {s['wall_s']:.2f} s)"]
    for name, q in s["sequences"].items():
        lines.append(f"  {name}: {q['frames']} frames x {q['cameras']} cameras ({q['images_decoded']} images decoded), "
                     f"masks {'yes' if q['masks'] else 'no'}, normals {'yes' if q['normals'] else 'no'}, "
                     f"cameras {q['camera_distance_m']} m from the body")
    b = s["body"]
    lines.append(f"  body: {b['type']} {b['file']}, {b['vertices']} vertices, extent {b['extent_m']} m")
    g = s["garment_template"]
    if g:
        lines.append(f"  garment: {g['file']} ({g['kind']}), {g['vertices']} vertices, {g['faces']} faces, "
                     f"{g['self_intersecting_faces']} self-intersecting, {g['degenerate_faces']} degenerate, "
                     f"{g['duplicate_faces']} duplicate faces")
    else:
        lines.append("  garment: none (tight clothes: no simulate/rig/fit)")
    lines += [f"  warning: {w}" for w in s["warnings"]]
    lines += [f"  note: {n}" for n in s.get("notes", [])]
    return "\n".join(lines)
