"""One mesh out of meshes read out in parts, welded where the parts meet.

A map read out in parts (the chunks of :mod:`openfusion.mapping.wholemap` when tiles are paged
out, the tiles of each geometry shard in :mod:`openfusion.shard_client`) gives each part its own
copy of a vertex on a seam: marching cubes puts a vertex on every edge the surface crosses, and an
edge on a seam belongs to the cubes of both parts. The parts' copies are computed from the same
voxels (a part reads its neighbours' voxels through its halo or ghosts), so they are bit-identical
float32 positions: :func:`join_welded` merges those, and a mesh read out in parts equals the mesh
read out in one grid (same vertex and triangle counts; tests/unit/test_mapping_paging.py). A
welded mesh is what downstream tools expect (smoothing, normals, collision and navigation meshes
see one connected surface, not cracks of zero width).

Only copies from *different* parts merge: within one part, marching cubes may itself put two
vertices at one position (a surface through a voxel centre ends two edges there), and those stay
apart as they do in one grid. Where a part holds k vertices at a position, the j-th of them
merges with the j-th of every other part's at that position.

:func:`weld_plan` is the numpy core (no Open3D: the client-side merge of the shards' meshes,
:func:`openfusion.mapping.shards.concat_meshes`, uses it too).

Written with numpy rather than Open3D's ``remove_duplicated_vertices`` (legacy meshes) because
that drops the per-vertex region keys and confidences a mesh carries here, and merges within a
part too; equality is exact (no tolerance): vertices that merely lie close stay apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from openfusion.mapping.readout import SurfaceMesh

__all__ = ["join_welded", "weld_plan"]


def weld_plan(vertices: np.ndarray, part_sizes: Sequence[int]) -> tuple[np.ndarray, np.ndarray] | None:
    """For ``vertices`` (V, 3) float32, the parts' vertices one after the other (``part_sizes``
    each): ``(kept, remap)``, the vertices kept (indices, in order of first copies) and each
    vertex's index among them (module docstring: copies across parts merge); None when no vertex
    merges."""
    verts = np.ascontiguousarray(vertices, np.float32).reshape(-1, 3)
    n = len(verts)
    if len(part_sizes) < 2 or n == 0:
        return None
    part = np.repeat(np.arange(len(part_sizes)), part_sizes)
    rows = verts.view(np.dtype((np.void, verts.dtype.itemsize * 3))).reshape(-1)
    _, position = np.unique(rows, return_inverse=True)
    position = position.reshape(-1)
    # Rank of each vertex among its part's vertices at its position (0 for all but marching cubes' own doubles).
    order = np.lexsort((np.arange(n), part, position))
    first_of_run = np.r_[True, (position[order][1:] != position[order][:-1]) | (part[order][1:] != part[order][:-1])]
    run_start = np.maximum.accumulate(np.where(first_of_run, np.arange(n), 0))
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n) - run_start
    # One vertex per (position, rank): the first copy in the parts' order.
    ident = position * (int(rank.max()) + 1) + rank
    _, first, inverse = np.unique(ident, return_index=True, return_inverse=True)
    if len(first) == n:
        return None
    kept = np.sort(first)
    new_index = np.empty(n, np.int64)
    new_index[kept] = np.arange(len(kept))
    return kept, new_index[first[inverse.reshape(-1)]]


def join_welded(parts: Sequence[SurfaceMesh]) -> SurfaceMesh:
    """The parts as one mesh (triangles re-indexed, in the parts' order), every vertex copied by
    several parts at one position (bit-identical float32) merged into its first copy (its color,
    normal, key and confidence); vertices in the order of their first copies. Raises ValueError
    for no parts."""
    if not parts:
        raise ValueError("join_welded needs at least one part")
    mesh_type = type(parts[0])
    counts = [len(m.vertices) for m in parts]
    offsets = np.cumsum([0, *counts[:-1]])
    verts = np.ascontiguousarray(np.concatenate([m.vertices for m in parts]), np.float32).reshape(-1, 3)
    tris = np.concatenate([np.asarray(m.triangles, np.int64).reshape(-1, 3) + o
                           for m, o in zip(parts, offsets, strict=True)])
    cols, normals = np.concatenate([m.colors for m in parts]), np.concatenate([m.normals for m in parts])
    keys, conf = np.concatenate([m.keys for m in parts]), np.concatenate([m.conf for m in parts])
    plan = weld_plan(verts, counts)
    if plan is None:
        return mesh_type(verts, tris.astype(np.int32), cols, normals, keys, conf)
    kept, remap = plan
    return mesh_type(verts[kept], remap[tris].astype(np.int32), cols[kept], normals[kept], keys[kept], conf[kept])
