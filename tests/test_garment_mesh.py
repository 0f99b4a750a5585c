"""Defect checks of a garment mesh (anidress_core.garment_mesh.mesh_defects); clean_and_remesh is tested in
test_garment.py."""
import numpy as np

from anidress_core.garment_mesh import mesh_defects


def test_mesh_defects_counts_each_kind():
    # two triangles of a unit square, one vertex duplicated (merged), one duplicate face,
    # one degenerate face, then a third face on the shared diagonal
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 1.0]], float)
    f = np.array([[0, 1, 2], [0, 4, 3], [2, 1, 0], [0, 1, 1]])
    d = mesh_defects(v, f)
    assert d.merged_vertices == 1
    assert d.duplicate_faces.tolist() == [2] and d.degenerate_faces.tolist() == [3]
    assert len(d.non_manifold_edges) == 0 and len(d.self_intersecting_faces) == 0
    d = mesh_defects(v, np.vstack([f, [[0, 2, 5]]]))
    assert d.non_manifold_edges.tolist() == [[0, 2]] and d.non_manifold_counts.tolist() == [3]


def test_mesh_defects_finds_a_crossing_triangle():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]], float)
    d = mesh_defects(v, np.array([[0, 1, 2], [3, 4, 5]]))
    assert sorted(d.self_intersecting_faces.tolist()) == [0, 1]
    v[3:, 2] += 1.0  # lifted clear of the first triangle
    assert len(mesh_defects(v, np.array([[0, 1, 2], [3, 4, 5]])).self_intersecting_faces) == 0
