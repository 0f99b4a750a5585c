import numpy as np
import pytest
import torch
import trimesh

from anidress_core.body import mannequin as mq
from anidress_core.body.kinematic import JOINT_INDEX, SMPL_PARENTS


@pytest.fixture(scope="module")
def data(mannequin):
    """The cached MannequinData behind the session's mannequin BodyModel."""
    return mq.load_or_build_mannequin()


def test_mesh_is_closed_manifold_and_oriented(mannequin):
    m = trimesh.Trimesh(mannequin.v_template.numpy(), mannequin.faces.numpy(), process=False)
    assert m.is_watertight
    assert m.is_winding_consistent
    assert m.volume > 0.03  # m^3, outward normals; an adult is ~0.05-0.08
    assert m.euler_number == 2  # one genus-0 component
    assert len(m.split(only_watertight=False)) == 1
    # No degenerate or duplicated triangles.
    assert m.area_faces.min() > 1e-7
    assert len(np.unique(np.sort(mannequin.faces.numpy(), 1), axis=0)) == len(mannequin.faces)


def test_size_and_proportions(mannequin):
    v = mannequin.v_template
    assert 5000 <= v.shape[0] <= 8000
    assert v.shape[0] == 6500  # the default target is met exactly for a genus-0 mesh
    height = float(v[:, 1].max() - v[:, 1].min())
    assert abs(height - 1.70) / 1.70 < 0.02
    J = mannequin.joints_rest
    assert torch.allclose(J[0], torch.zeros(3))  # pelvis at the origin
    # T-pose, facing +z: arm span about the height, left side at +x.
    span = float(v[:, 0].max() - v[:, 0].min())
    assert 0.9 * height < span < 1.1 * height
    assert J[JOINT_INDEX["left_wrist"], 0] > 0.5 and J[JOINT_INDEX["right_wrist"], 0] < -0.5
    assert J[JOINT_INDEX["head"], 1] > J[JOINT_INDEX["neck"], 1] > J[JOINT_INDEX["spine3"], 1] > 0
    assert J[JOINT_INDEX["left_foot"], 2] > J[JOINT_INDEX["left_ankle"], 2]  # toes forward
    # Left/right symmetric skeleton.
    mirror = J.clone()
    mirror[:, 0] *= -1
    for n in ("hip", "knee", "ankle", "foot", "collar", "shoulder", "elbow", "wrist", "hand"):
        torch.testing.assert_close(mirror[JOINT_INDEX[f"left_{n}"]], J[JOINT_INDEX[f"right_{n}"]])
    # Joints inside the body's bounding box; the mesh is the rest pose of joints_rest.
    assert torch.equal(mannequin.parents, torch.tensor(SMPL_PARENTS))


def test_weights_convex_and_sensible(mannequin):
    W = mannequin.weights
    assert W.shape == (mannequin.v_template.shape[0], 24)
    assert (W >= 0).all()
    torch.testing.assert_close(W.sum(1), torch.ones(W.shape[0]), atol=1e-5, rtol=0)
    names = mannequin.part_names
    dominant = W.argmax(1)
    vp = mannequin.vertex_part

    def frac(part, joints):
        sel = vp == names.index(part)
        ok = torch.isin(dominant[sel], torch.tensor([JOINT_INDEX[j] for j in joints]))
        return ok.float().mean().item()

    assert frac("head", ["head", "neck"]) > 0.95
    assert frac("left_hand", ["left_wrist", "left_hand", "left_elbow"]) > 0.95
    assert frac("right_lower_leg", ["right_knee", "right_hip", "right_ankle"]) > 0.95
    assert frac("left_foot", ["left_ankle", "left_foot", "left_knee"]) > 0.95
    # Smooth: weights change gradually along edges (no hard seams).
    e = np.concatenate([mannequin.faces[:, [0, 1]].numpy(), mannequin.faces[:, [1, 2]].numpy()])
    jump = (W[e[:, 0]] - W[e[:, 1]]).abs().sum(1)
    assert jump.max() < 0.6
    # Blends exist around the big joints (not rigid segments).
    for j in ("left_shoulder", "right_hip", "left_knee", "right_elbow"):
        w = W[:, JOINT_INDEX[j]]
        assert ((w > 0.2) & (w < 0.8)).sum() > 20


