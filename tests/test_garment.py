"""Garment templates: procedural skirt/dress, remeshing, band, body attachment, skinning."""
import numpy as np
import pytest
import torch
import trimesh

from anidress_core import garment as G
from anidress_core.body.model import mannequin_model
from anidress_core.body.motions import make_motion

TARGET = 2000


@pytest.fixture(scope="module")
def body():
    return mannequin_model()


@pytest.fixture(scope="module")
def skirt(body):
    return G.make_skirt(body, target_vertices=TARGET)


@pytest.fixture(scope="module")
def dress(body):
    return G.make_dress(body, target_vertices=TARGET)


def _is_edge_manifold(faces):
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    _, cnt = np.unique(e, axis=0, return_counts=True)
    return cnt.max() <= 2


def _check_clean(tpl, n_loops):
    v, f = tpl.verts.astype(np.float64), tpl.faces
    assert _is_edge_manifold(f)
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_winding_consistent
    assert len(np.unique(f)) == len(v)  # no unreferenced vertex
    assert len(trimesh.graph.connected_components(m.edges)) == 1
    loops = G.boundary_loops(f)
    assert len(loops) == n_loops
    # every boundary vertex lies on exactly one loop (a manifold boundary)
    allb = np.concatenate(loops)
    assert len(allb) == len(np.unique(allb))
    areas = m.area_faces
    assert areas.min() > 1e-8


@pytest.mark.parametrize("name,loops", [("skirt", 2), ("dress", 4)])
def test_procedural_garment_is_clean_and_outside_body(name, loops, request, body):
    tpl = request.getfixturevalue(name)
    assert tpl.kind == name
    _check_clean(tpl, loops)
    assert abs(tpl.num_vertices - TARGET) <= 0.05 * TARGET
    d, inside = G.body_clearance(tpl.verts, body)
    assert not inside.any()
    assert d.min() >= 0.005
    # normals point away from the body
    bv = body.v_template.numpy()
    c = tpl.verts[tpl.faces].mean(1)
    n = np.cross(*(tpl.verts[tpl.faces][:, k] - tpl.verts[tpl.faces][:, 0] for k in (1, 2)))
    away = c - bv[np.argmin(((c[:, None] - bv[None, ::7]) ** 2).sum(-1), 1) * 7]
    assert (np.einsum("fi,fi->f", n, away) > 0).mean() > 0.9
    # UVs per corner, inside [0, 1], no face spans the seam
    assert tpl.face_uv.shape == (len(tpl.faces), 3, 2)
    assert tpl.face_uv.min() >= -1e-6 and tpl.face_uv.max() <= 1 + 1e-6
    assert np.ptp(tpl.face_uv[..., 0], axis=1).max() < 0.2


def test_skirt_shape(skirt, body):
    v = skirt.verts
    loops = G.boundary_loops(skirt.faces)
    top = max(loops, key=lambda lp: v[lp, 1].mean())
    hem = min(loops, key=lambda lp: v[lp, 1].mean())
    yw = G.waist_height(body)
    assert abs(v[top, 1].mean() - yw) < 0.01
    assert 0.5 < v[top, 1].mean() - v[hem, 1].mean() < 0.6  # knee length
    # flared: the hem is much wider than the waist
    r = lambda lp: np.hypot(v[lp, 0], v[lp, 2]).mean()  # noqa: E731
    assert r(hem) > 1.5 * r(top)
    # the waist band hugs the body
    d, _ = G.body_clearance(v[top], body)
    assert d.max() < 0.03


def test_band_found(skirt, dress, body):
    assert skirt.band.any() and skirt.band.mean() < 0.2
    top = max(G.boundary_loops(skirt.faces), key=lambda lp: skirt.verts[lp, 1].mean())
    assert skirt.band[top].all()
    assert dress.band.any() and dress.band.mean() < 0.2
    # dress band = straps over the shoulders, both sides
    bandv = dress.verts[dress.band]
    assert (bandv[:, 0] > 0.03).any() and (bandv[:, 0] < -0.03).any()
    assert bandv[:, 1].min() > body.joints_rest[13, 1].item() - 0.05
    with pytest.raises(ValueError, match="kind"):
        G.band_vertices(skirt.verts, skirt.faces, "trousers", body)


