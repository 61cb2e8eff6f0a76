"""Mesh topology checks (``recon.mesh``) against Open3D's own on crafted meshes."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from tactile_slam.recon.mesh import face_components, is_closed_manifold


def o3d_mesh(vertices: np.ndarray, faces: np.ndarray) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64))
    m.triangles = o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32))
    return m


def tetra(offset: float = 0.0, first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64) + offset
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]) + first
    return v, f


def sphere() -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=12)
    return np.asarray(m.vertices), np.asarray(m.triangles).astype(np.int64)


def two_tetras_at_a_vertex() -> tuple[np.ndarray, np.ndarray]:
    """Closed and edge-manifold, but the shared vertex has two fans."""
    v1, f1 = tetra()
    v2 = np.array([[0, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=np.float64)
    f2 = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]) + 4
    f2[f2 == 4] = 0  # the second tetrahedron's apex is the first one's vertex 0
    return np.r_[v1, v2], np.r_[f1, f2]


def grid_sheet(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:n, 0:n]
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], 1).astype(np.float64)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    return v, np.r_[np.stack([a, b, c], 1), np.stack([b, d, c], 1)]


def fin() -> tuple[np.ndarray, np.ndarray]:
    """A closed tetrahedron with a third face on one of its edges."""
    v, f = tetra()
    return np.r_[v, [[0.5, -1.0, 0.5]]], np.r_[f, [[0, 1, 4]]]


@pytest.mark.parametrize("make", [sphere, tetra, two_tetras_at_a_vertex, grid_sheet, fin])
def test_closed_manifold_agrees_with_open3d(make):
    v, f = make()
    m = o3d_mesh(v, f)
    expected = m.is_edge_manifold(allow_boundary_edges=False) and m.is_vertex_manifold()
    assert is_closed_manifold(f) == expected
    assert is_closed_manifold(f) == (make in (sphere, tetra))


def test_closed_manifold_of_no_faces_is_false():
    assert not is_closed_manifold(np.zeros((0, 3), dtype=np.int64))


def test_components_are_edge_connected_as_open3d_clusters():
    """Two spheres, a tetrahedron touching the first sphere at one vertex only (not
    joined), and the fin mesh: the labels are Open3D's (numbered by first face)."""
    parts, verts, first = [], [], 0
    for v, f in (sphere(), tetra(5.0), sphere(), fin()):
        parts.append(f + first)
        verts.append(v + 10.0 * len(verts))
        first += len(v)
    v, f = np.concatenate(verts), np.concatenate(parts)
    touch = len(sphere()[0])  # the tetrahedron's vertex 0 becomes the first sphere's vertex 0
    f[f == touch] = 0
    labels = face_components(f)
    o3d_labels, counts, _ = o3d_mesh(v, f).cluster_connected_triangles()
    np.testing.assert_array_equal(labels, np.asarray(o3d_labels))
    assert labels.max() + 1 == 4 and np.bincount(labels).tolist() == list(np.asarray(counts))
    assert face_components(np.zeros((0, 3), dtype=np.int64)).shape == (0,)