def test_parts_and_uvs(mannequin, data):
    names = mannequin.part_names
    assert names == mq.PART_NAMES
    vp = mannequin.vertex_part
    assert vp.dtype == torch.int64 and int(vp.min()) >= 0 and int(vp.max()) < len(names)
    assert (torch.bincount(vp, minlength=len(names)) > 20).all()  # every part present
    v = mannequin.v_template
    for n in names:
        c = v[vp == names.index(n)].mean(0)
        if n.startswith("left_"):
            assert c[0] > 0.03
        if n.startswith("right_"):
            assert c[0] < -0.03
    assert v[vp == names.index("head"), 1].mean() > v[vp == names.index("torso"), 1].mean()
    uv = mannequin.face_uv
    assert uv.shape == (mannequin.faces.shape[0], 3, 2)
    assert (uv >= 0).all() and (uv <= 1).all()
    # One chart per part: the charts' bounding boxes do not overlap.
    fp = torch.from_numpy(data.face_part)
    boxes = []
    for p in range(len(names)):
        c = uv[fp == p].reshape(-1, 2)
        boxes.append((c.min(0).values, c.max(0).values))
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            lo = torch.maximum(boxes[i][0], boxes[j][0])
            hi = torch.minimum(boxes[i][1], boxes[j][1])
            assert ((hi - lo) <= 1e-6).any(), (names[i], names[j])
    # Seams are cut per corner: no face spans a large part of the atlas.
    span = uv.max(1).values - uv.min(1).values
    assert span.max() < 0.08
    # Charts keep the surface orientation almost everywhere (folds at the shoulders
    # and crotch of the cylindrical torso chart flip a few triangles).
    a = (uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1]) - (uv[:, 2, 0] - uv[:, 0, 0]) * (uv[:, 1, 1] - uv[:, 0, 1])
    assert (a < 0).float().mean() < 0.03
    assert (a.abs() > 0).all()


def test_cache_round_trip(mannequin, mannequin_cache, data, monkeypatch):
    files = list(mannequin_cache.glob("mannequin_*.npz"))
    assert len(files) == 1
    again = mq.load_or_build_mannequin()  # read back from the npz
    np.testing.assert_array_equal(again.vertices, mannequin.v_template.numpy())
    np.testing.assert_array_equal(again.faces, mannequin.faces.numpy())
    np.testing.assert_array_equal(again.face_uv, mannequin.face_uv.numpy())
    assert again.part_names == mannequin.part_names
    assert not list(mannequin_cache.glob("*.tmp*"))  # atomic write left no temp file
    # Another parameter set gets another file; a corrupt file is rebuilt, not trusted.
    calls = []
    monkeypatch.setattr(mq, "build_mannequin", lambda h, n: calls.append((h, n)) or data)
    path = mq.cache_path(1.61, 5000)
    assert path.parent == mannequin_cache and path != files[0]
    path.write_bytes(b"not an npz")
    mq.load_or_build_mannequin(1.61, 5000)
    assert calls == [(1.61, 5000)]
    mq.load_or_build_mannequin(1.61, 5000)  # now a valid cache hit
    assert calls == [(1.61, 5000)]


def test_build_is_deterministic_and_parametric():
    a = mq.build_mannequin(height=1.55, target_vertices=3000, voxel=0.012)
    b = mq.build_mannequin(height=1.55, target_vertices=3000, voxel=0.012)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.weights, b.weights)
    np.testing.assert_array_equal(a.face_uv, b.face_uv)
    assert abs(a.height - 1.55) < 1e-6
    assert abs(float(np.ptp(a.vertices[:, 1])) - 1.55) / 1.55 < 0.02
    assert 2700 <= len(a.vertices) <= 3300
    m = trimesh.Trimesh(a.vertices, a.faces, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="height"):
        mq.build_mannequin(height=5.0)
    with pytest.raises(ValueError, match="target_vertices"):
        mq.build_mannequin(target_vertices=10)
