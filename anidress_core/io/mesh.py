"""Triangle mesh files: OBJ (with per-face-corner UVs) and PLY (with vertex attributes).

Readers return ``(verts (V, 3) float64, faces (F, 3) int64, face_uv (F, 3, 2) | None)``
and raise errors that name the file (missing, unreadable, no faces, non-finite).
Writers are atomic (temporary file beside the target, then rename; see
:func:`anidress_core.io.files.atomic_path`).

UV convention: OBJ's, ``(u, v)`` with v pointing up in the texture image (row 0 of
an image array is v = 1). UVs are per face corner, so seams need no duplicated
vertices: an OBJ corner ``a/ta`` keeps its own ``vt`` while vertices stay shared.

OBJ is parsed here (the format is a few line types, Wavefront's spec: "v", "vt",
"f a/ta/na", polygons fanned into triangles, negative indices relative) because
trimesh's OBJ loader splits vertices along UV seams; other formats (PLY, STL, OFF,
GLB) go through ``trimesh.load``.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from .files import ArtifactError, atomic_path

__all__ = ["read_mesh", "write_obj", "write_ply"]


def _check_arrays(path, verts: np.ndarray, faces: np.ndarray, face_uv: np.ndarray | None) -> None:
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ArtifactError(f"{path}: mesh has no triangle faces")
    if verts.ndim != 2 or verts.shape[1] != 3 or verts.shape[0] == 0:
        raise ArtifactError(f"{path}: mesh has no vertices")
    if not np.isfinite(verts).all():
        raise ArtifactError(f"{path}: mesh has non-finite (NaN or inf) vertex coordinates")
    if faces.min() < 0 or faces.max() >= verts.shape[0]:
        raise ArtifactError(f"{path}: face indices out of range [0, {verts.shape[0]})")
    if face_uv is not None and not np.isfinite(face_uv).all():
        raise ArtifactError(f"{path}: mesh has non-finite texture coordinates")


def _parse_obj(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Minimal Wavefront OBJ reader: v, vt and f records (other records ignored)."""
    v: list[list[float]] = []
    vt: list[list[float]] = []
    fv: list[list[int]] = []  # triangles of vertex indices (already fanned)
    ft: list[list[int]] = []  # matching texture indices, -1 when a corner has none
    try:
        text = path.read_text(errors="strict")
    except (OSError, UnicodeDecodeError) as e:
        raise ArtifactError(f"{path}: unreadable OBJ file ({e})") from e
    try:
        for lineno, line in enumerate(text.splitlines(), 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            tag = parts[0]
            if tag == "v":
                v.append([float(x) for x in parts[1:4]])
            elif tag == "vt":
                vt.append([float(x) for x in parts[1:3]] + [0.0] * max(0, 2 - len(parts[1:3])))
            elif tag == "f":
                corners = []
                for c in parts[1:]:
                    idx = c.split("/")
                    vi = int(idx[0])
                    vi = vi - 1 if vi > 0 else len(v) + vi  # 1-based, negative = relative
                    ti = -1
                    if len(idx) > 1 and idx[1]:
                        ti = int(idx[1])
                        ti = ti - 1 if ti > 0 else len(vt) + ti
                    corners.append((vi, ti))
                if len(corners) < 3:
                    raise ValueError(f"line {lineno}: a face needs at least 3 corners")
                for k in range(1, len(corners) - 1):  # fan triangulation of polygons
                    tri = (corners[0], corners[k], corners[k + 1])
                    fv.append([c[0] for c in tri])
                    ft.append([c[1] for c in tri])
    except ValueError as e:
        raise ArtifactError(f"{path}: malformed OBJ ({e})") from e
    verts = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(fv, dtype=np.int64).reshape(-1, 3)
    tex = np.asarray(ft, dtype=np.int64).reshape(-1, 3)
    face_uv = None
    if len(vt) and tex.size and (tex >= 0).all():
        uv = np.asarray(vt, dtype=np.float64)
        if tex.max() >= len(uv):
            raise ArtifactError(f"{path}: texture index out of range [0, {len(uv)})")
        face_uv = uv[tex]
    return verts, faces, face_uv


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a triangle mesh -> (verts (V, 3) float64, faces (F, 3) int64, face_uv (F, 3, 2) | None).

    OBJ: UVs are kept per face corner (None when any face lacks them); polygons are
    fanned into triangles. Other formats are read with trimesh (no UVs).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    if path.suffix.lower() == ".obj":
        verts, faces, face_uv = _parse_obj(path)
    else:
        import trimesh

        try:
            m = trimesh.load(str(path), force="mesh", process=False)
            verts = np.asarray(m.vertices, dtype=np.float64)
            faces = np.asarray(m.faces, dtype=np.int64)
        except Exception as e:  # noqa: BLE001 - trimesh raises many types for corrupt files
            raise ArtifactError(f"{path}: unreadable mesh file ({e})") from e
        face_uv = None
    _check_arrays(path, verts, faces.reshape(-1, 3), face_uv)
    return verts, faces, face_uv


def write_obj(path: str | os.PathLike, verts: np.ndarray, faces: np.ndarray,
              face_uv: np.ndarray | None = None) -> None:
    """Write an OBJ (atomic). face_uv (F, 3, 2): per-corner UVs, written as one ``vt``
    per distinct UV value so shared corners stay shared."""
    verts = np.asarray(verts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{path}: write_obj expects verts (V, 3) and faces (F, 3), got "
                         f"{verts.shape}, {faces.shape}")
    lines = ["# anidress_core.io.mesh.write_obj", f"# {len(verts)} vertices, {len(faces)} faces"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in verts]
    if face_uv is not None:
        face_uv = np.asarray(face_uv, dtype=np.float64)
        if face_uv.shape != (faces.shape[0], 3, 2):
            raise ValueError(f"{path}: face_uv must be ({faces.shape[0]}, 3, 2), got {face_uv.shape}")
        uv, inv = np.unique(face_uv.reshape(-1, 2), axis=0, return_inverse=True)
        inv = inv.reshape(-1, 3) + 1
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in uv]
        f1 = faces + 1
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f1, inv)]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


