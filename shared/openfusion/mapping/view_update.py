"""One view's update of the semantic volume: which voxels its pixels write, and writing them.

Named *view* update because it is the per-view half of the update: it turns a key/confidence image
into per-voxel observations (the inverse of a render); the per-voxel arithmetic is
:mod:`openfusion.mapping.update_rule` and the public entry point is
:meth:`~openfusion.mapping.volume.SemanticVolume.apply_update`.

Update rule (inverse render), per voxel near the surface seen from the pose
    The view's ray cast (:func:`openfusion.mapping.raycast.ray_cast`) picks, for every pixel of the
    update's key/confidence map, the 8 voxels around its surface hit; a voxel reached by several
    pixels takes the pixel whose hit is nearest to it (largest trilinear weight). The voxel's key
    and confidence then follow the rule of :mod:`openfusion.mapping.update_rule`
    (``fuse_semantics``): with ``w = VolumeParams.conf_history_weight`` and an observation (key
    ``k``, confidence ``c``)

    - never labelled:  key <- k,  conf <- c
    - same key:        conf <- (w * conf + c) / (w + 1)               (weighted average)
    - other key:       conf <- conf - c / (w + 1); if that is negative the new key wins:
                       key <- k, conf <- c / (w + 1) - conf_old      (the remaining evidence)

    Pixels with key -1 or confidence 0 change nothing. Voxels behind the first surface are never
    reached by the rays, so occluded voxels are not updated. With the frame's depth, pixels whose
    map surface is not where the frame saw one are skipped (:func:`depth_consistent`).
"""

from __future__ import annotations

import numpy as np

from openfusion.frame import CameraIntrinsics, resize_nearest
from openfusion.mapping.raycast import RayHits
from openfusion.mapping.storage import VoxelStorage
from openfusion.mapping.update_rule import fuse_semantics


