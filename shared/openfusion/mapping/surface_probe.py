"""The map's labels where a frame's own depth sees surface: frame selection's view without a ray cast.

Frame selection scores a candidate frame by what the map holds at the surface the frame sees
(:mod:`openfusion.mapping.coverage`): per surface pixel, the region key and confidence there. A
render answers that with a ray cast of the map from the frame's pose. But Open3D's CPU
``ray_cast`` copies the grid's whole block hash map on every call (docs/EVAL.md, "The render grows
with the map"), so a scoring render costs in proportion to the blocks held, not to the pixels
asked: 11-14 ms at 2,000 blocks, 45-76 ms at 67,000-90,000 on a 2-core box, more than a semantic
step of a room, once per camera frame per robot.

A probe asks for less, because the frame's depth already says where along each ray the surface
is. Per pixel of the scored view with a valid depth ``z``:

1. the TSDF is sampled at the voxels holding the points of the pixel's ray from ``z - window`` to
   ``z + window``, one voxel apart (Open3D's convention: voxel ``i`` spans ``[i, i + 1)`` voxel
   sizes); ``window`` is the truncation distance, and twice that for the pixels that found no
   surface within it (a scored pixel at a depth edge takes its depth from one
   side of the edge; :data:`WIDE_SEARCH`). A depth further than that from the map's surface is
   surface the map does not hold there;
2. the first sign change from free space (TSDF > 0) to behind the surface (TSDF <= 0) between two
   observed samples (weight >= ``min_weight``) is the map's surface along that ray, its depth
   interpolated linearly between the two samples; no sign change: no map surface (key -1);
3. the pixel takes the key and confidence of the labelled voxel with the largest trilinear weight
   among the 8 around that point: the rule of a render (:func:`raycast.semantics_at_hits`), so a
   probe and a render name the same voxels where they find the same surface.

The result is the same three images a render gives (key, confidence, depth of the surface found),
so it composites across geometry shards as renders do (nearest depth), and the same hits (the 8
voxels around each pixel's surface point), so an update of that view writes through them as
through a render's: past ``MatchParams.step_probe_blocks`` the semantic step reads an encoded
frame's view this way too (docs/EVAL.md, "The step's view on a large map"). It costs two block-hash
lookups per scored pixel's samples (Open3D's ``HashMap.find``, which reads the map in place),
whatever the map's size. What it does not see that a render would: a surface of the map in front
of the frame's (something the map holds that has since moved away) — the frame scores what it
sees, which is what its encoder would label. Measured against renders in docs/EVAL.md ("A
candidate on a large map", "Scored at 32 px"): at 32 px it reads the map as well per encoder call
as a 64 px render, at a third of the time, and is frame selection's default (``select_view``).

Written here rather than taken from a library: Open3D has no call that samples a voxel block
grid at arbitrary points (its ``ray_cast`` is the copy above), and the sampling is a few numpy
gathers over buffers this package already indexes (:mod:`openfusion.mapping.storage`).
"""

from __future__ import annotations

import numpy as np

from openfusion.frame import CameraIntrinsics
from openfusion.mapping.raycast import RayHits, semantics_at_hits, view_key
from openfusion.mapping.storage import VoxelStorage, flat_voxel_index, split_voxel_coords

#: The second search, for pixels without a map surface within one truncation distance of their
#: depth, reaches this many truncation distances (measured on a bench room: 2.5 % of the surface
#: pixels a render labels confidently were missed with one, mostly at depth edges, where a scored
#: pixel's depth comes from the background and the ray of the render grazes the object; 0.7 % with
#: two, as many as the probe labels and the render does not; 0.7 % with four).
WIDE_SEARCH = 2

#: The 8 corners of a voxel cell, as offsets from its lowest corner.
_CORNERS = np.array([[dx, dy, dz] for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], np.int64)


def probe_view(
    storage: VoxelStorage, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, depth_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, RayHits]:
    """Key (int32 (h, w), -1 = none) and confidence (float32) of the map's surface near ``depth_m``
    (the frame's depth at ``intrinsics``' size) along every pixel's ray from ``T_world_cam`` (a
    checked rigid pose), and the hits they were read from (:func:`probe_hits`; their ``depth_m`` is
    the depth of the surface found, 0 where none). Raises ValueError when ``depth_m`` is not
    ``intrinsics``' size."""
    hits = probe_hits(storage, T_world_cam, intrinsics, depth_m)
    key_map, conf_map = semantics_at_hits(storage, hits)
    return key_map, conf_map, hits


def probe_hits(
    storage: VoxelStorage, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, depth_m: np.ndarray,
) -> RayHits:
    """What a ray cast of the view would return (:class:`~openfusion.mapping.raycast.RayHits`: per
    pixel the 8 voxels around the surface point, their trilinear weights, and the depth), for the
    map's surface found near ``depth_m`` (steps 1-2 of the module docstring); pixels without one
    have depth 0 and no voxels. An update can write through them as through a render's
    (``SemanticVolume.apply_update``)."""
    h, w = intrinsics.height_px, intrinsics.width_px
    if np.shape(depth_m) != (h, w):
        raise ValueError(f"probe depth is {np.shape(depth_m)}, the view is {(h, w)}")
    p = storage.params
    surface_m = np.zeros(h * w, np.float32)
    index = np.full((h * w, 8), -1, np.int64)
    ratio = np.zeros((h * w, 8), np.float32)
    mask = np.zeros((h * w, 8), bool)
    z = np.asarray(depth_m, np.float64).reshape(-1)
    px = np.flatnonzero(np.isfinite(z) & (z >= p.depth_min_m) & (z <= p.depth_max_m))
    if len(px) and storage.num_blocks:
        rows, d_m, dirs = _surface_along_rays(storage, T_world_cam, intrinsics, px, z[px])
        found = px[rows]
        surface_m[found] = d_m
        points_vox = (T_world_cam[:3, 3] + dirs[rows] * d_m[:, None]) / p.voxel_size_m
        index[found], ratio[found], mask[found] = _corners_of(storage, points_vox)
    return RayHits(surface_m.reshape(h, w), index.reshape(h, w, 8), ratio.reshape(h, w, 8), mask.reshape(h, w, 8),
                   storage.generation, view_key(T_world_cam, intrinsics))


