"""Small test garments and bodies for the cloth solver tests."""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree


def grid_faces(rows: int, cols: int, periodic: bool) -> np.ndarray:
    """Triangles of a rows x cols vertex grid (row-major), alternating diagonals."""
    f = []
    cmax = cols if periodic else cols - 1
    for r in range(rows - 1):
        for c in range(cmax):
            a, b = r * cols + c, r * cols + (c + 1) % cols
            d, e = a + cols, b + cols
            if (r + c) % 2:
                f += [[a, d, b], [b, d, e]]
            else:
                f += [[a, d, e], [a, e, b]]
    return np.asarray(f, dtype=np.int64)


def flared_skirt(around: int = 32, rows: int = 12, waist_y: float = 0.10, length: float = 0.55,
                 waist_r=(0.145, 0.108), hem_r=(0.40, 0.37), waist_z: float = -0.003):
    """Open cone skirt in the mannequin's canonical space (y up, facing +z).

    Returns (verts (V, 3), faces (F, 3), band (V,) bool: the top ring).
    """
    t = np.linspace(0.0, 1.0, rows)[:, None]
    a = np.linspace(0, 2 * np.pi, around, endpoint=False)[None, :]
    rx = waist_r[0] + (hem_r[0] - waist_r[0]) * t
    rz = waist_r[1] + (hem_r[1] - waist_r[1]) * t
    x = rx * np.cos(a)
    z = waist_z + rz * np.sin(a)
    y = np.broadcast_to(waist_y - length * t, x.shape)
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    f = grid_faces(rows, around, periodic=True)
    band = np.zeros(len(v), bool)
    band[:around] = True
    return v, f, band


def nearest_weights(verts: np.ndarray, body_rest: np.ndarray, body_weights: np.ndarray) -> np.ndarray:
    """Skinning weights of the nearest body vertex (V, J)."""
    _, i = cKDTree(body_rest).query(verts)
    return body_weights[i]


def sphere_body(radius: float = 0.2, center=(0.0, 0.0, 0.0), subdivisions: int = 3):
    """Icosphere body rigged to joint 0: (verts (Vb, 3), faces (Fb, 3), weights (Vb, 24))."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(s.vertices) + np.asarray(center)
    w = np.zeros((len(v), 24))
    w[:, 0] = 1
    return v, np.asarray(s.faces, dtype=np.int64), w


def square_cloth(n: int = 20, size: float = 0.5, height: float = 0.5):
    """Horizontal n x n cloth centred above the origin at z = height (world = rest)."""
    u = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(u, u, indexing="ij")
    v = np.stack([X.ravel(), Y.ravel(), np.full(n * n, height)], 1)
    return v, grid_faces(n, n, periodic=False)
