"""Read-out of the semantic volume: surface points and meshes with a region key each.

Named after the volume's read-out rule (queries, segmentation and exports all read the map through
here; rendering a view is the ray cast's job, :mod:`openfusion.mapping.raycast`).

Read-out
    Surface points (TSDF zero crossings of voxels observed ``min_weight`` times, or marching-cubes
    vertices) take the key of the nearest labelled voxel of their cell
    (:func:`semantics_at_points`); points with none take the nearest same-facing labelled point's
    within ``VolumeParams.label_fill_radius_m`` (:func:`fill_nearest_labels`); then every labelled
    point takes the key most of its same-facing labelled neighbours within
    ``VolumeParams.label_vote_radius_m`` hold when more of them hold it than its own
    (:func:`vote_labels`).

The vote is ours (Open3D has no label filter over a point cloud; neighbours come from scipy's
``cKDTree``). It reads the map and never writes it: a key that a few voxels took from a mask's
border draw (one noisy frame's spill over a neighbour) is outvoted by the points around it in the
answer, while the voxels keep their evidence for the next update (docs/EVAL.md, "The read-out's
vote").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c
from scipy.spatial import cKDTree

from openfusion.mapping.storage import VoxelStorage, flat_voxel_index, split_voxel_coords
from openfusion.mapping.tiles import NEIGHBOUR_OFFSETS, pack_coords, unpack_coords

FILL_MIN_NORMAL_COS = 0.5  # a fill source must face within 60 degrees of the point it labels
_FILL_CANDIDATES = 8


@dataclass
class SurfacePoints:
    """Surface points (TSDF zero crossings) with the region key and confidence of each."""

    points: np.ndarray  # (N, 3) float32, world metres
    colors: np.ndarray  # (N, 3) uint8 RGB
    keys: np.ndarray  # (N,) int32, -1 = no region
    conf: np.ndarray  # (N,) float32

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass
class SurfaceMesh:
    """Triangle mesh of the surface with a region key per vertex."""

    vertices: np.ndarray  # (V, 3) float32
    triangles: np.ndarray  # (T, 3) int32
    colors: np.ndarray  # (V, 3) uint8
    normals: np.ndarray  # (V, 3) float32
    keys: np.ndarray  # (V,) int32
    conf: np.ndarray  # (V,) float32

    def to_open3d(self) -> o3d.t.geometry.TriangleMesh:
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3c.Tensor(self.vertices)
        mesh.vertex.colors = o3c.Tensor(self.colors.astype(np.float32) / 255.0)
        mesh.vertex.normals = o3c.Tensor(self.normals)
        mesh.triangle.indices = o3c.Tensor(self.triangles)
        return mesh


def _empty_points() -> SurfacePoints:
    return SurfacePoints(
        np.zeros((0, 3), np.float32),
        np.zeros((0, 3), np.uint8),
        np.zeros(0, np.int32),
        np.zeros(0, np.float32),
    )


def _empty_mesh() -> SurfaceMesh:
    return SurfaceMesh(
        np.zeros((0, 3), np.float32),
        np.zeros((0, 3), np.int32),
        np.zeros((0, 3), np.uint8),
        np.zeros((0, 3), np.float32),
        np.zeros(0, np.int32),
        np.zeros(0, np.float32),
    )


def _unit_rows(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float32)
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def _key_filter(keys: np.ndarray, wanted: np.ndarray | list[int] | None) -> np.ndarray | None:
    if wanted is None:
        return None
    wanted_arr = np.asarray(list(wanted) if not isinstance(wanted, np.ndarray) else wanted, np.int64)
    return np.isin(keys, wanted_arr)


def fill_nearest_labels(
    points: np.ndarray,
    keys: np.ndarray,
    conf: np.ndarray,
    radius_m: float,
    normals: np.ndarray | None = None,
) -> int:
    """Give every unlabelled point (key -1) the key and confidence of the nearest labelled point
    within ``radius_m``, in place; returns the number filled.

    One pass from the originally labelled points only, so labels never creep further than
    ``radius_m`` from a voxel the update actually labelled. With ``normals`` (unit, per point) a
    source must face the same way (cosine >= ``FILL_MIN_NORMAL_COS``, among the 8 nearest): the
    floor behind a table, hidden at encoder resolution, does not take the table's key from the
    table's back face, while a thin pole still takes the key of the pole beside it.
    """
    if radius_m <= 0:
        return 0
    missing = np.flatnonzero(keys < 0)
    labelled = np.flatnonzero(keys >= 0)
    if len(missing) == 0 or len(labelled) == 0:
        return 0
    tree = cKDTree(points[labelled])
    k = 1 if normals is None else min(_FILL_CANDIDATES, len(labelled))
    dist, nearest = tree.query(points[missing], k=k, distance_upper_bound=radius_m)
    dist = dist.reshape(len(missing), k)
    nearest = nearest.reshape(len(missing), k)
    ok = np.isfinite(dist)
    if normals is not None:
        src = labelled[np.where(ok, nearest, 0)]
        facing = np.einsum("ij,ikj->ik", normals[missing], normals[src]) >= FILL_MIN_NORMAL_COS
        ok &= facing
    first = ok.argmax(axis=1)  # candidates come nearest first
    found = ok[np.arange(len(missing)), first]
    source = labelled[nearest[found, first[found]]]
    keys[missing[found]] = keys[source]
    conf[missing[found]] = conf[source]
    return int(found.sum())


def vote_labels(
    points: np.ndarray,
    keys: np.ndarray,
    conf: np.ndarray,
    radius_m: float,
    normals: np.ndarray | None = None,
    *,
    classes: np.ndarray | None = None,
    neighbours: tuple[np.ndarray, np.ndarray] | None = None,
) -> int:
    """Give every labelled point the key that most labelled points within ``radius_m`` hold
    (itself included; with ``normals``, only points facing the same way, cosine >=
    ``FILL_MIN_NORMAL_COS``) when more of them hold it than hold the point's own key, in place;
    returns the number of points that changed key. A changed point takes the mean confidence of
    the neighbours that outvoted it.

    One pass over the keys as given (every point votes with the key it came in with), so a point's
    result depends only on the points within ``radius_m`` of it: a tile read out with a halo wider
    than ``radius_m`` gives its own points the keys the whole map's read-out gives them. Every
    neighbour within the radius counts (not the k nearest, whose ties on the voxel grid would
    depend on the point set). Ties keep the point's own key; between two other keys the smaller
    wins. Unlabelled points (key -1) neither vote nor change.

    ``classes`` (per point, for labelled points): vote by these instead of the keys, for a read-out
    whose keys are storage slots (:mod:`openfusion.mapping.chunkreadouts`: two slots of one merged
    region vote together, as their key does in the whole map's read-out). A point outvoted takes
    the smallest key among its neighbours of the winning class. ``neighbours``: the pairs of
    :func:`vote_neighbours` for these arguments, when the caller has them already.
    """
    if radius_m <= 0:
        return 0
    receiver, voter = neighbours if neighbours is not None else vote_neighbours(
        points, keys, radius_m, normals, classes=classes)
    if len(receiver) == 0:
        return 0
    key = keys.astype(np.int64)
    cls = key if classes is None else np.asarray(classes).astype(np.int64)
    agree = cls[receiver] == cls[voter]
    own_votes = 1 + np.bincount(receiver[agree], minlength=len(key))
    receiver, voter = receiver[~agree], voter[~agree]  # votes for another class
    if len(receiver) == 0:
        return 0
    order = np.lexsort((key[voter], cls[voter], receiver))
    voter, receiver = voter[order], receiver[order]
    vote_cls = cls[voter]
    start = np.flatnonzero(np.r_[True, (receiver[1:] != receiver[:-1]) | (vote_cls[1:] != vote_cls[:-1])])
    count = np.diff(np.r_[start, len(receiver)])
    conf_sum = np.add.reduceat(conf[voter].astype(np.float64), start)
    g_point, g_cls, g_key = receiver[start], vote_cls[start], key[voter[start]]  # the group's smallest key
    # Per point, the group with the most votes; the smaller class first among equals (lexsort is stable).
    best = np.lexsort((g_cls, -count, g_point))
    first = best[np.r_[True, g_point[best][1:] != g_point[best][:-1]]]
    win = first[count[first] > own_votes[g_point[first]]]
    if len(win) == 0:
        return 0
    target = g_point[win]
    keys[target] = g_key[win].astype(keys.dtype)
    conf[target] = (conf_sum[win] / count[win]).astype(conf.dtype)
    return int(len(win))


def vote_neighbours(
    points: np.ndarray,
    keys: np.ndarray,
    radius_m: float,
    normals: np.ndarray | None = None,
    *,
    classes: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs :func:`vote_labels` counts, as (receiver, voter) indices into ``points``: every
    labelled point within ``radius_m`` (facing the same way) of each labelled point that may be
    outvoted. A point whose cell and the 26 cells around it hold only its own class has none: no
    merge or cleared key can change its vote, since every point around it changes alike."""
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    labelled = np.flatnonzero(keys >= 0)
    if radius_m <= 0 or len(labelled) < 2:
        return none
    at = points[labelled].astype(np.float64)
    cls = (keys if classes is None else np.asarray(classes))[labelled].astype(np.int64)
    cand = np.flatnonzero(_may_be_outvoted(at, cls, float(radius_m)))
    if len(cand) == 0:
        return none
    # The tree's pairs within a slightly larger radius, then our own distance test: which pairs a
    # tree finds at exactly the radius depends on how it split the points, and a tile's read-out
    # must not differ from the whole map's there. The tree's distance settles every pair but those
    # within a hair of the radius; only those are measured again (gathering the coordinates of
    # millions of pairs cost as much as the search).
    r = float(radius_m)
    near = cKDTree(at[cand]).sparse_distance_matrix(cKDTree(at), r * 1.01, output_type="ndarray")
    receiver, voter, dist = cand[near["i"]], near["j"], near["v"]
    ok = dist <= r * (1.0 - 1e-9)
    edge = np.flatnonzero(~ok & (dist <= r * (1.0 + 1e-9)))
    if len(edge):
        ok[edge] = ((at[receiver[edge]] - at[voter[edge]]) ** 2).sum(axis=1) <= r**2
    ok &= voter != receiver
    receiver, voter = receiver[ok], voter[ok]
    if normals is not None:
        n = normals[labelled]
        facing = np.einsum("ij,ij->i", n[receiver], n[voter]) >= FILL_MIN_NORMAL_COS
        receiver, voter = receiver[facing], voter[facing]
    return labelled[receiver], labelled[voter]


def _may_be_outvoted(at: np.ndarray, cls: np.ndarray, radius_m: float) -> np.ndarray:
    """Per point, whether a point of another class may lie within ``radius_m``: cells a little
    wider than the radius, and a point is left out when its cell and the 26 around it hold its
    class only (most of a map: the vote then only asks about the points along region borders)."""
    cell = pack_coords(np.floor(at / (radius_m * 1.001)).astype(np.int64))
    cells, inv = np.unique(cell, return_inverse=True)
    lo = np.full(len(cells), np.iinfo(np.int64).max)
    hi = np.full(len(cells), np.iinfo(np.int64).min)
    np.minimum.at(lo, inv, cls)
    np.maximum.at(hi, inv, cls)
    clean = lo == hi
    coords = unpack_coords(cells)
    for offset in NEIGHBOUR_OFFSETS:  # (0, 0, 0) among them: the cell against itself changes nothing
        nb = pack_coords(coords + offset)
        j = np.minimum(np.searchsorted(cells, nb), len(cells) - 1)
        there = cells[j] == nb
        clean &= ~there | ((lo[j] == hi[j]) & (lo[j] == lo))
    return ~clean[inv]


def semantics_at_points(
    storage: VoxelStorage, points: np.ndarray, normals: np.ndarray | None = None, *, vote: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Key and confidence for surface points: the nearest labelled voxel among the 8 corners of
    the voxel cell containing each point (surface points lie on cell edges); points left
    without one take the nearest labelled point's within ``params.label_fill_radius_m`` (facing
    the same way when ``normals`` are given; see :func:`fill_nearest_labels`); then, unless
    ``vote`` is false, the vote of :func:`vote_labels` within ``params.label_vote_radius_m``."""
    n_pts = len(points)
    keys = np.full(n_pts, -1, np.int32)
    conf = np.zeros(n_pts, np.float32)
    if n_pts == 0:
        return keys, conf
    params = storage.params
    vs = params.voxel_size_m
    res = params.block_resolution
    g = points.astype(np.float64) / vs
    base = np.floor(g).astype(np.int64)
    lookup = storage.block_lookup()
    best_d2 = np.full(n_pts, np.inf)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                gv = base + np.array([dx, dy, dz], np.int64)
                block, local = split_voxel_coords(gv, res)
                buf = lookup.find(block)
                ok = np.flatnonzero(buf >= 0)
                if len(ok) == 0:
                    continue
                flat = flat_voxel_index(buf[ok], local[ok], res)
                stored = storage.gather("key", flat)
                lab = stored > 0
                ok, flat, stored = ok[lab], flat[lab], stored[lab]
                d2 = ((g[ok] - gv[ok]) ** 2).sum(axis=1)
                better = d2 < best_d2[ok]
                sel = ok[better]
                best_d2[sel] = d2[better]
                keys[sel] = stored[better] - 1
                conf[sel] = storage.gather("conf", flat[better])
    fill_nearest_labels(points, keys, conf, params.label_fill_radius_m, normals)
    if vote:
        vote_labels(points, keys, conf, params.label_vote_radius_m, normals)
    return keys, conf


def surface_points(storage: VoxelStorage) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """The surface's points (zero crossings of voxels observed ``min_weight`` times), colours and
    unit normals, sorted by (x, y, z); None when there are none."""
    if storage.num_blocks == 0:
        return None
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pcd = storage.vbg.extract_point_cloud(float(storage.params.min_weight) - 0.5)
    if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
        return None
    points = pcd.point.positions.cpu().numpy().astype(np.float32, copy=False)
    colors = np.clip(np.round(pcd.point.colors.cpu().numpy() * 255.0), 0, 255).astype(np.uint8)
    # Open3D emits points in a thread-dependent order: sort so results are reproducible.
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
    normals = _unit_rows(pcd.point.normals.cpu().numpy()[order]) if "normals" in pcd.point else None
    return points[order], colors[order], normals


def extract_points(
    storage: VoxelStorage,
    keys: np.ndarray | list[int] | None = None,
    max_points: int | None = None,
    *,
    seed: int = 0,
) -> SurfacePoints:
    """Surface points (zero crossings of voxels observed ``min_weight`` times) with keys.

    Points are sorted by (x, y, z), so the same map always gives the same array. ``keys`` keeps
    only points of those regions; ``max_points`` subsamples uniformly at random
    (deterministic for a given ``seed``).
    """
    if max_points is not None and max_points < 0:
        raise ValueError(f"max_points must be >= 0, got {max_points}")
    surface = surface_points(storage)
    if surface is None:
        return _empty_points()
    points, colors, normals = surface
    pkeys, pconf = semantics_at_points(storage, points, normals)
    keep = _key_filter(pkeys, keys)
    if keep is not None:
        points, colors, pkeys, pconf = points[keep], colors[keep], pkeys[keep], pconf[keep]
    if max_points is not None and len(points) > max_points:
        rng = np.random.default_rng(seed)
        sel = np.sort(rng.choice(len(points), size=max_points, replace=False))
        points, colors, pkeys, pconf = points[sel], colors[sel], pkeys[sel], pconf[sel]
    return SurfacePoints(points, colors, pkeys, pconf)


def extract_mesh(storage: VoxelStorage, keys: np.ndarray | list[int] | None = None) -> SurfaceMesh:
    """Surface mesh (marching cubes); with ``keys``, only triangles whose 3 vertices carry one of
    those keys (unreferenced vertices dropped)."""
    if storage.num_blocks == 0:
        return _empty_mesh()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = storage.vbg.extract_triangle_mesh(float(storage.params.min_weight) - 0.5)
    if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0:
        return _empty_mesh()
    vertices = mesh.vertex.positions.cpu().numpy().astype(np.float32, copy=False)
    triangles = mesh.triangle.indices.cpu().numpy().astype(np.int32, copy=False)
    colors = np.clip(np.round(mesh.vertex.colors.cpu().numpy() * 255.0), 0, 255).astype(np.uint8)
    has_normals = "normals" in mesh.vertex
    normals = (
        mesh.vertex.normals.cpu().numpy().astype(np.float32, copy=False)
        if has_normals
        else np.zeros_like(vertices)
    )
    vkeys, vconf = semantics_at_points(storage, vertices, _unit_rows(normals) if has_normals else None)
    keep_vertex = _key_filter(vkeys, keys)
    if keep_vertex is not None:
        tri_keep = keep_vertex[triangles].all(axis=1)
        triangles = triangles[tri_keep]
        used = np.zeros(len(vertices), bool)
        used[triangles.reshape(-1)] = True
        remap = np.full(len(vertices), -1, np.int64)
        remap[used] = np.arange(int(used.sum()))
        triangles = remap[triangles].astype(np.int32)
        vertices, colors, normals, vkeys, vconf = (
            vertices[used],
            colors[used],
            normals[used],
            vkeys[used],
            vconf[used],
        )
    return SurfaceMesh(vertices, triangles, colors, normals, vkeys, vconf)