def _surface_along_rays(
    storage: VoxelStorage, T_world_cam: np.ndarray, K: CameraIntrinsics, px: np.ndarray, z_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows of ``px`` with a map surface near their depth, that surface's depth, every row's ray
    direction in the world per metre of depth). Searched within one truncation distance of the
    depth, then, for the rows without a surface there, within :data:`WIDE_SEARCH` of them."""
    p = storage.params
    w = K.width_px
    u = (px % w).astype(np.float64)
    v = (px // w).astype(np.float64)
    rays_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=1)
    dirs = rays_cam @ np.asarray(T_world_cam, np.float64)[:3, :3].T
    half = max(1, int(np.ceil(p.trunc_voxels)))
    rows, d_m = _first_crossing(storage, T_world_cam[:3, 3], dirs, z_m, half)
    missing = np.ones(len(px), bool)
    missing[rows] = False
    rest = np.flatnonzero(missing)
    if len(rest):
        more, d_more = _first_crossing(storage, T_world_cam[:3, 3], dirs[rest], z_m[rest], WIDE_SEARCH * half)
        rows, d_m = np.concatenate([rows, rest[more]]), np.concatenate([d_m, d_more])
    return rows, d_m, dirs


def _first_crossing(storage: VoxelStorage, origin: np.ndarray, dirs: np.ndarray, z_m: np.ndarray,
                    half: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows with a surface within ``half`` voxels of their depth ``z_m`` along ``dirs`` from
    ``origin``, its depth): the first observed sign change from free space, one voxel per sample."""
    p = storage.params
    vs = p.voxel_size_m
    offsets_m = np.arange(-half, half + 1, dtype=np.float64) * vs
    n = len(offsets_m)
    depths = z_m[:, None] + offsets_m[None, :]  # (m, n)
    grid = np.floor(origin / vs + (dirs / vs)[:, None, :] * depths[..., None]).astype(np.int64)
    tsdf, weight = _sample(storage, grid.reshape(-1, 3))
    tsdf, observed = tsdf.reshape(-1, n), (weight >= p.min_weight).reshape(-1, n)
    crossing = observed[:, :-1] & observed[:, 1:] & (tsdf[:, :-1] > 0) & (tsdf[:, 1:] <= 0)
    rows = np.flatnonzero(crossing.any(axis=1))
    k = crossing[rows].argmax(axis=1)
    before, after = tsdf[rows, k], tsdf[rows, k + 1]
    return rows, depths[rows, k] + vs * before / np.maximum(before - after, 1e-6)


def _flat_at(storage: VoxelStorage, grid: np.ndarray) -> np.ndarray:
    """Flat voxel index (int64) of each row of ``grid`` (int64 (N, 3) voxel coordinates); -1 where
    its block is not resident. Every row is indexed, then the absent ones masked: picking the
    resident rows of the (N, 3) coordinates first cost a third of a probe's time."""
    res = storage.params.block_resolution
    block, local = split_voxel_coords(grid, res)
    buf = storage.find_blocks(block)
    flat = flat_voxel_index(buf, local, res)
    flat[buf < 0] = -1
    return flat


def _sample(storage: VoxelStorage, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TSDF (1 = free where no block) and weight (0 where no block) at voxel coordinates."""
    tsdf = np.ones(len(grid), np.float32)
    weight = np.zeros(len(grid), np.float32)
    flat = _flat_at(storage, grid)
    ok = flat >= 0
    if ok.any():
        index = flat[ok]
        tsdf[ok] = storage.gather("tsdf", index)
        weight[ok] = storage.gather("weight", index)
    return tsdf, weight


def _corners_of(storage: VoxelStorage, points_vox: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 8 corners of each point's cell (``points_vox``: float (M, 3) in voxel units): their flat
    voxel indices (int64 (M, 8), -1 where the block is not resident), trilinear weights (float32)
    and whether each is observed (bool: resident, weight > 0); a label is then picked by the
    render's own rule (:func:`raycast.semantics_at_hits`)."""
    m = len(points_vox)
    base = np.floor(points_vox).astype(np.int64)
    corners = (base[:, None, :] + _CORNERS[None, :, :]).reshape(-1, 3)  # (m * 8, 3)
    frac = points_vox - base
    ratio = np.ones((m, 8))  # the trilinear weight of each corner: 1 - |point - corner| per axis
    for axis in range(3):
        ratio *= np.where(_CORNERS[:, axis] == 1, frac[:, axis, None], 1.0 - frac[:, axis, None])
    flat = _flat_at(storage, corners)
    observed = flat >= 0
    observed[observed] = storage.gather("weight", flat[observed]) > 0
    return flat.reshape(m, 8), ratio.astype(np.float32), observed.reshape(m, 8)
