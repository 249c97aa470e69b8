"""Welding a mesh read out in parts: exact duplicates merged, near ones kept, attributes carried."""

from __future__ import annotations

import numpy as np

from openfusion.mapping.mesh_weld import weld_vertices
from openfusion.mapping.readout import SurfaceMesh


def _mesh(vertices: list, triangles: list) -> SurfaceMesh:
    v = np.asarray(vertices, np.float32)
    n = len(v)
    return SurfaceMesh(v, np.asarray(triangles, np.int32).reshape(-1, 3), np.arange(3 * n, dtype=np.uint8).reshape(n, 3),
                       np.zeros((n, 3), np.float32), np.arange(n, dtype=np.int32) + 10, np.linspace(0, 1, n, dtype=np.float32))


def test_two_parts_sharing_a_seam_become_one_connected_mesh() -> None:
    # Part A: triangle (0,1,2); part B: triangle (3,4,5) whose vertices 3 and 4 repeat A's 1 and 2.
    mesh = _mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [3, 4, 5]])
    welded = weld_vertices(mesh)
    assert len(welded.vertices) == 4 and len(welded.triangles) == 2
    np.testing.assert_array_equal(welded.triangles, [[0, 1, 2], [1, 2, 3]])
    np.testing.assert_array_equal(welded.vertices[welded.triangles], mesh.vertices[mesh.triangles])  # same shape
    np.testing.assert_array_equal(welded.keys, [10, 11, 12, 15])  # the first copy's attributes
    np.testing.assert_array_equal(welded.colors, mesh.colors[[0, 1, 2, 5]])


def test_near_but_not_equal_vertices_and_meshes_without_duplicates_are_left_alone() -> None:
    eps = np.float32(1e-6)
    mesh = _mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1 + eps, 0, 0]], [[0, 1, 2], [3, 2, 1]])
    assert weld_vertices(mesh) is mesh
    empty = _mesh(np.zeros((0, 3)).tolist(), [])
    assert weld_vertices(empty) is empty
