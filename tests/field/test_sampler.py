"""Sampling that skips what is empty: mask boxes, occupancy from posed meshes, joint candidates, marching."""
import torch

from anidress_core.field.sampler import SurfacePart, box_pixels, build_occupancy, march, mask_boxes


def _tetra_part(T=2, K=3, dilate=0.05):
    """A small closed tetrahedron per frame, translated, with weights on joints 0 and 1."""
    v = torch.tensor([[0.0, 0, 0], [0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.3]])
    f = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    verts = torch.stack([v + torch.tensor([t * 1.0, 0, 0]) for t in range(T)])
    w = torch.zeros(4, K)
    w[:, 0] = torch.tensor([1.0, 0.7, 0.5, 0.2])
    w[:, 1] = 1 - w[:, 0]
    return SurfacePart(verts, f, w, dilate)


def test_mask_boxes_dilate_and_clip():
    m = torch.zeros(3, 20, 30, dtype=torch.bool)
    m[0, 5:8, 10:12] = True
    m[1, 0:2, 28:30] = True
    b = mask_boxes(m, 2)
    assert b[0].tolist() == [3, 10, 8, 14]
    assert b[1].tolist() == [0, 4, 26, 30]
    assert b[2].tolist() == [0, 0, 0, 0]  # empty mask: no rays
    ys, xs = box_pixels(b[0])
    assert ys.numel() == 7 * 6 and m[0, 5, 10] and ((ys == 5) & (xs == 10)).any()


def test_occupancy_covers_the_surface_and_lists_its_joints():
    part = _tetra_part()
    grid = build_occupancy([part], (32, 32, 32), max_joints=2)
    assert grid.index.shape == (2, 32 ** 3) and grid.cand.shape[1] == 2
    for t in range(2):
        # every surface point is occupied, with joints 0 and 1 as candidates, never joint 2
        s = torch.rand(300, 2)
        s = s / s.sum(1, keepdim=True).clamp_min(1) * 0.999
        pts = torch.cat([part.verts[t], part.verts[t, 0] + s[:, :1] * (part.verts[t, 1] - part.verts[t, 0])
                         + s[:, 1:] * (part.verts[t, 2] - part.verts[t, 0])])
        row, inside = grid.lookup(torch.full((pts.shape[0],), t), pts)
        assert inside.all() and (row >= 0).all()
        c = grid.cand[row].long()
        assert ((c == 0) | (c == 1)).all()
    # far from the surface: empty; most of the grid is empty
    row, _ = grid.lookup(torch.tensor([0]), torch.tensor([[0.1, 0.1, 0.5]]))
    assert row.item() == -1
    assert grid.occupied_fraction() < 0.5


def test_march_keeps_occupied_samples_sorted_by_ray_and_depth():
    part = _tetra_part(T=1)
    grid = build_occupancy([part], (32, 32, 32), max_joints=2)
    o = torch.tensor([[0.05, 0.05, -2.0], [0.05, 0.05, -2.0], [5.0, 5.0, -2.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    fr = torch.zeros(3, dtype=torch.long)
    s = march(o, d, fr, grid, 0.01)
    assert s.ray.numel() > 0 and (s.ray != 2).all()  # the third ray misses the grid
    key = s.ray * 100 + s.t
    assert (key[1:] >= key[:-1]).all()
    row, _ = grid.lookup(fr[s.ray], s.x)
    assert (row >= 0).all()
    # without occupancy every in-box sample is kept (a superset), with all joints for the empty ones
    s_all = march(o, d, fr, grid, 0.01, use_occupancy=False)
    assert s_all.ray.numel() > s.ray.numel() and s_all.considered == s.considered
    assert s_all.cand.shape[1] == grid.num_joints
    # jittered samples come from the generator; one offset per ray, so a ray's samples stay
    # on a grid of exactly one step (shifted from the midpoints by less than a step)
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    a = march(o, d, fr, grid, 0.01, generator=g1, jitter=True)
    b = march(o, d, fr, grid, 0.01, generator=g2, jitter=True)
    assert torch.equal(a.t, b.t)
    offsets = []
    for r in (0, 1):
        t_mid, t_jit = s.t[s.ray == r].double(), a.t[a.ray == r].double()
        frac = (t_jit - t_jit[0]) / 0.01
        assert torch.allclose(frac, frac.round(), atol=1e-3)  # the gaps are whole steps
        shift = (t_jit[0] - t_mid[0]) / 0.01 + 0.5  # the offset in [0, 1) of the step
        offsets.append(float(shift - shift.floor()))
    assert offsets[0] != offsets[1]  # two identical rays, two offsets


def test_wide_margin_path_covers_the_margin_with_candidates():
    """The separable max filter (wide margins) covers at least what the ball splat covers."""
    part = _tetra_part(T=1, dilate=0.2)
    ball = build_occupancy([part], (32, 32, 32), max_joints=2)
    box = build_occupancy([part], (32, 32, 32), max_joints=2, max_splat=0)  # force the filter
    occ_ball, occ_box = ball.index[0] >= 0, box.index[0] >= 0
    assert occ_box[occ_ball].all() and occ_box.sum() >= occ_ball.sum()
    v = part.verts[0]
    pts = torch.cat([v, v + torch.tensor([0.0, 0.0, -0.19]), v + torch.tensor([-0.19, 0.0, 0.0])])
    for grid in (ball, box):
        row, inside = grid.lookup(torch.zeros(pts.shape[0], dtype=torch.long), pts)
        assert inside.all() and (row >= 0).all()
        c = grid.cand[row].long()
        assert ((c == 0) | (c == 1)).all() and (c[:, 0] == 0).any()


def test_march_kernel_matches_the_torch_path():
    """The Warp marcher against the torch one: the same samples (rays, depths, points, candidates) on
    rays through, beside and behind the subject, with jitter, in two frames; and an empty batch."""
    part = _tetra_part(T=2)
    grid = build_occupancy([part], (32, 32, 32), max_joints=2)
    g = torch.Generator().manual_seed(0)
    n = 400
    o = torch.cat([torch.rand(n, 3, generator=g) * torch.tensor([1.6, 0.5, 0.0]) + torch.tensor([-0.2, -0.1, -2.0]),
                   torch.tensor([[9.0, 9.0, -2.0], [0.05, 0.05, 3.0]])])  # far beside; behind, looking away
    d = torch.cat([torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.05 + torch.tensor([0, 0, 1.0]),
                                                 dim=-1), torch.tensor([[0.0, 0, 1], [0.0, 0, 1]])])
    fr = torch.randint(2, (n + 2,), generator=g)
    for jitter in (False, True):
        a = march(o, d, fr, grid, 0.01, generator=torch.Generator().manual_seed(4), jitter=jitter, backend="warp")
        b = march(o, d, fr, grid, 0.01, generator=torch.Generator().manual_seed(4), jitter=jitter, backend="torch",
                  chunk=n + 2)  # one chunk: the same jitter draws
        assert a.ray.numel() > 100 and not (a.ray >= n).any()
        assert torch.equal(a.ray, b.ray) and torch.equal(a.cand, b.cand) and a.considered == b.considered
        assert torch.allclose(a.t, b.t, atol=1e-6) and torch.allclose(a.x, b.x, atol=1e-6)
    e = march(o[:0], d[:0], fr[:0], grid, 0.01, backend="warp")
    assert e.ray.shape == (0,) and e.x.shape == (0, 3) and e.considered == 0
