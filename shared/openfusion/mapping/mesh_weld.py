"""One vertex per point of the surface: meshes read out in parts, welded where the parts meet.

A map read out in parts (the chunks of :mod:`openfusion.mapping.wholemap` when tiles are paged
out, the tiles of each geometry shard in :mod:`openfusion.shard_client`) gives each part its own
copy of a vertex on a seam: marching cubes puts a vertex on every edge the surface crosses, and an
edge on a seam belongs to the cubes of both parts. The parts' copies are computed from the same
voxels (a part reads its neighbours' voxels through its halo or ghosts), so they are bit-identical
float32 positions: :func:`weld_vertices` merges exactly those, and a mesh read out in parts equals
the mesh read out in one grid (same vertex and triangle counts; tests/unit/test_mapping_paging.py).
A welded mesh is what downstream tools expect (smoothing, normals, collision and navigation meshes
see one connected surface, not cracks of zero width).

Written with numpy rather than Open3D's ``remove_duplicated_vertices`` (legacy meshes) because
that drops the per-vertex region keys and confidences a mesh carries here, and because exact
equality (no tolerance) is the rule: vertices that merely lie close stay apart.
"""

from __future__ import annotations

import numpy as np

from openfusion.mapping.readout import SurfaceMesh

__all__ = ["weld_vertices"]


def weld_vertices(mesh: SurfaceMesh) -> SurfaceMesh:
    """``mesh`` with every set of vertices at the same position (bit-identical float32) merged into
    the first of them (its color, normal, key and confidence), triangles re-indexed, vertex order
    the first occurrence's; a mesh with no duplicate is returned as it is."""
    n = len(mesh.vertices)
    if n == 0:
        return mesh
    verts = np.ascontiguousarray(mesh.vertices, np.float32).reshape(-1, 3)
    rows = verts.view(np.dtype((np.void, verts.dtype.itemsize * 3))).reshape(-1)
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    if len(first) == n:
        return mesh
    # Keep the unique vertices in the order of their first occurrence (stable output for a stable input).
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    keep = first[order]
    remap = rank[inverse.reshape(-1)]
    return SurfaceMesh(
        mesh.vertices[keep], remap[mesh.triangles].astype(np.int32), mesh.colors[keep], mesh.normals[keep],
        mesh.keys[keep], mesh.conf[keep],
    )
