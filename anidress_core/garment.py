"""Garment templates: procedural skirt/dress, cleaning + remeshing, band, body attachment.

The ``template`` stage of DESIGN.md §4: a garment mesh in the body's canonical T-pose
frame (SMPL: metres, y up, facing +z, pelvis at the origin) is cleaned and remeshed to
a target vertex count (AniDress downsamples its garment templates to 6-9K vertices),
its *band* (the vertices the body holds: the waist band of a skirt, the shoulder straps
of a dress) is found, and every vertex gets body skinning weights from the nearest
point of the body surface, so the template can be posed by the body (the garment
prior of the radiance field, the kinematic boundary condition of the cloth solver).

Everything here is numpy/torch math; no file is opened (see ``stages.template``). The
cleaning and remeshing (:func:`clean_and_remesh`, importable from here) and the defect
checks live in :mod:`anidress_core.garment_mesh`.

Shapes: V garment vertices, F garment faces, J = 24 body joints, T frames.
UVs are per face corner ``face_uv (F, 3, 2)`` in the OBJ convention (v up).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage, sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree
from torch import Tensor

from .body.kinematic import JOINT_INDEX, NUM_JOINTS
from .garment_mesh import clean_and_remesh
from .geometry import lbs

__all__ = [
    "KINDS",
    "GarmentTemplate",
    "ClosestPoints",
    "closest_points",
    "boundary_loops",
    "waist_height",
    "skirt_surface",
    "dress_surface",
    "make_skirt",
    "make_dress",
    "clean_and_remesh",
    "grid_faces",
    "transfer_uv",
    "cylindrical_uv",
    "band_vertices",
    "attach_to_body",
    "body_clearance",
    "check_placement",
    "prepare_template",
]

log = logging.getLogger("anidress.garment")

KINDS = ("skirt", "dress")


# ============================================================================ template
@dataclass(frozen=True, eq=False)
class GarmentTemplate:
    """A garment in the body's canonical T-pose frame, attached to the body.

    Arrays are numpy; the template is immutable and compares by identity.
    """

    verts: np.ndarray
    """(V, 3) float32 rest vertices, metres, body canonical frame."""
    faces: np.ndarray
    """(F, 3) int64 triangles, counter-clockwise seen from outside (away from the body)."""
    face_uv: np.ndarray
    """(F, 3, 2) float32 per-corner UVs in [0, 1], OBJ convention (v up)."""
    band: np.ndarray
    """(V,) bool: vertices held by the body (skirt: waist band; dress: shoulder straps)."""
    body_weights: np.ndarray
    """(V, 24) float32 convex body skinning weights (see :func:`attach_to_body`)."""
    kind: str
    """'skirt' or 'dress'."""

    def __post_init__(self):
        V, F = self.verts.shape[0], self.faces.shape[0]
        if self.verts.shape != (V, 3):
            raise ValueError(f"GarmentTemplate: verts must be (V, 3), got {self.verts.shape}")
        if self.faces.shape != (F, 3):
            raise ValueError(f"GarmentTemplate: faces must be (F, 3), got {self.faces.shape}")
        if self.face_uv.shape != (F, 3, 2):
            raise ValueError(f"GarmentTemplate: face_uv must be ({F}, 3, 2), got {self.face_uv.shape}")
        if self.band.shape != (V,) or self.band.dtype != bool:
            raise ValueError(f"GarmentTemplate: band must be ({V},) bool, got {self.band.shape} {self.band.dtype}")
        if self.body_weights.shape != (V, NUM_JOINTS):
            raise ValueError(f"GarmentTemplate: body_weights must be ({V}, {NUM_JOINTS}), "
                             f"got {self.body_weights.shape}")
        if self.kind not in KINDS:
            raise ValueError(f"GarmentTemplate: kind must be one of {KINDS}, got {self.kind!r}")

    @property
    def num_vertices(self) -> int:
        return self.verts.shape[0]

    def skin(self, body_transforms: Tensor | np.ndarray) -> Tensor | np.ndarray:
        """Pose the template with the body's joint transforms by linear blend skinning.

        body_transforms: (T, 24, 4, 4) (or (24, 4, 4)) rest -> posed, e.g.
        ``BodyModel.pose(...).transforms``. Returns (T, V, 3) (or (V, 3)), a torch
        tensor in the transforms' dtype, or numpy if numpy was given.
        """
        as_numpy = isinstance(body_transforms, np.ndarray)
        M = torch.as_tensor(body_transforms)
        if M.shape[-3:] != (NUM_JOINTS, 4, 4):
            raise ValueError(f"GarmentTemplate.skin: transforms must be (T, {NUM_JOINTS}, 4, 4), "
                             f"got {tuple(M.shape)}")
        if not M.is_floating_point():
            M = M.double()
        rest = torch.as_tensor(self.verts, dtype=M.dtype)
        W = torch.as_tensor(self.body_weights, dtype=M.dtype)
        out = lbs(rest, W, M)
        return out.numpy() if as_numpy else out


# ============================================================================ mesh helpers
def _mesh_np(body) -> tuple[np.ndarray, np.ndarray]:
    return body.v_template.detach().cpu().numpy().astype(np.float64), body.faces.cpu().numpy().astype(np.int64)


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Boundary loops of a triangle mesh as ordered vertex index arrays.

    A boundary edge belongs to exactly one face. Loops are traced over the undirected
    boundary edges (so face orientation does not matter), assuming a manifold
    boundary: every boundary vertex has exactly two boundary edges.
    """
    f = np.asarray(faces, dtype=np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key, cnt = np.unique(e, axis=0, return_counts=True)
    b = key[cnt == 1]
    if len(b) == 0:
        return []
    nbr: dict[int, list[int]] = {}
    for i, j in b.tolist():
        nbr.setdefault(i, []).append(j)
        nbr.setdefault(j, []).append(i)
    loops, seen = [], set()
    for start in sorted(nbr):
        if start in seen:
            continue
        loop, prev, v = [start], -1, start
        seen.add(start)
        while True:
            nxt = [w for w in nbr[v] if w != prev and w not in seen]
            if not nxt:
                break
            prev, v = v, nxt[0]
            seen.add(v)
            loop.append(v)
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def _edges(faces: np.ndarray) -> np.ndarray:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def _laplacian(faces: np.ndarray, n: int) -> sparse.csr_matrix:
    """Combinatorial graph Laplacian L = D - A (V, V) of the mesh edges."""
    e = _edges(faces)
    A = sparse.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                          shape=(n, n)).tocsr()
    return (sparse.diags(np.asarray(A.sum(1)).ravel()) - A).tocsr()


