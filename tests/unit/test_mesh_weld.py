"""Joining meshes read out in parts: copies across parts merged, a part's own doubles and near
vertices kept, attributes carried, no parts refused."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping.mesh_weld import join_welded
from openfusion.mapping.readout import SurfaceMesh


def _mesh(vertices: list, triangles: list, key0: int = 10) -> SurfaceMesh:
    v = np.asarray(vertices, np.float32).reshape(-1, 3)
    n = len(v)
    return SurfaceMesh(v, np.asarray(triangles, np.int32).reshape(-1, 3), np.full((n, 3), key0, np.uint8),
                       np.zeros((n, 3), np.float32), np.arange(n, dtype=np.int32) + key0, np.full(n, 0.5, np.float32))


def test_two_parts_sharing_a_seam_become_one_connected_mesh() -> None:
    a = _mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], key0=10)
    b = _mesh([[1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2]], key0=20)  # its first two are a's seam copies
    welded = join_welded([a, b])
    assert len(welded.vertices) == 4 and len(welded.triangles) == 2
    np.testing.assert_array_equal(welded.triangles, [[0, 1, 2], [1, 2, 3]])
    np.testing.assert_array_equal(welded.keys, [10, 11, 12, 22])  # the first copy's attributes
    np.testing.assert_array_equal(welded.colors[:, 0], [10, 10, 10, 20])


def test_a_parts_own_doubles_and_near_vertices_stay_apart() -> None:
    eps = np.float32(1e-6)
    # Part a holds two vertices at (1, 0, 0) (marching cubes' own double); part b one copy of it and a near one.
    a = _mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]], [[0, 1, 2], [3, 2, 0]])
    b = _mesh([[1, 0, 0], [1 + eps, 1, 0], [0, 1, 0]], [[0, 1, 2]])
    welded = join_welded([a, b])
    assert len(welded.vertices) == 5  # a's 4 (its double kept) + b's near vertex
    np.testing.assert_array_equal(welded.triangles[2], [1, 4, 2])  # b's copies became a's first ones
    single = join_welded([a])
    assert len(single.vertices) == 4
    with pytest.raises(ValueError, match="at least one part"):
        join_welded([])