def test_attach_weights_convex_and_exact_on_body(body, skirt):
    bv = body.v_template.numpy().astype(np.float64)
    idx = np.array([0, 100, 2500, 4000, 6400])
    pts = np.concatenate([bv[idx], skirt.verts[:50]])
    tri = np.array([[0, 1, 2]])
    for smoothing in (0.0,):
        W = G.attach_to_body(pts, tri, body, smoothing=smoothing)
        assert W.shape == (len(pts), 24)
        assert W.min() >= 0 and np.allclose(W.sum(1), 1)
        np.testing.assert_allclose(W[: len(idx)], body.weights.numpy()[idx], atol=1e-5)
    Ws = skirt.body_weights
    assert Ws.min() >= 0 and np.allclose(Ws.sum(1), 1, atol=1e-5)


def test_smoothed_weights_do_not_split_the_hem(skirt, body):
    raw = G.attach_to_body(skirt.verts, skirt.faces, body, smoothing=0.0)
    sm = G.attach_to_body(skirt.verts, skirt.faces, body, smoothing=2.0, anchors=skirt.band)
    hem = min(G.boundary_loops(skirt.faces), key=lambda lp: skirt.verts[lp, 1].mean())
    # neighbouring hem vertices: raw weights jump between the legs, smoothed ones do not
    jump = lambda W: np.abs(W[hem] - W[np.roll(hem, 1)]).sum(1).max()  # noqa: E731
    assert jump(sm) < jump(raw)
    np.testing.assert_allclose(sm[skirt.band], raw[skirt.band], atol=0.02)
    assert sm.min() >= 0 and np.allclose(sm.sum(1), 1)


def test_closest_points_matches_trimesh(body):
    rng = np.random.default_rng(0)
    q = rng.uniform(-0.5, 0.5, (300, 3))
    bv, bf = body.v_template.numpy().astype(np.float64), body.faces.numpy()
    cp = G.closest_points(q, bv, bf)
    _, d_ref, _ = trimesh.proximity.closest_point(trimesh.Trimesh(bv, bf, process=False), q)
    np.testing.assert_allclose(cp.distance, d_ref, atol=1e-9)
    np.testing.assert_allclose(np.einsum("ni,nij->nj", cp.bary, bv[bf[cp.face]]), cp.points, atol=1e-12)
    assert cp.bary.min() >= -1e-12


def test_skin_rest_reproduces_template(skirt, body):
    rest = body.pose(torch.zeros(1, 72)).transforms.double()
    out = skirt.skin(rest)
    assert out.shape == (1, skirt.num_vertices, 3)
    np.testing.assert_allclose(out[0].numpy(), skirt.verts, atol=1e-5)
    np.testing.assert_allclose(skirt.skin(rest[0].numpy()), skirt.verts, atol=1e-5)


def test_band_follows_body_when_walking(skirt, dress, body):
    m = make_motion("walk", 20, body=body)
    posed = body.pose(m.poses[[5, 15]], m.Rh[[5, 15]], m.Th[[5, 15]])
    for tpl in (skirt, dress):
        g = tpl.skin(posed.transforms)
        for t in range(2):
            bv = posed.vertices[t].numpy().astype(np.float64)
            d = G.closest_points(g[t].numpy()[tpl.band], bv, body.faces.numpy()).distance
            d_rest, _ = G.body_clearance(tpl.verts[tpl.band], body)
            assert d.max() < d_rest.max() + 0.02


def test_clean_and_remesh_repairs_a_dirty_mesh():
    # a 40x20 grid cylinder (open at both ends), then duplicated vertices + degenerate faces
    n, r = 40, 20
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ys = np.linspace(0, 0.5, r)
    v = np.stack([0.2 * np.sin(th)[None].repeat(r, 0), ys[:, None].repeat(n, 1), 0.2 * np.cos(th)[None].repeat(r, 0)], -1).reshape(-1, 3)
    f = G.grid_faces(r, n, wrap=True)
    dup = np.arange(0, len(v), 3)
    v2 = np.concatenate([v, v[dup]])
    f2 = f.copy()
    f2[::5] = np.where(np.isin(f2[::5], dup), len(v) + np.searchsorted(dup, f2[::5]), f2[::5])  # use the copies
    degen = np.array([[0, 0, 1], [5, 6, 5], [10, 11, 12]])  # two repeated-index faces and a duplicate
    degen[2] = f[7]
    f2 = np.concatenate([f2, degen, f2[:3, ::-1]])  # plus reversed duplicates
    f2[1::2] = f2[1::2, ::-1]  # scrambled orientation
    rv, rf = G.clean_and_remesh(v2, f2, 600)
    assert abs(len(rv) - 600) <= 30
    assert _is_edge_manifold(rf)
    assert trimesh.Trimesh(rv, rf, process=False).is_winding_consistent
    assert len(G.boundary_loops(rf)) == 2
    t = rv[rf]
    assert np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).min() > 1e-10
    # still the same cylinder: radius 0.2, height 0.5
    np.testing.assert_allclose(np.hypot(rv[:, 0], rv[:, 2]), 0.2, atol=0.01)
    assert abs(np.ptp(rv[:, 1]) - 0.5) < 1e-3


