"""Tests of anidress_core.raster against a slow, obviously-correct reference.

The reference is trimesh's ray casting (``RayMeshIntersector``, rtree) of the pixel-centre
rays; watertightness is checked face by face on planar triangulations whose vertices sit
exactly on pixel centres, so the fill rule is exercised on edges and vertices.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import Delaunay
from trimesh.ray.ray_triangle import RayMeshIntersector

from anidress_core.raster import (
    Fragments,
    antialias,
    barycentrics,
    face_adjacency,
    interpolate,
    project_vertices,
    rasterize,
    render_mesh,
    sample_texture,
    shade_lambert,
)

H, W = 48, 64


@pytest.fixture(params=["warp", "torch"])
def backend(request):
    """rasterize's two implementations of coverage and depth test (they must agree)."""
    return request.param


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), dtype=torch.float64) -> torch.Tensor:
    """OpenCV world_to_cam (4, 4): z towards target, y down (against `up`)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, y, z])
    M[:3, 3] = -M[:3, :3] @ eye
    return torch.tensor(M, dtype=dtype)


def intrinsics(f=55.0, h=H, w=W, dtype=torch.float64) -> torch.Tensor:
    return torch.tensor([[f, 0.0, (w - 1) / 2 + 0.13], [0.0, f * 1.02, (h - 1) / 2 - 0.21], [0, 0, 1]], dtype=dtype)


def bumpy_sphere(seed=0, subdivisions=3) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    rng = np.random.default_rng(seed)
    r = 1.0 + 0.15 * rng.standard_normal(len(m.vertices)).clip(-2, 2)
    return trimesh.Trimesh(m.vertices * r[:, None] * [1.0, 0.8, 1.2], m.faces, process=False)


def box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.6, 1.1, 1.3))


def reference(mesh: trimesh.Trimesh, K: torch.Tensor, E: torch.Tensor, h=H, w=W):
    """Ray-cast pixel centres: face id (h, w) (-1 none), depth (h, w), hit point (h, w, 3)."""
    K, E = K.double().numpy(), E.double().numpy()
    R, t = E[:3, :3], E[:3, 3]
    ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    pix = np.stack([jj.ravel(), ii.ravel(), np.ones(h * w)], 1)
    Einv = np.linalg.inv(E)
    dirs = pix @ np.linalg.inv(K).T @ Einv[:3, :3].T
    origin = np.broadcast_to(Einv[:3, 3], dirs.shape)
    tri, ray, loc = RayMeshIntersector(mesh).intersects_id(
        origin, dirs, multiple_hits=False, return_locations=True
    )
    fid = np.full(h * w, -1)
    fid[ray] = tri
    hit = np.zeros((h * w, 3))
    hit[ray] = loc
    depth = np.full(h * w, np.inf)
    depth[ray] = (loc @ R.T + t)[:, 2]
    return fid.reshape(h, w), depth.reshape(h, w), hit.reshape(h, w, 3)


def edge_distance_px(mesh, K, E, fid, h=H, w=W) -> np.ndarray:
    """Pixel distance from each pixel centre to the boundary of face fid (inf if -1)."""
    uv, _ = project_vertices(torch.tensor(mesh.vertices), K.double(), E.double())
    uv = uv[0].numpy()
    out = np.full((h, w), np.inf)
    ii, jj = np.nonzero(fid >= 0)
    tri = uv[mesh.faces[fid[ii, jj]]]  # (N, 3, 2)
    p = np.stack([jj, ii], 1).astype(np.float64)
    dmin = np.full(len(p), np.inf)
    for k in range(3):
        a, b = tri[:, k], tri[:, (k + 1) % 3]
        ab = b - a
        s = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-300), 0, 1)
        dmin = np.minimum(dmin, np.linalg.norm(a + s[:, None] * ab - p, axis=1))
    out[ii, jj] = dmin
    return out


def coverage_count(verts, faces, K, E, h, w, backend="warp") -> torch.Tensor:
    """(h, w) number of faces covering each pixel, rasterising the faces one at a time."""
    count = torch.zeros(h, w, dtype=torch.int64)
    for f in range(faces.shape[0]):
        count += (rasterize(verts, faces[f : f + 1], K, E, h, w, backend=backend).face_id[0] >= 0).long()
    return count


# --------------------------------------------------------------------------------------
# against the ray-casting reference
# --------------------------------------------------------------------------------------

CASES = [
    ("sphere", bumpy_sphere, (3.2, -2.1, 1.4)),
    ("sphere_close", bumpy_sphere, (1.9, 1.3, -0.9)),
    ("box", box, (2.5, 1.7, 1.9)),
]


@functools.lru_cache(maxsize=None)
def _case(name):
    """(mesh, K, E, reference face id, depth, hit point) of a CASES entry, computed once."""
    _, make, eye = next(c for c in CASES if c[0] == name)
    mesh = make()
    K, E = intrinsics(), look_at(eye)
    return (mesh, K, E, *reference(mesh, K, E))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", [c[0] for c in CASES])
def test_matches_ray_casting(name, dtype, backend):
    mesh, K, E, ref_fid, ref_depth, ref_hit = _case(name)
    V = torch.tensor(mesh.vertices, dtype=dtype)
    frags = rasterize(V, torch.tensor(mesh.faces), K.to(dtype), E.to(dtype), H, W, backend=backend)
    fid = frags.face_id[0].numpy()
    assert frags.face_id.shape == (1, H, W) and frags.bary.shape == (1, H, W, 3)
    assert frags.depth.shape == (1, H, W) and frags.face_id.dtype == torch.int64
    assert (ref_fid >= 0).sum() > 300

    # face ids: >= 99.5 % agree, and every disagreement is within 0.02 px of an edge
    agree = fid == ref_fid
    assert agree.mean() >= 0.995
    near_edge = np.minimum(edge_distance_px(mesh, K, E, fid), edge_distance_px(mesh, K, E, ref_fid))
    assert (near_edge[~agree] < 0.02).all(), near_edge[~agree]

    # depth and hit points where both see the same face
    both = agree & (fid >= 0)
    depth = frags.depth[0].double().numpy()
    assert np.abs(depth[both] - ref_depth[both]).max() < 1e-4 * ref_depth[both].max()
    assert np.isinf(depth[fid < 0]).all()
    b = frags.bary[0].double().numpy()
    hit = (b[..., None] * mesh.vertices[mesh.faces[fid.clip(0)]]).sum(-2)
    assert np.abs(hit[both] - ref_hit[both]).max() < 1e-4 * ref_depth[both].max()
    assert (b[fid < 0] == 0).all()
    np.testing.assert_allclose(b[fid >= 0].sum(-1), 1.0, atol=1e-5)
    assert b[fid >= 0].min() > -1e-3  # inside up to the 1/256 px snapping


def test_silhouette_has_no_holes(backend):
    mesh = bumpy_sphere(seed=3)
    K, E = intrinsics(), look_at((2.2, 2.0, 0.7))
    ref_fid, _, _ = reference(mesh, K, E)
    for cull in (False, True):
        frags = rasterize(torch.tensor(mesh.vertices), torch.tensor(mesh.faces), K, E, H, W, cull_backfaces=cull,
                          backend=backend)
        mask = frags.face_id[0].numpy() >= 0
        ref = ref_fid >= 0
        # every disagreement is on the silhouette, within 0.02 px of a face edge
        diff = mask != ref
        d = np.minimum(
            edge_distance_px(mesh, K, E, frags.face_id[0].numpy()), edge_distance_px(mesh, K, E, ref_fid)
        )
        assert (d[diff] < 0.02).all()
        # no holes: the mask is filled (each covered pixel's 4-neighbours inside the
        # reference silhouette are covered too)
        inner = ref.copy()
        inner[1:-1, 1:-1] &= ref[:-2, 1:-1] & ref[2:, 1:-1] & ref[1:-1, :-2] & ref[1:-1, 2:]
        assert mask[inner].all()


def _plane_camera(h, w, dtype=torch.float64):
    """Identity pose, K = I: a vertex (x, y, 1) projects exactly to pixel (u, v) = (x, y)."""
    return torch.eye(3, dtype=dtype), torch.eye(4, dtype=dtype)


def test_two_triangle_quad_covers_each_pixel_once(backend):
    K, E = _plane_camera(40, 50)
    for corners in ([(3, 4), (44, 4), (44, 35), (3, 35)], [(2.3, 3.7), (45.1, 5.2), (41.6, 36.9), (4.4, 33.3)]):
        q = torch.tensor([[x, y, 1.0] for x, y in corners], dtype=torch.float64)
        for diag in ([[0, 1, 2], [0, 2, 3]], [[0, 1, 3], [1, 2, 3]]):
            faces = torch.tensor(diag)
            count = coverage_count(q, faces, K, E, 40, 50, backend)
            ref = Delaunay(q[:, :2].numpy())
            jj, ii = np.meshgrid(np.arange(50), np.arange(40))
            inside = ref.find_simplex(np.stack([jj.ravel(), ii.ravel()], 1), tol=-1e-9).reshape(40, 50) >= 0
            assert count.max() <= 1
            assert (count.numpy()[inside] == 1).all()
            # the diagonal of the axis-aligned quad goes through pixel centres: each once
            both = rasterize(q, faces, K, E, 40, 50, backend=backend).face_id[0]
            assert ((both >= 0) == (count == 1)).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_triangulation_watertight_on_edges_and_vertices(seed, backend):
    """A planar triangulation with many vertices and edges exactly on pixel centres is
    covered exactly once inside its convex hull (fill rule at shared edges AND vertices),
    and the pixels on two opposite hull edges are taken exactly once between them."""
    rng = np.random.default_rng(seed)
    h, w = 24, 30
    pts = np.concatenate(
        [
            rng.integers(1, [w - 1, h - 1], size=(25, 2)).astype(np.float64),  # on pixel centres
            rng.uniform([0.5, 0.5], [w - 1.5, h - 1.5], size=(15, 2)),
            np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0], [10.0, 0.0], [0.0, 10.0]]),
        ]
    )
    pts = np.unique(pts, axis=0)
    tri = Delaunay(pts)
    verts = torch.tensor(np.concatenate([pts, np.ones((len(pts), 1))], 1))
    faces = torch.tensor(tri.simplices)
    faces[1::2] = faces[1::2].flip(1)  # mixed winding: front- and back-facing faces
    K, E = _plane_camera(h, w)
    count = coverage_count(verts, faces, K, E, h, w, backend)
    assert count.max() <= 1
    # strictly inside the hull (the image border rectangle) every pixel is covered once;
    # on the hull itself the fill rule keeps only the faces on the left of their edge
    assert (count[1:-1, 1:-1] == 1).all(), (count[1:-1, 1:-1] != 1).sum()
    assert (count[0] == 1).sum() + (count[-1] == 1).sum() in (w - 1, w, w + 1)


# --------------------------------------------------------------------------------------
# batching, chunking
# --------------------------------------------------------------------------------------


def _cams(C=3, dtype=torch.float64):
    eyes = [(3.0, -2.0, 1.0), (-2.5, -2.5, 0.5), (0.3, 3.4, -1.2), (2.0, 2.0, 2.0)][:C]
    E = torch.stack([look_at(e, dtype=dtype) for e in eyes])
    K = torch.stack([intrinsics(50 + 5 * i, dtype=dtype) for i in range(C)])
    return K, E


def test_batched_cameras_equal_one_by_one_and_per_camera_verts():
    mesh = bumpy_sphere(seed=5, subdivisions=2)
    V, Fc = torch.tensor(mesh.vertices), torch.tensor(mesh.faces)
    K, E = _cams(3)
    all_ = rasterize(V, Fc, K, E, H, W)
    per_cam = rasterize(V.expand(3, -1, -1), Fc, K, E, H, W)
    for c in range(3):
        one = rasterize(V, Fc, K[c], E[c], H, W)
        assert torch.equal(one.face_id[0], all_.face_id[c])
        torch.testing.assert_close(one.bary[0], all_.bary[c])
        torch.testing.assert_close(one.depth[0], all_.depth[c])
    for a, b in zip(all_, per_cam):
        torch.testing.assert_close(a, b)
    # a closed surface seen from outside shows front faces only: culling changes nothing
    culled = rasterize(V, Fc, K, E, H, W, cull_backfaces=True)
    assert torch.equal(culled.face_id, all_.face_id)
    # per-camera geometry: camera c sees the mesh moved by c * 0.1 along x
    shift = torch.tensor([0.1, 0.0, 0.0], dtype=V.dtype)
    Vc = torch.stack([V + c * shift for c in range(3)])
    moved = rasterize(Vc, Fc, K, E, H, W)
    for c in range(3):
        one = rasterize(V + c * shift, Fc, K[c], E[c], H, W)
        assert torch.equal(one.face_id[0], moved.face_id[c])


def test_chunking_does_not_change_the_result_and_big_faces_work():
    mesh = bumpy_sphere(seed=2)
    V, Fc = torch.tensor(mesh.vertices), torch.tensor(mesh.faces)
    # add a large quad right in front of camera 0 covering the whole image, behind the
    # near plane for none of its vertices
    K, E = _cams(2)
    Einv = torch.linalg.inv(E[0])
    quad_cam = torch.tensor([[-5.0, -5, 0.5, 1], [5, -5, 0.5, 1], [5, 5, 0.6, 1], [-5, 5, 0.6, 1]], dtype=V.dtype)
    quad = (quad_cam @ Einv.T)[:, :3]
    Vq = torch.cat([V, quad])
    n = len(V)
    Fq = torch.cat([Fc, torch.tensor([[n, n + 1, n + 2], [n, n + 2, n + 3]])])
    big = rasterize(Vq, Fq, K, E, 150, 200)
    assert (big.face_id[0] >= Fc.shape[0]).all()  # the quad hides everything
    assert (big.face_id[1] < Fc.shape[0]).all()  # camera 1 does not see it
    small = rasterize(Vq, Fq, K, E, 150, 200, faces_per_chunk=7, pixels_per_chunk=3000)
    for a, b in zip(big, small):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_warp_and_torch_backends_agree_on_a_hard_soup(dtype):
    """The Warp kernel and the batched torch code give the same face ids and depth keys on a
    triangle soup with everything the rasteriser must handle: interpenetrating faces, faces
    bigger than the torch path's 64-px tiles, vertices behind the near plane, far off screen
    and non-finite, degenerate faces, both windings (with and without culling), per-camera
    vertices."""
    g = torch.Generator().manual_seed(7)
    K, E = _cams(4, dtype=torch.float64)
    n = 300
    centres = torch.randn(n, 1, 3, generator=g, dtype=torch.float64) * 0.6
    size = torch.where(torch.rand(n, 1, 1, generator=g) < 0.1, 3.0, 0.15).double()
    V = (centres + size * torch.randn(n, 3, 3, generator=g, dtype=torch.float64)).reshape(-1, 3)
    V[5] = torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64)  # camera 0's centre: behind its near plane
    V[11] = torch.tensor([1e7, 3e6, 0.0], dtype=torch.float64)  # far off screen
    V[17] = float("nan")
    Fc = torch.arange(3 * n).view(n, 3)
    Fc[20] = torch.tensor([60, 60, 61])  # degenerate
    V, K, E = V.to(dtype), K.to(dtype), E.to(dtype)
    shift = torch.tensor([0.05, -0.02, 0.0], dtype=dtype)
    for verts in (V, torch.stack([V + c * shift for c in range(4)])):
        for cull in (False, True):
            w = rasterize(verts, Fc, K, E, 150, 200, cull_backfaces=cull, with_bary=False, backend="warp")
            t = rasterize(verts, Fc, K, E, 150, 200, cull_backfaces=cull, with_bary=False, backend="torch")
            assert (w.face_id >= 0).sum() > 5000
            assert torch.equal(w.face_id, t.face_id)
            # the quantised 1/z may differ by a unit in its last place (order of the sums)
            torch.testing.assert_close(w.depth, t.depth, rtol=1e-9 if dtype == torch.float64 else 2.5e-7, atol=0)
    with pytest.raises(ValueError, match="backend"):
        rasterize(V, Fc, K, E, 15, 20, backend="numpy")


# --------------------------------------------------------------------------------------
# differentiability
# --------------------------------------------------------------------------------------


def _small_scene(dtype=torch.float64):
    mesh = bumpy_sphere(seed=1, subdivisions=1)
    V = torch.tensor(mesh.vertices, dtype=dtype)
    Fc = torch.tensor(mesh.faces)
    K = torch.tensor([[14.0, 0, 7.3], [0, 14.5, 5.6], [0, 0, 1]], dtype=dtype)
    E = look_at((2.6, -1.7, 1.1), dtype=dtype)
    return V, Fc, K, E


def test_barycentrics_match_rasterize_and_gradcheck():
    V, Fc, K, E = _small_scene()
    frags = rasterize(V, Fc, K, E, 12, 15)
    assert (frags.face_id >= 0).sum() > 40
    torch.testing.assert_close(barycentrics(V, Fc, K, E, frags), frags.bary)
    attr = torch.randn(V.shape[0], 2, dtype=torch.float64)

    def f(v, a):
        return interpolate(a, Fc, frags, barycentrics(v, Fc, K, E, frags))

    assert torch.autograd.gradcheck(f, (V.clone().requires_grad_(), attr.clone().requires_grad_()))
    # per-corner attributes and per-camera vertices
    corner = torch.randn(Fc.shape[0], 3, 1, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda v, a: interpolate(a, Fc, frags, barycentrics(v[None], Fc, K[None], E[None], frags), per_corner=True),
        (V.clone().requires_grad_(), corner),
        fast_mode=True,
    )


def test_interpolate_matches_loop():
    V, Fc, K, E = _small_scene()
    frags = rasterize(V, Fc, K, E, 12, 15)
    attr = torch.randn(V.shape[0], 3, dtype=torch.float64)
    out = interpolate(attr, Fc, frags)
    for i in range(12):
        for j in range(15):
            f = int(frags.face_id[0, i, j])
            want = torch.zeros(3, dtype=torch.float64) if f < 0 else (frags.bary[0, i, j, :, None] * attr[Fc[f]]).sum(0)
            torch.testing.assert_close(out[0, i, j], want)


def test_antialias_gradcheck_and_rectangle_area():
    V, Fc, K, E = _small_scene()
    frags = rasterize(V, Fc, K, E, 12, 15)
    adj = face_adjacency(Fc)
    mask = (frags.face_id >= 0)[..., None].double()

    def f(v):
        col = interpolate(v[:, :1] * 0 + 1, Fc, frags, barycentrics(v, Fc, K, E, frags))
        return antialias(col, v, Fc, K, E, frags, adj)

    out = f(V)
    assert (out != mask).any()  # some silhouette pixels were blended
    assert torch.autograd.gradcheck(f, (V.clone().requires_grad_(),), fast_mode=True)

    # an axis-aligned rectangle: the antialiased coverage is close to the true area, and
    # moving an edge by dx changes it by (covered pixels along that edge) * dx
    Kp, Ep = _plane_camera(20, 30)
    x0, x1, y0, y1 = 4.3, 21.8, 3.6, 14.2
    q = torch.tensor([[x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1]], dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    fr = rasterize(q.detach(), faces, Kp, Ep, 20, 30)
    hard = (fr.face_id >= 0)[..., None].double()
    cov = antialias(hard, q, faces, Kp, Ep, fr)
    area = (x1 - x0) * (y1 - y0)
    assert abs(cov.sum() - area) < 0.5 and abs(cov.sum() - area) < abs(hard.sum() - area)
    cov.sum().backward()
    # nvdiffrast's rule: a pair of pixels counts for an edge if the covered pixel's own
    # face has that edge (near the corners the diagonal gives the pixel to the other face)
    rows = int((fr.face_id[0, 4:15, 21] == 0).sum())  # right edge belongs to face 0
    cols = int((fr.face_id[0, 14, 5:22] == 1).sum())  # bottom edge belongs to face 1
    assert rows >= 9 and cols >= 15
    torch.testing.assert_close(q.grad[1, 0] + q.grad[2, 0], torch.tensor(float(rows), dtype=torch.float64))
    torch.testing.assert_close(q.grad[2, 1] + q.grad[3, 1], torch.tensor(float(cols), dtype=torch.float64))


def test_face_adjacency_closed_mesh():
    m = trimesh.creation.icosphere(subdivisions=1)
    Fc = torch.tensor(m.faces)
    adj = face_adjacency(Fc)
    assert (adj >= 0).all()
    for f in range(len(Fc)):
        for k in range(3):
            g = int(adj[f, k])
            edge = {int(Fc[f, (k + 1) % 3]), int(Fc[f, (k + 2) % 3])}
            assert edge <= set(Fc[g].tolist()) and g != f
    # an open fan has boundary edges
    assert (face_adjacency(torch.tensor([[0, 1, 2], [0, 2, 3]])) == -1).sum() == 4


# --------------------------------------------------------------------------------------
# edge cases
# --------------------------------------------------------------------------------------


def test_near_plane_and_empty_scenes():
    V, Fc, K, E = _small_scene()
    frags = rasterize(V, Fc, K, E, 12, 15)
    # move the camera inside the mesh-ish region: faces crossing z = near are dropped
    E_in = look_at((0.4, -0.2, 0.1))
    fr = rasterize(V, Fc, K, E_in, 12, 15, near=0.3)
    uv, z = project_vertices(V, K, E_in)
    zf = z[0][Fc]  # (F, 3)
    drawn = fr.face_id[fr.face_id >= 0].unique()
    assert drawn.numel() > 0 and (zf[drawn] >= 0.3).all()
    crossing = (zf.min(1).values < 0.3) & (zf.max(1).values >= 0.3)
    assert crossing.any()  # there were faces across the near plane, and they are not drawn
    # everything behind the camera: all background
    E_back = E.clone()
    E_back[:3, :] *= torch.tensor([[-1.0], [1.0], [-1.0]], dtype=E.dtype)  # turn around (rotate 180 deg about y)
    fr = rasterize(V, Fc, K, E_back, 12, 15)
    assert (fr.face_id == -1).all() and torch.isinf(fr.depth).all() and (fr.bary == 0).all()
    # no faces at all
    fr = rasterize(V, Fc[:0], K, E, 12, 15)
    assert (fr.face_id == -1).all() and fr.face_id.shape == (1, 12, 15)
    assert frags.face_id.max() >= 0


def test_degenerate_faces_give_no_nan():
    V, Fc, K, E = _small_scene()
    n = V.shape[0]
    V2 = torch.cat([V, V[:1] * 0.5, V[:1] * 0.7])  # three collinear points with V[0] ... and the origin
    bad = torch.tensor([[0, 0, 1], [2, 2, 2], [0, n, n + 1]])
    F2 = torch.cat([bad, Fc, bad])
    frags = rasterize(V2, F2, K, E, 12, 15)
    assert not torch.isnan(frags.bary).any() and not torch.isnan(frags.depth).any()
    assert not torch.isin(frags.face_id, torch.tensor([0, 1, 2, F2.shape[0] - 3, F2.shape[0] - 2])).any()
    # barycentrics of degenerate winning faces (forced): 0, no NaN, finite gradient
    forced = Fragments(torch.zeros_like(frags.face_id), frags.bary, frags.depth)
    v = V2.clone().requires_grad_()
    b = barycentrics(v, F2, K, E, forced)
    assert (b == 0).all()
    b.sum().backward()
    assert torch.isfinite(v.grad).all()


def test_bad_shapes_raise():
    V, Fc, K, E = _small_scene()
    with pytest.raises(ValueError, match="faces"):
        rasterize(V, Fc[:, :2], K, E, 12, 15)
    with pytest.raises(ValueError, match="verts"):
        rasterize(V[:, :2], Fc, K, E, 12, 15)
    with pytest.raises(ValueError, match="K"):
        rasterize(V, Fc, K[:2], E, 12, 15)
    with pytest.raises(ValueError, match="camera counts"):
        rasterize(V, Fc, K.expand(2, 3, 3), E.expand(3, 4, 4), 12, 15)
    frags = rasterize(V, Fc, K, E, 12, 15)
    with pytest.raises(ValueError, match="attr"):
        interpolate(torch.zeros(5, 4, 2), Fc, frags)
    with pytest.raises(ValueError, match="texture"):
        sample_texture(torch.zeros(4, 4), torch.zeros(2, 2))


# --------------------------------------------------------------------------------------
# texture, shading, render_mesh
# --------------------------------------------------------------------------------------


def test_sample_texture_orientation_and_bilinear():
    tex = torch.zeros(4, 6, 3)
    tex[0] = torch.tensor([1.0, 0, 0])  # top row red
    tex[-1] = torch.tensor([0, 0, 1.0])  # bottom row blue
    uv = torch.tensor([[0.5, 1.0], [0.5, 0.0], [0.3, 1 - 0.5 / 4]])
    out = sample_texture(tex, uv)
    torch.testing.assert_close(out[0], torch.tensor([1.0, 0, 0]))
    torch.testing.assert_close(out[1], torch.tensor([0, 0, 1.0]))
    torch.testing.assert_close(out[2], torch.tensor([1.0, 0, 0]))
    # bilinear against a direct formula, random texture, inside texel centres
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(5, 7, 2, generator=g, dtype=torch.float64)
    inner = torch.rand(30, 2, generator=g, dtype=torch.float64)
    uv = inner * torch.tensor([6 / 7, 4 / 5]) + torch.tensor([0.5 / 7, 0.5 / 5])
    out = sample_texture(tex, uv)
    for n in range(30):
        x, y = uv[n, 0] * 7 - 0.5, (1 - uv[n, 1]) * 5 - 0.5
        j, i = int(x), int(y)
        a, b = x - j, y - i
        want = (1 - a) * (1 - b) * tex[i, j] + a * (1 - b) * tex[i, j + 1]
        want = want + (1 - a) * b * tex[i + 1, j] + a * b * tex[i + 1, j + 1]
        torch.testing.assert_close(out[n], want)
    # wrap modes and mask
    edge = torch.tensor([[0.0, 0.5]], dtype=torch.float64)
    left, right = tex[2, 0], tex[2, -1]
    torch.testing.assert_close(sample_texture(tex, edge)[0], left)
    torch.testing.assert_close(sample_texture(tex, edge, wrap="repeat")[0], (left + right) / 2)
    m = torch.tensor([True, False, True])
    out = sample_texture(tex, uv[:3], mask=m)
    assert (out[1] == 0).all() and torch.equal(out[0], sample_texture(tex, uv[:1])[0])
    for wrap in ("clamp", "repeat"):
        args = (tex[:3, :3].clone().requires_grad_(), (uv[:4] * 0.9).clone().requires_grad_())
        assert torch.autograd.gradcheck(lambda t, u: sample_texture(t, u, wrap=wrap), args)


def test_project_vertices():
    K = torch.tensor([[100.0, 0.0, 32.0], [0.0, 90.0, 24.0], [0.0, 0.0, 1.0]])
    E = torch.eye(4)
    E[:3, 3] = torch.tensor([0.1, -0.2, 2.0])
    uv, z = project_vertices(torch.tensor([[0.0, 0.0, 0.0], [0.4, 0.2, 2.0]]), K, E)
    torch.testing.assert_close(z, torch.tensor([[2.0, 4.0]]))
    torch.testing.assert_close(uv, torch.tensor([[[32 + 100 * 0.05, 24 - 90 * 0.1], [32 + 100 * 0.5 / 4, 24 + 0.0]]]))


def test_shade_lambert():
    albedo = torch.full((1, 1, 2, 3), 0.5)
    normals = torch.tensor([[[[0.0, 0, 1], [0, 0, -1]]]])
    dirs = torch.tensor([[0.0, 0, 2.0], [1.0, 0, 0]])
    cols = torch.tensor([[1.0, 0.5, 0.0], [1.0, 1.0, 1.0]])
    out = shade_lambert(albedo, normals, dirs, cols, torch.tensor([0.1, 0.1, 0.1]))
    torch.testing.assert_close(out[0, 0, 0], 0.5 * torch.tensor([1.1, 0.6, 0.1]))
    torch.testing.assert_close(out[0, 0, 1], 0.5 * torch.tensor([0.1, 0.1, 0.1]))
    two = shade_lambert(albedo, normals, dirs, cols, torch.zeros(3), two_sided=True)
    torch.testing.assert_close(two[0, 0, 1], 0.5 * torch.tensor([1.0, 0.5, 0.0]))
    assert shade_lambert(torch.ones_like(albedo), normals, dirs * 1, cols * 5, torch.zeros(3)).max() == 1.0
    # per-camera lights (C, L, 3)
    alb2 = albedo.expand(2, 1, 2, 3)
    n2 = normals.expand(2, 1, 2, 3)
    d2 = torch.stack([dirs, -dirs])
    out2 = shade_lambert(alb2, n2, d2, cols.expand(2, 2, 3), torch.zeros(3))
    torch.testing.assert_close(out2[0], shade_lambert(albedo, normals, dirs, cols, torch.zeros(3))[0])
    torch.testing.assert_close(out2[1], shade_lambert(albedo, normals, -dirs, cols, torch.zeros(3))[0])


def test_render_mesh():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.vertices *= [1.0, 0.7, 1.2]
    V = torch.tensor(mesh.vertices, dtype=torch.float32)
    Fc = torch.tensor(mesh.faces)
    K, E = _cams(2, torch.float32)
    face_uv = torch.rand(Fc.shape[0], 3, 2, generator=torch.Generator().manual_seed(0))
    tex = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(1))
    r = render_mesh(
        V, Fc, K, E, H, W, face_uv=face_uv, texture=tex,
        light_dirs=torch.tensor([[0.0, 0.0, 1.0]]), light_colors=torch.tensor([[0.8, 0.8, 0.8]]),
        ambient=torch.tensor([0.2, 0.2, 0.2]), background=torch.tensor([0.0, 1.0, 0.0]),
    )
    assert r.rgb.shape == (2, H, W, 3) and r.mask.shape == (2, H, W) and r.normals_cam.shape == (2, H, W, 3)
    assert r.rgb.min() >= 0 and r.rgb.max() <= 1
    assert (r.rgb[~r.mask] == torch.tensor([0.0, 1.0, 0.0])).all()
    n = r.normals_cam[r.mask]
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(n.shape[0]))
    # normals face the camera: n . X_cam < 0 (X_cam = depth * K^-1 [j, i, 1])
    ii, jj = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    ray = torch.stack([jj, ii, torch.ones_like(ii)], -1).float()
    for c in range(2):
        d = ray @ torch.linalg.inv(K[c]).T
        m = r.mask[c]
        assert ((r.normals_cam[c][m] * d[m]).sum(-1) < 0).float().mean() > 0.97
    # an open surface seen from behind still gets camera-facing normals
    half = Fc[mesh.triangles_center[:, 0] > 0]
    rb = render_mesh(V, half, K, E, H, W, vertex_colors=torch.ones_like(V) * 0.5)
    for c in range(2):
        d = ray @ torch.linalg.inv(K[c]).T
        m = rb.mask[c]
        assert ((rb.normals_cam[c][m] * d[m]).sum(-1) < 0).float().mean() > 0.97
    torch.testing.assert_close(rb.rgb[rb.mask], torch.full_like(rb.rgb[rb.mask], 0.5))
    # gradients reach the vertices (inside faces) and the texture
    v = V.clone().requires_grad_()
    t = tex.clone().requires_grad_()
    rg = render_mesh(v, Fc, K, E, H, W, face_uv=face_uv, texture=t, light_dirs=torch.tensor([[0.0, 0.0, 1.0]]))
    rg.rgb.sum().backward()
    assert v.grad.abs().sum() > 0 and t.grad.abs().sum() > 0