def _vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    t = verts[faces]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])  # area-weighted
    vn = np.zeros_like(verts)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


# ============================================================================ closest points
class ClosestPoints(NamedTuple):
    """Nearest points of a triangle mesh to query points (N queries)."""

    points: np.ndarray
    """(N, 3) closest points on the mesh."""
    distance: np.ndarray
    """(N,) unsigned distances."""
    face: np.ndarray
    """(N,) int64 index of the face holding the closest point."""
    bary: np.ndarray
    """(N, 3) barycentric coordinates of the closest point in that face."""


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentrics (..., 3) of the point of triangle (a, b, c) closest to p (all (..., 3)).

    Ericson, "Real-Time Collision Detection" (2005), §5.1.5 ClosestPtPointTriangle,
    vectorised: the Voronoi-region tests are evaluated for every pair and the first
    region that holds wins (np.select keeps Ericson's order). Degenerate triangles
    fall into a vertex or edge region or get a guarded denominator.
    """
    dot = lambda u, v: np.einsum("...i,...i->...", u, v)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    safe = lambda x: np.where(np.abs(x) > 1e-30, x, 1e-30)  # noqa: E731
    v_ab = d1 / safe(d1 - d3)
    w_ac = d2 / safe(d2 - d6)
    w_bc = (d4 - d3) / safe((d4 - d3) + (d5 - d6))
    den = safe(va + vb + vc)
    v_in, w_in = vb / den, vc / den
    one, zero = np.ones_like(d1), np.zeros_like(d1)
    conds = [
        (d1 <= 0) & (d2 <= 0),  # vertex a
        (d3 >= 0) & (d4 <= d3),  # vertex b
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab
        (d6 >= 0) & (d5 <= d6),  # vertex c
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ac
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),  # edge bc
    ]
    bu = np.select(conds, [one, zero, 1 - v_ab, zero, 1 - w_ac, zero], 1 - v_in - w_in)
    bv = np.select(conds, [zero, one, v_ab, zero, zero, 1 - w_bc], v_in)
    bw = np.select(conds, [zero, zero, zero, one, w_ac, w_bc], w_in)
    return np.stack([bu, bv, bw], -1)


def closest_points(points: np.ndarray, verts: np.ndarray, faces: np.ndarray, k0: int = 16) -> ClosestPoints:
    """Exact closest points of a triangle mesh to many query points, batched.

    1. A k-d tree over face centroids gives each query its k nearest faces; the
       exact point-triangle distances to them give an upper bound u.
    2. A face whose centroid is farther than u + r_max (r_max: the largest
       centroid-to-corner radius) cannot be closer, so the answer is final once the
       k-th centroid lies beyond that; unresolved queries retry with 4k faces.
    Same result as ``trimesh.proximity.closest_point`` (which bounds candidates by
    the nearest vertex instead), several times faster for points far from the mesh.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    V = np.asarray(verts, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    tri = V[F]  # (F, 3, 3)
    cen = tri.mean(1)
    r_max = float(np.linalg.norm(tri - cen[:, None], axis=-1).max())
    tree = cKDTree(cen)
    N = len(p)
    best_d = np.full(N, np.inf)
    best_f = np.zeros(N, dtype=np.int64)
    best_b = np.zeros((N, 3))
    todo = np.arange(N)
    k = min(k0, len(F))
    while len(todo):
        dc, fi = tree.query(p[todo], k=k)
        dc, fi = dc.reshape(len(todo), k), fi.reshape(len(todo), k)
        t = tri[fi]  # (n, k, 3, 3)
        q = p[todo][:, None, :].repeat(k, 1)
        bary = _closest_on_triangles(q, t[..., 0, :], t[..., 1, :], t[..., 2, :])
        cp = np.einsum("nki,nkij->nkj", bary, t)
        d = np.linalg.norm(cp - q, axis=-1)
        j = d.argmin(1)
        r = np.arange(len(todo))
        best_d[todo], best_f[todo], best_b[todo] = d[r, j], fi[r, j], bary[r, j]
        if k >= len(F):
            break
        unresolved = dc[:, -1] <= best_d[todo] + r_max
        todo = todo[unresolved]
        k = min(4 * k, len(F))
    closest = np.einsum("ni,nij->nj", best_b, tri[best_f])
    return ClosestPoints(closest, best_d, best_f, best_b)


def body_clearance(verts: np.ndarray, body) -> tuple[np.ndarray, np.ndarray]:
    """(distance (V,), inside (V,) bool) of points to the T-posed body surface.

    Inside-ness by ray parity (``trimesh.Trimesh.contains``; the body must be closed).
    """
    import trimesh

    bv, bf = _mesh_np(body)
    d = closest_points(verts, bv, bf).distance
    inside = trimesh.Trimesh(bv, bf, process=False).contains(np.asarray(verts, dtype=np.float64))
    return d, inside


def _push_outside(verts: np.ndarray, body, margin: float) -> tuple[np.ndarray, int]:
    """Move vertices inside the body or closer than ``margin`` to closest point +
    margin along the interpolated body normal. Returns (verts, number moved)."""
    import trimesh

    bv, bf = _mesh_np(body)
    cp = closest_points(verts, bv, bf)
    inside = trimesh.Trimesh(bv, bf, process=False).contains(verts)
    bad = inside | (cp.distance < margin)
    if not bad.any():
        return verts, 0
    n = np.einsum("ni,nij->nj", cp.bary[bad], _vertex_normals(bv, bf)[bf[cp.face[bad]]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    out = verts.copy()
    out[bad] = cp.points[bad] + margin * n
    return out, int(bad.sum())


# ============================================================================ body measurements
def _surface_samples(verts: np.ndarray, faces: np.ndarray, k: int = 3) -> np.ndarray:
    """Deterministic dense surface samples: a barycentric lattice of step 1/k on every face."""
    i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
    keep = i + j <= k
    b = np.stack([i[keep], j[keep], k - i[keep] - j[keep]], -1) / k  # (S, 3)
    return np.einsum("si,fij->fsj", b, verts[faces]).reshape(-1, 3)


def waist_height(body) -> float:
    """Height (y, metres) of the natural waist: the narrowest torso cross-section
    between the spine1 joint and the middle of spine2-spine3 (arms are level with the
    shoulders in the T-pose, so only the torso is cut there)."""
    v, f = _mesh_np(body)
    J = body.joints_rest.detach().cpu().numpy().astype(np.float64)
    lo = J[JOINT_INDEX["spine1"], 1]
    hi = 0.5 * (J[JOINT_INDEX["spine2"], 1] + J[JOINT_INDEX["spine3"], 1])
    pts = _surface_samples(v, f)
    ys = np.linspace(lo, hi, 41)
    h = max((hi - lo) / 40, 0.004)
    # Width proxy: x extent + z extent of the slab at each height.
    sel = np.abs(pts[None, :, 1] - ys[:, None]) < h  # (Y, N)
    ext = np.where(sel[..., None], pts[None], np.nan)
    width = (np.nanmax(ext[..., 0], 1) - np.nanmin(ext[..., 0], 1)) + (np.nanmax(ext[..., 2], 1) - np.nanmin(ext[..., 2], 1))
    return float(ys[np.nanargmin(width)])


def _radial_extent(pts: np.ndarray, cx: float, cz: float, y_edges: np.ndarray, n_theta: int) -> np.ndarray:
    """Largest distance from the vertical axis (cx, cz) of the points in each
    (height, angle) bin: (len(y_edges) - 1, n_theta); 0 where a bin is empty.
    Angle theta = atan2(x - cx, z - cz): 0 in front (+z), pi/2 at the body's left (+x)."""
    iy = np.searchsorted(y_edges, pts[:, 1]) - 1
    ok = (iy >= 0) & (iy < len(y_edges) - 1)
    th = np.arctan2(pts[ok, 0] - cx, pts[ok, 2] - cz)
    it = np.floor((th + np.pi) / (2 * np.pi) * n_theta).astype(np.int64) % n_theta
    r = np.hypot(pts[ok, 0] - cx, pts[ok, 2] - cz)
    R = np.zeros((len(y_edges) - 1, n_theta))
    np.maximum.at(R, (iy[ok], it), r)
    return R


def _upper_smooth(a: np.ndarray, size: tuple[int, int], wrap_axis1: bool = True) -> np.ndarray:
    """A smooth function >= a: maximum filter, then a box filter no wider than it
    (each box average is over values that all bound the centre from above)."""
    mode = ("nearest", "wrap" if wrap_axis1 else "nearest")
    m = ndimage.maximum_filter(a, size=size, mode=mode)
    return ndimage.uniform_filter(m, size=size, mode=mode)


def _torso_axis(pts: np.ndarray, y: float, h: float = 0.01) -> tuple[float, float]:
    s = pts[np.abs(pts[:, 1] - y) < h]
    return 0.5 * float(s[:, 0].min() + s[:, 0].max()), 0.5 * float(s[:, 2].min() + s[:, 2].max())


def _tube_radii(pts: np.ndarray, cx: float, cz: float, ys: np.ndarray, y_waist: float, n_theta: int,
                ease: float, flare: float, fitted_above_waist: bool) -> np.ndarray:
    """Radii (n_rows, n_theta) of a garment tube at heights ys (descending).

    Below the waist the garment hangs: the radius never decreases going down
    (running max of body extent + ease), plus ``flare`` metres of extra radius per
    metre of drop. Above the waist (dress bodice) it follows the body + ease.
    """
    dy = abs(ys[0] - ys[1])
    bin_h = 0.005
    y_edges = np.arange(ys.min() - 2 * dy, ys.max() + 2 * dy + bin_h, bin_h)
    R = _radial_extent(pts, cx, cz, y_edges, n_theta) + ease
    win_y = 2 * int(np.ceil(1.5 * dy / bin_h)) + 1
    R = _upper_smooth(R, (win_y, 5))
    yc = 0.5 * (y_edges[1:] + y_edges[:-1])
    rows = np.clip(np.searchsorted(yc, ys), 0, len(yc) - 1)
    r = R[rows]  # (n_rows, n_theta), rows descending in y
    below = ys <= y_waist
    if below.any():
        i0 = int(np.argmax(below))
        r[i0:] = np.maximum.accumulate(r[i0:], axis=0)
        r[i0:] += flare * (y_waist - ys[i0:, None])
        if not fitted_above_waist:
            r = r[i0:]
    return _upper_smooth(r, (3, 3))


def grid_faces(n_rows: int, n_cols: int, wrap: bool) -> np.ndarray:
    """Triangles (F, 3) int of a (n_rows, n_cols) vertex grid indexed row-major: two per cell,
    F = 2 (n_rows - 1) n_cols when the columns wrap (``wrap``: a tube), else 2 (n_rows - 1) (n_cols - 1)."""
    i, j = np.meshgrid(np.arange(n_rows - 1), np.arange(n_cols if wrap else n_cols - 1), indexing="ij")
    a = i * n_cols + j
    b = i * n_cols + (j + 1) % n_cols
    c = (i + 1) * n_cols + j
    d = (i + 1) * n_cols + (j + 1) % n_cols
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])


def cylindrical_uv(verts: np.ndarray, faces: np.ndarray, center_xz: tuple[float, float] = (0.0, 0.0),
                   y_range: tuple[float, float] | None = None) -> np.ndarray:
    """Per-corner cylindrical UVs (F, 3, 2): u = angle around the vertical axis
    through center_xz (0 and 1 at the back, 0.5 in front), v = height (OBJ: v up).

    The seam is cut per corner: the small-u corners of a face straddling the back
    are shifted by +1 (so no face spans the texture), then u is rescaled into [0, 1].
    """
    v = np.asarray(verts, dtype=np.float64)
    th = np.arctan2(v[:, 0] - center_xz[0], v[:, 2] - center_xz[1])
    u = (th + np.pi) / (2 * np.pi)  # back (-z) at 0/1, front at 0.5
    lo, hi = (v[:, 1].min(), v[:, 1].max()) if y_range is None else y_range
    vv = (v[:, 1] - lo) / max(hi - lo, 1e-9)
    fu = u[faces]
    wrap = (fu.max(1) - fu.min(1)) > 0.5
    fu = np.where(wrap[:, None] & (fu < 0.5), fu + 1.0, fu)
    fu = fu / max(float(fu.max()), 1.0)  # the seam faces reached past 1: rescale into [0, 1]
    uv = np.stack([fu, vv[faces]], -1)
    return uv.astype(np.float64)


# ============================================================================ procedural garments
def _tube(ys, r, cx, cz, n_theta):
    th = -np.pi + (np.arange(n_theta) + 0.5) * 2 * np.pi / n_theta  # avoid a column on the seam
    x = cx + r * np.sin(th)[None]
    z = cz + r * np.cos(th)[None]
    y = np.broadcast_to(ys[:, None], r.shape)
    return np.stack([x, y, z], -1).reshape(-1, 3), th


def skirt_surface(body, length: float = 0.55, flare: float = 0.35, waist_ease: float = 0.012,
                  spacing: float = 0.008) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw procedural flared skirt (a structured grid, before remeshing).

    An open tube from the natural waist (top ring ``waist_ease`` outside the skin,
    following the body's cross-section) down ``length`` metres, hanging over the hips
    and widening by ``flare`` metres of radius per metre of drop. Returns
    (verts (V, 3), faces (F, 3), face_uv (F, 3, 2)).
    """
    v, f = _mesh_np(body)
    pts = _surface_samples(v, f)
    yw = waist_height(body)
    cx, cz = _torso_axis(pts, yw)
    n_theta = int(np.clip(round(2 * np.pi * 0.15 / spacing), 48, 512))
    n_rows = max(int(round(length / spacing)) + 1, 8)
    ys = yw - np.linspace(0.0, length, n_rows)
    r = _tube_radii(pts, cx, cz, ys, yw, n_theta, waist_ease, flare, fitted_above_waist=False)
    verts, _ = _tube(ys, r, cx, cz, n_theta)
    faces = grid_faces(n_rows, n_theta, wrap=True)
    return verts, faces, cylindrical_uv(verts, faces, (cx, cz))


def dress_surface(body, length: float = 0.80, flare: float = 0.30, ease: float = 0.015,
                  strap_width: float = 0.045, spacing: float = 0.008) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw procedural long dress (structured grids, before remeshing).

    1. Bodice + skirt: one open tube from a little below the armpits down to
       ``length`` metres under the natural waist (mid-calf on a 1.70 m body), fitted
       (body + ``ease``) above the waist and hanging/flaring below it like the skirt.
    2. Two straps: strips of ``strap_width`` whose ends are the front and back arcs of
       the tube's top ring and which arch over the shoulders between the neck and the
       shoulder joint, ``ease`` clear of the body.
    Boundaries: hem, neck, two arm holes. Returns (verts, faces, face_uv).
    """
    v, f = _mesh_np(body)
    pts = _surface_samples(v, f)
    J = body.joints_rest.detach().cpu().numpy().astype(np.float64)
    yw = waist_height(body)
    cx, cz = _torso_axis(pts, yw)
    # Armpit: lowest surface point of the arms beyond the shoulder joints.
    xs = abs(J[JOINT_INDEX["left_shoulder"], 0] - J[JOINT_INDEX["right_shoulder"], 0]) / 2
    arm = pts[(np.abs(pts[:, 0] - cx) > xs + 0.04) & (pts[:, 1] > yw)]
    y_top = float(arm[:, 1].min()) - 0.05
    y_head = J[JOINT_INDEX["neck"], 1] + 0.25 * (J[JOINT_INDEX["head"], 1] - J[JOINT_INDEX["neck"], 1])
    # 1. Tube.
    n_theta = int(np.clip(round(2 * np.pi * 0.15 / spacing), 48, 512))
    n_rows = max(int(round((y_top - (yw - length)) / spacing)) + 1, 8)
    ys = np.linspace(y_top, yw - length, n_rows)
    r = _tube_radii(pts, cx, cz, ys, yw, n_theta, ease, flare, fitted_above_waist=True)
    tube, th = _tube(ys, r, cx, cz, n_theta)
    faces = [grid_faces(n_rows, n_theta, wrap=True)]
    top = tube[:n_theta]  # row 0 = top ring
    new_verts = [tube]
    n_used = len(tube)
    # 2. Straps (left: +x, right: -x), centred between the neck and the shoulder joint.
    for side in (1.0, -1.0):
        xc = cx + side * 0.6 * xs
        near = np.abs(top[:, 0] - xc) <= strap_width / 2
        front = np.flatnonzero(near & (top[:, 2] > cz))
        back = np.flatnonzero(near & (top[:, 2] < cz))
        n = min(len(front), len(back))
        if n < 2:
            raise ValueError(f"dress_surface: strap of width {strap_width} m spans fewer than 2 columns")
        front = front[np.argsort(np.abs(top[front, 0] - xc))[:n]]
        back = back[np.argsort(np.abs(top[back, 0] - xc))[:n]]
        front, back = front[np.argsort(top[front, 0])], back[np.argsort(top[back, 0])]
        Pf, Pb = top[front], top[back]  # (n, 3)
        czc = 0.5 * (Pf[:, 2] + Pb[:, 2])  # per column centre of the arch
        rho_f, rho_b = Pf[:, 2] - czc, czc - Pb[:, 2]
        path = 0.5 * np.pi * (rho_f.mean() + rho_b.mean())
        n_l = max(int(round(path / spacing)) + 1, 8)
        phi = np.linspace(0.0, np.pi, n_l)
        # Needed arch radius: body points in the strap's slab, binned by arch angle.
        # (Below the head: the strap passes under the jaw, over the shoulder.)
        slab = pts[(np.abs(pts[:, 0] - xc) < strap_width / 2 + 0.015) & (pts[:, 1] > y_top - 0.02)
                   & (pts[:, 1] < y_head)]
        rel_y, rel_z = slab[:, 1] - y_top, slab[:, 2] - czc.mean()
        ph = np.arctan2(rel_y, rel_z)
        n_bins = 90
        ib = np.clip(np.floor(ph / np.pi * n_bins).astype(int), 0, n_bins - 1)
        okb = (ph > -0.2) & (ph < np.pi + 0.2)
        need = np.zeros(n_bins)
        np.maximum.at(need, ib[okb], np.hypot(rel_y, rel_z)[okb])
        need = ndimage.uniform_filter1d(ndimage.maximum_filter1d(need + ease + 0.005, 7, mode="nearest"),
                                        7, mode="nearest")
        need_phi = np.interp(phi, (np.arange(n_bins) + 0.5) / n_bins * np.pi, need)
        t = phi / np.pi
        blend = rho_f[None] * (1 - t[:, None]) + rho_b[None] * t[:, None]  # (n_l, n)
        rho = np.maximum(blend, need_phi[:, None])
        # Keep the ends on the tube ring: fade the lift in over the first/last rows.
        s = np.sin(phi)[:, None] ** 0.5
        rho = blend + s * (rho - blend)
        x = Pf[:, 0][None] * (1 - t[:, None]) + Pb[:, 0][None] * t[:, None]
        y = y_top + rho * np.sin(phi)[:, None]
        z = czc[None] + rho * np.cos(phi)[:, None]
        strip = np.stack([x, y, z], -1)[1:-1].reshape(-1, 3)  # interior rows only
        idx = np.empty((n_l, n), dtype=np.int64)
        idx[0], idx[-1] = front, back
        idx[1:-1] = n_used + np.arange((n_l - 2) * n).reshape(n_l - 2, n)
        n_used += len(strip)
        new_verts.append(strip)
        g = grid_faces(n_l, n, wrap=False)[:, ::-1]  # wound like the tube across the shared rows
        faces.append(idx.reshape(-1)[g])
    verts = np.concatenate(new_verts)
    faces = np.concatenate(faces)
    return verts, faces, cylindrical_uv(verts, faces, (cx, cz))


def _finish_procedural(verts, faces, face_uv, kind, body, target_vertices, margin):
    tpl = prepare_template(verts, faces, face_uv, kind, body, target_vertices)
    # Remeshing reprojects onto the raw surface, which clears the body by the ease;
    # anything closer (a chord over a concave spot) is pushed out to the margin.
    v, moved = _push_outside(tpl.verts.astype(np.float64), body, margin)
    if moved:
        log.info("%s template: pushed %d vertices out of the body to a %.1f mm margin", kind, moved, margin * 1e3)
        tpl = GarmentTemplate(v.astype(np.float32), tpl.faces, tpl.face_uv, tpl.band, tpl.body_weights, kind)
    return tpl


def make_skirt(body, length: float = 0.55, flare: float = 0.35, waist_ease: float = 0.012,
               target_vertices: int = 3000, margin: float = 0.006) -> GarmentTemplate:
    """A flared knee-length skirt fitted to ``body`` (see :func:`skirt_surface`),
    remeshed to ``target_vertices`` and attached (see :func:`prepare_template`); every
    vertex at least ``margin`` metres outside the T-posed body."""
    v, f, uv = skirt_surface(body, length, flare, waist_ease)
    return _finish_procedural(v, f, uv, "skirt", body, target_vertices, margin)


def make_dress(body, length: float = 0.80, flare: float = 0.30, ease: float = 0.015,
               strap_width: float = 0.045, target_vertices: int = 3000, margin: float = 0.006) -> GarmentTemplate:
    """A long strapped dress fitted to ``body`` (see :func:`dress_surface`), remeshed
    and attached like :func:`make_skirt`."""
    v, f, uv = dress_surface(body, length, flare, ease, strap_width)
    return _finish_procedural(v, f, uv, "dress", body, target_vertices, margin)


# ============================================================================ UV transfer
def transfer_uv(src_verts: np.ndarray, src_faces: np.ndarray, src_face_uv: np.ndarray,
                verts: np.ndarray, faces: np.ndarray, seam_tol: float | None = None) -> np.ndarray:
    """Per-corner UVs (F, 3, 2) of a remeshed surface from the original's.

    1. Every new vertex is projected onto the original surface (closest point) and
       takes the barycentric interpolation of that face's corner UVs: continuous
       inside a chart.
    2. Every new face's centroid is projected too; its original face's affine UV map
       (barycentrics in that face's plane, extrapolated) gives a second value per
       corner, always within one chart.
    3. Corners where the two differ by more than ``seam_tol`` (default: 5x the median
       UV edge length of the original) sit across a seam: they take the
       extrapolated value, so no face stretches across the texture (then clipped to
       the input's UV range).
    """
    sv, sf = np.asarray(src_verts, np.float64), np.asarray(src_faces, np.int64)
    suv = np.asarray(src_face_uv, np.float64)
    v, f = np.asarray(verts, np.float64), np.asarray(faces, np.int64)
    # 1.
    cpv = closest_points(v, sv, sf)
    uv_v = np.einsum("ni,nij->nj", cpv.bary, suv[cpv.face])  # (V, 2)
    uv1 = uv_v[f]  # (F, 3, 2)
    # 2. Barycentrics of each corner w.r.t. the centroid's original triangle (a, b, c):
    #    solve the 2x2 normal equations of p - a = s (b - a) + t (c - a).
    cpc = closest_points(v[f].mean(1), sv, sf)
    tri = sv[sf[cpc.face]]  # (F, 3, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = v[f] - tri[:, None, 0]  # (F, 3, 3)
    g11, g12, g22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    det = np.where(np.abs(g11 * g22 - g12 ** 2) > 1e-30, g11 * g22 - g12 ** 2, 1e-30)
    r1, r2 = np.einsum("fki,fi->fk", d, e1), np.einsum("fki,fi->fk", d, e2)
    s = (g22[:, None] * r1 - g12[:, None] * r2) / det[:, None]
    t = (g11[:, None] * r2 - g12[:, None] * r1) / det[:, None]
    fuv = suv[cpc.face]  # (F, 3, 2)
    uv2 = fuv[:, None, 0] + s[..., None] * (fuv[:, None, 1] - fuv[:, None, 0]) + t[..., None] * (fuv[:, None, 2] - fuv[:, None, 0])
    # 3.
    if seam_tol is None:
        el = np.linalg.norm(suv - np.roll(suv, 1, axis=1), axis=-1)
        seam_tol = 5.0 * float(np.median(el))
    jump = np.linalg.norm(uv1 - uv2, axis=-1) > seam_tol
    out = np.where(jump[..., None], uv2, uv1)
    # Extrapolated corners may overshoot the chart's edge slightly: keep the input's UV range.
    flat = suv.reshape(-1, 2)
    return np.clip(out, flat.min(0), flat.max(0))


# ============================================================================ band + attachment
def band_vertices(verts: np.ndarray, faces: np.ndarray, kind: str, body, width: float = 0.015) -> np.ndarray:
    """(V,) bool: the garment vertices the body holds.

    skirt: the top boundary loop (highest mean height; the waist band) and every
        vertex within ``width`` metres of it.
    dress: the straps over the shoulders: vertices above the collar joints' height
        (minus ``width``) and within 3 cm of the body surface.
    """
    v = np.asarray(verts, dtype=np.float64)
    if kind == "skirt":
        loops = boundary_loops(faces)
        if not loops:
            raise ValueError("band_vertices: the skirt has no boundary loop (is it closed?)")
        top = max(loops, key=lambda lp: v[lp, 1].mean())
        d, _ = cKDTree(v[top]).query(v)
        return d <= width
    if kind == "dress":
        J = body.joints_rest.detach().cpu().numpy()
        y0 = 0.5 * (J[JOINT_INDEX["left_collar"], 1] + J[JOINT_INDEX["right_collar"], 1]) - width
        bv, bf = _mesh_np(body)
        cand = v[:, 1] >= y0
        band = np.zeros(len(v), dtype=bool)
        if cand.any():
            band[cand] = closest_points(v[cand], bv, bf).distance < 0.03
        if not band.any():
            raise ValueError("band_vertices: no dress vertex lies over the shoulders (no straps?)")
        return band
    raise ValueError(f"band_vertices: kind must be one of {KINDS}, got {kind!r}")


def attach_to_body(verts: np.ndarray, faces: np.ndarray, body, smoothing: float = 0.0,
                   falloff: float = 0.03, anchors: np.ndarray | None = None) -> np.ndarray:
    """Body skinning weights (V, 24) for garment vertices from the nearest body surface.

    1. Closest point on the body triangles (:func:`closest_points`), its face's
       vertex weights interpolated barycentrically: ``w_hat`` (convex; exactly the
       body's weights for a vertex on a body vertex).
    2. ``smoothing`` > 0 (what :func:`prepare_template` uses): nearest-surface weights
       tear a skirt between the legs (the hem's front splits into left/right thigh
       weights), so they are diffused over the garment mesh, trusted where the garment
       touches the body and free where it hangs away:
       minimise  sum_i c_i |w_i - w_hat_i|^2 + smoothing * sum_(i,j) in edges |w_i - w_j|^2,
       c_i = exp(-(d_i / falloff)^2) + 1e-3 (d_i: distance to the body), c_i = 1e3 on
       ``anchors`` (the band, held by the body), i.e. (C + smoothing L) W = C W_hat with
       the graph Laplacian L. C + s L is an M-matrix and L 1 = 0, so W stays convex.
    """
    v = np.asarray(verts, dtype=np.float64)
    bv, bf = _mesh_np(body)
    BW = body.weights.detach().cpu().numpy().astype(np.float64)
    cp = closest_points(v, bv, bf)
    # w_hat[n, j] = sum_k bary[n, k] BW[face[n, k], j]
    w_hat = np.einsum("nk,nkj->nj", cp.bary, BW[bf[cp.face]])
    w_hat = np.clip(w_hat, 0.0, None)
    w_hat /= w_hat.sum(1, keepdims=True)
    if smoothing <= 0:
        return w_hat
    c = np.exp(-(cp.distance / falloff) ** 2) + 1e-3
    if anchors is not None:
        c = np.where(np.asarray(anchors, bool), 1e3, c)
    A = (sparse.diags(c) + smoothing * _laplacian(np.asarray(faces, np.int64), len(v))).tocsc()
    W = splu(A).solve(c[:, None] * w_hat)
    W = np.clip(W, 0.0, None)  # round-off only
    return W / W.sum(1, keepdims=True)


# ============================================================================ the stage math
def check_placement(verts: np.ndarray, body) -> None:
    """Raise ValueError when a garment cannot be in the body's canonical frame in metres:
    its bounding box far larger/smaller than the body's (units), or away from it."""
    v = np.asarray(verts, dtype=np.float64)
    bv, _ = _mesh_np(body)
    blo, bhi = bv.min(0), bv.max(0)
    glo, ghi = v.min(0), v.max(0)
    bd, gd = float(np.linalg.norm(bhi - blo)), float(np.linalg.norm(ghi - glo))
    ratio = gd / bd
    if ratio > 5.0 or ratio < 0.02:
        guess = {1000: "millimetres", 100: "centimetres", 10: "decimetres", 1 / 1000: "kilometres"}
        nearest = min(guess, key=lambda k: abs(np.log10(ratio) - np.log10(k)))
        raise ValueError(
            f"garment template is {ratio:.3g}x the body's size (bounding-box diagonal {gd:.4g} vs {bd:.3g} m): "
            f"wrong units? It looks like {guess[nearest]}; the pipeline works in metres, scale the template "
            f"by {1 / nearest:g}")
    pad = 0.1 * bd
    if np.any(glo > bhi + pad) or np.any(ghi < blo - pad):
        raise ValueError(
            f"garment template lies away from the body (its box {glo.round(3).tolist()}..{ghi.round(3).tolist()} "
            f"vs the body's {blo.round(3).tolist()}..{bhi.round(3).tolist()} m): it must be in the body's "
            "canonical T-pose frame (metres, y up, facing +z, pelvis at the origin)")


def _orient_outward(verts: np.ndarray, faces: np.ndarray, body) -> np.ndarray:
    """Flip all faces if most of the area faces the body (normals should point away)."""
    bv, bf = _mesh_np(body)
    t = verts[faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    c = t.mean(1)
    away = c - bv[cKDTree(bv).query(c)[1]]  # nearest body vertex: enough for a global vote
    return faces[:, ::-1].copy() if np.einsum("fi,fi->", n, away) < 0 else faces


def prepare_template(verts: np.ndarray, faces: np.ndarray, face_uv: np.ndarray | None, kind: str, body,
                     target_vertices: int, smoothing: float = 2.0, falloff: float = 0.03,
                     band_width: float = 0.015) -> GarmentTemplate:
    """The ``template`` stage math: check, clean + remesh, UVs, band, body weights.

    verts (V, 3), faces (F, 3): the garment in the body's canonical T-pose frame,
    metres; face_uv (F, 3, 2) or None (then cylindrical UVs around the body's axis);
    kind: 'skirt' | 'dress'; body: the BodyModel it is worn on; target_vertices: the
    remeshed vertex count (paper: 6-9K; demo: ~3K).
    smoothing, falloff: see :func:`attach_to_body` (band vertices are anchored).
    """
    if kind not in KINDS:
        raise ValueError(f"prepare_template: kind must be one of {KINDS}, got {kind!r}")
    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"prepare_template: verts must be (V, 3) with V > 0, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"prepare_template: the garment has no faces (faces {f.shape}); need (F, 3) triangles")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"prepare_template: face indices out of range [0, {len(v)})")
    if not np.isfinite(v).all():
        raise ValueError(f"prepare_template: {int((~np.isfinite(v).all(1)).sum())} vertices are not finite (NaN/inf)")
    if face_uv is not None:
        face_uv = np.asarray(face_uv, dtype=np.float64)
        if face_uv.shape != (len(f), 3, 2):
            raise ValueError(f"prepare_template: face_uv must be ({len(f)}, 3, 2), got {face_uv.shape}")
    check_placement(v, body)
    # 1. Clean + remesh.
    rv, rf = clean_and_remesh(v, f, target_vertices)
    rf = _orient_outward(rv, rf, body)
    # 2. UVs: carried over from the input surface, or cylindrical.
    if face_uv is not None:
        ok = np.isfinite(face_uv).all()
        uv = transfer_uv(v, f, face_uv, rv, rf) if ok else None
    else:
        uv = None
    if uv is None:
        pts = _surface_samples(*_mesh_np(body))
        uv = cylindrical_uv(rv, rf, _torso_axis(pts, waist_height(body)))
    # 3. Band and 4. body weights (band anchored to the nearest-surface weights).
    band = band_vertices(rv, rf, kind, body, band_width)
    W = attach_to_body(rv, rf, body, smoothing=smoothing, falloff=falloff, anchors=band)
    return GarmentTemplate(verts=rv.astype(np.float32), faces=rf, face_uv=uv.astype(np.float32), band=band,
                           body_weights=W.astype(np.float32), kind=kind)