def test_transfer_uv_follows_the_parametrisation(body):
    v, f, uv = G.skirt_surface(body)
    rv, rf = G.clean_and_remesh(v, f, 1500)
    out = G.transfer_uv(v, f, uv, rv, rf)
    ref = G.cylindrical_uv(rv, rf, (0.5 * (v[:, 0].min() + v[:, 0].max()), 0.0), (v[:, 1].min(), v[:, 1].max()))
    # v (height) matches exactly up to the projection; u up to the seam rescale
    np.testing.assert_allclose(out[..., 1], ref[..., 1], atol=0.01)
    assert np.ptp(out[..., 0], axis=1).max() < 0.2  # no face stretched across the seam


def test_prepare_template_validates(body, skirt):
    v, f = skirt.verts.astype(np.float64), skirt.faces
    with pytest.raises(ValueError, match="units"):
        G.prepare_template(v * 1000, f, None, "skirt", body, 1000)
    with pytest.raises(ValueError, match="millimetres"):
        G.prepare_template(v * 1000, f, None, "skirt", body, 1000)
    with pytest.raises(ValueError, match="away from the body"):
        G.prepare_template(v + np.array([5.0, 0, 0]), f, None, "skirt", body, 1000)
    with pytest.raises(ValueError, match="no faces"):
        G.prepare_template(v, np.zeros((0, 3), int), None, "skirt", body, 1000)
    bad = v.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        G.prepare_template(bad, f, None, "skirt", body, 1000)
    with pytest.raises(ValueError, match="kind"):
        G.prepare_template(v, f, None, "cape", body, 1000)


def test_prepare_template_on_user_mesh_keeps_uvs(body, skirt):
    # a user template: the skirt with its own UVs, re-prepared at another resolution
    tpl = G.prepare_template(skirt.verts, skirt.faces, skirt.face_uv, "skirt", body, 1200)
    assert abs(tpl.num_vertices - 1200) <= 60
    assert tpl.band.any() and len(G.boundary_loops(tpl.faces)) == 2
    assert np.ptp(tpl.face_uv[..., 0], axis=1).max() < 0.2


def test_run_template_writes_artifacts(tmp_path, body, skirt):
    from anidress_core.io.files import load_npz
    from anidress_core.io.mesh import read_mesh, write_obj
    from anidress_core.io.template import read_template
    from anidress_core.stages.template import run_template

    src = tmp_path / "garment" / "template.obj"
    src.parent.mkdir()
    write_obj(src, skirt.verts, skirt.faces, skirt.face_uv)
    ply, npz = tmp_path / "out" / "template.ply", tmp_path / "out" / "template.npz"
    tpl = run_template(src, "skirt", body, 1000, ply, npz, config={"target_vertices": 1000})
    v, f, _ = read_mesh(ply)
    np.testing.assert_allclose(v, tpl.verts, atol=1e-6)
    raw = trimesh.load(ply, process=False).metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(raw["band"].astype(bool), tpl.band)
    arrays, header = load_npz(npz)
    assert str(arrays["kind"]) == "skirt" and header["meta"]["vertices_inside_body"] == 0
    back = read_template(npz)
    np.testing.assert_array_equal(back.faces, tpl.faces)
    np.testing.assert_allclose(back.body_weights, tpl.body_weights)
    # a template in millimetres: the error names the file and the units
    write_obj(src, skirt.verts * 1000, skirt.faces)
    with pytest.raises(ValueError, match="template.obj.*units"):
        run_template(src, "skirt", body, 1000, ply, npz)
