"""One-time preprocessing of the cloth solver: constraints, colouring, attachments,
sparse skinning tables, transform interpolation. numpy / torch, no Warp."""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
import torch

from ..geometry import axis_angle_to_matrix, matrix_to_axis_angle

__all__ = [
    "mesh_edges",
    "bending_pairs",
    "vertex_masses",
    "color_constraints",
    "long_range_attachments",
    "sparse_weights",
    "joint_pivots",
    "interpolate_transforms",
    "smootherstep",
]


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2), i < j, of triangles (F, 3)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 0)
    return np.unique(np.sort(e, axis=1), axis=0)


def bending_pairs(faces: np.ndarray) -> np.ndarray:
    """Opposite vertices (H, 2) of the two triangles of every interior (manifold) edge.

    The cross-edge ("bending spring") between them resists folding about the edge.
    Edges with one face (boundary) or more than two (non-manifold) give none.
    """
    F = faces.shape[0]
    # Edge k of face f is (faces[f, k], faces[f, k+1]); its opposite corner is faces[f, k+2].
    a = faces[:, [0, 1, 2]].reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    opp = faces[:, [2, 0, 1]].reshape(-1)
    key = np.stack([np.minimum(a, b), np.maximum(a, b)], 1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    order = np.argsort(inv, kind="stable")
    inv_sorted = inv[order]
    starts = np.searchsorted(inv_sorted, np.arange(counts.shape[0]))
    two = np.nonzero(counts == 2)[0]
    k = opp[order[starts[two]]]
    l = opp[order[starts[two] + 1]]
    keep = k != l
    assert F == 0 or inv.shape[0] == 3 * F
    return np.stack([k[keep], l[keep]], 1)


def vertex_masses(verts: np.ndarray, faces: np.ndarray, area_density: float) -> np.ndarray:
    """Lumped masses (V,) kg: a third of each adjacent triangle's area times the density."""
    v0, v1, v2 = (verts[faces[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=1)
    m = np.zeros(verts.shape[0])
    np.add.at(m, faces.reshape(-1), np.repeat(area / 3.0, 3))
    return m * area_density


def color_constraints(pairs: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Greedy graph colouring of two-particle constraints (C, 2).

    Constraints of one colour share no particle. Returns (colour (C,) int, order (C,)
    sorting the constraints by colour, stable). Deterministic.
    """
    used = [0] * num_vertices  # bitmask of colours touching each vertex
    color = np.empty(pairs.shape[0], dtype=np.int64)
    pl = pairs.tolist()
    for c, (i, j) in enumerate(pl):
        m = used[i] | used[j]
        col = (~m & (m + 1)).bit_length() - 1  # lowest free colour
        color[c] = col
        bit = 1 << col
        used[i] |= bit
        used[j] |= bit
    return color, np.argsort(color, kind="stable")


def long_range_attachments(verts: np.ndarray, edges: np.ndarray, band: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest band vertex along the mesh graph and the rest graph distance to it.

    Kim et al. 2012 (long range attachments): a particle may never be farther (in
    3D) from its anchor than its rest geodesic distance; the shortest path along
    rest edges is the geodesic estimate (an upper bound, so the limit is never too
    tight). Returns (anchor (V,) int, -1 where unreachable or band; max_dist (V,)).
    """
    V = verts.shape[0]
    src = np.nonzero(band)[0]
    anchor = np.full(V, -1, dtype=np.int64)
    max_dist = np.zeros(V)
    if src.size == 0:
        return anchor, max_dist
    L = np.linalg.norm(verts[edges[:, 0]] - verts[edges[:, 1]], axis=1)
    L = np.maximum(L, 1e-12)  # csgraph treats explicit zeros as missing edges
    G = sp.coo_matrix((L, (edges[:, 0], edges[:, 1])), shape=(V, V)).tocsr()
    dist, _, sources = dijkstra(G, directed=False, indices=src, min_only=True, return_predecessors=True)
    ok = np.isfinite(dist) & ~band
    anchor[ok] = sources[ok]
    max_dist[ok] = dist[ok]
    return anchor, max_dist


def sparse_weights(weights: np.ndarray, max_influences: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Dense (N, J) skinning weights -> (bone (N, K) int32, weight (N, K) float32).

    K = the largest number of nonzero weights of any row (at most ``max_influences``;
    rows with more keep their largest and are renormalised). Padding has weight 0.
    Exact (same sums as dense LBS) whenever no row exceeds ``max_influences``.
    """
    nnz = int((weights != 0).sum(1).max()) if weights.size else 1
    K = max(1, min(nnz, max_influences))
    bone = np.argsort(-np.abs(weights), axis=1, kind="stable")[:, :K]
    w = np.take_along_axis(weights, bone, axis=1)
    if nnz > K:
        w = w / np.maximum(w.sum(1, keepdims=True), 1e-12)
    return bone.astype(np.int32), w.astype(np.float32)


def joint_pivots(rest: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(J, 3) weight-averaged rest position of each bone's region (the pivot about which
    :func:`interpolate_transforms` rotates); the rest centroid for unused bones."""
    s = weights.sum(0)  # (J,)
    c = (weights.T @ rest) / np.maximum(s, 1e-12)[:, None]
    c[s <= 1e-12] = rest.mean(0)
    return c


def smootherstep(x):
    """Quintic 6x^5 - 15x^4 + 10x^3 clamped to [0, 1] (C2 ease in/out)."""
    x = min(max(float(x), 0.0), 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def interpolate_transforms(A0: torch.Tensor, A1: torch.Tensor, pivots: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Rigid interpolation of per-bone transforms.

    A0, A1: (J, 4, 4) rest -> world; pivots: (J, 3) rest-space pivot c_j; w: (S,) in
    [0, 1]. Returns (S, J, 4, 4) with
        R(w) = exp(w log(R1 R0^T)) R0        (geodesic rotation interpolation)
        p(w) = (1 - w) (R0 c + t0) + w (R1 c + t1)   (the pivot moves on a line)
        t(w) = p(w) - R(w) c,
    so w = 0 and w = 1 give A0 and A1 (to rounding), each bone stays rigid and a
    skinned vertex never shrinks towards the bone as a linear blend of matrices would.
    """
    R0, R1 = A0[:, :3, :3], A1[:, :3, :3]
    t0, t1 = A0[:, :3, 3], A1[:, :3, 3]
    aa = matrix_to_axis_angle(R1 @ R0.transpose(-1, -2))  # (J, 3)
    Rw = axis_angle_to_matrix(w[:, None, None] * aa[None]) @ R0[None]  # (S, J, 3, 3)
    p0 = torch.einsum("jab,jb->ja", R0, pivots) + t0
    p1 = torch.einsum("jab,jb->ja", R1, pivots) + t1
    pw = (1 - w)[:, None, None] * p0[None] + w[:, None, None] * p1[None]
    tw = pw - torch.einsum("sjab,jb->sja", Rw, pivots)
    out = torch.zeros(w.shape[0], A0.shape[0], 4, 4, dtype=A0.dtype)
    out[..., :3, :3] = Rw
    out[..., :3, 3] = tw
    out[..., 3, 3] = 1
    # Exact end points (the log/exp round trip is only accurate to ~1e-7).
    out[w == 1.0] = A1
    out[w == 0.0] = A0
    return out


def _check_finite(name: str, a: np.ndarray) -> None:
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains NaN or inf")


class Topology(NamedTuple):
    """Constraint tables of a garment (numpy)."""

    edges: np.ndarray  # (E, 2)
    pairs: np.ndarray  # (C, 2) stretch edges then bending pairs, sorted by colour
    rest: np.ndarray  # (C,) rest lengths
    is_bend: np.ndarray  # (C,) bool
    color_starts: np.ndarray  # (G + 1,) offsets of the colour groups in ``pairs``


def build_topology(verts: np.ndarray, faces: np.ndarray) -> Topology:
    """Stretch edges + bending cross-edges of a triangle mesh, coloured (see above)."""
    edges = mesh_edges(faces)
    bend = bending_pairs(faces)
    pairs = np.concatenate([edges, bend], 0)
    is_bend = np.concatenate([np.zeros(len(edges), bool), np.ones(len(bend), bool)])
    color, order = color_constraints(pairs, verts.shape[0])
    pairs, is_bend, color = pairs[order], is_bend[order], color[order]
    rest = np.linalg.norm(verts[pairs[:, 0]] - verts[pairs[:, 1]], axis=1)
    G = int(color.max()) + 1 if color.size else 0
    starts = np.searchsorted(color, np.arange(G + 1))
    return Topology(edges, pairs, rest, is_bend, starts)


def substeps_for(fps: float, time_scale: float, substep_dt: float) -> int:
    """Substeps per captured frame: ceil(time_scale / (fps * substep_dt))."""
    return max(1, math.ceil(time_scale / (fps * substep_dt) - 1e-9))
