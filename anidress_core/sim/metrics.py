"""Quality metrics of simulated garments (used by the benchmark and the tests)."""
from __future__ import annotations

import numpy as np
import torch

from .setup import mesh_edges

__all__ = ["body_contacts", "edge_stretch", "penetration_depth"]


def _np(a, dtype):
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=dtype)


def edge_stretch(frames, rest, faces) -> np.ndarray:
    """Edge length / rest length of every unique edge.

    frames: (T, V, 3) or (V, 3); rest: (V, 3); faces: (F, 3).
    Returns (T, E) (or (E,)) ratios; 1 = rest length, NaN where a frame has NaN.
    """
    x = _np(frames, np.float64)
    r = _np(rest, np.float64)
    f = _np(faces, np.int64)
    if r.ndim != 2 or r.shape[1] != 3 or x.shape[-2:] != r.shape:
        raise ValueError(f"edge_stretch: frames (T, V, 3) and rest (V, 3) must match, got {x.shape}, {r.shape}")
    e = mesh_edges(f)
    L0 = np.linalg.norm(r[e[:, 0]] - r[e[:, 1]], axis=1)
    L = np.linalg.norm(x[..., e[:, 0], :] - x[..., e[:, 1], :], axis=-1)
    return L / np.maximum(L0, 1e-12)


def penetration_depth(frames, body_vertices, body_faces, max_dist: float = 0.1, device: str = "cpu") -> np.ndarray:
    """Depth of garment vertices inside the body, m (0 outside).

    frames: (T, V, 3) garment; body_vertices: (T, Vb, 3) posed body (closed mesh);
    body_faces: (Fb, 3). Inside/outside by the generalised winding number (robust
    on LBS-posed bodies), depth = distance to the closest body point, capped at
    ``max_dist``. Returns (T, V) float64.
    """
    import warp as wp

    from . import kernels as K

    x = _np(frames, np.float32)
    b = _np(body_vertices, np.float32)
    f = _np(body_faces, np.int32)
    if x.ndim != 3 or b.ndim != 3 or x.shape[0] != b.shape[0] or x.shape[-1] != 3 or b.shape[-1] != 3:
        raise ValueError(f"penetration_depth: expected frames (T, V, 3), body (T, Vb, 3), got {x.shape}, {b.shape}")
    wp.init()
    pts = wp.array(b[0], dtype=wp.vec3, device=device)
    mesh = wp.Mesh(points=pts, indices=wp.array(f.reshape(-1), dtype=wp.int32, device=device),
                   support_winding_number=True)
    xs = wp.zeros(x.shape[1], dtype=wp.vec3, device=device)
    sd = wp.zeros(x.shape[1], dtype=wp.float32, device=device)
    out = np.zeros(x.shape[:2])
    for t in range(x.shape[0]):
        pts.assign(b[t])
        mesh.refit()
        xs.assign(np.nan_to_num(x[t]))
        wp.launch(K.signed_distance, x.shape[1], inputs=[mesh.id, xs, float(max_dist), sd], device=device)
        out[t] = np.clip(-sd.numpy(), 0.0, None)
    return out


def body_contacts(points, body_vertices, body_faces, max_dist: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest points of a closed body mesh to ``points`` and the outward normals there.

    points: (N, 3); body_vertices: (Vb, 3); body_faces: (Fb, 3). Returns point (N, 3), normal
    (N, 3) (float64, on the points' device) and found (N,) bool (a body point within
    ``max_dist``; elsewhere point and normal are 0). Inside / outside by the generalised winding
    number (:func:`kernels.closest_point_signed`), so (x - point) . normal is x's signed distance
    (< 0 inside) wherever found -- inside a limb, exactly when the closest point lies within a face.
    """
    import warp as wp

    from . import kernels as K

    dev = points.device if isinstance(points, torch.Tensor) else torch.device("cpu")
    x = _np(points, np.float32)
    b = _np(body_vertices, np.float32)
    f = _np(body_faces, np.int32)
    if x.ndim != 2 or x.shape[-1] != 3 or b.ndim != 2 or b.shape[-1] != 3 or f.ndim != 2 or f.shape[-1] != 3:
        raise ValueError(f"body_contacts: expected points (N, 3), body (Vb, 3), faces (Fb, 3), got {x.shape}, "
                         f"{b.shape}, {f.shape}")
    wp.init()
    mesh = wp.Mesh(points=wp.array(b, dtype=wp.vec3), indices=wp.array(f.reshape(-1), dtype=wp.int32),
                   support_winding_number=True)
    n = x.shape[0]
    xs = wp.array(np.nan_to_num(x, nan=1e9, posinf=1e9, neginf=-1e9), dtype=wp.vec3)
    cp, cn, ok = wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.int32)
    wp.launch(K.closest_point_signed, n, inputs=[mesh.id, xs, float(max_dist), cp, cn, ok])
    found = torch.from_numpy(ok.numpy() != 0) & torch.from_numpy(np.isfinite(x).all(-1))
    as64 = lambda a: torch.from_numpy(a.numpy().astype(np.float64))  # noqa: E731
    return as64(cp).to(dev), as64(cn).to(dev), found.to(dev)