_PLY_TYPES = {"f4": "float", "f8": "double", "i4": "int", "u4": "uint", "u1": "uchar", "i1": "char",
              "i2": "short", "u2": "ushort"}


def write_ply(path: str | os.PathLike, verts: np.ndarray, faces: np.ndarray,
              vertex_attributes: Mapping[str, np.ndarray] | None = None) -> None:
    """Write a binary little-endian PLY (atomic) with extra per-vertex properties.

    vertex_attributes: name -> (V,) or (V, k) array; a (V, k) attribute becomes
    properties ``name_0 .. name_{k-1}``; bool is stored as uchar, other integers as
    int, floats as float (float64 kept as double).
    """
    verts = np.asarray(verts)
    faces = np.asarray(faces, dtype=np.int64)
    V = verts.shape[0]
    if verts.ndim != 2 or verts.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{path}: write_ply expects verts (V, 3) and faces (F, 3), got {verts.shape}, {faces.shape}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = [verts[:, 0], verts[:, 1], verts[:, 2]]
    for name, a in (vertex_attributes or {}).items():
        a = np.asarray(a)
        if a.shape[0] != V or a.ndim not in (1, 2):
            raise ValueError(f"{path}: vertex attribute '{name}' must be ({V},) or ({V}, k), got {a.shape}")
        if a.dtype == bool:
            dt = "<u1"
        elif a.dtype.kind in "iu":
            dt = "<i4"
        elif a.dtype == np.float64:
            dt = "<f8"
        else:
            dt = "<f4"
        cols = [a] if a.ndim == 1 else [a[:, k] for k in range(a.shape[1])]
        names = [name] if a.ndim == 1 else [f"{name}_{k}" for k in range(a.shape[1])]
        for n, c in zip(names, cols):
            fields.append((n, dt))
            columns.append(c)
    vrec = np.empty(V, dtype=fields)
    for (n, _), c in zip(fields, columns):
        vrec[n] = c
    frec = np.empty(faces.shape[0], dtype=[("n", "<u1"), ("i", "<i4", (3,))])
    frec["n"] = 3
    frec["i"] = faces
    header = ["ply", "format binary_little_endian 1.0", "comment anidress_core.io.mesh.write_ply",
              f"element vertex {V}"]
    header += [f"property {_PLY_TYPES[np.dtype(dt).str[1:]]} {n}" for n, dt in fields]
    header += [f"element face {faces.shape[0]}", "property list uchar int vertex_indices", "end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(vrec.tobytes())
            fh.write(frec.tobytes())
