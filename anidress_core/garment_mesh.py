"""Cleaning, remeshing and defect checks of a garment mesh (pymeshlab, scipy).

:func:`clean_and_remesh` is the template stage's repair (:func:`anidress_core.garment.prepare_template`);
:func:`mesh_defects` reports, before any repair, what that cleaning would meet
(the scene validation, :mod:`anidress_core.stages.validate`, decides which defects are errors).

Pure numpy math and pymeshlab filters; no file is opened. Shapes: V vertices, F faces.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["clean_and_remesh", "MERGE_TOL_M", "MeshDefects", "mesh_defects"]

MERGE_TOL_M = 1e-6
"""Vertices closer than this are one vertex (:func:`clean_and_remesh`'s ``merge_tol``)."""


# ============================================================================ clean + remesh
def _isotropic(ms, L: float, iterations: int, split_collapse: bool = True) -> None:
    """pymeshlab isotropic explicit remeshing (Botsch & Kobbelt 2004) with every
    parameter spelled out: pymeshlab 2025.7 remembers a filter's last arguments as
    the defaults of its next call (see body/mannequin.py)."""
    import pymeshlab

    ms.meshing_isotropic_explicit_remeshing(
        iterations=iterations, adaptive=False, selectedonly=False, targetlen=pymeshlab.PureValue(L),
        featuredeg=180.0, checksurfdist=False, maxsurfdist=pymeshlab.PureValue(L), splitflag=split_collapse,
        collapseflag=split_collapse, swapflag=True, smoothflag=True, reprojectflag=True)


def _clean(ms, merge_tol: float, min_component: float) -> None:
    """Cleaning filters (names: pymeshlab filter list, pymeshlab.readthedocs.io)."""
    import pymeshlab

    ms.meshing_merge_close_vertices(threshold=pymeshlab.PureValue(merge_tol))
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_repair_non_manifold_edges(method="Remove Faces")
    ms.meshing_repair_non_manifold_vertices(vertdispratio=0.0)
    nf = ms.current_mesh().face_number()
    ms.meshing_remove_connected_component_by_face_number(
        mincomponentsize=max(int(min_component * nf), 1), removeunref=True)
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_re_orient_faces_coherently()


def _euler_and_boundary(faces: np.ndarray, n_verts: int) -> tuple[int, int]:
    """(Euler characteristic V - E + F, number of boundary vertices)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, cnt = np.unique(np.sort(e, 1), axis=0, return_counts=True)
    E = len(cnt)
    nb = int((cnt == 1).sum())  # boundary edges == boundary vertices on closed loops
    return n_verts - E + len(faces), nb


def clean_and_remesh(verts: np.ndarray, faces: np.ndarray, target_vertices: int, merge_tol: float = 1e-6,
                     min_component: float = 0.01, iterations: int = 6, tolerance: float = 0.03
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Clean a garment mesh and remesh it isotropically to ``target_vertices`` (within ~3%).

    1. Clean (pymeshlab): merge vertices closer than ``merge_tol`` metres, drop
       duplicate and zero-area faces, unreferenced vertices, non-manifold edges and
       vertices, components smaller than ``min_component`` of the faces; orient
       faces coherently.
    2. Isotropic explicit remeshing (Botsch & Kobbelt 2004, vcglib via pymeshlab) with
       reprojection onto the input surface; the edge length starts from
       V ~ area / (sqrt(3)/2 L^2) aiming a little above the target and shrinks by the
       observed count ratio while the result has too few vertices. Boundary edges are kept on the boundary, so the
       open loops (hem, waist, neck, arm holes) survive.
    3. Quadric edge-collapse decimation (Garland & Heckbert 1997) with boundary
       preservation down to the face count of the target (Euler: F = 2 (V - chi) - nb),
       then a relaxation pass without splits/collapses.
    tolerance: the remesher aims ``(1 + tolerance / 2) * target_vertices`` before the
    decimation (the count is exact whenever the remesh overshoots, the usual case).
    Returns (verts (V, 3) float64, faces (F, 3) int64).
    """
    import pymeshlab

    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if target_vertices < 100:
        raise ValueError(f"clean_and_remesh: target_vertices must be >= 100, got {target_vertices}")

    def fresh() -> "pymeshlab.MeshSet":
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))
        _clean(ms, merge_tol, min_component)
        return ms

    ms = fresh()  # keep the MeshSet alive while its mesh is read (see body/mannequin.py)
    m = ms.current_mesh()
    cv, cf = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    if len(cf) == 0:
        raise ValueError("clean_and_remesh: no faces left after cleaning (all degenerate?)")
    t = cv[cf]
    area = float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())
    goal = (1.0 + tolerance / 2) * target_vertices
    L = float(np.sqrt(area / (np.sqrt(3) / 2 * goal)))
    # 1-2. Remesh; while that leaves fewer vertices than the target, shrink the edge
    #      length by the observed ratio (vertex count ~ 1 / L^2) and start again.
    for attempt in range(5):
        if attempt:
            del ms
            ms = fresh()
        _isotropic(ms, L, iterations)
        n = ms.current_mesh().vertex_number()
        if n >= target_vertices:
            break
        L *= 0.98 * float(np.sqrt(n / goal))
    # 3. Decimate the excess to the exact count, keeping the boundary.
    m = ms.current_mesh()
    n = m.vertex_number()
    if n > target_vertices:
        chi, nb = _euler_and_boundary(m.face_matrix().astype(np.int64), n)
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=int(2 * (target_vertices - chi) - nb), targetperc=0.0, qualitythr=0.5,
            preserveboundary=True, boundaryweight=10.0, preservenormal=True, preservetopology=True,
            optimalplacement=True, planarquadric=False, planarweight=0.001, qualityweight=False,
            autoclean=True, selected=False)
        _isotropic(ms, L, 3, split_collapse=False)
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_re_orient_faces_coherently()
    m = ms.current_mesh()
    out_v, out_f = m.vertex_matrix().astype(np.float64).copy(), m.face_matrix().astype(np.int64).copy()
    del ms
    return out_v, out_f