def check_update_maps(
    key_map: np.ndarray, conf_map: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """``(key_map, conf_map as float32)`` after checking both are ``shape``, keys are -1 or int32
    region keys and confidences are finite within [0, 1]; ``ValueError`` otherwise."""
    key_map = np.asarray(key_map)
    conf_map = np.asarray(conf_map)
    if key_map.shape != shape or conf_map.shape != shape:
        raise ValueError(
            f"key_map {key_map.shape} and conf_map {conf_map.shape} must both be {shape} (the intrinsics' size)"
        )
    if not np.issubdtype(key_map.dtype, np.integer):
        raise ValueError(f"key_map must be an integer array, got {key_map.dtype}")
    if key_map.size and (key_map.min() < -1 or key_map.max() >= np.iinfo(np.int32).max):
        raise ValueError("key_map values must be -1 (none) or non-negative int32 region keys")
    conf_map = conf_map.astype(np.float32, copy=False)
    if not ((conf_map >= 0) & (conf_map <= 1)).all():  # NaN fails both comparisons
        raise ValueError("conf_map must be finite and within [0, 1]")
    return key_map, conf_map


def enlarge_update_maps(
    intrinsics: CameraIntrinsics, key_map: np.ndarray, conf_map: np.ndarray, min_width_px: int
) -> tuple[CameraIntrinsics, np.ndarray, np.ndarray]:
    """``(intrinsics, key_map, conf_map)`` enlarged by the smallest whole factor that makes them at
    least ``min_width_px`` wide (each pixel repeated, nearest neighbour; the intrinsics of the same
    camera at that size), or as given when they are that wide already or ``min_width_px`` is 0.

    Why: a pixel's ray writes the 8 voxels around its hit, so rays further apart than a voxel leave
    voxels between them unlabelled. An encoder's maps are a quarter of the frame's size or less
    (80x60 for a 320x240 frame: at 2 m one ray per 1.5 voxels of 2 cm); the map rendered at 32 px
    then shows most of a frame's own view unlabelled, and frame selection encodes the same surface
    again (docs/EVAL.md, "Rays for every voxel"). Repeating pixels adds rays, not detail: region
    borders stay where the encoder put them."""
    width = intrinsics.width_px
    if min_width_px <= 0 or width >= min_width_px or width == 0:
        return intrinsics, key_map, conf_map
    factor = -(-int(min_width_px) // width)
    big = intrinsics.scaled(width * factor, intrinsics.height_px * factor)
    size_hw = (big.height_px, big.width_px)
    return big, resize_nearest(key_map, size_hw), resize_nearest(conf_map, size_hw)


def depth_consistent(
    map_depth_m: np.ndarray,
    observed_depth_m: np.ndarray,
    trunc_m: float,
    depth_tolerance_m: float | None = None,
) -> np.ndarray:
    """Pixels (bool, ``map_depth_m``'s shape) whose map surface lies within ``depth_tolerance_m``
    (default: ``trunc_m`` + 2 % of the depth) of the observed depth (any size, resampled)."""
    observed = resize_nearest(np.asarray(observed_depth_m, np.float32), map_depth_m.shape)
    tol = (trunc_m + 0.02 * map_depth_m) if depth_tolerance_m is None else depth_tolerance_m
    return (observed > 0) & (np.abs(map_depth_m - observed) <= tol)


def write_view(
    storage: VoxelStorage,
    hits: RayHits,
    use: np.ndarray,
    key_map: np.ndarray,
    conf_map: np.ndarray,
    history_weight: float,
) -> tuple[int, tuple[int, int, int, int], np.ndarray]:
    """Fuse the pixels ``use`` (bool (h, w)) of ``key_map``/``conf_map`` into the voxels around
    their hits; returns the voxels updated, ``fuse_semantics``' (labelled, reinforced, weakened,
    switched) counts and the flat indices written. ``hits`` must be of the storage's current generation."""
    h, w = use.shape
    entry = np.flatnonzero((hits.mask.reshape(h * w, 8) & use.reshape(h * w, 1)).reshape(-1))
    if len(entry) == 0:
        return 0, (0, 0, 0, 0), np.zeros(0, np.int64)
    voxel = hits.index.reshape(-1)[entry]
    ratio = hits.ratio.reshape(-1)[entry]
    pixel = entry >> 3
    # One observation per voxel: the pixel whose hit is nearest (largest trilinear weight).
    chosen = _nearest_per_voxel(voxel, ratio)
    voxel = voxel[chosen]
    pixel = pixel[chosen]
    new_key1 = key_map.reshape(-1)[pixel].astype(np.int32) + 1
    new_conf = conf_map.reshape(-1)[pixel]
    old_key1 = storage.gather("key", voxel)
    old_conf = storage.gather("conf", voxel)
    out_key1, out_conf, counts = fuse_semantics(
        old_key1, old_conf, new_key1, new_conf, history_weight=history_weight
    )
    storage.scatter("key", voxel, out_key1)
    storage.scatter("conf", voxel, out_conf)
    return int(len(voxel)), counts, voxel


def _nearest_per_voxel(voxel: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """Index of the entry with the largest ratio for every distinct voxel (ties: lowest index).

    Packs (voxel, quantised 1 - ratio, entry index) into one int64 and sorts the values, which is
    about three times faster than an argsort of the same size.
    """
    n = len(voxel)
    entry_bits = max(int(n).bit_length(), 1)
    ratio_bits = 12
    shift = entry_bits + ratio_bits
    if int(voxel.max()) >= (1 << (62 - shift)):
        order = np.lexsort((np.arange(n), -ratio, voxel))
        voxel_sorted = voxel[order]
        first = np.ones(n, bool)
        first[1:] = voxel_sorted[1:] != voxel_sorted[:-1]
        return order[first]
    quant = np.round((1.0 - np.clip(ratio, 0.0, 1.0)) * ((1 << ratio_bits) - 1)).astype(np.int64)
    packed = (voxel.astype(np.int64) << shift) | (quant << entry_bits) | np.arange(n, dtype=np.int64)
    packed.sort()
    voxel_sorted = packed >> shift
    first = np.ones(n, bool)
    first[1:] = voxel_sorted[1:] != voxel_sorted[:-1]
    return packed[first] & ((1 << entry_bits) - 1)
