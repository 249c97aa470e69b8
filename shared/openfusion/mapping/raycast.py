"""Depth-tested ray casting of the semantic volume: which voxels every pixel of a view sees.

Named after Open3D's ``ray_cast``, which it drives; rendering a view is a ray cast plus one pick
per pixel, so the render's rule lives here too.

Both :meth:`~openfusion.mapping.volume.SemanticVolume.render` and the update rule
(:meth:`~openfusion.mapping.volume.SemanticVolume.apply_update`) start from :func:`ray_cast`, so
this module holds everything about driving Open3D's ``VoxelBlockGrid.ray_cast`` for them.

Render (depth-tested)
    :func:`ray_cast` ray-casts the TSDF from a pose with Open3D's ``ray_cast``. Each pixel's ray
    stops at the first zero crossing, so occluded surfaces never appear. The ray cast returns the 8
    voxels around the hit (flat voxel indices, see :mod:`openfusion.mapping.storage`) with their
    trilinear weights and an observed-voxel mask (:class:`RayHits`); the pixel takes the key and
    confidence of the labelled voxel among them with the largest weight, the nearest one
    (:func:`semantics_at_hits`).

Open3D ray-cast notes (open3d 0.20, measured)
    ``ray_cast`` estimates a per-pixel depth range from the blocks it is given, in fragments kept
    in a buffer owned by the grid. When the buffer is too small it logs "Could not generate full
    range map" and renders an *incomplete* image for that call. We pass only the blocks in the view
    frustum (:func:`frustum_blocks`) and, before casting, grow the buffer (one quiet warm-up cast
    with synthetic blocks, :func:`ensure_fragment_capacity`) to an upper bound of the fragments the
    cast can need. The range-map down factor must divide the image size (otherwise the last rows
    read outside the range map); we pick 8, 4, 2 or 1 (:func:`range_map_down_factor`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from openfusion.frame import CameraIntrinsics
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.storage import VoxelStorage
from openfusion.poses import invert_pose

logger = logging.getLogger(__name__)

_FRAGMENT_SIZE = 16  # Open3D's range-map fragment edge, in range-map cells


@dataclass
class RayHits:
    """Raw ray-cast result of one view: per pixel the 8 voxels around the surface hit.

    ``index`` holds flat voxel indices into the grid's attribute buffers; they are valid only while
    the volume's ``generation`` is unchanged (a grid that grows re-hashes its blocks).
    """

    depth_m: np.ndarray  # (h, w) float32, 0 = no surface
    index: np.ndarray  # (h, w, 8) int64
    ratio: np.ndarray  # (h, w, 8) float32 trilinear weights
    mask: np.ndarray  # (h, w, 8) bool, voxel exists and was observed
    generation: int
    pose_key: bytes


def range_map_down_factor(width_px: int, height_px: int) -> int:
    """Largest of 8, 4, 2, 1 dividing both image sides (Open3D reads past the range map otherwise)."""
    for factor in (8, 4, 2, 1):
        if width_px % factor == 0 and height_px % factor == 0:
            return factor
    return 1


def view_key(T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> bytes:
    """Identity of a view (pose and intrinsics), stored in :class:`RayHits` to recognise reuse."""
    return T_world_cam.tobytes() + repr(intrinsics).encode()


def frustum_blocks(
    coords: np.ndarray, params: VolumeParams, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics
) -> tuple[np.ndarray, int]:
    """Those of the blocks ``coords`` (int32 (N, 3)) that can project into the image, and an upper
    bound of the range-map fragments Open3D needs for them at the chosen down factor."""
    if len(coords) == 0:
        return coords, 0
    bs = params.block_size_m
    radius = bs * math.sqrt(3.0) / 2.0
    centers = (coords.astype(np.float64) + 0.5) * bs
    R = T_world_cam[:3, :3]
    pc = (centers - T_world_cam[:3, 3]) @ R
    z = pc[:, 2]
    keep = (z > -radius) & (z < params.depth_max_m + radius)
    z_near = np.maximum(z - radius, 1e-3)
    zc = np.maximum(z, 1e-3)
    w, h = intrinsics.width_px, intrinsics.height_px
    u = intrinsics.fx * pc[:, 0] / zc + intrinsics.cx
    v = intrinsics.fy * pc[:, 1] / zc + intrinsics.cy
    span_u = 2.0 * radius * intrinsics.fx / z_near
    span_v = 2.0 * radius * intrinsics.fy / z_near
    in_view = (u > -span_u) & (u < w + span_u) & (v > -span_v) & (v < h + span_v)
    keep &= in_view | (z <= radius)
    factor = range_map_down_factor(w, h)
    cells_u = np.minimum(span_u[keep], w) / factor + 2.0
    cells_v = np.minimum(span_v[keep], h) / factor + 2.0
    fragments = int(np.sum(np.ceil(cells_u / _FRAGMENT_SIZE) * np.ceil(cells_v / _FRAGMENT_SIZE)))
    return np.ascontiguousarray(coords[keep]), fragments


def ensure_fragment_capacity(storage: VoxelStorage, fragments_needed: int) -> None:
    """Grow Open3D's range-map fragment buffer (owned by the grid) above ``fragments_needed``.

    One quiet ray cast over synthetic blocks that fill a small 90-degree view: Open3D reallocates
    its buffer to the number of fragments that cast needs (at least one per synthetic block)."""
    if fragments_needed < storage.fragment_capacity:
        return
    target = max(2 * fragments_needed, 2 * storage.fragment_capacity, 2048)
    layers = []
    total = 0
    zb = 2
    while total < target:
        xs = np.arange(-zb, zb)
        gx, gy = np.meshgrid(xs, xs, indexing="ij")
        layer = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, zb)], axis=1)
        layers.append(layer)
        total += len(layer)
        zb += 1
    fake = np.concatenate(layers).astype(np.int32)
    params = storage.params
    bs = params.block_size_m
    size_px = 32
    K = o3c.Tensor(
        np.array([[size_px / 2, 0, size_px / 2], [0, size_px / 2, size_px / 2], [0, 0, 1]], np.float64)
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        storage.vbg.ray_cast(
            o3c.Tensor(fake, device=storage.device),
            K,
            o3c.Tensor(np.eye(4)),
            size_px,
            size_px,
            ["depth"],
            1.0,
            0.01,
            float((zb + 2) * bs),
            float(params.min_weight),
            float(params.trunc_voxels),
            1,
        )
    # Blocks clipped at the view's edge may produce no fragment: count half of them.
    storage.fragment_capacity = total // 2
    logger.debug("ray-cast fragment buffer grown to >= %d fragments", storage.fragment_capacity)


def ray_cast(
    storage: VoxelStorage, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, K: o3c.Tensor
) -> RayHits:
    """Depth and the 8 voxels around the first surface hit of every pixel (depth-tested).

    ``T_world_cam`` must be a checked rigid pose; ``K`` is ``intrinsics.K`` as a float64 tensor.
    """
    h, w = intrinsics.height_px, intrinsics.width_px
    pose_key = view_key(T_world_cam, intrinsics)
    all_coords, _ = storage.active_blocks()
    coords, fragments = frustum_blocks(all_coords, storage.params, T_world_cam, intrinsics)
    if len(coords) == 0:
        return RayHits(
            np.zeros((h, w), np.float32),
            np.zeros((h, w, 8), np.int64),
            np.zeros((h, w, 8), np.float32),
            np.zeros((h, w, 8), bool),
            storage.generation,
            pose_key,
        )
    ensure_fragment_capacity(storage, fragments)
    p = storage.params
    result = storage.vbg.ray_cast(
        o3c.Tensor(coords, device=storage.device),
        K,
        o3c.Tensor(invert_pose(T_world_cam)),
        w,
        h,
        ["depth", "index", "interp_ratio", "mask"],
        1.0,
        p.depth_min_m,
        p.depth_max_m,
        float(p.min_weight),
        float(p.trunc_voxels),
        range_map_down_factor(w, h),
    )
    return RayHits(
        result["depth"].cpu().numpy().reshape(h, w),
        result["index"].cpu().numpy(),
        result["interp_ratio"].cpu().numpy(),
        result["mask"].cpu().numpy(),
        storage.generation,
        pose_key,
    )


def semantics_at_hits(storage: VoxelStorage, hits: RayHits) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the key (int32 (h, w), -1 = no labelled surface) and confidence (float32) of the
    labelled voxel with the largest trilinear weight among the 8 around the pixel's hit."""
    h, w = hits.depth_m.shape
    # Stored keys (key + 1) of the 8 voxels around every pixel's hit; 0 where none / unobserved.
    index = hits.index.reshape(h * w, 8)
    stored = storage.gather("key", index.reshape(-1), clip=True).reshape(h * w, 8)
    stored *= hits.mask.reshape(h * w, 8)
    labelled = stored > 0
    # The labelled voxel with the largest trilinear weight (the nearest one) names the pixel.
    best = np.where(labelled, hits.ratio.reshape(h * w, 8), -1.0).argmax(axis=1)[:, None]
    best_key1 = np.take_along_axis(stored, best, axis=1)[:, 0]
    px = np.flatnonzero(best_key1)
    key_map = (best_key1 - 1).astype(np.int32, copy=False).reshape(h, w)
    conf_map = np.zeros((h, w), np.float32)
    if len(px):
        best_index = np.take_along_axis(index, best, axis=1)[:, 0][px]
        conf_map.reshape(-1)[px] = storage.gather("conf", best_index)
    return key_map, conf_map