# ============================================================================ defects
class MeshDefects(NamedTuple):
    """Problems of a triangle mesh, in the input's numbering (see :func:`mesh_defects`)."""

    merged_vertices: int
    """vertices within ``merge_tol`` of another one (merged by cleaning)."""
    degenerate_faces: np.ndarray
    """(K,) faces with a repeated vertex (after merging) or zero area."""
    duplicate_faces: np.ndarray
    """(K,) faces over the same three vertices as an earlier face."""
    non_manifold_edges: np.ndarray
    """(E, 2) vertex pairs (input numbering) of edges shared by more than two faces."""
    non_manifold_counts: np.ndarray
    """(E,) how many faces share each of those edges."""
    self_intersecting_faces: np.ndarray
    """(K,) faces that intersect a face they share no vertex or edge with (pymeshlab)."""

    @property
    def repairable_faces(self) -> int:
        return int(len(self.degenerate_faces) + len(self.duplicate_faces))


def _merge_map(verts: np.ndarray, tol: float) -> np.ndarray:
    """(V,) representative of each vertex: the smallest index within ``tol`` (transitively)."""
    V = len(verts)
    pairs = cKDTree(verts).query_pairs(tol, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(V)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(V, V))
    _, comp = connected_components(g, directed=False)
    rep = np.full(comp.max() + 1, V, dtype=np.int64)
    np.minimum.at(rep, comp, np.arange(V))
    return rep[comp]


def mesh_defects(verts: np.ndarray, faces: np.ndarray, merge_tol: float = MERGE_TOL_M,
                 self_intersections: bool = True) -> MeshDefects:
    """Degenerate, duplicate, non-manifold and self-intersecting faces of a triangle mesh.

    verts (V, 3) metres, faces (F, 3). Steps, mirroring what the template stage's
    cleaning (:func:`anidress_core.garment.clean_and_remesh`) sees:
    1. vertices closer than ``merge_tol`` are merged (exported meshes often split them);
    2. degenerate faces: a repeated vertex after merging, or area below
       1e-14 x (bounding-box diagonal)^2 (zero in float64 terms);
    3. duplicate faces: the same vertex set as an earlier face (either orientation);
    4. edges of the remaining faces shared by more than two faces (non-manifold);
    5. faces of the remaining mesh crossing another face they are not adjacent to
       (pymeshlab ``compute_selection_by_self_intersections_per_face``, vcglib's
       triangle-triangle test over a uniform grid).
    """
    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    # 1.
    rep = _merge_map(v, merge_tol)
    fm = rep[f]  # (F, 3)
    # 2.
    t = v[fm]
    area2 = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    diag = float(np.linalg.norm(v.max(0) - v.min(0))) or 1.0
    degenerate = (fm[:, 0] == fm[:, 1]) | (fm[:, 1] == fm[:, 2]) | (fm[:, 0] == fm[:, 2]) | (area2 <= 2e-14 * diag ** 2)
    # 3.
    keep = np.flatnonzero(~degenerate)
    key = np.sort(fm[keep], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    dup_mask = np.ones(len(keep), bool)
    dup_mask[first] = False
    duplicate = keep[dup_mask]
    kept = keep[~dup_mask]
    # 4. undirected edge counts over the kept faces
    fk = fm[kept]
    e = np.sort(np.concatenate([fk[:, [0, 1]], fk[:, [1, 2]], fk[:, [2, 0]]]), axis=1)
    edges, cnt = np.unique(e, axis=0, return_counts=True) if len(e) else (np.zeros((0, 2), np.int64), np.zeros(0))
    bad = cnt > 2
    # 5.
    inter = np.zeros(0, dtype=np.int64)
    if self_intersections and len(kept):
        import pymeshlab

        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=fk.astype(np.int32)))
        ms.compute_selection_by_self_intersections_per_face()
        sel = np.asarray(ms.current_mesh().face_selection_array(), dtype=bool)
        del ms
        inter = kept[sel]
    return MeshDefects(
        merged_vertices=int((rep != np.arange(len(v))).sum()),
        degenerate_faces=np.flatnonzero(degenerate),
        duplicate_faces=duplicate,
        non_manifold_edges=edges[bad].astype(np.int64),
        non_manifold_counts=cnt[bad].astype(np.int64),
        self_intersecting_faces=np.asarray(inter, dtype=np.int64),
    )
