"""Plain arrays of the volume's voxels: which blocks and voxels carry a key, and the check of a map's arrays.

Pure numpy on the values :class:`~openfusion.mapping.storage.VoxelStorage` hands out (stored keys are
key + 1, 0 = never labelled; a voxel's place in its block is ``(z * res + y) * res + x``, see
:func:`~openfusion.mapping.storage.flat_voxel_index`). Kept apart from the storage so that read-outs of
paged-out tiles and the loading of a saved map use them without the Open3D grid.
"""

from __future__ import annotations

import numpy as np

from openfusion.mapping.params import VolumeParams


def labelled_of(coords: np.ndarray, key1_blocks: np.ndarray | None, res: int) -> tuple[np.ndarray, np.ndarray]:
    """(coords int64, keys (N, R, R, R) int32) of the blocks with a labelled voxel, from per-block
    stored keys (key + 1, ``(N, R**3)``)."""
    if key1_blocks is None or len(coords) == 0:
        return np.zeros((0, 3), np.int64), np.zeros((0, res, res, res), np.int32)
    keep = (key1_blocks > 0).any(axis=1)
    keys = key1_blocks[keep].astype(np.int32) - 1
    return np.asarray(coords)[keep].astype(np.int64), keys.reshape(-1, res, res, res)


def voxels_of_labelled(coords: np.ndarray, keys: np.ndarray, res: int) -> tuple[np.ndarray, np.ndarray]:
    """(voxel coordinates (n, 3) int64, keys (n,) int64) of the labelled voxels of :func:`labelled_of` output."""
    if len(coords) == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    flat = keys.reshape(len(coords), -1)
    block, within = np.nonzero(flat >= 0)
    # Position in the block: flat = (z * res + y) * res + x (see flat_voxel_index).
    local = np.stack([within % res, (within // res) % res, within // (res * res)], axis=1)
    voxels = coords[block].astype(np.int64) * res + local
    return voxels, flat[block, within].astype(np.int64)


def check_arrays(params: VolumeParams, arrays: dict[str, np.ndarray]) -> None:
    """Raise ``ValueError`` unless ``arrays`` are consistent :meth:`VoxelStorage.to_arrays` output
    for ``params`` (shapes, dtypes, unique blocks, keys >= -1, within ``max_blocks``)."""
    res = params.block_resolution
    coords = np.asarray(arrays["block_coords"])
    if coords.ndim != 2 or coords.shape[1] != 3 or not np.issubdtype(coords.dtype, np.integer):
        raise ValueError(f"block_coords must be (N, 3) integers, got {coords.dtype} {coords.shape}")
    n = len(coords)
    expected = {
        "tsdf": ((n, res, res, res), np.float32),
        "weight": ((n, res, res, res), np.float32),
        "color": ((n, res, res, res, 3), np.float32),
        "key": ((n, res, res, res), np.int32),
        "conf": ((n, res, res, res), np.float32),
    }
    for name, (shape, dtype) in expected.items():
        arr = np.asarray(arrays[name])
        if arr.shape != shape or arr.dtype != dtype:
            raise ValueError(f"{name} must be {np.dtype(dtype).name} {shape}, got {arr.dtype} {arr.shape}")
    if n and len(np.unique(coords, axis=0)) != n:
        raise ValueError("block_coords contain duplicates")
    if n and int(np.asarray(arrays["key"]).min()) < -1:
        raise ValueError("key values must be >= -1")
    if params.max_blocks is not None and n > params.max_blocks:
        raise ValueError(f"{n} blocks exceed max_blocks={params.max_blocks}")
